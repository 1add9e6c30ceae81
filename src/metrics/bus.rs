//! The metrics of one bus and the events of its line that log and count from one call site: a
//! transaction's round trip and retries, a slave's state as `bus::health` reports it, a port
//! opened, lost or failing to open, what went over the line.

use super::labels::{decimal, seconds_since_epoch, Fate, LinkDrop, OTHER};
use super::polls::POLL_OUTCOMES;
use super::{Definer, RequestCounters, BUS_EVENTS};
use crate::config;
use crate::error::{Answer, Outcome, RequestError};
use crate::line::LineCounters;
use crate::master::{Class, Protocol};
use prometheus::core::Collector;
use prometheus::{
    Counter, CounterVec, Gauge, GaugeVec, Histogram, HistogramVec, IntCounter, IntCounterVec,
    IntGauge, IntGaugeVec,
};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::io;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tracing::{debug, info, warn};

/// The families of every bus's series, registry-wide; each bus takes its label values.
pub(super) struct BusFamilies {
    line: LineFamilies,
    pub(super) queue: QueueFamilies,
    port: PortFamilies,
    slave: SlaveFamilies,
}

/// What went over the line: its round trips, busy time and bytes.
pub(super) struct LineFamilies {
    round_trip: HistogramVec,
    busy: CounterVec,
    sent: IntCounterVec,
    received: IntCounterVec,
    discarded_frames: IntCounterVec,
    stray_bytes: IntCounterVec,
}

/// The queue in front of the line, and the line's settings.
pub(super) struct QueueFamilies {
    queue_wait: HistogramVec,
    pub(super) queue_depth: IntGaugeVec,
    info: IntGaugeVec,
    queue_capacity: IntGaugeVec,
}

/// The serial port: open or not, reopens, its adapter's latency timer.
pub(super) struct PortFamilies {
    port_up: IntGaugeVec,
    port_reopens: IntCounterVec,
    port_open_errors: IntCounterVec,
    link_dropped: IntCounterVec,
    link_round_trip: GaugeVec,
    link_budget: GaugeVec,
    latency_timer: GaugeVec,
}

/// Each known slave's series.
pub(super) struct SlaveFamilies {
    retries: IntCounterVec,
    coalesced: IntCounterVec,
    cache_hits: IntCounterVec,
    slave_up: IntGaugeVec,
    slave_last_success: GaugeVec,
    polls: IntCounterVec,
    poll_errors: IntCounterVec,
}

impl LineFamilies {
    fn new(define: &Definer) -> Self {
        let bus = &["bus"];
        LineFamilies {
            round_trip: define.histogram(
                "modbus_gateway_round_trip_seconds",
                "From a request's first frame on the line to its answer or last timeout, retries \
                 included.",
                bus,
            ),
            busy: define.counter(
                "modbus_gateway_line_busy_seconds_total",
                "Time characters were on the line, sent and received; its rate is the line's \
                 utilisation.",
                bus,
            ),
            sent: define.int_counter(
                "modbus_gateway_line_sent_bytes_total",
                "Bytes of the frames the gateway sent on the line.",
                bus,
            ),
            received: define.int_counter(
                "modbus_gateway_line_received_bytes_total",
                "Bytes received from the line: replies, other frames, noise.",
                bus,
            ),
            discarded_frames: define.int_counter(
                "modbus_gateway_discarded_frames_total",
                "Intact frames that answered no request (late replies, other addresses), \
                 discarded.",
                bus,
            ),
            stray_bytes: define.int_counter(
                "modbus_gateway_stray_bytes_total",
                "Bytes received while no reply was awaited, discarded.",
                bus,
            ),
        }
    }
}

impl QueueFamilies {
    fn new(define: &Definer) -> Self {
        let bus = &["bus"];
        QueueFamilies {
            queue_wait: define.histogram(
                "modbus_gateway_queue_wait_seconds",
                "Time requests spent in the bus queue before the line took them, by class \
                 (the masters, the priority masters, the gateway's polls of plant values).",
                &["bus", "class"],
            ),
            queue_depth: define.int_gauge(
                "modbus_gateway_queue_depth",
                "Requests waiting in the bus queue.",
                bus,
            ),
            info: define.int_gauge(
                "modbus_gateway_bus_info",
                "The bus's line: its framing (rtu, ascii, or tcp for a Modbus TCP device), serial \
                 format (none on a Modbus TCP device) and transport (serial, sim, tcp, rfc2217, \
                 tls); always 1.",
                &["bus", "framing", "format", "transport"],
            ),
            queue_capacity: define.int_gauge(
                "modbus_gateway_queue_capacity",
                "Requests the bus queue holds before it answers 0x06 (queue_depth).",
                bus,
            ),
        }
    }
}

impl PortFamilies {
    fn new(define: &Definer) -> Self {
        let bus = &["bus"];
        PortFamilies {
            port_up: define.int_gauge(
                "modbus_gateway_port_up",
                "1 while the bus has its serial port open (or its device server connected), \
                 else 0.",
                bus,
            ),
            port_reopens: define.int_counter(
                "modbus_gateway_port_reopens_total",
                "Times the serial port was opened (or the device server connected) again after \
                 being lost or failing to open.",
                bus,
            ),
            port_open_errors: define.int_counter(
                "modbus_gateway_port_open_errors_total",
                "Attempts to open the serial port (or connect to the device server) that failed.",
                bus,
            ),
            link_dropped: define.int_counter(
                "modbus_gateway_link_dropped_total",
                "A line behind a serial device server: connections the gateway closed itself \
                 because the converter went past a limit, by reason.",
                &["bus", "reason"],
            ),
            link_round_trip: define.gauge(
                "modbus_gateway_link_round_trip_seconds",
                "A line behind a serial device server: the least round trip the kernel has \
                 measured on its connection; no series while it is not connected.",
                bus,
            ),
            link_budget: define.gauge(
                "modbus_gateway_link_budget_seconds",
                "A line behind a serial device server: the time added to every frame's for the \
                 link, which the response timeout counts from; no series while it is not \
                 connected.",
                bus,
            ),
            latency_timer: define.gauge(
                "modbus_gateway_serial_latency_timer_seconds",
                "The USB serial adapter's latency timer, read when the port was opened; no series \
                 if the device has none.",
                bus,
            ),
        }
    }
}

impl SlaveFamilies {
    fn new(define: &Definer) -> Self {
        let bus_slave = &["bus", "slave"];
        SlaveFamilies {
            retries: define.int_counter(
                "modbus_gateway_retries_total",
                "Requests sent again after a failed attempt.",
                bus_slave,
            ),
            coalesced: define.int_counter(
                "modbus_gateway_coalesced_requests_total",
                "Reads answered by another master's identical read, without a transaction of \
                 their own.",
                bus_slave,
            ),
            cache_hits: define.int_counter(
                "modbus_gateway_cache_hits_total",
                "Reads answered from the slave's cache, without touching the line.",
                bus_slave,
            ),
            slave_up: define.int_gauge(
                "modbus_gateway_slave_up",
                "1 if the slave answered its last request (normally or with an exception), else \
                 0.",
                bus_slave,
            ),
            slave_last_success: define.gauge(
                "modbus_gateway_slave_last_success_timestamp_seconds",
                "Unix time of the slave's last answer (normal or exception); 0 if none yet.",
                bus_slave,
            ),
            polls: define.int_counter(
                "modbus_gateway_polls_total",
                "Reads the gateway sent of its own to poll the slave's plant values.",
                bus_slave,
            ),
            poll_errors: define.int_counter(
                "modbus_gateway_poll_errors_total",
                "Polls of plant values that failed, by outcome; their values are not exported \
                 until a poll is good again.",
                &["bus", "slave", "outcome"],
            ),
        }
    }
}

impl BusFamilies {
    pub(super) fn new(define: &Definer) -> Self {
        BusFamilies {
            line: LineFamilies::new(define),
            queue: QueueFamilies::new(define),
            port: PortFamilies::new(define),
            slave: SlaveFamilies::new(define),
        }
    }

    /// The metrics of one bus, with its series and those of its known slaves at zero from now
    /// on.
    pub(super) fn of(&self, settings: &config::Bus, counters: RequestCounters) -> BusMetrics {
        let name = settings.name.as_str();
        let labels = &[name];
        self.queue.queue_depth.with_label_values(labels).set(0);
        let metrics = BusMetrics {
            name: name.into(),
            info: self.queue.info.clone(),
            info_labels: Mutex::new(None),
            queue_capacity: self.queue.queue_capacity.with_label_values(labels),
            char_time: settings.line_timing().char_time.as_secs_f64(),
            counters,
            round_trip: self.line.round_trip.with_label_values(labels),
            queue_wait: Class::ALL.map(|class| {
                self.queue
                    .queue_wait
                    .with_label_values(&[name, class.label()])
            }),
            busy: self.line.busy.with_label_values(labels),
            sent: self.line.sent.with_label_values(labels),
            received: self.line.received.with_label_values(labels),
            discarded_frames: self.line.discarded_frames.with_label_values(labels),
            stray_bytes: self.line.stray_bytes.with_label_values(labels),
            port_up: self.port.port_up.with_label_values(labels),
            port_reopens: self.port.port_reopens.with_label_values(labels),
            port_open_errors: self.port.port_open_errors.with_label_values(labels),
            link_dropped: self.port.link_dropped.clone(),
            latency_timer: self.port.latency_timer.clone(),
            link_round_trip: self.port.link_round_trip.clone(),
            link_budget: self.port.link_budget.clone(),
            link: Mutex::new(None),
            network: AtomicBool::new(false),
            retries: self.slave.retries.clone(),
            coalesced: self.slave.coalesced.clone(),
            cache_hits: self.slave.cache_hits.clone(),
            slave_up: self.slave.slave_up.clone(),
            slave_last_success: self.slave.slave_last_success.clone(),
            polls: self.slave.polls.clone(),
            poll_errors: self.slave.poll_errors.clone(),
            slaves: BusMetrics::no_slaves(),
        };
        metrics.reconfigured(settings);
        metrics
    }

    /// Remove the series of `bus`, gone, but its requests' and exceptions' counts.
    pub(super) fn forget(&self, bus: &BusMetrics) {
        let labels = &[&*bus.name];
        bus.set_info(None);
        for vec in [
            &self.queue.queue_depth,
            &self.queue.queue_capacity,
            &self.port.port_up,
        ] {
            let _ = vec.remove_label_values(labels);
        }
        for vec in [
            &self.line.sent,
            &self.line.received,
            &self.line.discarded_frames,
            &self.line.stray_bytes,
            &self.port.port_reopens,
            &self.port.port_open_errors,
        ] {
            let _ = vec.remove_label_values(labels);
        }
        let _ = self.line.busy.remove_label_values(labels);
        let _ = self.port.latency_timer.remove_label_values(labels);
        let _ = self.port.link_round_trip.remove_label_values(labels);
        let _ = self.port.link_budget.remove_label_values(labels);
        for reason in LinkDrop::ALL {
            let labels = &[&*bus.name, reason.label()];
            let _ = self.port.link_dropped.remove_label_values(labels);
        }
        let _ = self.line.round_trip.remove_label_values(labels);
        for class in Class::ALL {
            let _ = self
                .queue
                .queue_wait
                .remove_label_values(&[&*bus.name, class.label()]);
        }
        for address in bus.known_slaves() {
            let labels = &[&*bus.name, decimal(address)];
            let _ = self.slave.slave_up.remove_label_values(labels);
            let _ = self.slave.slave_last_success.remove_label_values(labels);
            for vec in [
                &self.slave.retries,
                &self.slave.coalesced,
                &self.slave.cache_hits,
                &self.slave.polls,
            ] {
                let _ = vec.remove_label_values(labels);
            }
            for outcome in POLL_OUTCOMES {
                let labels = &[&*bus.name, decimal(address), outcome];
                let _ = self.slave.poll_errors.remove_label_values(labels);
            }
        }
    }
}

/// Round trips kept per slave for the status page's median.
const RECENT_ROUND_TRIPS: usize = 32;

/// A slave's own series, and its last round trips.
pub(super) struct SlaveMetrics {
    up: IntGauge,
    last_success: Gauge,
    retries: IntCounter,
    coalesced: IntCounter,
    cache_hits: IntCounter,
    round_trips: Mutex<VecDeque<Duration>>,
    /// The gateway's polls of its plant values, for the status page.
    pub(super) polls: AtomicU64,
}

/// What the status page shows of a slave, as its metrics have it.
pub struct SlaveSnapshot {
    pub address: u8,
    pub up: bool,
    /// Its last answer, normal or exception.
    pub last_answer: Option<SystemTime>,
    pub(crate) round_trip_p50: Option<Duration>,
    /// Its requests by outcome label.
    pub requests: BTreeMap<String, u64>,
    /// The gateway's own polls of its plant values.
    pub polls: u64,
}

/// A device server's connection, as the status page shows it.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkSnapshot {
    /// The address connected to.
    pub peer: String,
    /// What the gateway adds to each frame's time for the link.
    pub budget: Duration,
    /// The least round trip the kernel has measured, if it did.
    pub round_trip: Option<Duration>,
}

/// The metrics of one bus, label values resolved once. Shared by its handle and its task.
pub struct BusMetrics {
    pub(super) name: Arc<str>,
    pub(super) info: IntGaugeVec,
    /// The framing, format and transport labels of the bus's info series, to remove when they
    /// change.
    pub(super) info_labels: Mutex<Option<[String; 3]>>,
    pub(super) queue_capacity: IntGauge,
    /// Seconds per character on the line, to turn bytes into busy time.
    pub(super) char_time: f64,
    pub(super) counters: RequestCounters,
    pub(super) round_trip: Histogram,
    /// Per class, in the order of [`Class::ALL`].
    pub(super) queue_wait: [Histogram; 3],
    pub(super) busy: Counter,
    pub(super) sent: IntCounter,
    pub(super) received: IntCounter,
    pub(super) discarded_frames: IntCounter,
    pub(super) stray_bytes: IntCounter,
    pub(super) port_up: IntGauge,
    pub(super) port_reopens: IntCounter,
    pub(super) port_open_errors: IntCounter,
    pub(super) link_dropped: IntCounterVec,
    pub(super) latency_timer: GaugeVec,
    pub(super) link_round_trip: GaugeVec,
    pub(super) link_budget: GaugeVec,
    /// The device server's connection as last reported, for the status page.
    pub(super) link: Mutex<Option<LinkSnapshot>>,
    /// The line is behind a device server: its port events are told as connections.
    pub(super) network: AtomicBool,
    pub(super) retries: IntCounterVec,
    pub(super) coalesced: IntCounterVec,
    pub(super) cache_hits: IntCounterVec,
    pub(super) slave_up: IntGaugeVec,
    pub(super) slave_last_success: GaugeVec,
    pub(super) polls: IntCounterVec,
    pub(super) poll_errors: IntCounterVec,
    pub(super) slaves: Box<[OnceLock<SlaveMetrics>; 256]>,
}

impl BusMetrics {
    /// No slave's series made yet.
    pub(super) fn no_slaves() -> Box<[OnceLock<SlaveMetrics>; 256]> {
        Box::new(std::array::from_fn(|_| OnceLock::new()))
    }

    /// The addresses whose series have been made: the known slaves.
    pub(super) fn known_slaves(&self) -> impl Iterator<Item = u8> + '_ {
        (0..=u8::MAX).filter(|a| self.is_known(*a))
    }

    /// A slave is known once it is configured (`[[bus.slave]]`, simulated) or has answered: only
    /// known slaves have series of their own and their address as a label value, so a master
    /// asking every unit id makes no series for the addresses where nobody answers.
    fn is_known(&self, address: u8) -> bool {
        self.slaves[usize::from(address)].get().is_some()
    }

    /// The `slave` label of requests to `address`: the address of a known slave or of the
    /// broadcast, else `other`.
    fn slave_label(&self, address: u8) -> &'static str {
        if address == crate::line::BROADCAST || self.is_known(address) {
            decimal(address)
        } else {
            OTHER
        }
    }

    /// The series of `address` if it is a known slave.
    pub(super) fn known(&self, address: u8) -> Option<&SlaveMetrics> {
        self.slaves[usize::from(address)].get()
    }

    /// The series of `address`, made now if it was not known.
    fn slave(&self, address: u8) -> &SlaveMetrics {
        self.slaves[usize::from(address)].get_or_init(|| {
            let labels = &[&*self.name, decimal(address)];
            let slave = SlaveMetrics {
                up: self.slave_up.with_label_values(labels),
                last_success: self.slave_last_success.with_label_values(labels),
                retries: self.retries.with_label_values(labels),
                coalesced: self.coalesced.with_label_values(labels),
                cache_hits: self.cache_hits.with_label_values(labels),
                round_trips: Mutex::new(VecDeque::with_capacity(RECENT_ROUND_TRIPS)),
                polls: AtomicU64::new(0),
            };
            slave.up.set(0);
            slave
        })
    }

    /// The bus's settings, at start or after a reload: its queue capacity, and series at zero for
    /// its known slaves (`[[bus.slave]]` and simulated ones).
    pub fn reconfigured(&self, settings: &config::Bus) {
        let transport = settings.transport();
        self.network
            .store(transport.is_network(), Ordering::Relaxed);
        for reason in LinkDrop::ALL
            .into_iter()
            .filter(|r| r.transport() == transport)
        {
            self.link_dropped
                .with_label_values(&[&*self.name, reason.label()]);
        }
        self.set_info(Some([
            settings.framing.name().to_owned(),
            settings.format_label(),
            transport.label().to_owned(),
        ]));
        self.queue_capacity
            .set(i64::try_from(settings.queue_depth).unwrap_or(i64::MAX));
        let sim_slaves = settings.sim_slave.iter().flat_map(|s| s.address.iter());
        for address in settings.slave.iter().map(|s| s.address).chain(sim_slaves) {
            self.slave(address);
        }
    }

    /// Replace the bus's info series with one of `labels` (framing, format, transport), or none.
    fn set_info(&self, labels: Option<[String; 3]>) {
        let mut current = self
            .info_labels
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if *current == labels {
            return;
        }
        if let Some([framing, format, transport]) = current.take() {
            let _ = self
                .info
                .remove_label_values(&[&*self.name, &framing, &format, &transport]);
        }
        if let Some([framing, format, transport]) = &labels {
            self.info
                .with_label_values(&[&*self.name, framing, format, transport])
                .set(1);
        }
        *current = labels;
    }

    /// Count a request's outcome; `None` if it was dropped unsent because its master left.
    pub fn request(&self, slave: u8, function: u8, protocol: Protocol, outcome: Option<&Outcome>) {
        let slave = self.slave_label(slave);
        self.counters
            .count(&self.name, slave, function, protocol, outcome);
    }

    /// The line took a request after it waited `wait` in the queue; `priority` if it came from
    /// a master in `server.priority`.
    pub(crate) fn dequeued(&self, wait: Duration, class: Class) {
        self.queue_wait[class.index()].observe(wait.as_secs_f64());
    }

    /// A read to `slave` joined another master's identical one.
    pub fn coalesced(&self, slave: u8) {
        if let Some(slave) = self.known(slave) {
            slave.coalesced.inc();
        }
    }

    /// A read to `slave` was answered from its cache.
    pub(crate) fn cache_hit(&self, slave: u8) {
        if let Some(slave) = self.known(slave) {
            slave.cache_hits.inc();
        }
    }

    /// The line ran a request to `slave`: its round trip (`None` if it never got on the wire),
    /// how many attempts it took, and how it ended.
    pub fn transaction(
        &self,
        slave: u8,
        attempts: u32,
        round_trip: Option<Duration>,
        outcome: &Outcome,
    ) {
        if let Some(round_trip) = round_trip {
            self.round_trip.observe(round_trip.as_secs_f64());
        }
        // An answer makes the slave known; a request nobody answered makes no series.
        let answered = matches!(outcome, Ok(Answer::Reply(_) | Answer::Malformed(_)));
        let metrics = if answered {
            self.slave(slave)
        } else {
            match self.known(slave) {
                Some(metrics) => metrics,
                None => return,
            }
        };
        if let Some(round_trip) = round_trip {
            let mut recent = metrics
                .round_trips
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            if recent.len() == RECENT_ROUND_TRIPS {
                recent.pop_front();
            }
            recent.push_back(round_trip);
        }
        metrics
            .retries
            .inc_by(u64::from(attempts.saturating_sub(1)));
        if answered {
            metrics.last_success.set(seconds_since_epoch());
        }
    }

    /// `slave` answered validly, for the first time or `again` after failing or being down
    /// (`bus::health` decides).
    pub(crate) fn slave_answering(&self, slave: u8, again: bool) {
        self.slave(slave).up.set(1);
        if again {
            info!(target: BUS_EVENTS, bus = &*self.name, slave, "slave answering again");
        }
    }

    /// `slave` stopped giving valid replies with the transaction that ended in `outcome`.
    /// Logged at warn for a known slave; an address nobody has answered at is only a master's
    /// guess, logged at debug.
    pub(crate) fn slave_failing(&self, slave: u8, outcome: &Outcome) {
        let bus = &*self.name;
        let label = Fate::of(outcome).0.label();
        let Some(metrics) = self.known(slave) else {
            debug!(target: BUS_EVENTS, bus, slave, outcome = label, "no valid reply at an address no slave has answered at");
            return;
        };
        metrics.up.set(0);
        if let Err(error @ RequestError::NoResponse { attempts, .. }) = outcome {
            warn!(target: BUS_EVENTS, bus, slave, attempts, outcome = label, %error, "slave gives no valid reply");
        }
    }

    /// `slave` timed out `timeouts` times in a row: its requests are answered 0x0B unsent (and
    /// counted `slave_down`) but for one probe per `probe_interval`. Logged at warn for a known
    /// slave, at debug for an address nobody has answered at.
    pub(crate) fn slave_down(&self, slave: u8, timeouts: u32, probe_interval: Duration) {
        let bus = &*self.name;
        let probe_interval = humantime::format_duration(probe_interval).to_string();
        let Some(metrics) = self.known(slave) else {
            debug!(target: BUS_EVENTS, bus, slave, timeouts, probe_interval, "no slave answers at this address; answering 0x0B without sending, probing once per interval");
            return;
        };
        metrics.up.set(0);
        warn!(target: BUS_EVENTS, bus, slave, timeouts, probe_interval, "slave down; answering 0x0B without sending, probing once per interval");
    }

    /// Seconds characters were on the line since the bus started.
    pub(crate) fn busy_seconds(&self) -> f64 {
        self.busy.get()
    }

    /// Transactions on the line since the bus started.
    pub fn transactions(&self) -> u64 {
        self.round_trip.get_sample_count()
    }

    /// Every known slave (configured, simulated, or that has answered), by address, as its series and
    /// recent round trips have it.
    pub fn slaves(&self) -> Vec<SlaveSnapshot> {
        let mut requests = self.requests_by_slave();
        self.known_slaves()
            .filter_map(|address| {
                let slave = self.slaves[usize::from(address)].get()?;
                let last = slave.last_success.get();
                let round_trips = slave
                    .round_trips
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner);
                Some(SlaveSnapshot {
                    address,
                    up: slave.up.get() == 1,
                    last_answer: (last > 0.0).then(|| UNIX_EPOCH + Duration::from_secs_f64(last)),
                    round_trip_p50: super::median::median(round_trips.iter().copied()),
                    requests: requests.remove(&address).unwrap_or_default(),
                    polls: slave.polls.load(Ordering::Relaxed),
                })
            })
            .collect()
    }

    /// This bus's request counts by slave and outcome, summed over functions and protocols.
    fn requests_by_slave(&self) -> HashMap<u8, BTreeMap<String, u64>> {
        let mut by_slave: HashMap<u8, BTreeMap<String, u64>> = HashMap::new();
        for family in self.counters.requests.collect() {
            for metric in family.get_metric() {
                let label = |name: &str| {
                    metric
                        .get_label()
                        .iter()
                        .find(|pair| pair.name() == name)
                        .map(|pair| pair.value())
                };
                if label("bus") != Some(&*self.name) {
                    continue;
                }
                let (Some(Ok(slave)), Some(outcome)) =
                    (label("slave").map(str::parse::<u8>), label("outcome"))
                else {
                    continue;
                };
                // Counters hold whole numbers.
                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                let count = metric.get_counter().get_value() as u64;
                *by_slave
                    .entry(slave)
                    .or_default()
                    .entry(outcome.to_owned())
                    .or_default() += count;
            }
        }
        by_slave
    }

    /// What went over the line since the last call.
    pub fn line(&self, traffic: &LineCounters) {
        self.sent.inc_by(traffic.sent_bytes);
        self.received.inc_by(traffic.received_bytes);
        self.discarded_frames.inc_by(traffic.foreign_frames);
        self.stray_bytes.inc_by(traffic.stray_bytes);
        let characters = traffic.sent_bytes + traffic.received_bytes;
        self.busy.inc_by(characters as f64 * self.char_time);
    }

    pub(super) fn is_network(&self) -> bool {
        self.network.load(Ordering::Relaxed)
    }

    /// The device server's connection now (`None`: not connected): its series and the status
    /// page's figures. Cheap when nothing changed, as after most transactions.
    pub(crate) fn link(&self, now: Option<(&str, Duration, Option<Duration>)>) {
        let mut link = self.link.lock().unwrap_or_else(PoisonError::into_inner);
        let was = link
            .as_ref()
            .map(|l| (l.peer.as_str(), l.budget, l.round_trip));
        if was == now {
            return;
        }
        let now = now.map(|(peer, budget, round_trip)| LinkSnapshot {
            peer: peer.to_owned(),
            budget,
            round_trip,
        });
        let labels = &[&*self.name];
        match &now {
            Some(snapshot) => {
                self.link_budget
                    .with_label_values(labels)
                    .set(snapshot.budget.as_secs_f64());
                match snapshot.round_trip {
                    Some(rtt) => self
                        .link_round_trip
                        .with_label_values(labels)
                        .set(rtt.as_secs_f64()),
                    None => {
                        let _ = self.link_round_trip.remove_label_values(labels);
                    }
                }
            }
            None => {
                let _ = self.link_budget.remove_label_values(labels);
                let _ = self.link_round_trip.remove_label_values(labels);
            }
        }
        *link = now;
    }

    /// The device server's connection as last reported, if connected.
    pub fn link_snapshot(&self) -> Option<LinkSnapshot> {
        self.link
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// The USB adapter's latency timer as the port's open found (and maybe set) it, with the
    /// sysfs file it is read from, or `None` if the device has none; `refused` is why setting
    /// the configured value failed. `key` is the bus's (`bus[0]`).
    pub fn latency_timer(
        &self,
        device: &str,
        key: &str,
        timer: Option<(Duration, &std::path::Path)>,
        refused: Option<&io::Error>,
    ) {
        let bus = &*self.name;
        let Some((value, file)) = timer else {
            let _ = self.latency_timer.remove_label_values(&[bus]);
            return;
        };
        let latency_timer_ms = value.as_millis();
        let file = file.display().to_string();
        match refused {
            None => {
                info!(target: BUS_EVENTS, bus, device, latency_timer_ms, file, "USB adapter latency timer");
            }
            Some(error) => {
                warn!(target: BUS_EVENTS, bus, device, latency_timer_ms, file, %error, "cannot set {key}.latency_timer; the adapter keeps its timer (see docs/rs485.md for a udev rule)");
            }
        }
        self.latency_timer
            .with_label_values(&[bus])
            .set(value.as_secs_f64());
    }
}

#[cfg(test)]
mod latency_tests {
    use crate::metrics::Metrics;
    use std::path::Path;
    use std::time::Duration;

    const SERIES: &str = "modbus_gateway_serial_latency_timer_seconds{bus=\"line1\"}";

    fn sample(metrics: &Metrics) -> Option<f64> {
        crate::metrics::sample(&metrics.render().unwrap(), SERIES)
    }

    #[test]
    fn the_latency_timer_found_at_open_is_exported_in_seconds_and_dropped_when_there_is_none() {
        let metrics = Metrics::new();
        let settings =
            crate::Config::from_toml_str("[[bus]]\nname = \"line1\"\ndevice = \"/dev/ttyUSB0\"\n")
                .unwrap()
                .bus
                .remove(0);
        let bus = metrics.bus(&settings);
        assert_eq!(sample(&metrics), None, "unknown until the port opens");
        let file = Path::new("/sys/bus/usb-serial/devices/ttyUSB0/latency_timer");
        let timer = (Duration::from_millis(16), file);
        bus.latency_timer("/dev/ttyUSB0", "bus[0]", Some(timer), None);
        assert_eq!(sample(&metrics), Some(0.016));
        bus.latency_timer("/dev/ttyUSB0", "bus[0]", None, None);
        assert_eq!(sample(&metrics), None);
    }
}
