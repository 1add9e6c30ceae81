//! What the gateway counts, as `modbus_gateway_*` Prometheus metrics, and the notable events that
//! both log and count from one call site: a request's outcome, a slave going silent or coming
//! back, a port lost or reopened, a connection refused or closed. Labels are bounded (bus, slave
//! address, function code, outcome, exception code, reason), never a peer address. The operator's
//! HTTP endpoint (`web`) serves them. Callers say what happened, in plain values; this module
//! knows nothing of frames, sockets, timing or the runtime's parts (it imports neither `bus` nor
//! `dispatch` nor `net`).

mod audit;
mod bus;
mod labels;
mod median;
mod mqtt;
mod polls;
mod port;
mod serial;
mod tcp;
mod throttle;
mod tls;
mod udp;
mod virtual_units;

pub(crate) use audit::AuditMetrics;
pub(crate) use bus::BusMetrics;

use bus::BusFamilies;
pub(crate) use bus::Discarded;
pub(crate) use labels::Closing;
pub(crate) use labels::Fate;
pub(crate) use labels::LinkDrop;
pub(crate) use labels::Rejection;
pub(crate) use port::PortLoss;
pub(crate) use serial::{PortMetrics, PortOutcome, SerialMetrics};

use labels::{hex, OTHER};
pub(crate) use mqtt::{MqttFailure, MqttMessage, MqttMetrics};
pub(crate) use tcp::Refusal;
pub(crate) use tcp::TcpMetrics;
pub(crate) use tls::TlsMaster;
pub(crate) use tls::TlsMetrics;
pub(crate) use udp::UdpDrop;
pub(crate) use udp::UdpMetrics;
pub(crate) use virtual_units::{VirtualMetrics, VirtualOutcome};

use crate::config;
use crate::error::{Answer, Outcome};
use crate::master::Protocol;
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
    /// `outcome` is `None` for a request dropped unsent because its master left. `slave` is the
    /// label value of the slave (its address, or `other`). Every outcome but an answer is also
    /// logged at debug level, under the same name as its label.
    fn count(
        &self,
        bus: &str,
        slave: &str,
        function: u8,
        protocol: Protocol,
        outcome: Option<&Outcome>,
    ) {
        let (fate, exception) = outcome.map_or((Fate::Dropped, None), Fate::of);
        let label = fate.label();
        let function = labels::function(function);
        self.requests
            .with_label_values(&[bus, slave, function, label, protocol.label()])
            .inc();
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
                .with_label_values(&[bus, slave, source.label(), hex(code)])
                .inc();
        }
    }
}

type ScrapeHook = Box<dyn Fn() + Send + Sync>;

/// Every metric of one gateway, in its own registry.
pub struct Metrics {
    registry: Registry,
    counters: RequestCounters,
    buses: BusFamilies,
    pub tcp: TcpMetrics,
    pub udp: UdpMetrics,
    pub tls: TlsMetrics,
    /// The serial master ports.
    pub serial: SerialMetrics,
    /// The virtual units.
    pub(crate) virtual_units: VirtualMetrics,
    /// The writes, and the audit journal.
    pub audit: AuditMetrics,
    /// The live trace of the lines' frames (`GET /trace`).
    pub trace: Arc<crate::trace::TraceHub>,
    /// Gauges read from their source at scrape time (queue depths).
    scrape_hooks: Mutex<Vec<ScrapeHook>>,
    /// The MQTT client's, defined when it starts.
    mqtt: std::sync::OnceLock<MqttMetrics>,
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
        let metrics = Metrics {
            counters: RequestCounters {
                requests: define.int_counter(
                    "modbus_gateway_requests_total",
                    "Requests by bus, slave address, function code, outcome and the master's \
                     protocol.",
                    &["bus", "slave", "function", "outcome", "protocol"],
                ),
                exceptions: define.int_counter(
                    "modbus_gateway_exceptions_total",
                    "Exception replies by code, made by the slave or by the gateway.",
                    &["bus", "slave", "source", "code"],
                ),
            },
            buses: BusFamilies::new(&define),
            tcp: TcpMetrics::new(&define),
            udp: UdpMetrics::new(&define),
            tls: TlsMetrics::new(&define),
            serial: SerialMetrics::new(&define),
            virtual_units: VirtualMetrics::new(&define),
            audit: AuditMetrics::new(&define),
            trace: Arc::new(crate::trace::TraceHub::new()),
            scrape_hooks: Mutex::new(Vec::new()),
            mqtt: std::sync::OnceLock::new(),
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
        Arc::new(self.buses.of(settings, self.counters.clone()))
    }

    /// Remove the series of a bus that is gone, so that none of them (its port down, say)
    /// outlives it. Request and exception counters of past traffic stay.
    pub(crate) fn forget_bus(&self, bus: &BusMetrics) {
        self.buses.forget(bus);
    }

    /// The gauge of bus `name`'s queue depth, to be set by `hook` at every scrape.
    pub fn queue_depth(&self, name: &str) -> IntGauge {
        self.buses.queue.queue_depth.with_label_values(&[name])
    }

    /// Collect what `collector` has at every scrape besides the gateway's own metrics (the plant
    /// values, whose names come from the configuration). It describes nothing up front; the
    /// configuration's check keeps its names apart from the gateway's.
    pub(crate) fn collect_also(&self, collector: Box<dyn prometheus::core::Collector>) {
        if let Err(e) = self.registry.register(collector) {
            tracing::error!(%e, "a collector of the metrics could not be registered");
        }
    }

    /// The MQTT client's metrics, defined at the first call.
    pub(crate) fn mqtt(&self) -> MqttMetrics {
        self.mqtt
            .get_or_init(|| MqttMetrics::new(&self.registry))
            .clone()
    }

    /// Run `hook` before every scrape, to read a gauge from its source.
    pub(crate) fn on_scrape(&self, hook: impl Fn() + Send + Sync + 'static) {
        self.scrape_hooks
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(Box::new(hook));
    }

    /// Count a request the gateway answered without a bus: its unit id has no route. Counted
    /// with no bus and `slave="other"`: the unit id is the master's to choose, and a label it
    /// chooses would let it make series without end.
    pub(crate) fn unrouted(&self, function: u8, protocol: Protocol, outcome: Option<&Outcome>) {
        self.counters.count("", OTHER, function, protocol, outcome);
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

/// The value of the series `name{labels}` in the text format `text`, if present: what the
/// unit tests read of the metrics.
#[cfg(test)]
pub(crate) fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines()
        .find_map(|line| line.strip_prefix(series)?.strip_prefix(' '))
        .map(|v| v.parse().expect("a sample's value is a number"))
}

#[cfg(test)]
mod tests {
    use super::labels::ExceptionSource;
    use super::*;
    use crate::error::NoReply;
    use crate::error::RequestError;
    use crate::line::LineCounters;
    use std::sync::atomic::Ordering;
    use std::time::Duration;

    fn bus(extra: &str) -> config::Bus {
        let text = format!("[[bus]]\nname = \"line1\"\ndevice = \"sim\"\nbaud = 9600\n{extra}");
        crate::Config::from_toml_str(&text).unwrap().bus.remove(0)
    }

    #[test]
    fn every_definition_registers_and_renders() {
        let metrics = Metrics::new();
        let text = metrics.render().unwrap();
        assert_eq!(
            sample(&text, "modbus_gateway_build_info{version=\"0.1.0\"}"),
            Some(1.0)
        );
        assert_eq!(
            sample(&text, "modbus_gateway_tcp_connections{protocol=\"tcp\"}"),
            Some(0.0)
        );
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
            "modbus_gateway_queue_wait_seconds_count{bus=\"line1\",class=\"normal\"}",
            "modbus_gateway_queue_wait_seconds_count{bus=\"line1\",class=\"priority\"}",
            "modbus_gateway_port_reopens_total{bus=\"line1\"}",
            "modbus_gateway_slave_up{bus=\"line1\",slave=\"1\"}",
            "modbus_gateway_slave_up{bus=\"line1\",slave=\"2\"}",
            "modbus_gateway_slave_up{bus=\"line1\",slave=\"9\"}",
            "modbus_gateway_slave_last_success_timestamp_seconds{bus=\"line1\",slave=\"9\"}",
            "modbus_gateway_retries_total{bus=\"line1\",slave=\"9\"}",
            "modbus_gateway_coalesced_requests_total{bus=\"line1\",slave=\"9\"}",
            "modbus_gateway_cache_hits_total{bus=\"line1\",slave=\"9\"}",
        ] {
            assert_eq!(sample(&text, series), Some(0.0), "{series}");
        }
        assert_eq!(
            sample(&text, "modbus_gateway_queue_capacity{bus=\"line1\"}"),
            Some(64.0)
        );
        assert_eq!(
            sample(&text, "modbus_gateway_slave_up{bus=\"line1\",slave=\"3\"}"),
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
            last: NoReply::Timeout,
        });
        assert_eq!(
            Fate::of(&timeout),
            (Fate::Timeout, Some((ExceptionSource::Gateway, 0x0B)))
        );
        let crc: Outcome = Err(RequestError::NoResponse {
            attempts: 1,
            last: NoReply::Check,
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
        let tcp = Protocol::Tcp;
        let exception = Ok(Answer::Reply(vec![0x83, 0x02]));
        // Slave 7 answers (with an exception), so it is known by its address.
        line1.transaction(7, 1, Some(Duration::from_millis(20)), &exception);
        line1.request(7, 0x03, tcp, Some(&exception));
        line1.request(7, 0x03, tcp, Some(&exception));
        line1.request(7, 0x10, tcp, None);
        metrics.unrouted(0x03, tcp, Some(&Err(RequestError::NoRoute(250))));
        let text = metrics.render().unwrap();
        let series = [
            ("modbus_gateway_requests_total{bus=\"line1\",function=\"0x03\",outcome=\"exception\",protocol=\"tcp\",slave=\"7\"}", 2.0),
            ("modbus_gateway_exceptions_total{bus=\"line1\",code=\"0x02\",slave=\"7\",source=\"slave\"}", 2.0),
            ("modbus_gateway_requests_total{bus=\"line1\",function=\"0x10\",outcome=\"dropped\",protocol=\"tcp\",slave=\"7\"}", 1.0),
            // No route: no bus, and no unit id (a label the master would choose).
            ("modbus_gateway_requests_total{bus=\"\",function=\"0x03\",outcome=\"no_route\",protocol=\"tcp\",slave=\"other\"}", 1.0),
            ("modbus_gateway_exceptions_total{bus=\"\",code=\"0x0A\",slave=\"other\",source=\"gateway\"}", 1.0),
        ];
        for (series, expected) in series {
            assert_eq!(sample(&text, series), Some(expected), "{series}\n{text}");
        }
        assert_eq!(text.matches("modbus_gateway_exceptions_total{").count(), 2);
    }

    /// Requests to every unit with every function code.
    #[test]
    fn every_unit_and_function_code_makes_series_only_for_known_slaves_and_codes() {
        let metrics = Metrics::new();
        // Slave 3 is configured; nobody else has answered.
        let line1 = metrics.bus(&bus("[[bus.slave]]\naddress = 3\n"));
        let before = metrics.render().unwrap().lines().count();
        let timeout: Outcome = Err(RequestError::NoResponse {
            attempts: 1,
            last: NoReply::Timeout,
        });
        for unit in 1..=u8::MAX {
            for function in 1..=u8::MAX {
                line1.transaction(unit, 1, Some(Duration::from_millis(5)), &timeout);
                line1.slave_failing(unit, &timeout);
                line1.request(unit, function, Protocol::Udp, Some(&timeout));
                metrics.unrouted(
                    function,
                    Protocol::Tcp,
                    Some(&Err(RequestError::NoRoute(unit))),
                );
            }
        }
        let text = metrics.render().unwrap();
        let requests = text
            .lines()
            .filter(|l| l.starts_with("modbus_gateway_requests_total{"))
            .count();
        // Slave 3 and `other`, by the table's 19 codes and `other`, on the bus; `other` by
        // the same 20 without a route.
        assert_eq!(requests, 2 * 20 + 20, "{text}");
        assert!(
            text.contains(
                "modbus_gateway_requests_total{bus=\"line1\",function=\"other\",outcome=\"timeout\",protocol=\"udp\",slave=\"other\"}"
            ),
            "{text}"
        );
        // No per-slave series for addresses nobody answered at.
        assert!(!text.contains("modbus_gateway_slave_up{bus=\"line1\",slave=\"4\"}"));
        assert!(text.lines().count() < before + 2 * 20 + 20 + 40, "{text}");
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
        let busy = sample(
            &text,
            "modbus_gateway_line_busy_seconds_total{bus=\"line1\"}",
        )
        .unwrap();
        assert!((busy - 17.0 * 11.0 / 9600.0).abs() < 17e-9, "{busy}");
        assert_eq!(
            sample(&text, "modbus_gateway_line_sent_bytes_total{bus=\"line1\"}"),
            Some(8.0)
        );
        assert_eq!(
            sample(
                &text,
                "modbus_gateway_discarded_frames_total{bus=\"line1\"}"
            ),
            Some(1.0)
        );
    }

    /// `slave_up` follows the changes health reports.
    #[test]
    fn slave_up_follows_health_and_transactions_count_retries_and_round_trips() {
        let metrics = Metrics::new();
        let line1 = metrics.bus(&bus(""));
        let up = "modbus_gateway_slave_up{bus=\"line1\",slave=\"5\"}";
        let answered = Ok(Answer::Reply(vec![0x83, 0x02]));
        line1.transaction(5, 1, Some(Duration::from_millis(40)), &answered);
        line1.slave_answering(5, false);
        let text = metrics.render().unwrap();
        assert_eq!(sample(&text, up), Some(1.0));
        let since = sample(
            &text,
            "modbus_gateway_slave_last_success_timestamp_seconds{bus=\"line1\",slave=\"5\"}",
        )
        .unwrap();
        assert!(since > 1.7e9, "{since}");
        let failed = Err(RequestError::NoResponse {
            attempts: 3,
            last: NoReply::Timeout,
        });
        line1.transaction(5, 3, Some(Duration::from_secs(3)), &failed);
        // A transaction alone says nothing of the slave: `bus::health` does.
        assert_eq!(sample(&metrics.render().unwrap(), up), Some(1.0));
        line1.slave_failing(5, &failed);
        let text = metrics.render().unwrap();
        assert_eq!(sample(&text, up), Some(0.0));
        line1.slave_answering(5, true);
        assert_eq!(sample(&metrics.render().unwrap(), up), Some(1.0));
        line1.slave_down(5, 3, Duration::from_secs(5));
        let text = metrics.render().unwrap();
        assert_eq!(sample(&text, up), Some(0.0));
        assert_eq!(
            sample(
                &text,
                "modbus_gateway_retries_total{bus=\"line1\",slave=\"5\"}"
            ),
            Some(2.0)
        );
        assert_eq!(
            sample(
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
            sample(&text, "modbus_gateway_queue_depth{bus=\"line1\"}"),
            Some(17.0)
        );
    }
}
