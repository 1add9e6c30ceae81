//! The serial master ports' metrics and events: each port's requests by outcome, whether its
//! device is open, and what it is (`[[server.serial]]`).

use super::Definer;
use prometheus::{IntCounter, IntCounterVec, IntGauge, IntGaugeVec};
use tracing::{debug, info, warn};

/// The log target of the serial master ports' events.
pub(crate) const SERIAL_EVENTS: &str = "modbus_gateway::serial";

/// How a frame from a port's master ended: the `outcome` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PortOutcome {
    /// Answered with the slave's (or the gateway's acknowledgement's) normal reply.
    Answered,
    /// Answered with an exception, the slave's or the gateway's.
    Exception,
    /// A broadcast (unit 0), forwarded and, as the spec says, not answered.
    Broadcast,
    /// To a unit outside the port's `units`: not for this slave, silence.
    NotAddressed,
    /// A bad CRC or LRC, too short, broken by a gap, or no request: silence.
    BadFrame,
    /// Its reply was not ready within `answer_within` (or the master sent its next request
    /// first): never sent.
    TooLate,
}

impl PortOutcome {
    pub(crate) const ALL: [PortOutcome; 6] = [
        PortOutcome::Answered,
        PortOutcome::Exception,
        PortOutcome::Broadcast,
        PortOutcome::NotAddressed,
        PortOutcome::BadFrame,
        PortOutcome::TooLate,
    ];

    pub fn label(self) -> &'static str {
        match self {
            PortOutcome::Answered => "answered",
            PortOutcome::Exception => "exception",
            PortOutcome::Broadcast => "broadcast",
            PortOutcome::NotAddressed => "not_addressed",
            PortOutcome::BadFrame => "bad_frame",
            PortOutcome::TooLate => "too_late",
        }
    }
}

/// The families every port's series are in.
pub struct SerialMetrics {
    requests: IntCounterVec,
    up: IntGaugeVec,
    info: IntGaugeVec,
}

/// One port's series, resolved once.
#[derive(Clone)]
pub struct PortMetrics {
    name: String,
    outcomes: [IntCounter; PortOutcome::ALL.len()],
    up: IntGauge,
}

impl SerialMetrics {
    pub(super) fn new(define: &Definer) -> Self {
        SerialMetrics {
            requests: define.int_counter(
                "modbus_gateway_serial_requests_total",
                "Frames from the master of a serial master port, by how they ended.",
                &["port", "outcome"],
            ),
            up: define.int_gauge(
                "modbus_gateway_serial_port_up",
                "1 while a serial master port's device is open, 0 while the gateway waits to \
                 open it again.",
                &["port"],
            ),
            info: define.int_gauge(
                "modbus_gateway_serial_port_info",
                "A serial master port: its device, format and framing; always 1.",
                &["port", "device", "format", "framing"],
            ),
        }
    }

    /// The series of the port `name` on `device` in `format` (`19200 8E1`) and `framing`, at
    /// zero.
    pub fn port(&self, name: &str, device: &str, format: &str, framing: &str) -> PortMetrics {
        self.info
            .with_label_values(&[name, device, format, framing])
            .set(1);
        PortMetrics {
            name: name.to_owned(),
            outcomes: PortOutcome::ALL.map(|o| self.requests.with_label_values(&[name, o.label()])),
            up: self.up.with_label_values(&[name]),
        }
    }
}

impl PortMetrics {
    /// A frame ended in `outcome`; `unit` and `function` as far as it had them.
    pub fn count(&self, outcome: PortOutcome, unit: Option<u8>, function: Option<u8>) {
        self.outcomes[outcome as usize].inc();
        let (port, outcome) = (self.name.as_str(), outcome.label());
        debug!(target: SERIAL_EVENTS, port, outcome, unit, function, "serial master's frame");
    }

    /// How many frames ended in `outcome` so far.
    pub fn counted(&self, outcome: PortOutcome) -> u64 {
        self.outcomes[outcome as usize].get()
    }

    /// The device is open.
    pub fn opened(&self, device: &str) {
        self.up.set(1);
        info!(target: SERIAL_EVENTS, port = self.name, device, "serial master port open");
    }

    /// The device could not be opened, or was lost: tried again after `retry`.
    pub fn lost(&self, device: &str, error: &dyn std::fmt::Display, retry: std::time::Duration) {
        let was_up = self.up.get() == 1;
        self.up.set(0);
        if was_up {
            warn!(target: SERIAL_EVENTS, port = self.name, device, %error, ?retry, "serial master port lost; opening it again");
        } else {
            debug!(target: SERIAL_EVENTS, port = self.name, device, %error, ?retry, "serial master port not open yet");
        }
    }

    pub fn is_up(&self) -> bool {
        self.up.get() == 1
    }
}
