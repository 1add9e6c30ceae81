//! The TCP side's metrics and events: connections open, accepted, refused and closed, requests
//! refused for what the master may do or for their length. What a master's own doing causes is
//! logged at warn at most once a minute per source address and kind ([`PeerThrottle`]).

use super::labels::{hex, Closing, Rejection};
use super::throttle::PeerThrottle;
use super::{Definer, TCP_EVENTS};
use crate::master::{Peer, Protocol};
use crate::timer::RealInstant;
use prometheus::{IntCounter, IntCounterVec, IntGaugeVec};
use std::fmt::Display;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, PoisonError};
use std::time::Duration;
use tracing::{debug, info, warn};

/// The TCP side: connections open, accepted, refused and closed.
pub struct TcpMetrics {
    open: IntGaugeVec,
    accepted: IntCounterVec,
    rejected: IntCounterVec,
    closed: IntCounterVec,
    bad_crc: IntCounter,
    /// Whether connections are being refused for `max_connections`, so a storm logs once.
    refusing: AtomicBool,
    /// When a refusal for `server.allow` was last logged at warn, so a scan logs little.
    not_allowed_logged: Mutex<Option<RealInstant>>,
    /// The same for `server.max_connections_per_address`.
    per_address_logged: Mutex<Option<RealInstant>>,
    /// Connections closed for breaking the framing or for a request that never arrived whole.
    protocol_errors: PeerThrottle,
    /// Requests refused for what the master may do.
    refusals: PeerThrottle,
    /// Requests refused for their length.
    bad_lengths: PeerThrottle,
}

/// Why a request was refused for what its master may do (the request is counted `read_only` or
/// `no_access`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Refusal {
    /// A request that may change the slave, from a read-only master.
    ReadOnly,
    /// Any request, from a master whose TLS role allows none.
    NoAccess,
    /// A request whose length the gateway cannot check, from a master whose TLS role names the
    /// units it may address: such bytes could hold a frame to another unit.
    Unverifiable,
}

impl Refusal {
    /// The `access` field of the log line.
    fn access(self) -> &'static str {
        match self {
            Refusal::ReadOnly => "read_only",
            Refusal::NoAccess => "none",
            Refusal::Unverifiable => "units",
        }
    }

    fn event(self) -> &'static str {
        match self {
            Refusal::ReadOnly => "refusing a write from a read-only master (0x01)",
            Refusal::NoAccess => "refusing a request of a master whose role allows none (0x01)",
            Refusal::Unverifiable => {
                "refusing a request whose length cannot be checked from a master limited to some units (0x01)"
            }
        }
    }
}

/// At most one warning per this interval about masters outside `server.allow`.
const NOT_ALLOWED_LOG_INTERVAL: Duration = Duration::from_secs(10);

impl TcpMetrics {
    /// The log target of the events of masters on TCP (and TLS), here and where the network
    /// side logs them itself.
    pub(crate) const EVENTS: &'static str = TCP_EVENTS;

    pub(super) fn new(define: &Definer) -> Self {
        let open = define.int_gauge(
            "modbus_gateway_tcp_connections",
            "TCP connections of masters open now, by protocol.",
            &["protocol"],
        );
        let accepted = define.int_counter(
            "modbus_gateway_tcp_connections_accepted_total",
            "TCP connections of masters accepted, by protocol.",
            &["protocol"],
        );
        let rejected = define.int_counter(
            "modbus_gateway_tcp_connections_rejected_total",
            "TCP connections of masters refused at accept, by reason and protocol.",
            &["reason", "protocol"],
        );
        let closed = define.int_counter(
            "modbus_gateway_tcp_connections_closed_total",
            "TCP connections of masters that ended, by reason and protocol.",
            &["reason", "protocol"],
        );
        // Every series of Modbus TCP at zero from the start; those of RTU over TCP appear with
        // its first connection.
        let tcp = Protocol::Tcp.label();
        open.with_label_values(&[tcp]);
        accepted.with_label_values(&[tcp]);
        for reason in Rejection::ALL {
            rejected.with_label_values(&[reason.label(), tcp]);
        }
        for reason in Closing::ALL {
            closed.with_label_values(&[reason.label(), tcp]);
        }
        let bad_crc = define
            .int_counter(
                "modbus_gateway_tcp_bad_crc_total",
                "RTU over TCP requests whose CRC failed, dropped unanswered as a slave would.",
                &[],
            )
            .with_label_values::<&str>(&[]);
        TcpMetrics {
            open,
            accepted,
            rejected,
            closed,
            bad_crc,
            refusing: AtomicBool::new(false),
            not_allowed_logged: Mutex::new(None),
            per_address_logged: Mutex::new(None),
            protocol_errors: PeerThrottle::new(),
            refusals: PeerThrottle::new(),
            bad_lengths: PeerThrottle::new(),
        }
    }

    /// An RTU over TCP request from `master` failed its CRC and was dropped unanswered.
    pub fn bad_crc(&self, master: u64, peer: &dyn Display) {
        self.bad_crc.inc();
        debug!(target: TCP_EVENTS, master, %peer, "RTU over TCP request with a bad CRC dropped");
    }

    pub fn accepted(&self, protocol: Protocol, master: u64, peer: &dyn Display, read_only: bool) {
        let label = protocol.label();
        self.accepted.with_label_values(&[label]).inc();
        self.open.with_label_values(&[label]).inc();
        self.refusing.store(false, Ordering::Relaxed);
        debug!(target: TCP_EVENTS, protocol = label, master, %peer, read_only, "master connected");
    }

    /// A connection of a master of `protocol` refused at `listen`. For `max_connections`, logged
    /// once until a connection is accepted again; for `server.allow` and
    /// `server.max_connections_per_address`, at most once per ten seconds each.
    pub fn rejected(
        &self,
        reason: Rejection,
        protocol: Protocol,
        listen: &dyn Display,
        peer: &dyn Display,
    ) {
        self.count_rejected(reason, protocol);
        let protocol = protocol.label();
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
                    *logged = Some(RealInstant::now());
                }
                (due, "refusing a master outside server.allow")
            }
            Rejection::MaxConnectionsPerAddress => (
                due(&self.per_address_logged),
                "refusing a connection beyond server.max_connections_per_address",
            ),
            Rejection::TlsHandshake => (false, "TLS handshake failed"),
        };
        let reason = reason.label();
        if warn {
            warn!(target: TCP_EVENTS, protocol, %listen, %peer, reason, "{event}");
        } else {
            debug!(target: TCP_EVENTS, protocol, %listen, %peer, reason, "connection refused");
        }
    }

    /// Count a connection refused at accept, without logging it.
    pub(super) fn count_rejected(&self, reason: Rejection, protocol: Protocol) {
        self.rejected
            .with_label_values(&[reason.label(), protocol.label()])
            .inc();
    }

    /// A master whose role names the units it may address asked for another (counted with the
    /// request, as `no_access`). Logged at warn at most once a minute per source address.
    pub(crate) fn unit_refused(&self, master: u64, peer: &Peer, unit: u8) {
        match self.refusals.due(peer.host()) {
            Some(held_back) => {
                warn!(target: TCP_EVENTS, master, %peer, unit, held_back, "refusing a unit the master's role may not address (0x01)");
            }
            None => debug!(target: TCP_EVENTS, master, %peer, unit, "unit refused"),
        }
    }

    /// A master asked for something it may not (counted with the request, as `read_only` or
    /// `no_access`). Logged at warn at most once a minute per source address, with how many
    /// were held back since the last.
    pub(crate) fn request_refused(&self, master: u64, peer: &Peer, function: u8, refusal: Refusal) {
        let function = hex(function);
        let access = refusal.access();
        match self.refusals.due(peer.host()) {
            Some(held_back) => {
                warn!(target: TCP_EVENTS, master, %peer, function, access, held_back, "{}", refusal.event());
            }
            None => debug!(target: TCP_EVENTS, master, %peer, function, access, "request refused"),
        }
    }

    /// A request longer or shorter than its function code says was refused with 0x03, unsent
    /// (counted with the request, as `bad_length`). Logged at warn at most once a minute per
    /// source address.
    pub fn bad_length(&self, master: u64, peer: &Peer, function: u8, len: usize) {
        let function = hex(function);
        match self.bad_lengths.due(peer.host()) {
            Some(held_back) => {
                warn!(target: TCP_EVENTS, master, %peer, function, len, held_back, "refusing a request not as long as its function code says (0x03); nothing sent");
            }
            None => {
                debug!(target: TCP_EVENTS, master, %peer, function, len, "request of the wrong length refused")
            }
        }
    }

    /// A connection accepted earlier has ended. Protocol errors and frame timeouts are logged at
    /// warn, at most once a minute per source address; a master leaving is routine.
    pub fn closed(
        &self,
        protocol: Protocol,
        reason: Closing,
        master: u64,
        peer: &SocketAddr,
        error: &dyn Display,
    ) {
        let protocol = protocol.label();
        self.open.with_label_values(&[protocol]).dec();
        self.closed
            .with_label_values(&[reason.label(), protocol])
            .inc();
        let master_fault = matches!(
            reason,
            Closing::ProtocolError | Closing::FrameTimeout | Closing::WriteTimeout
        );
        if master_fault {
            match self.protocol_errors.due(peer.ip()) {
                Some(held_back) => {
                    warn!(target: TCP_EVENTS, protocol, master, %peer, %error, held_back, "connection closed");
                }
                None => {
                    debug!(target: TCP_EVENTS, protocol, master, %peer, %error, "connection closed");
                }
            }
        } else if reason == Closing::Evicted {
            info!(target: TCP_EVENTS, protocol, master, %peer, "closed a connection that was not working to admit a new master");
        } else {
            debug!(target: TCP_EVENTS, protocol, master, %peer, %error, "master disconnected");
        }
    }
}

/// Whether a warning last logged at `logged` may be logged again; if so, now is the last time.
fn due(logged: &Mutex<Option<RealInstant>>) -> bool {
    let mut logged = logged.lock().unwrap_or_else(PoisonError::into_inner);
    let due = logged.is_none_or(|at| at.elapsed() >= NOT_ALLOWED_LOG_INTERVAL);
    if due {
        *logged = Some(RealInstant::now());
    }
    due
}
