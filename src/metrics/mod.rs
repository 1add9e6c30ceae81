//! What the gateway counts, as `modbus_gateway_*` Prometheus metrics, and the notable events that
//! both log and count from one call site: a request's outcome, a slave going silent or coming
//! back, a port lost or reopened, a connection refused or closed. Labels are bounded (bus, slave
//! address, function code, outcome, exception code, reason), never a peer address. [`http`] serves
//! the text format and the health endpoints. Callers say what happened; this module knows nothing
//! of frames, sockets or timing.

pub mod http;

use crate::config;
use crate::error::{Answer, Outcome, RequestError};
use crate::line::{LineCounters, TxError};
use prometheus::{
    Counter, CounterVec, Gauge, GaugeVec, Histogram, HistogramOpts, HistogramVec, IntCounter,
    IntCounterVec, IntGauge, IntGaugeVec, Opts, Registry, TextEncoder,
};
use std::fmt::Display;
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tracing::{debug, info, warn};

/// Log targets of the events counted here: named after where they happen, not after this module.
const BUS_EVENTS: &str = "modbus_gateway::bus";
const TCP_EVENTS: &str = "modbus_gateway::tcp";

/// Histogram buckets in seconds, for round trips and queue waits alike: from one short exchange
/// at 115200 baud (about 1 ms) to a slow drive's timeout.
const BUCKETS: &[f64] = &[
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// What became of one request: the `outcome` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fate {
    /// The slave's normal reply (or, for a broadcast, the frame went out).
    Ok,
    /// The slave's own exception reply.
    Exception,
    /// The slave's reply, forwarded as it came, though it does not have the shape the request
    /// asks for (byte count, echo).
    MalformedReply,
    /// No reply to this request within the response timeout, retries included.
    Timeout,
    /// The last reply failed its CRC check.
    CrcError,
    /// The last reply was incomplete at its deadline, or longer than a frame can be.
    FrameError,
    /// The line never fell silent long enough to send.
    LineBusy,
    /// No route for the unit id (0x0A).
    NoRoute,
    /// A function code the gateway refuses itself: invalid, or a read to the broadcast address
    /// (0x01).
    Refused,
    /// The bus queue was full (0x06).
    QueueFull,
    /// Not sent within the queue timeout (0x06).
    Expired,
    /// The bus had no open port (0x0A).
    PortDown,
    /// Still queued when the shutdown timeout ran out (0x0A).
    Shutdown,
    /// The master left before the request was sent; it was never sent.
    Dropped,
    /// A request from a read-only master that may change the slave; never sent (0x01).
    ReadOnly,
    /// The slave is down (timed out again and again) and it was not its probe's turn; never
    /// sent (0x0B).
    SlaveDown,
}

impl Fate {
    pub fn label(self) -> &'static str {
        match self {
            Fate::Ok => "ok",
            Fate::Exception => "exception",
            Fate::MalformedReply => "malformed_reply",
            Fate::Timeout => "timeout",
            Fate::CrcError => "crc_error",
            Fate::FrameError => "frame_error",
            Fate::LineBusy => "line_busy",
            Fate::NoRoute => "no_route",
            Fate::Refused => "refused",
            Fate::QueueFull => "queue_full",
            Fate::Expired => "expired",
            Fate::PortDown => "port_down",
            Fate::Shutdown => "shutdown",
            Fate::Dropped => "dropped",
            Fate::ReadOnly => "read_only",
            Fate::SlaveDown => "slave_down",
        }
    }

    /// The fate of an answered request, with the exception code in its answer and who made it.
    pub fn of(outcome: &Outcome) -> (Fate, Option<(Source, u8)>) {
        match outcome {
            Ok(Answer::Reply(pdu))
                if pdu
                    .first()
                    .is_some_and(|f| f & crate::pdu::EXCEPTION_BIT != 0) =>
            {
                (
                    Fate::Exception,
                    Some((Source::Slave, pdu.get(1).copied().unwrap_or(0))),
                )
            }
            Ok(Answer::Malformed(_)) => (Fate::MalformedReply, None),
            Ok(_) => (Fate::Ok, None),
            Err(error) => {
                let fate = match error {
                    RequestError::InvalidFunction(_) | RequestError::NotBroadcastable(_) => {
                        Fate::Refused
                    }
                    RequestError::ReadOnly(_) => Fate::ReadOnly,
                    RequestError::SlaveDown { .. } => Fate::SlaveDown,
                    RequestError::NoRoute(_) => Fate::NoRoute,
                    RequestError::PortDown => Fate::PortDown,
                    RequestError::QueueFull => Fate::QueueFull,
                    RequestError::Expired => Fate::Expired,
                    RequestError::ShuttingDown => Fate::Shutdown,
                    RequestError::NoResponse { last, .. } => match last {
                        TxError::Timeout => Fate::Timeout,
                        TxError::Crc => Fate::CrcError,
                        TxError::Frame => Fate::FrameError,
                        TxError::LineBusy => Fate::LineBusy,
                        TxError::PortLost(_) => Fate::PortDown,
                    },
                };
                (fate, Some((Source::Gateway, error.exception_code() as u8)))
            }
        }
    }
}

/// Who made an exception reply: the `source` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    Slave,
    Gateway,
}

impl Source {
    pub fn label(self) -> &'static str {
        match self {
            Source::Slave => "slave",
            Source::Gateway => "gateway",
        }
    }
}

/// Why a TCP connection was refused at accept: the `reason` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rejection {
    /// `max_connections` open, none of them idle (or `when_full = "refuse"`).
    MaxConnections,
    /// The peer's address is outside `server.allow`.
    NotAllowed,
}

impl Rejection {
    pub const ALL: [Rejection; 2] = [Rejection::MaxConnections, Rejection::NotAllowed];

    pub fn label(self) -> &'static str {
        match self {
            Rejection::MaxConnections => "max_connections",
            Rejection::NotAllowed => "not_allowed",
        }
    }
}

/// Why a TCP connection ended: the `reason` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Closing {
    /// The master closed it.
    ByMaster,
    /// The master broke the Modbus TCP framing.
    ProtocolError,
    /// Idle for `idle_timeout`.
    Idle,
    /// A socket error.
    IoError,
    /// The gateway is stopping; the master's requests were answered first.
    Shutdown,
    /// A request's bytes did not all arrive within `frame_timeout`.
    FrameTimeout,
    /// Idle longest of all when a new master came at `max_connections`.
    Evicted,
}

impl Closing {
    pub const ALL: [Closing; 7] = [
        Closing::ByMaster,
        Closing::ProtocolError,
        Closing::Idle,
        Closing::IoError,
        Closing::Shutdown,
        Closing::FrameTimeout,
        Closing::Evicted,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Closing::ByMaster => "by_master",
            Closing::ProtocolError => "protocol_error",
            Closing::Idle => "idle_timeout",
            Closing::IoError => "io_error",
            Closing::Shutdown => "shutdown",
            Closing::FrameTimeout => "frame_timeout",
            Closing::Evicted => "evicted",
        }
    }
}

/// Label values for addresses and codes, made once: the request path formats nothing.
fn decimal(n: u8) -> &'static str {
    static TABLE: OnceLock<Vec<String>> = OnceLock::new();
    &TABLE.get_or_init(|| (0..=u8::MAX).map(|n| n.to_string()).collect())[usize::from(n)]
}

/// `0x03`, as the Modbus spec writes function and exception codes.
fn hex(n: u8) -> &'static str {
    static TABLE: OnceLock<Vec<String>> = OnceLock::new();
    &TABLE.get_or_init(|| (0..=u8::MAX).map(|n| format!("0x{n:02X}")).collect())[usize::from(n)]
}

fn seconds_since_epoch() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs_f64()
}

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
            slaves: Box::new(std::array::from_fn(|_| OnceLock::new())),
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
        for address in (0..=u8::MAX).filter(|a| bus.slaves[usize::from(*a)].get().is_some()) {
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

/// A slave's own series, and whether it answered last time (for logging the changes).
struct SlaveMetrics {
    up: IntGauge,
    last_success: Gauge,
    retries: IntCounter,
    state: AtomicU8,
}

const SLAVE_UNKNOWN: u8 = 0;
const SLAVE_UP: u8 = 1;
const SLAVE_DOWN: u8 = 2;

/// The metrics of one bus, label values resolved once. Shared by its handle and its task.
pub struct BusMetrics {
    name: Arc<str>,
    queue_capacity: IntGauge,
    /// Seconds per character on the line, to turn bytes into busy time.
    char_time: f64,
    counters: RequestCounters,
    round_trip: Histogram,
    queue_wait: Histogram,
    busy: Counter,
    sent: IntCounter,
    received: IntCounter,
    discarded_frames: IntCounter,
    stray_bytes: IntCounter,
    port_up: IntGauge,
    port_reopens: IntCounter,
    port_open_errors: IntCounter,
    retries: IntCounterVec,
    slave_up: IntGaugeVec,
    slave_last_success: GaugeVec,
    slaves: Box<[OnceLock<SlaveMetrics>; 256]>,
}

impl BusMetrics {
    fn slave(&self, address: u8) -> &SlaveMetrics {
        self.slaves[usize::from(address)].get_or_init(|| {
            let labels = &[&*self.name, decimal(address)];
            let slave = SlaveMetrics {
                up: self.slave_up.with_label_values(labels),
                last_success: self.slave_last_success.with_label_values(labels),
                retries: self.retries.with_label_values(labels),
                state: AtomicU8::new(SLAVE_UNKNOWN),
            };
            slave.up.set(0);
            slave
        })
    }

    /// The bus's settings, at start or after a reload: its queue capacity, and series at zero for
    /// its known slaves (`[[bus.slave]]` and simulated ones).
    pub fn reconfigured(&self, settings: &config::Bus) {
        self.queue_capacity
            .set(i64::try_from(settings.queue_depth).unwrap_or(i64::MAX));
        let sim_slaves = settings.sim_slave.iter().flat_map(|s| s.address.iter());
        for address in settings.slave.iter().map(|s| s.address).chain(sim_slaves) {
            self.slave(address);
        }
    }

    /// Count a request's outcome; `None` if it was dropped unsent because its master left.
    pub fn request(&self, slave: u8, function: u8, outcome: Option<&Outcome>) {
        self.counters.count(&self.name, slave, function, outcome);
    }

    /// The line took a request after it waited `wait` in the queue.
    pub fn dequeued(&self, wait: Duration) {
        self.queue_wait.observe(wait.as_secs_f64());
    }

    /// The line ran a request to `slave`: its round trip (`None` if it never got on the wire),
    /// how many attempts it took, and how it ended. A slave that stops or starts giving valid
    /// replies is logged once per change. A timeout tells of the slave only if
    /// `timeout_counts` (the bus's down policy says whether it does: see `bus::health`); a line
    /// too busy to send on tells nothing of it.
    pub fn transaction(
        &self,
        slave: u8,
        attempts: u32,
        round_trip: Option<Duration>,
        outcome: &Outcome,
        timeout_counts: bool,
    ) {
        if let Some(round_trip) = round_trip {
            self.round_trip.observe(round_trip.as_secs_f64());
        }
        let metrics = self.slave(slave);
        metrics
            .retries
            .inc_by(u64::from(attempts.saturating_sub(1)));
        let bus = &*self.name;
        match outcome {
            Ok(Answer::Reply(_) | Answer::Malformed(_)) => {
                metrics.up.set(1);
                metrics.last_success.set(seconds_since_epoch());
                if metrics.state.swap(SLAVE_UP, Ordering::Relaxed) == SLAVE_DOWN {
                    info!(target: BUS_EVENTS, bus, slave, "slave answering again");
                }
            }
            Err(RequestError::NoResponse {
                last: TxError::LineBusy,
                ..
            }) => {}
            Err(RequestError::NoResponse {
                last: TxError::Timeout,
                ..
            }) if !timeout_counts => {}
            Err(error @ RequestError::NoResponse { attempts, .. }) => {
                metrics.up.set(0);
                if metrics.state.swap(SLAVE_DOWN, Ordering::Relaxed) != SLAVE_DOWN {
                    let outcome = Fate::of(outcome).0.label();
                    warn!(target: BUS_EVENTS, bus, slave, attempts, outcome, %error, "slave gives no valid reply");
                }
            }
            _ => {}
        }
    }

    /// `slave` timed out `timeouts` times in a row: its requests are answered 0x0B unsent (and
    /// counted `slave_down`) but for one probe per `probe_interval`.
    pub fn slave_down(&self, slave: u8, timeouts: u32, probe_interval: Duration) {
        let bus = &*self.name;
        let probe_interval = humantime::format_duration(probe_interval).to_string();
        warn!(target: BUS_EVENTS, bus, slave, timeouts, probe_interval, "slave down; answering 0x0B without sending, probing once per interval");
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

    /// The port is open: for the first time (`down` is `None`), or again after `down` (how long,
    /// and how many opens failed meanwhile).
    pub fn port_opened(&self, device: &str, down: Option<(Duration, u32)>) {
        let bus = &*self.name;
        match down {
            None => info!(target: BUS_EVENTS, bus, device, "serial port open"),
            Some((down_for, failed_opens)) => {
                self.port_reopens.inc();
                info!(target: BUS_EVENTS,
                    bus,
                    device,
                    failed_opens,
                    down_s = down_for.as_secs_f64(),
                    "serial port reopened"
                );
            }
        }
        self.port_up.set(1);
    }

    pub fn port_lost(&self, device: &str, error: &dyn Display) {
        self.port_up.set(0);
        warn!(target: BUS_EVENTS, bus = &*self.name, device, %error, "serial port lost; answering 0x0A and reopening");
    }

    /// An open failed; only the first failure of an outage is logged above debug level.
    pub fn open_failed(&self, device: &str, error: &dyn Display, first: bool) {
        self.port_open_errors.inc();
        let bus = &*self.name;
        if first {
            warn!(target: BUS_EVENTS, bus, device, %error, "cannot open serial port; answering 0x0A and retrying");
        } else {
            debug!(target: BUS_EVENTS, bus, device, %error, "serial port still cannot be opened");
        }
    }
}

/// The TCP side: connections open, accepted, refused and closed.
pub struct TcpMetrics {
    open: IntGauge,
    accepted: IntCounter,
    rejected: IntCounterVec,
    closed: IntCounterVec,
    /// Whether connections are being refused for `max_connections`, so a storm logs once.
    refusing: AtomicBool,
    /// When a refusal for `server.allow` was last logged at warn, so a scan logs little.
    not_allowed_logged: Mutex<Option<std::time::Instant>>,
}

/// At most one warning per this interval about masters outside `server.allow`.
const NOT_ALLOWED_LOG_INTERVAL: Duration = Duration::from_secs(10);

impl TcpMetrics {
    fn new(define: &Definer) -> Self {
        let open = define
            .int_gauge(
                "modbus_gateway_tcp_connections",
                "Modbus TCP connections open now.",
                &[],
            )
            .with_label_values::<&str>(&[]);
        let accepted = define
            .int_counter(
                "modbus_gateway_tcp_connections_accepted_total",
                "Modbus TCP connections accepted.",
                &[],
            )
            .with_label_values::<&str>(&[]);
        let rejected = define.int_counter(
            "modbus_gateway_tcp_connections_rejected_total",
            "Modbus TCP connections refused at accept, by reason.",
            &["reason"],
        );
        for reason in Rejection::ALL {
            rejected.with_label_values(&[reason.label()]);
        }
        let closed = define.int_counter(
            "modbus_gateway_tcp_connections_closed_total",
            "Modbus TCP connections that ended, by reason.",
            &["reason"],
        );
        for reason in Closing::ALL {
            closed.with_label_values(&[reason.label()]);
        }
        TcpMetrics {
            open,
            accepted,
            rejected,
            closed,
            refusing: AtomicBool::new(false),
            not_allowed_logged: Mutex::new(None),
        }
    }

    pub fn accepted(&self, master: u64, peer: &dyn Display, read_only: bool) {
        self.accepted.inc();
        self.open.inc();
        self.refusing.store(false, Ordering::Relaxed);
        debug!(target: TCP_EVENTS, master, %peer, read_only, "master connected");
    }

    /// A connection refused at accept. For `max_connections`, logged once until a connection is
    /// accepted again; for `server.allow`, at most once per ten seconds.
    pub fn rejected(&self, reason: Rejection, listen: &dyn Display, peer: &dyn Display) {
        self.rejected.with_label_values(&[reason.label()]).inc();
        let (warn, event) = match reason {
            Rejection::MaxConnections => (
                !self.refusing.swap(true, Ordering::Relaxed),
                "refusing connections until one closes",
            ),
            Rejection::NotAllowed => {
                let mut logged = self
                    .not_allowed_logged
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner);
                let due = logged.is_none_or(|at| at.elapsed() >= NOT_ALLOWED_LOG_INTERVAL);
                if due {
                    *logged = Some(std::time::Instant::now());
                }
                (due, "refusing a master outside server.allow")
            }
        };
        let reason = reason.label();
        if warn {
            warn!(target: TCP_EVENTS, %listen, %peer, reason, "{event}");
        } else {
            debug!(target: TCP_EVENTS, %listen, %peer, reason, "connection refused");
        }
    }

    /// A read-only master asked for something that may change a slave (counted with the
    /// request, as `read_only`). Logged at warn for the first on each connection.
    pub fn write_refused(&self, master: u64, peer: &dyn Display, function: u8, first: bool) {
        let function = hex(function);
        if first {
            warn!(target: TCP_EVENTS, master, %peer, function, "refusing writes from a read-only master (0x01)");
        } else {
            debug!(target: TCP_EVENTS, master, %peer, function, "write refused");
        }
    }

    /// A connection accepted earlier has ended. Protocol errors are logged; a master leaving
    /// is routine.
    pub fn closed(&self, reason: Closing, master: u64, peer: &dyn Display, error: &dyn Display) {
        self.open.dec();
        self.closed.with_label_values(&[reason.label()]).inc();
        if matches!(reason, Closing::ProtocolError | Closing::FrameTimeout) {
            warn!(target: TCP_EVENTS, master, %peer, %error, "connection closed");
        } else if reason == Closing::Evicted {
            info!(target: TCP_EVENTS, master, %peer, "closed the connection idle longest to admit a new master");
        } else {
            debug!(target: TCP_EVENTS, master, %peer, %error, "master disconnected");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
            (Fate::Exception, Some((Source::Slave, 0x02)))
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
            (Fate::Timeout, Some((Source::Gateway, 0x0B)))
        );
        let crc: Outcome = Err(RequestError::NoResponse {
            attempts: 1,
            last: TxError::Crc,
        });
        assert_eq!(Fate::of(&crc).0, Fate::CrcError);
        assert_eq!(
            Fate::of(&Err(RequestError::NoRoute(250))),
            (Fate::NoRoute, Some((Source::Gateway, 0x0A)))
        );
        assert_eq!(
            Fate::of(&Err(RequestError::Expired)),
            (Fate::Expired, Some((Source::Gateway, 0x06)))
        );
        assert_eq!(
            Fate::of(&Err(RequestError::NotBroadcastable(3))),
            (Fate::Refused, Some((Source::Gateway, 0x01)))
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
    fn a_slave_is_up_after_an_answer_and_down_after_a_failure_that_tells_of_it() {
        let metrics = Metrics::new();
        let line1 = metrics.bus(&bus(""));
        let up = "modbus_gateway_slave_up{bus=\"line1\",slave=\"5\"}";
        line1.transaction(
            5,
            1,
            Some(Duration::from_millis(40)),
            &Ok(Answer::Reply(vec![0x83, 0x02])),
            true,
        );
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
        // A timeout the down policy does not count (a function the slave never answered), or a
        // line too busy to send on, says nothing of the slave.
        line1.transaction(5, 1, Some(Duration::from_secs(1)), &failed, false);
        let busy = Err(RequestError::NoResponse {
            attempts: 1,
            last: TxError::LineBusy,
        });
        line1.transaction(5, 1, None, &busy, true);
        let text = metrics.render().unwrap();
        assert_eq!(value(&text, up), Some(1.0));
        line1.transaction(5, 3, Some(Duration::from_secs(3)), &failed, true);
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
            Some(3.0)
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
