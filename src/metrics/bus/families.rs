//! The families of every bus's series, defined once for the registry: what went over the line,
//! the queue in front of it, the port or device server behind it, each known slave. A bus takes
//! its label values from them (`of`) and gives them back when it is removed (`forget`); what the
//! series mean at run time is `BusMetrics`'s.

use super::BusMetrics;
use crate::config;
use crate::master::Class;
use crate::metrics::labels::{decimal, LinkDrop};
use crate::metrics::polls::POLL_OUTCOMES;
use crate::metrics::{Definer, RequestCounters};
use prometheus::{CounterVec, GaugeVec, HistogramVec, IntCounterVec, IntGaugeVec};
use std::sync::atomic::AtomicBool;
use std::sync::Mutex;

/// The families of every bus's series, registry-wide; each bus takes its label values.
pub(in crate::metrics) struct BusFamilies {
    line: LineFamilies,
    pub(in crate::metrics) queue: QueueFamilies,
    port: PortFamilies,
    slave: SlaveFamilies,
    observed: super::ObservedFamilies,
}

/// What went over the line: its round trips, busy time and bytes.
pub(in crate::metrics) struct LineFamilies {
    round_trip: HistogramVec,
    busy: CounterVec,
    sent: IntCounterVec,
    received: IntCounterVec,
    discarded_frames: IntCounterVec,
    stray_bytes: IntCounterVec,
}

/// The queue in front of the line, and the line's settings.
pub(in crate::metrics) struct QueueFamilies {
    queue_wait: HistogramVec,
    pub(in crate::metrics) queue_depth: IntGaugeVec,
    info: IntGaugeVec,
    queue_capacity: IntGaugeVec,
}

/// The serial port: open or not, reopens, its adapter's latency timer.
pub(in crate::metrics) struct PortFamilies {
    port_up: IntGaugeVec,
    port_reopens: IntCounterVec,
    port_open_errors: IntCounterVec,
    link_dropped: IntCounterVec,
    link_round_trip: GaugeVec,
    link_budget: GaugeVec,
    latency_timer: GaugeVec,
}

/// Each known slave's series.
pub(in crate::metrics) struct SlaveFamilies {
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
                 format (none on a Modbus TCP device), transport (serial, sim, tcp, rfc2217, \
                 tls) and mode (master, or listen: the gateway never transmits); always 1.",
                &["bus", "framing", "format", "transport", "mode"],
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
    pub(in crate::metrics) fn new(define: &Definer) -> Self {
        BusFamilies {
            line: LineFamilies::new(define),
            queue: QueueFamilies::new(define),
            port: PortFamilies::new(define),
            slave: SlaveFamilies::new(define),
            observed: super::ObservedFamilies::new(define),
        }
    }

    /// The metrics of one bus, with its series and those of its known slaves at zero from now
    /// on.
    pub(in crate::metrics) fn of(
        &self,
        settings: &config::Bus,
        counters: RequestCounters,
    ) -> BusMetrics {
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
            observed: self.observed.clone(),
        };
        metrics.reconfigured(settings);
        metrics
    }

    /// Remove the series of `bus`, gone, but its requests' and exceptions' counts.
    pub(in crate::metrics) fn forget(&self, bus: &BusMetrics) {
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
        self.observed.forget(&bus.name, bus.known_slaves());
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
