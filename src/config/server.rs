//! The `[server]` section: the Modbus TCP side's listeners, limits, timeouts and access lists, as
//! values. Knows nothing of sockets or sessions.

use super::defaults;
use super::serde_adapters::{duration, text_list};
use super::serde_adapters::{words, Choice};
use super::{ServerSerial, Tls};
use ipnet::IpNet;
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::time::Duration;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Server {
    /// One address, a comma-separated string of them, or a list.
    #[serde(with = "text_list")]
    pub listen: Vec<SocketAddr>,
    /// Where masters that send plain RTU frames on TCP (RTU over TCP) connect; none by default.
    #[serde(with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub listen_rtu_over_tcp: Vec<SocketAddr>,
    /// Where Modbus UDP masters send their datagrams; none by default.
    #[serde(with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub listen_udp: Vec<SocketAddr>,
    /// Where Modbus/TCP Security (TLS) masters connect; none by default. Needs `tls`.
    #[serde(with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub listen_tls: Vec<SocketAddr>,
    /// TCP connections open at once, over all listeners; more are refused.
    pub max_connections: usize,
    /// TCP connections one source address may hold at once; more are refused at accept. Left
    /// out: all but 8 of `max_connections` (filled in by
    /// `Config::resolve`); 0, or `max_connections` or more: no limit of
    /// its own per address.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_connections_per_address: Option<usize>,
    /// A connection with no request and nothing pending for this long is closed ("0s": never).
    #[serde(with = "duration")]
    pub idle_timeout: Duration,
    /// Requests one connection may have in flight; the gateway stops reading until one is answered.
    pub pipeline_depth: usize,
    /// On SIGTERM/SIGINT, how long queued requests may still be served; the rest get 0x0A.
    #[serde(with = "duration")]
    pub shutdown_timeout: Duration,
    /// What a new connection does at `max_connections`.
    pub(crate) when_full: WhenFull,
    /// A request's bytes must all be in this long after its first byte, or the connection closes.
    #[serde(with = "duration")]
    pub frame_timeout: Duration,
    /// TCP keepalive: silence before the first probe of a connection's peer ("0s": off).
    #[serde(with = "duration")]
    pub keepalive: Duration,
    /// Who may connect: addresses or networks; empty: anyone.
    #[serde(with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub allow: Vec<IpNet>,
    /// Masters connecting from these may only read: anything else gets exception 0x01.
    #[serde(with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub read_only: Vec<IpNet>,
    /// Masters connecting from these are served before the others, on every bus.
    #[serde(with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub priority: Vec<IpNet>,
    /// Most share of the line's transactions priority masters take while others wait.
    pub(crate) priority_share: f64,
    /// The certificates and roles of the `listen_tls` listeners.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tls: Option<Tls>,
    /// Serial master ports: masters on serial lines, the gateway their slave.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub serial: Vec<ServerSerial>,
}

/// What a connection beyond `server.max_connections` does.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) enum WhenFull {
    /// Close a connection that is not working, then accept: one whose master does not read its
    /// replies, else one that never completed a request, else the one idle longest among those
    /// that completed none recently; refuse if every connection is working (a request in
    /// flight, or one answered recently).
    #[default]
    CloseOldestIdle,
    /// Refuse the new connection.
    Refuse,
}

impl Choice for WhenFull {
    const ALL: &'static [Self] = &[WhenFull::CloseOldestIdle, WhenFull::Refuse];
    fn word(self) -> &'static str {
        match self {
            WhenFull::CloseOldestIdle => "close_oldest_idle",
            WhenFull::Refuse => "refuse",
        }
    }
}

words!(WhenFull);

impl Default for Server {
    fn default() -> Self {
        Server {
            listen: defaults::listen(),
            listen_rtu_over_tcp: Vec::new(),
            listen_udp: Vec::new(),
            listen_tls: Vec::new(),
            max_connections: defaults::MAX_CONNECTIONS,
            max_connections_per_address: None,
            idle_timeout: defaults::IDLE_TIMEOUT,
            pipeline_depth: defaults::PIPELINE_DEPTH,
            shutdown_timeout: defaults::SHUTDOWN_TIMEOUT,
            when_full: WhenFull::default(),
            frame_timeout: defaults::FRAME_TIMEOUT,
            keepalive: defaults::KEEPALIVE,
            allow: Vec::new(),
            read_only: Vec::new(),
            priority: Vec::new(),
            priority_share: defaults::PRIORITY_SHARE,
            tls: None,
            serial: Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::config::testing::MINIMAL;
    use crate::config::Config;

    #[test]
    fn allow_and_read_only_take_networks_single_addresses_and_comma_strings() {
        let c = Config::from_toml_str(&format!(
            "[server]\nallow = [\"10.1.0.0/16\", \"192.168.1.7\", \"fd00::/8\"]\n\
             read_only = \"10.1.2.0/24, ::1\"\n{MINIMAL}"
        ))
        .unwrap();
        let nets: Vec<String> = c.server.allow.iter().map(ToString::to_string).collect();
        assert_eq!(nets, ["10.1.0.0/16", "192.168.1.7/32", "fd00::/8"]);
        let nets: Vec<String> = c.server.read_only.iter().map(ToString::to_string).collect();
        assert_eq!(nets, ["10.1.2.0/24", "::1/128"]);
        // Host bits are dropped: "10.1.2.3/8" is the network 10.0.0.0/8.
        let c =
            Config::from_toml_str(&format!("[server]\nallow = \"10.1.2.3/8\"\n{MINIMAL}")).unwrap();
        assert_eq!(c.server.allow[0].to_string(), "10.0.0.0/8");
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
    }
}
