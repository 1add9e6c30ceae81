//! What the gateway counts, as `modbus_gateway_*` Prometheus metrics, and the notable events that
//! both log and count from one call site: a request's outcome, a slave going silent or coming
//! back, a port lost or reopened, a connection refused or closed. Labels are bounded (bus, slave
//! address, function code, outcome, exception code, reason), never a peer address. [`http`] serves
//! the text format and the health endpoints. Callers say what happened; this module knows nothing
//! of frames, sockets or timing.

mod bus;
pub mod http;
mod labels;
mod tcp;

pub use bus::BusMetrics;
pub use labels::{Closing, ExceptionSource, Fate, Rejection};

use labels::{decimal, hex};
pub use tcp::TcpMetrics;

use crate::config;
use crate::error::{Answer, Outcome};
use prometheus::{
    CounterVec, GaugeVec, HistogramOpts, HistogramVec, IntCounterVec, IntGauge, IntGaugeVec, Opts,
    Registry, TextEncoder,
};
use std::sync::{Arc, Mutex, PoisonError};
use tracing::debug;

/// Log targets of the events counted here: named after where they happen, not after this module.
const BUS_EVENTS: &str = "modbus_gateway::bus";
const TCP_EVENTS: &str = "modbus_gateway::tcp";

/// Histogram buckets in seconds, for round trips and queue waits alike: from one short exchange
/// at 115200 baud (about 1 ms) to a slow drive's timeout.
const BUCKETS: &[f64] = &[
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// Registers metrics as they are defined. Definitions are constants of this module, so a
/// failure is a bug caught by its tests, never a runtime condition.
struct Definer<'a>(&'a Registry);

impl Definer<'_> {
    fn register<M: prometheus::core::Collector + Clone + 'static>(&self, metric: M) -> M {
        self.0
            .register(Box::new(metric.clone()))
            .expect("metric definitions are unique and well-formed");
        metric
    }

    fn int_counter(&self, name: &str, help: &str, labels: &[&str]) -> IntCounterVec {
        self.register(IntCounterVec::new(Opts::new(name, help), labels).expect("valid counter"))
    }

    fn counter(&self, name: &str, help: &str, labels: &[&str]) -> CounterVec {
        self.register(CounterVec::new(Opts::new(name, help), labels).expect("valid counter"))
    }

    fn int_gauge(&self, name: &str, help: &str, labels: &[&str]) -> IntGaugeVec {
        self.register(IntGaugeVec::new(Opts::new(name, help), labels).expect("valid gauge"))
    }

    fn gauge(&self, name: &str, help: &str, labels: &[&str]) -> GaugeVec {
        self.register(GaugeVec::new(Opts::new(name, help), labels).expect("valid gauge"))
    }

    fn histogram(&self, name: &str, help: &str, labels: &[&str]) -> HistogramVec {
        let opts = HistogramOpts::new(name, help).buckets(BUCKETS.to_vec());
        self.register(HistogramVec::new(opts, labels).expect("valid histogram"))
    }
}

/// Requests and exceptions, counted from wherever a request's fate is decided.
#[derive(Clone)]
struct RequestCounters {
    requests: IntCounterVec,
    exceptions: IntCounterVec,
}

impl RequestCounters {
    /// `outcome` is `None` for a request dropped unsent because its master left. Every outcome
    /// but an answer is also logged at debug level, under the same name as its label.
    fn count(&self, bus: &str, slave: u8, function: u8, outcome: Option<&Outcome>) {
        let (fate, exception) = outcome.map_or((Fate::Dropped, None), Fate::of);
        let label = fate.label();
        self.requests
            .with_label_values(&[bus, decimal(slave), hex(function), label])
            .inc();
        let function = hex(function);
        match outcome {
            Some(Ok(Answer::Malformed(pdu))) => {
                debug!(target: BUS_EVENTS, bus, slave, function, outcome = label, len = pdu.len(), "reply does not fit the request; forwarded as the slave sent it");
            }
            Some(Err(error)) => {
                debug!(target: BUS_EVENTS, bus, slave, function, outcome = label, %error, "request answered by the gateway");
            }
            None => {
                debug!(target: BUS_EVENTS, bus, slave, function, outcome = label, "request dropped: its master left")
            }
            Some(Ok(_)) => {}
        }
        if let Some((source, code)) = exception {
            self.exceptions
                .with_label_values(&[bus, decimal(slave), source.label(), hex(code)])
                .inc();
        }
    }
}

type ScrapeHook = Box<dyn Fn() + Send + Sync>;

/// Every metric of one gateway, in its own registry.
pub struct Metrics {
    registry: Registry,
    counters: RequestCounters,
    round_trip: HistogramVec,
    queue_wait: HistogramVec,
    queue_depth: IntGaugeVec,
    queue_capacity: IntGaugeVec,
    busy: CounterVec,
    sent: IntCounterVec,
    received: IntCounterVec,
    discarded_frames: IntCounterVec,
    stray_bytes: IntCounterVec,
    retries: IntCounterVec,
    slave_up: IntGaugeVec,
    slave_last_success: GaugeVec,
    port_up: IntGaugeVec,
    port_reopens: IntCounterVec,
    port_open_errors: IntCounterVec,
    pub tcp: TcpMetrics,
    /// Gauges read from their source at scrape time (queue depths).
    scrape_hooks: Mutex<Vec<ScrapeHook>>,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let registry = Registry::new();
        let define = Definer(&registry);
        let bus = &["bus"];
        let bus_slave = &["bus", "slave"];
        let metrics = Metrics {
            counters: RequestCounters {
                requests: define.int_counter(
                    "modbus_gateway_requests_total",
                    "Modbus TCP requests by bus, slave address, function code and outcome.",
                    &["bus", "slave", "function", "outcome"],
                ),
                exceptions: define.int_counter(
                    "modbus_gateway_exceptions_total",
                    "Exception replies by code, made by the slave or by the gateway.",
                    &["bus", "slave", "source", "code"],
                ),
            },
            round_trip: define.histogram(
                "modbus_gateway_round_trip_seconds",
                "From a request's first frame on the line to its answer or last timeout, retries \
                 included.",
                bus,
            ),
            queue_wait: define.histogram(
                "modbus_gateway_queue_wait_seconds",
                "Time requests spent in the bus queue before the line took them.",
                bus,
            ),
            queue_depth: define.int_gauge(
                "modbus_gateway_queue_depth",
                "Requests waiting in the bus queue.",
                bus,
            ),
            queue_capacity: define.int_gauge(
                "modbus_gateway_queue_capacity",
                "Requests the bus queue holds before it answers 0x06 (queue_depth).",
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
            retries: define.int_counter(
                "modbus_gateway_retries_total",
                "Requests sent again after a failed attempt.",
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
            port_up: define.int_gauge(
                "modbus_gateway_port_up",
                "1 while the bus has its serial port open, else 0.",
                bus,
            ),
            port_reopens: define.int_counter(
                "modbus_gateway_port_reopens_total",
                "Times the serial port was opened again after being lost or failing to open.",
                bus,
            ),
            port_open_errors: define.int_counter(
                "modbus_gateway_port_open_errors_total",
                "Attempts to open the serial port that failed.",
                bus,
            ),
            tcp: TcpMetrics::new(&define),
            scrape_hooks: Mutex::new(Vec::new()),
            registry: registry.clone(),
        };
        define
            .int_gauge(
                "modbus_gateway_build_info",
                "The running build; always 1.",
                &["version"],
            )
            .with_label_values(&[env!("CARGO_PKG_VERSION")])
            .set(1);
        metrics
    }

    /// The metrics of one bus, with its series and those of its known slaves (`[[bus.slave]]`
    /// and simulated ones) at zero from now on.
    pub fn bus(&self, settings: &config::Bus) -> Arc<BusMetrics> {
        let name = settings.name.as_str();
        let labels = &[name];
        self.queue_depth.with_label_values(labels).set(0);
        let metrics = BusMetrics {
            name: name.into(),
            queue_capacity: self.queue_capacity.with_label_values(labels),
            char_time: settings.line_timing().char_time.as_secs_f64(),
            counters: self.counters.clone(),
            round_trip: self.round_trip.with_label_values(labels),
            queue_wait: self.queue_wait.with_label_values(labels),
            busy: self.busy.with_label_values(labels),
            sent: self.sent.with_label_values(labels),
            received: self.received.with_label_values(labels),
            discarded_frames: self.discarded_frames.with_label_values(labels),
            stray_bytes: self.stray_bytes.with_label_values(labels),
            port_up: self.port_up.with_label_values(labels),
            port_reopens: self.port_reopens.with_label_values(labels),
            port_open_errors: self.port_open_errors.with_label_values(labels),
            retries: self.retries.clone(),
            slave_up: self.slave_up.clone(),
            slave_last_success: self.slave_last_success.clone(),
            slaves: BusMetrics::no_slaves(),
        };
        metrics.reconfigured(settings);
        Arc::new(metrics)
    }

    /// Remove the series of a bus that is gone, so that none of them (its port down, say)
    /// outlives it. Request and exception counters of past traffic stay.
    pub fn forget_bus(&self, bus: &BusMetrics) {
        let labels = &[&*bus.name];
        for vec in [&self.queue_depth, &self.queue_capacity, &self.port_up] {
            let _ = vec.remove_label_values(labels);
        }
        for vec in [
            &self.sent,
            &self.received,
            &self.discarded_frames,
            &self.stray_bytes,
            &self.port_reopens,
            &self.port_open_errors,
        ] {
            let _ = vec.remove_label_values(labels);
        }
        let _ = self.busy.remove_label_values(labels);
        let _ = self.round_trip.remove_label_values(labels);
        let _ = self.queue_wait.remove_label_values(labels);
        for address in bus.known_slaves() {
            let labels = &[&*bus.name, decimal(address)];
            let _ = self.slave_up.remove_label_values(labels);
            let _ = self.slave_last_success.remove_label_values(labels);
            let _ = self.retries.remove_label_values(labels);
        }
    }

    /// The gauge of bus `name`'s queue depth, to be set by `hook` at every scrape.
    pub fn queue_depth(&self, name: &str) -> IntGauge {
        self.queue_depth.with_label_values(&[name])
    }

    /// Run `hook` before every scrape, to read a gauge from its source.
    pub fn on_scrape(&self, hook: impl Fn() + Send + Sync + 'static) {
        self.scrape_hooks
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(Box::new(hook));
    }

    /// Count a request the gateway answered without a bus (no route, a refused function code).
    /// `bus` is empty when the unit has no route; `slave` is then the unit id.
    pub fn request(&self, bus: &str, slave: u8, function: u8, outcome: &Outcome) {
        self.counters.count(bus, slave, function, Some(outcome));
    }

    /// Every metric in the Prometheus text format.
    pub fn render(&self) -> Result<String, prometheus::Error> {
        for hook in self
            .scrape_hooks
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .iter()
        {
            hook();
        }
        TextEncoder::new().encode_to_string(&self.registry.gather())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::RequestError;
    use crate::line::{LineCounters, TxError};
    use std::sync::atomic::Ordering;
    use std::time::Duration;

    fn bus(extra: &str) -> config::Bus {
        let text = format!("[[bus]]\nname = \"line1\"\ndevice = \"sim\"\nbaud = 9600\n{extra}");
        crate::Config::from_toml_str(&text).unwrap().bus.remove(0)
    }

    /// The value of the series `name{labels}` in `text`, if present.
    fn value(text: &str, series: &str) -> Option<f64> {
        text.lines()
            .find_map(|line| line.strip_prefix(series)?.strip_prefix(' '))
            .map(|v| v.parse().unwrap())
    }

    #[test]
    fn every_definition_registers_and_renders() {
        let metrics = Metrics::new();
        let text = metrics.render().unwrap();
        assert_eq!(
            value(&text, "modbus_gateway_build_info{version=\"0.1.0\"}"),
            Some(1.0)
        );
        assert_eq!(value(&text, "modbus_gateway_tcp_connections"), Some(0.0));
    }

    #[test]
    fn a_bus_and_its_known_slaves_have_series_at_zero_from_the_start() {
        let metrics = Metrics::new();
        let _bus = metrics.bus(&bus(
            "queue_depth = 64\n[[bus.slave]]\naddress = 9\n[[bus.sim_slave]]\naddress = \"1-2\"\n",
        ));
        let text = metrics.render().unwrap();
        for series in [
            "modbus_gateway_port_up{bus=\"line1\"}",
            "modbus_gateway_queue_depth{bus=\"line1\"}",
            "modbus_gateway_line_busy_seconds_total{bus=\"line1\"}",
            "modbus_gateway_round_trip_seconds_count{bus=\"line1\"}",
            "modbus_gateway_queue_wait_seconds_count{bus=\"line1\"}",
            "modbus_gateway_port_reopens_total{bus=\"line1\"}",
            "modbus_gateway_slave_up{bus=\"line1\",slave=\"1\"}",
            "modbus_gateway_slave_up{bus=\"line1\",slave=\"2\"}",
            "modbus_gateway_slave_up{bus=\"line1\",slave=\"9\"}",
            "modbus_gateway_slave_last_success_timestamp_seconds{bus=\"line1\",slave=\"9\"}",
            "modbus_gateway_retries_total{bus=\"line1\",slave=\"9\"}",
        ] {
            assert_eq!(value(&text, series), Some(0.0), "{series}");
        }
        assert_eq!(
            value(&text, "modbus_gateway_queue_capacity{bus=\"line1\"}"),
            Some(64.0)
        );
        assert_eq!(
            value(&text, "modbus_gateway_slave_up{bus=\"line1\",slave=\"3\"}"),
            None
        );
    }

    #[test]
    fn outcomes_map_to_their_label_and_exception_source() {
        let slave_exception: Outcome = Ok(Answer::Reply(vec![0x83, 0x02]));
        assert_eq!(
            Fate::of(&slave_exception),
            (Fate::Exception, Some((ExceptionSource::Slave, 0x02)))
        );
        assert_eq!(
            Fate::of(&Ok(Answer::Reply(vec![0x03, 0x02, 0, 1]))),
            (Fate::Ok, None)
        );
        assert_eq!(Fate::of(&Ok(Answer::Nothing)), (Fate::Ok, None));
        let timeout: Outcome = Err(RequestError::NoResponse {
            attempts: 2,
            last: TxError::Timeout,
        });
        assert_eq!(
            Fate::of(&timeout),
            (Fate::Timeout, Some((ExceptionSource::Gateway, 0x0B)))
        );
        let crc: Outcome = Err(RequestError::NoResponse {
            attempts: 1,
            last: TxError::Crc,
        });
        assert_eq!(Fate::of(&crc).0, Fate::CrcError);
        assert_eq!(
            Fate::of(&Err(RequestError::NoRoute(250))),
            (Fate::NoRoute, Some((ExceptionSource::Gateway, 0x0A)))
        );
        assert_eq!(
            Fate::of(&Err(RequestError::Expired)),
            (Fate::Expired, Some((ExceptionSource::Gateway, 0x06)))
        );
        assert_eq!(
            Fate::of(&Err(RequestError::NotBroadcastable(3))),
            (Fate::Refused, Some((ExceptionSource::Gateway, 0x01)))
        );
    }

    #[test]
    fn a_request_counts_once_by_outcome_and_its_exception_by_source() {
        let metrics = Metrics::new();
        let line1 = metrics.bus(&bus(""));
        line1.request(7, 0x03, Some(&Ok(Answer::Reply(vec![0x83, 0x02]))));
        line1.request(7, 0x03, Some(&Ok(Answer::Reply(vec![0x83, 0x02]))));
        line1.request(7, 0x10, None);
        metrics.request("", 250, 0x03, &Err(RequestError::NoRoute(250)));
        let text = metrics.render().unwrap();
        let series = [
            ("modbus_gateway_requests_total{bus=\"line1\",function=\"0x03\",outcome=\"exception\",slave=\"7\"}", 2.0),
            ("modbus_gateway_exceptions_total{bus=\"line1\",code=\"0x02\",slave=\"7\",source=\"slave\"}", 2.0),
            ("modbus_gateway_requests_total{bus=\"line1\",function=\"0x10\",outcome=\"dropped\",slave=\"7\"}", 1.0),
            ("modbus_gateway_requests_total{bus=\"\",function=\"0x03\",outcome=\"no_route\",slave=\"250\"}", 1.0),
            ("modbus_gateway_exceptions_total{bus=\"\",code=\"0x0A\",slave=\"250\",source=\"gateway\"}", 1.0),
        ];
        for (series, expected) in series {
            assert_eq!(value(&text, series), Some(expected), "{series}\n{text}");
        }
        assert_eq!(text.matches("modbus_gateway_exceptions_total{").count(), 2);
    }

    #[test]
    fn line_traffic_becomes_bytes_and_busy_time_at_the_character_time() {
        let metrics = Metrics::new();
        let line1 = metrics.bus(&bus(""));
        line1.line(&LineCounters {
            sent_bytes: 8,
            received_bytes: 9,
            foreign_frames: 1,
            stray_bytes: 2,
        });
        let text = metrics.render().unwrap();
        // 9600 8E1: 11 bits a character (a whole number of nanoseconds).
        let busy = value(
            &text,
            "modbus_gateway_line_busy_seconds_total{bus=\"line1\"}",
        )
        .unwrap();
        assert!((busy - 17.0 * 11.0 / 9600.0).abs() < 17e-9, "{busy}");
        assert_eq!(
            value(&text, "modbus_gateway_line_sent_bytes_total{bus=\"line1\"}"),
            Some(8.0)
        );
        assert_eq!(
            value(
                &text,
                "modbus_gateway_discarded_frames_total{bus=\"line1\"}"
            ),
            Some(1.0)
        );
    }

    #[test]
    fn slave_up_follows_the_changes_health_reports_and_transactions_count_retries_and_round_trips()
    {
        let metrics = Metrics::new();
        let line1 = metrics.bus(&bus(""));
        let up = "modbus_gateway_slave_up{bus=\"line1\",slave=\"5\"}";
        let answered = Ok(Answer::Reply(vec![0x83, 0x02]));
        line1.transaction(5, 1, Some(Duration::from_millis(40)), &answered);
        line1.slave_answering(5, false);
        let text = metrics.render().unwrap();
        assert_eq!(value(&text, up), Some(1.0));
        let since = value(
            &text,
            "modbus_gateway_slave_last_success_timestamp_seconds{bus=\"line1\",slave=\"5\"}",
        )
        .unwrap();
        assert!(since > 1.7e9, "{since}");
        let failed = Err(RequestError::NoResponse {
            attempts: 3,
            last: TxError::Timeout,
        });
        line1.transaction(5, 3, Some(Duration::from_secs(3)), &failed);
        // A transaction alone says nothing of the slave: `bus::health` does.
        assert_eq!(value(&metrics.render().unwrap(), up), Some(1.0));
        line1.slave_failing(5, &failed);
        let text = metrics.render().unwrap();
        assert_eq!(value(&text, up), Some(0.0));
        line1.slave_answering(5, true);
        assert_eq!(value(&metrics.render().unwrap(), up), Some(1.0));
        line1.slave_down(5, 3, Duration::from_secs(5));
        let text = metrics.render().unwrap();
        assert_eq!(value(&text, up), Some(0.0));
        assert_eq!(
            value(
                &text,
                "modbus_gateway_retries_total{bus=\"line1\",slave=\"5\"}"
            ),
            Some(2.0)
        );
        assert_eq!(
            value(
                &text,
                "modbus_gateway_round_trip_seconds_count{bus=\"line1\"}"
            ),
            Some(2.0)
        );
    }

    #[test]
    fn queue_depth_is_read_from_its_source_at_each_scrape() {
        let metrics = Metrics::new();
        let _line1 = metrics.bus(&bus(""));
        let depth = Arc::new(std::sync::atomic::AtomicI64::new(0));
        let gauge = metrics.queue_depth("line1");
        let source = depth.clone();
        metrics.on_scrape(move || gauge.set(source.load(Ordering::Relaxed)));
        depth.store(17, Ordering::Relaxed);
        let text = metrics.render().unwrap();
        assert_eq!(
            value(&text, "modbus_gateway_queue_depth{bus=\"line1\"}"),
            Some(17.0)
        );
    }
}
