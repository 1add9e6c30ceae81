//! Modbus/TCP Security's metrics and events: connections by certificate role, the server
//! certificate's expiry, and handshakes that failed (counted with the other refusals, as
//! `reason="tls_handshake"`). Failed handshakes and unreadable roles are logged at warn at most
//! once a minute per peer address.

use super::labels::Rejection;
use super::throttle::PeerThrottle;
use super::{Definer, TcpMetrics, TCP_EVENTS};
use crate::master::Protocol;
use prometheus::{IntCounterVec, IntGauge};
use std::fmt::Display;
use std::net::SocketAddr;
use std::time::{SystemTime, UNIX_EPOCH};
use tracing::{debug, info, warn};

pub struct TlsMetrics {
    accepted: IntCounterVec,
    expiry: IntGauge,
    /// Failed handshakes' warn lines, by peer address.
    handshakes_failed: PeerThrottle,
    /// Warn lines about certificate roles that could not be read, by peer address.
    role_problems: PeerThrottle,
}

/// What the log says of a master that completed its handshake.
pub struct TlsMaster<'a> {
    pub master: u64,
    pub peer: SocketAddr,
    /// The `role` label: a role of `server.tls.roles`, or `other`.
    pub(crate) role_label: &'a str,
    /// The role its certificate carries, as written, if any.
    pub role: Option<&'a str>,
    /// What it may do: `read_write`, `read_only` or `none`.
    pub access: &'static str,
    /// Why its certificate's RoleOID extension was not read as a role, if it has one.
    pub(crate) role_problem: Option<&'static str>,
    pub(crate) subject: &'a str,
}

impl TlsMetrics {
    pub(super) fn new(define: &Definer) -> Self {
        let accepted = define.int_counter(
            "modbus_gateway_tls_connections_accepted_total",
            "Modbus/TCP Security connections that completed their handshake, by the role of the \
             master's certificate (a role of server.tls.roles, or other).",
            &["role"],
        );
        let expiry = define
            .int_gauge(
                "modbus_gateway_tls_certificate_expiry_seconds",
                "Unix time at which the first certificate of the TLS server's chain expires; 0 \
                 without TLS listeners.",
                &[],
            )
            .with_label_values::<&str>(&[]);
        TlsMetrics {
            accepted,
            expiry,
            handshakes_failed: PeerThrottle::new(),
            role_problems: PeerThrottle::new(),
        }
    }

    /// The server certificate in force expires at `expires`.
    pub(crate) fn certificate_expires(&self, expires: SystemTime) {
        let seconds = match expires.duration_since(UNIX_EPOCH) {
            Ok(after) => i64::try_from(after.as_secs()).unwrap_or(i64::MAX),
            Err(_) => 0,
        };
        self.expiry.set(seconds);
    }

    /// A master completed its handshake: counted by role, logged with it.
    pub fn accepted(&self, master: &TlsMaster<'_>) {
        self.accepted.with_label_values(&[master.role_label]).inc();
        info!(
            target: TCP_EVENTS,
            protocol = Protocol::Tls.label(),
            master = master.master,
            peer = %master.peer,
            role = master.role.unwrap_or(""),
            access = master.access,
            subject = master.subject,
            "master connected with a certificate"
        );
        if let Some(problem) = master.role_problem {
            match self.role_problems.due(master.peer.ip()) {
                Some(held_back) => warn!(
                    target: TCP_EVENTS,
                    master = master.master,
                    peer = %master.peer,
                    subject = master.subject,
                    held_back,
                    "certificate role ignored: {problem}; the master gets default_role_access"
                ),
                None => debug!(
                    target: TCP_EVENTS,
                    master = master.master,
                    peer = %master.peer,
                    "certificate role ignored: {problem}"
                ),
            }
        }
    }

    /// A TLS handshake from `peer` failed (or timed out): counted with the refused connections,
    /// logged at warn at most once a minute per peer address.
    pub(crate) fn handshake_failed(
        &self,
        tcp: &TcpMetrics,
        listen: &dyn Display,
        peer: SocketAddr,
        error: &dyn Display,
    ) {
        tcp.count_rejected(Rejection::TlsHandshake, Protocol::Tls);
        let due = self.handshakes_failed.due(peer.ip());
        let reason = Rejection::TlsHandshake.label();
        if let Some(held_back) = due {
            warn!(target: TCP_EVENTS, protocol = Protocol::Tls.label(), %listen, %peer, reason, %error, held_back, "TLS handshake failed; connection closed");
        } else {
            debug!(target: TCP_EVENTS, protocol = Protocol::Tls.label(), %listen, %peer, reason, %error, "TLS handshake failed");
        }
    }
}
