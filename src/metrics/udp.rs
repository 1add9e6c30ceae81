//! Modbus UDP's metrics and events: datagrams dropped, by reason.

use super::Definer;
use crate::master::Protocol;
use prometheus::IntCounterVec;
use std::fmt::Display;
use tracing::debug;

/// Why a datagram was dropped: the `reason` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UdpDrop {
    /// From a source outside `server.allow`.
    NotAllowed,
    /// Not exactly one MBAP request.
    Malformed,
    /// Its source already had `pipeline_depth` requests pending.
    Overloaded,
}

impl UdpDrop {
    pub(crate) const ALL: [UdpDrop; 3] =
        [UdpDrop::NotAllowed, UdpDrop::Malformed, UdpDrop::Overloaded];

    pub fn label(self) -> &'static str {
        match self {
            UdpDrop::NotAllowed => "not_allowed",
            UdpDrop::Malformed => "malformed",
            UdpDrop::Overloaded => "overloaded",
        }
    }
}

/// The UDP side: datagrams dropped unanswered.
pub struct UdpMetrics {
    dropped: IntCounterVec,
}

/// The log target of Modbus UDP's events, apart from those of connections (`modbus_gateway::tcp`).
const UDP_EVENTS: &str = "modbus_gateway::udp";

impl UdpMetrics {
    /// The log target of Modbus UDP's events, here and where the network side logs them itself.
    pub(crate) const EVENTS: &'static str = UDP_EVENTS;

    pub(super) fn new(define: &Definer) -> Self {
        let dropped = define.int_counter(
            "modbus_gateway_udp_dropped_total",
            "Modbus UDP datagrams dropped unanswered, by reason.",
            &["reason"],
        );
        for reason in UdpDrop::ALL {
            dropped.with_label_values(&[reason.label()]);
        }
        UdpMetrics { dropped }
    }

    /// A datagram from `peer` was dropped for `reason`. Logged at debug only: a flood must not
    /// flood the log.
    pub fn dropped(&self, reason: UdpDrop, peer: &dyn Display) {
        let reason = reason.label();
        self.dropped.with_label_values(&[reason]).inc();
        let protocol = Protocol::Udp.name();
        debug!(target: UDP_EVENTS, protocol, %peer, reason, "datagram dropped");
    }
}
