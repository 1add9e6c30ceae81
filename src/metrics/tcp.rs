//! The TCP side's metrics and events: connections open, accepted, refused and closed, writes
//! refused on read-only connections.

use super::labels::{hex, Closing, Protocol, Rejection};
use super::{Definer, TCP_EVENTS};
use crate::dispatch::Rights;
use prometheus::{IntCounter, IntCounterVec, IntGaugeVec};
use std::fmt::Display;
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
    not_allowed_logged: Mutex<Option<std::time::Instant>>,
    /// The same for `server.max_connections_per_address`.
    per_address_logged: Mutex<Option<std::time::Instant>>,
}

/// At most one warning per this interval about masters outside `server.allow`.
const NOT_ALLOWED_LOG_INTERVAL: Duration = Duration::from_secs(10);

impl TcpMetrics {
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
                    *logged = Some(std::time::Instant::now());
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
    /// request, as `no_access`). Logged at warn for the first refusal on each connection.
    pub fn unit_refused(&self, master: u64, peer: &dyn Display, unit: u8, first: bool) {
        if first {
            warn!(target: TCP_EVENTS, master, %peer, unit, "refusing a unit the master's role may not address (0x01)");
        } else {
            debug!(target: TCP_EVENTS, master, %peer, unit, "unit refused");
        }
    }

    /// A master asked for something its `rights` do not allow (counted with the request, as
    /// `read_only` or `no_access`). Logged at warn for the first on each connection.
    pub fn request_refused(
        &self,
        master: u64,
        peer: &dyn Display,
        function: u8,
        rights: Rights,
        first: bool,
    ) {
        let function = hex(function);
        let access = rights.name();
        if !first {
            debug!(target: TCP_EVENTS, master, %peer, function, access, "request refused");
        } else if rights == Rights::NoAccess {
            warn!(target: TCP_EVENTS, master, %peer, function, access, "refusing every request of a master whose role allows none (0x01)");
        } else {
            warn!(target: TCP_EVENTS, master, %peer, function, access, "refusing writes from a read-only master (0x01)");
        }
    }

    /// A connection accepted earlier has ended. Protocol errors are logged; a master leaving
    /// is routine.
    pub fn closed(
        &self,
        protocol: Protocol,
        reason: Closing,
        master: u64,
        peer: &dyn Display,
        error: &dyn Display,
    ) {
        let protocol = protocol.label();
        self.open.with_label_values(&[protocol]).dec();
        self.closed
            .with_label_values(&[reason.label(), protocol])
            .inc();
        if matches!(
            reason,
            Closing::ProtocolError | Closing::FrameTimeout | Closing::WriteTimeout
        ) {
            warn!(target: TCP_EVENTS, protocol, master, %peer, %error, "connection closed");
        } else if reason == Closing::Evicted {
            info!(target: TCP_EVENTS, protocol, master, %peer, "closed a connection that was not working to admit a new master");
        } else {
            debug!(target: TCP_EVENTS, protocol, master, %peer, %error, "master disconnected");
        }
    }
}

/// Whether a warning last logged at `logged` may be logged again; if so, now is the last time.
fn due(logged: &Mutex<Option<std::time::Instant>>) -> bool {
    let mut logged = logged.lock().unwrap_or_else(PoisonError::into_inner);
    let due = logged.is_none_or(|at| at.elapsed() >= NOT_ALLOWED_LOG_INTERVAL);
    if due {
        *logged = Some(std::time::Instant::now());
    }
    due
}
