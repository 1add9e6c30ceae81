//! The `mqtt-` scenarios: the `values-` scenario's 247 slaves x 20 plant values on the simulated
//! 115200 8N1 line, published by the gateway (`[mqtt]`: QoS 1, retained, Home Assistant's
//! discovery on, the scenario's `publish_interval`) to a mosquitto the bench starts on a free
//! loopback port (test-support's broker: a config of its own in a temp dir, `persistence
//! false`), and read back by a `mosquitto_sub` of the bench's on `modbus-gateway/#` and
//! `homeassistant/#`, which notes when each message came. The same gateway without `[mqtt]` is
//! measured first, the same way, as the yardstick. For each: the first pass over every value
//! (`GET /values`, as `plant` waits for it) and, with MQTT, the first full publication (every
//! value, discovery config and availability, and the status, received); then a window of
//! `--seconds` in which the gateway only polls (and publishes): its CPU, the broker's, the
//! messages received and the gateway's own count of those it sent, its RSS; then [`MASTERS`]
//! Modbus TCP masters each reading 10 holding registers every [`PERIOD`] beside it, for as long:
//! their latency. The simulated slaves' values never change, so after the first publication
//! every message is a value's again at `publish_interval` (and nothing is published on change):
//! the steady rate is the values over the interval. The figures are `report`'s.

use crate::beside::{self, Driven};
use crate::gateway::{cpu_time, rss_mb, Gateway};
use crate::plant;
use crate::scenarios::{Scenario, PLANT_VALUES, SLAVES};
use crate::watch::{sample, sample_any, scrape};
use crate::Cli;
use std::collections::{HashMap, HashSet};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
use test_support::mosquitto::Broker;
use test_support::process::tool;

/// The masters reading beside the polls and the publishing.
pub(crate) const MASTERS: usize = 10;
/// How often each master reads, the masters' turns spread evenly over it: 50 reads a second of
/// 6.4 ms of the line each at 115200, a third of it, half with the polls: the line has room, so
/// what the masters wait for beyond a read's own time is a poll or another master's read ahead
/// of theirs, or the gateway.
pub(crate) const PERIOD: Duration = Duration::from_millis(200);
/// The gateway's default `topic_prefix` and `discovery_prefix`.
const PREFIX: &str = "modbus-gateway";
const DISCOVERY: &str = "homeassistant";
/// How long the first publication may take to complete after the first pass.
const PUBLICATION_LIMIT: Duration = Duration::from_secs(60);
/// How long mosquitto_sub may take to subscribe.
const SUBSCRIBE_LIMIT: Duration = Duration::from_secs(10);
/// How often the bench looks whether a wait is over.
const CHECK: Duration = Duration::from_millis(20);

/// The values every slave lists, in all.
fn values() -> usize {
    usize::from(SLAVES) * PLANT_VALUES.len()
}

/// What the subscriber received, and when.
#[derive(Default)]
struct Arrivals {
    /// When each message came, in order.
    times: Vec<Instant>,
    /// The distinct topics, by kind; a value's with when it last came.
    values: HashMap<String, Instant>,
    discovery: HashSet<String>,
    availability: HashSet<String>,
    status: bool,
    /// When the last discovery config came; when the first publication was complete, and the
    /// messages received by then.
    discovery_done: Option<Instant>,
    complete: Option<(Instant, usize)>,
    /// The time between two messages of one value, each time one came again: how many, in all,
    /// the longest.
    gaps: (usize, Duration, Duration),
}

/// `topic` into `set`, if it is not there yet.
fn note(set: &mut HashSet<String>, topic: &str) {
    if !set.contains(topic) {
        set.insert(topic.to_owned());
    }
}

impl Arrivals {
    /// A message on `topic` came `at`.
    fn take(&mut self, topic: &str, at: Instant) {
        self.times.push(at);
        if topic.starts_with(DISCOVERY) && topic.ends_with("/config") {
            note(&mut self.discovery, topic);
            if self.discovery_done.is_none() && self.discovery.len() >= values() {
                self.discovery_done = Some(at);
            }
        } else if topic == format!("{PREFIX}/status") {
            self.status = true;
        } else if topic.ends_with("/availability") {
            note(&mut self.availability, topic);
        } else if let Some(last) = self.values.get_mut(topic) {
            let gap = at - *last;
            *last = at;
            self.gaps = (self.gaps.0 + 1, self.gaps.1 + gap, self.gaps.2.max(gap));
        } else {
            self.values.insert(topic.to_owned(), at);
        }
        let complete = self.status
            && self.values.len() >= values()
            && self.discovery.len() >= values()
            && self.availability.len() >= usize::from(SLAVES);
        if complete && self.complete.is_none() {
            self.complete = Some((at, self.times.len()));
        }
    }

    /// Messages that came within `from..=to`.
    fn within(&self, from: Instant, to: Instant) -> usize {
        let first = self.times.partition_point(|t| *t < from);
        let after = self.times.partition_point(|t| *t <= to);
        after - first
    }

    /// The most messages that came within one second, in whole seconds from the first one.
    fn peak_per_s(&self) -> usize {
        let Some(&first) = self.times.first() else {
            return 0;
        };
        let mut bins: Vec<usize> = Vec::new();
        for t in &self.times {
            let bin = usize::try_from((*t - first).as_secs()).unwrap_or(usize::MAX);
            if bins.len() <= bin {
                bins.resize(bin + 1, 0);
            }
            bins[bin] += 1;
        }
        bins.into_iter().max().unwrap_or(0)
    }
}

/// mosquitto_sub on the gateway's topics and the discovery configs (QoS 1), each message's topic
/// one line of its output, noted with the time it was read; killed when dropped.
struct Subscriber {
    child: Child,
    arrivals: Arc<Mutex<Arrivals>>,
}

impl Subscriber {
    /// mosquitto_sub (`program`) on `broker`, once both its subscriptions hold: mosquitto logs
    /// each filter of a SUBSCRIBE as it takes it, so once the last is in its log, both are.
    async fn start(program: &Path, broker: &Broker) -> Result<Subscriber, String> {
        let id = format!("mbgw-bench-sub-{}", std::process::id());
        let addr = broker.addr();
        let (values, discovery) = (format!("{PREFIX}/#"), format!("{DISCOVERY}/#"));
        let mut child = Command::new(program)
            .args(["-h", &addr.ip().to_string(), "-p", &addr.port().to_string()])
            .args([
                "-q", "1", "-i", &id, "-F", "%t", "-t", &values, "-t", &discovery,
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("{}: {e}", program.display()))?;
        let stdout = child.stdout.take().ok_or("mosquitto_sub: no output")?;
        let arrivals = Arc::new(Mutex::new(Arrivals::default()));
        let into = arrivals.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(topic) = line else { return };
                let at = Instant::now();
                let mut arrivals = into.lock().unwrap_or_else(PoisonError::into_inner);
                arrivals.take(&topic, at);
            }
        });
        let mut subscriber = Subscriber { child, arrivals };
        let logged = format!("{id} 1 {discovery}");
        let started = Instant::now();
        while !broker.log().contains(&logged) {
            if let Ok(Some(status)) = subscriber.child.try_wait() {
                return Err(format!("mosquitto_sub exited ({status})"));
            }
            if started.elapsed() > SUBSCRIBE_LIMIT {
                return Err(format!(
                    "mosquitto_sub did not subscribe within {SUBSCRIBE_LIMIT:?}"
                ));
            }
            tokio::time::sleep(CHECK).await;
        }
        Ok(subscriber)
    }

    /// Wait (at most [`PUBLICATION_LIMIT`]) until the first publication is complete.
    async fn until_complete(&self) {
        let waited = Instant::now();
        while self.with(|a| a.complete.is_none()) && waited.elapsed() < PUBLICATION_LIMIT {
            tokio::time::sleep(CHECK).await;
        }
    }

    fn with<T>(&self, f: impl FnOnce(&Arrivals) -> T) -> T {
        f(&self.arrivals.lock().unwrap_or_else(PoisonError::into_inner))
    }
}

impl Drop for Subscriber {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The broker's process: the mosquitto whose config is in a temp dir of this process's brokers
/// (test-support's names them `mbgw-mosquitto-PID-N`), of which the bench runs one at a time.
fn broker_pid() -> Option<u32> {
    let dir = std::env::temp_dir().join(format!("mbgw-mosquitto-{}-", std::process::id()));
    let needle = dir.to_string_lossy().into_owned();
    std::fs::read_dir("/proc").ok()?.find_map(|entry| {
        let entry = entry.ok()?;
        let pid: u32 = entry.file_name().to_str()?.parse().ok()?;
        let cmdline = std::fs::read(entry.path().join("cmdline")).ok()?;
        let cmdline = String::from_utf8_lossy(&cmdline);
        let program = cmdline.split('\0').next()?;
        (program.ends_with("mosquitto") && cmdline.contains(&needle)).then_some(pid)
    })
}

/// One gateway's figures: with MQTT or without.
pub(crate) struct Side {
    /// From the gateway listening until every value had been read once.
    pub(crate) first_pass: Duration,
    /// The window in which the gateway only polled (and published): its length, the gateway's
    /// CPU time across it, its polls, and its memory after it.
    pub(crate) polling: Duration,
    pub(crate) polling_cpu: Duration,
    pub(crate) polls: f64,
    pub(crate) rss_polling_mb: f64,
    /// The masters reading beside, and the gateway's memory at the end.
    pub(crate) masters: Driven,
    pub(crate) rss_mb: f64,
}

/// The gateway's MQTT counters (`modbus_gateway_mqtt_*`) on one metrics page.
#[derive(Clone, Copy, Default)]
pub(crate) struct Counters {
    pub(crate) published: f64,
    pub(crate) dropped: f64,
    pub(crate) set_received: f64,
    pub(crate) set_refused: f64,
    pub(crate) connection_failures: f64,
    pub(crate) connected: f64,
}

impl Counters {
    fn of(page: &str) -> Counters {
        let messages = |kind: &str| {
            let kind = format!("kind=\"{kind}\"");
            sample_any(page, "modbus_gateway_mqtt_messages_total", &[&kind])
        };
        Counters {
            published: messages("published"),
            dropped: messages("dropped"),
            set_received: messages("set_received"),
            set_refused: messages("set_refused"),
            connection_failures: sample_any(
                page,
                "modbus_gateway_mqtt_connection_failures_total",
                &[],
            ),
            connected: sample_any(page, "modbus_gateway_mqtt_connected", &[]),
        }
    }
}

/// What the subscriber and the gateway's counters saw of the publishing; times from the gateway
/// listening.
pub(crate) struct Published {
    pub(crate) first_message: Option<Duration>,
    pub(crate) discovery: Option<Duration>,
    /// The first publication complete, and the messages received by then.
    pub(crate) complete: Option<(Duration, usize)>,
    /// Messages received from the first to the last discovery config.
    pub(crate) discovery_messages: usize,
    /// Distinct topics received: values, discovery configs, availabilities.
    pub(crate) value_topics: usize,
    pub(crate) discovery_topics: usize,
    pub(crate) availability_topics: usize,
    /// In the polling window: messages received, the gateway's count of those it sent, and the
    /// broker's CPU time (if its process was found).
    pub(crate) received_polling: usize,
    pub(crate) published_polling: f64,
    pub(crate) broker_cpu: Option<Duration>,
    /// How often a value came again: the mean and the longest time between two of its messages.
    pub(crate) value_gap_mean: Option<Duration>,
    pub(crate) value_gap_max: Option<Duration>,
    /// Messages received in the masters' window.
    pub(crate) received_masters: usize,
    /// The most received in one second, from the first message.
    pub(crate) peak_per_s: usize,
    /// Received in all by the time the bench asked for the gateway's counters at the end (what
    /// was on its way then, or sent while the page was asked for, is not in it), and those
    /// counters.
    pub(crate) received: usize,
    pub(crate) counters: Counters,
}

/// What the scenario saw.
pub(crate) struct MqttWindow {
    pub(crate) values: usize,
    pub(crate) publish_interval: Duration,
    pub(crate) without: Side,
    pub(crate) with: Side,
    pub(crate) published: Published,
}

/// The `[mqtt]` table of the gateway publishing to the broker at `url` every `interval`.
fn mqtt_table(url: &str, interval: Duration) -> String {
    format!(
        "[mqtt]\nurl = \"{url}\"\nclient_id = \"modbus-gateway-bench-{}\"\nqos = 1\n\
         retain = true\npublish_interval = \"{}s\"\nhome_assistant = true\n",
        std::process::id(),
        interval.as_secs()
    )
}

/// mosquitto and mosquitto_sub, or why the scenario cannot run.
fn programs() -> Result<PathBuf, String> {
    let missing = "mosquitto and mosquitto_sub are needed (Debian: apt install mosquitto \
                   mosquitto-clients)";
    let broker = Path::new("/usr/sbin/mosquitto").is_file() || tool("mosquitto").is_some();
    match tool("mosquitto_sub") {
        Some(sub) if broker && tool("mosquitto_pub").is_some() => Ok(sub),
        _ => Err(missing.to_owned()),
    }
}

/// Run scenario `s` on the gateway binary at `binary`, its bus on `device`: the gateway
/// without `[mqtt]`, then with it, publishing to a mosquitto started for it.
pub(crate) async fn measure(
    cli: &Cli,
    binary: &Path,
    s: &Scenario,
    device: &str,
) -> Result<MqttWindow, String> {
    let interval = s.publish_interval.ok_or("no publish_interval")?;
    let sub = programs()?;
    let without = side(cli, binary, s, device, None).await?.0;
    let broker = Broker::start()
        .await
        .ok_or("mosquitto did not start: mosquitto, mosquitto_sub and mosquitto_pub are needed")?;
    let subscriber = Subscriber::start(&sub, &broker).await?;
    let publishing = Some((&broker, &subscriber, interval));
    let (with, published) = side(cli, binary, s, device, publishing).await?;
    Ok(MqttWindow {
        values: values(),
        publish_interval: interval,
        without,
        with,
        published: published.ok_or("no MQTT figures")?,
    })
}

/// One gateway: without MQTT, or publishing to `publishing`'s broker (read by its subscriber)
/// every interval; its figures, and what was published.
async fn side(
    cli: &Cli,
    binary: &Path,
    s: &Scenario,
    device: &str,
    publishing: Option<(&Broker, &Subscriber, Duration)>,
) -> Result<(Side, Option<Published>), String> {
    let tables = publishing.map_or_else(String::new, |(broker, _, interval)| {
        mqtt_table(&broker.url(), interval)
    });
    let gateway = Gateway::start_with(binary, s, device, None, &tables).await?;
    let listening = Instant::now();
    let (pid, addr) = (gateway.pid(), gateway.metrics);
    let listed = plant::first_pass(addr).await?;
    let first_pass = listening.elapsed();
    if listed != values() {
        return Err(format!(
            "GET /values lists {listed} values, not {}",
            values()
        ));
    }
    let subscriber = publishing.map(|(_, subscriber, _)| subscriber);
    if let Some(subscriber) = subscriber {
        subscriber.until_complete().await;
    }
    let broker = publishing.and_then(|_| broker_pid());
    let before = scrape(addr).await?;
    let broker_start = broker.map(cpu_time);
    let (start, cpu_start) = (Instant::now(), cpu_time(pid));
    tokio::time::sleep(Duration::from_secs_f64(cli.seconds)).await;
    let (end, cpu_end) = (Instant::now(), cpu_time(pid));
    let broker_cpu = broker.map(cpu_time).zip(broker_start).map(|(e, s)| e - s);
    let after = scrape(addr).await?;
    let rss_polling_mb = rss_mb(pid);
    let conns = beside::connect(gateway.listen, MASTERS).await?;
    let masters = beside::drive_every(cli.seconds, conns, Some(pid), PERIOD).await?;
    let asked = Instant::now();
    let last = scrape(addr).await?;
    let rss_mb = rss_mb(pid);
    let polls = |page: &str| sample(page, "modbus_gateway_polls_total", &[]);
    let side = Side {
        first_pass,
        polling: end - start,
        polling_cpu: cpu_end - cpu_start,
        polls: polls(&after) - polls(&before),
        rss_polling_mb,
        masters,
        rss_mb,
    };
    let Some(subscriber) = subscriber else {
        return Ok((side, None));
    };
    drop(gateway);
    let marks = Marks {
        listening,
        polling: (start, end),
        masters: side.masters.window.unwrap_or((end, end)),
        asked,
    };
    let published = subscriber.with(|a| a.published(&marks, [&before, &after, &last], broker_cpu));
    Ok((side, Some(published)))
}

/// When one gateway's phases began and ended: it listened, the polling window, the masters',
/// and the bench asked for its counters at the end.
struct Marks {
    listening: Instant,
    polling: (Instant, Instant),
    masters: (Instant, Instant),
    asked: Instant,
}

impl Arrivals {
    /// What was published in the phases of `marks`, with the gateway's metrics `pages` before
    /// and after the polling window and at the end, and the broker's CPU time in that window.
    fn published(
        &self,
        marks: &Marks,
        [before, after, last]: [&str; 3],
        broker_cpu: Option<Duration>,
    ) -> Published {
        let since = |at: Instant| at - marks.listening;
        let (start, end) = marks.polling;
        let (again, total, longest) = self.gaps;
        Published {
            first_message: self.times.first().map(|&t| since(t)),
            discovery: self.discovery_done.map(since),
            complete: self.complete.map(|(at, n)| (since(at), n)),
            discovery_messages: self
                .discovery_done
                .zip(self.times.first())
                .map_or(0, |(done, &first)| self.within(first, done)),
            value_topics: self.values.len(),
            discovery_topics: self.discovery.len(),
            availability_topics: self.availability.len(),
            received_polling: self.within(start, end),
            published_polling: Counters::of(after).published - Counters::of(before).published,
            broker_cpu,
            value_gap_mean: (again > 0).then(|| total / u32::try_from(again).unwrap_or(u32::MAX)),
            value_gap_max: (again > 0).then_some(longest),
            received_masters: self.within(marks.masters.0, marks.masters.1),
            peak_per_s: self.peak_per_s(),
            received: self.times.partition_point(|t| *t <= marks.asked),
            counters: Counters::of(last),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_publication_is_complete_with_every_value_config_availability_and_the_status() {
        let mut arrivals = Arrivals::default();
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        arrivals.take(&format!("{PREFIX}/status"), at(0));
        for slave in 1..=SLAVES {
            let node = format!("{DISCOVERY}/sensor/modbus_gateway_bench_{slave}");
            for v in &PLANT_VALUES {
                arrivals.take(&format!("{node}/{}/config", v.name), at(1));
            }
            arrivals.take(&format!("{PREFIX}/bench/{slave}/availability"), at(2));
        }
        assert_eq!(arrivals.discovery_done, Some(at(1)));
        // Every value twice: published again, a value is one topic still.
        for ms in [1500, 2500] {
            for slave in 1..=SLAVES {
                for v in &PLANT_VALUES {
                    arrivals.take(&format!("{PREFIX}/bench/{slave}/{}", v.name), at(ms));
                }
            }
        }
        let (slaves, values) = (usize::from(SLAVES), values());
        let (done, received) = arrivals.complete.expect("complete");
        assert_eq!((done, received), (at(1500), 1 + 2 * values + slaves));
        assert_eq!(arrivals.values.len(), values);
        assert_eq!(arrivals.times.len(), 1 + 3 * values + slaves);
        assert_eq!(arrivals.within(at(1), at(2)), values + slaves);
        assert_eq!(arrivals.within(at(1500), at(2500)), 2 * values);
        let (again, total, longest) = arrivals.gaps;
        assert_eq!(again, values);
        assert_eq!(
            total / u32::try_from(again).unwrap(),
            Duration::from_secs(1)
        );
        assert_eq!(longest, Duration::from_secs(1));
        // The first second has the status, the configs and the availabilities.
        assert_eq!(arrivals.peak_per_s(), 1 + values + slaves);
    }

    #[test]
    fn the_mqtt_table_is_one_the_gateway_accepts() {
        use test_support::{Bus, GatewayConfig};
        let config = GatewayConfig::new()
            .bus(Bus::sim("bench").text(&plant::slaves()))
            .tables(&mqtt_table(
                "mqtt://127.0.0.1:18830",
                Duration::from_secs(10),
            ))
            .load();
        let mqtt = config.mqtt.expect("an [mqtt] table");
        assert_eq!(mqtt.publish_interval, Duration::from_secs(10));
        assert!(mqtt.home_assistant && mqtt.retain && mqtt.qos() == 1);
        assert_eq!(mqtt.topic_prefix, PREFIX);
        assert_eq!(mqtt.discovery_prefix, DISCOVERY);
    }
}
