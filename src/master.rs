//! Who a request comes from: the vocabulary every layer shares (a master's id, how it talks to
//! the gateway, what it may ask for, whose turn and share it takes). Plain values; imports
//! nothing from the crate, so every module may use it.

use std::fmt;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

/// One master: a connection, or one source port of a Modbus UDP address.
pub(crate) type MasterId = u64;

/// Who a request comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Origin {
    pub master: MasterId,
    /// Whose share of a full queue it counts against and whose turn on the line it takes: the
    /// master's own id for a connection; for Modbus UDP, one id for every port of a source
    /// address (ports cost a sender nothing).
    pub admission: MasterId,
    /// How the master talks to the gateway, for the requests' `protocol` label.
    pub protocol: Protocol,
    /// Whose ring it waits in: the masters', the priority masters' or the gateway's own polls.
    pub class: Class,
}

/// Which ring of the bus queue a request waits in, and the `class` label of its queue wait.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Class {
    /// A master's.
    #[default]
    Normal,
    /// A master's in `server.priority`: served before the others up to `priority_share`.
    Priority,
    /// The gateway's own read of a plant value: served after every master, up to `poll_share`.
    Poll,
}

impl Class {
    pub const ALL: [Class; 3] = [Class::Normal, Class::Priority, Class::Poll];

    /// A master in `server.priority`, or not.
    pub fn of_master(priority: bool) -> Class {
        if priority {
            Class::Priority
        } else {
            Class::Normal
        }
    }

    /// Its place in [`Class::ALL`]: the queue's ring, the metrics' series.
    pub fn index(self) -> usize {
        self as usize
    }

    /// The `class` label.
    pub fn label(self) -> &'static str {
        match self {
            Class::Normal => "normal",
            Class::Priority => "priority",
            Class::Poll => "poll",
        }
    }
}

/// How a master talks to the gateway: a transport and a framing, as the gateway offers them
/// (RTU frames go on a plain TCP stream only), and the `protocol` label of connections and
/// requests. [`Protocol::spec`] is the one table of what each is; a pair it does not hold
/// ([`Protocol::of`] says `None`) is no listener the gateway has.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Protocol {
    /// Modbus TCP (`server.listen`).
    #[default]
    Tcp,
    /// RTU frames on TCP (`server.listen_rtu_over_tcp`).
    RtuOverTcp,
    /// Modbus UDP (`server.listen_udp`).
    Udp,
    /// Modbus/TCP Security: Modbus TCP in TLS (`server.listen_tls`).
    Tls,
    /// A master on a serial line, the gateway its slave (`[[server.serial]]`), in RTU or ASCII.
    Serial,
    /// A value's `set` topic on the MQTT broker (`[mqtt] writes`): the gateway makes the write.
    Mqtt,
}

/// Where a master is: a socket address on the network, or a serial master port of the gateway's.
/// What the journal, the status page and the logs call it ([`fmt::Display`]: the address, or
/// `serial:NAME`).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum Peer {
    Net(SocketAddr),
    /// `[[server.serial]]`'s `name`.
    Port(Arc<str>),
    /// Whoever published to a `set` topic on the MQTT broker (MQTT does not say who).
    Mqtt,
}

impl Peer {
    /// The network address, canonical (an IPv4 address mapped into IPv6 as IPv4); `None` for a
    /// serial port's master, which no address rule (`masters`, `allow`) matches.
    pub fn ip(&self) -> Option<IpAddr> {
        match self {
            Peer::Net(addr) => Some(addr.ip().to_canonical()),
            Peer::Port(_) | Peer::Mqtt => None,
        }
    }

    /// Where the logs' throttles count a peer's refusals: its host, or its port.
    pub(crate) fn host(&self) -> Host {
        match self {
            Peer::Net(addr) => Host::Ip(addr.ip()),
            Peer::Port(name) => Host::Port(name.clone()),
            Peer::Mqtt => Host::Port(Arc::from(MQTT_PEER)),
        }
    }
}

impl From<SocketAddr> for Peer {
    fn from(addr: SocketAddr) -> Peer {
        Peer::Net(addr)
    }
}

/// How a serial master port's master is named (`serial:NAME`): in the journal, on the status
/// page, and as the port's bus on the trace.
pub(crate) const PORT_PEER_PREFIX: &str = "serial:";

/// What the journal, the status page and the logs call the MQTT broker's `set` messages' master.
pub(crate) const MQTT_PEER: &str = "mqtt";

/// How a virtual unit's requests are named on the trace (`virtual:NAME`), where, as on a serial
/// master port, the gateway is the slave.
pub(crate) const VIRTUAL_TRACE_PREFIX: &str = "virtual:";

impl fmt::Display for Peer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Peer::Net(addr) => addr.fmt(f),
            Peer::Port(name) => write!(f, "{PORT_PEER_PREFIX}{name}"),
            Peer::Mqtt => f.write_str(MQTT_PEER),
        }
    }
}

/// A peer's host, without its source port: what one sender is, for the logs' throttles.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub(crate) enum Host {
    Ip(IpAddr),
    Port(Arc<str>),
}

impl From<IpAddr> for Host {
    fn from(ip: IpAddr) -> Host {
        Host::Ip(ip)
    }
}

/// How a master's bytes travel: on a stream, plain or in TLS, or in datagrams.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UpstreamTransport {
    /// A TCP connection.
    Tcp,
    /// A TLS session on a TCP connection, the master authenticated by its certificate.
    Tls,
    /// UDP datagrams, one request each.
    Udp,
    /// A serial line (a UART, a pty, or one behind a serial device server) to one master.
    Serial,
    /// Messages through an MQTT broker.
    Broker,
}

impl UpstreamTransport {
    /// A connection (TCP or TLS, or a serial master port's line, which one master holds)
    /// rather than datagrams.
    pub(crate) fn is_stream(self) -> bool {
        self != UpstreamTransport::Udp
    }
}

/// How a master delimits and addresses its requests (the codec is the network side's).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UpstreamFraming {
    /// An MBAP header (transaction id, protocol id, length, unit id) before each PDU.
    Mbap,
    /// As on a serial line: address, PDU, CRC-16, no header; replies the same way.
    Rtu,
}

/// What a protocol is, in one row.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Spec {
    pub transport: UpstreamTransport,
    pub framing: UpstreamFraming,
    /// What the logs and `accepting ... masters` call it.
    pub name: &'static str,
    /// The `protocol` label.
    pub label: &'static str,
}

impl Protocol {
    pub(crate) const ALL: [Protocol; 6] = [
        Protocol::Tcp,
        Protocol::RtuOverTcp,
        Protocol::Udp,
        Protocol::Tls,
        Protocol::Serial,
        Protocol::Mqtt,
    ];

    /// The one table of the protocols: their transport, framing, name and label.
    pub const fn spec(self) -> Spec {
        let (transport, framing, name, label) = match self {
            Protocol::Tcp => (
                UpstreamTransport::Tcp,
                UpstreamFraming::Mbap,
                "Modbus TCP",
                "tcp",
            ),
            Protocol::RtuOverTcp => (
                UpstreamTransport::Tcp,
                UpstreamFraming::Rtu,
                "RTU over TCP",
                "rtu_over_tcp",
            ),
            Protocol::Udp => (
                UpstreamTransport::Udp,
                UpstreamFraming::Mbap,
                "Modbus UDP",
                "udp",
            ),
            Protocol::Tls => (
                UpstreamTransport::Tls,
                UpstreamFraming::Mbap,
                "Modbus/TCP Security",
                "tls",
            ),
            // A port's framing is its own (`framing`, RTU or ASCII); RTU is the table's.
            Protocol::Serial => (
                UpstreamTransport::Serial,
                UpstreamFraming::Rtu,
                "serial master port",
                "serial",
            ),
            // No Modbus framing reaches the gateway: it makes the PDU of a value's write itself;
            // MBAP is the table's, as RTU is the serial port's.
            Protocol::Mqtt => (
                UpstreamTransport::Broker,
                UpstreamFraming::Mbap,
                "MQTT",
                "mqtt",
            ),
        };
        Spec {
            transport,
            framing,
            name,
            label,
        }
    }

    /// The protocol of `framing` over `transport`; `None` for a pair the gateway does not offer
    /// (RTU in TLS or in UDP datagrams).
    pub fn of(transport: UpstreamTransport, framing: UpstreamFraming) -> Option<Protocol> {
        let offered = |p: &Protocol| (p.transport(), p.framing()) == (transport, framing);
        Protocol::ALL.into_iter().find(offered)
    }

    pub fn transport(self) -> UpstreamTransport {
        self.spec().transport
    }

    pub fn framing(self) -> UpstreamFraming {
        self.spec().framing
    }

    /// What the logs and `accepting ... masters` call it.
    pub fn name(self) -> &'static str {
        self.spec().name
    }

    pub fn label(self) -> &'static str {
        self.spec().label
    }
}

/// What a master may ask for: from its address (`server.read_only`) and, on a TLS connection,
/// its certificate's role. Ordered from least to most, so the stricter of two is their `min`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Rights {
    /// Nothing: every request gets 0x01, unsent (a TLS role with access `"none"`).
    NoAccess,
    /// Only requests known to change nothing on a slave; anything else gets 0x01, unsent.
    ReadOnly,
    ReadWrite,
}

impl Rights {
    /// The `access` field of the logs.
    pub fn name(self) -> &'static str {
        match self {
            Rights::NoAccess => "none",
            Rights::ReadOnly => "read_only",
            Rights::ReadWrite => "read_write",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each offered pair is one protocol; RTU framing goes on plain TCP only.
    #[test]
    fn each_transport_and_framing_pair_is_one_protocol_and_rtu_is_plain_tcp_only() {
        for protocol in Protocol::ALL {
            assert_eq!(
                Protocol::of(protocol.transport(), protocol.framing()),
                Some(protocol)
            );
        }
        assert_eq!(
            Protocol::of(UpstreamTransport::Tls, UpstreamFraming::Rtu),
            None
        );
        assert_eq!(
            Protocol::of(UpstreamTransport::Udp, UpstreamFraming::Rtu),
            None
        );
        let names: Vec<&str> = Protocol::ALL.iter().map(|p| p.name()).collect();
        assert_eq!(
            names,
            [
                "Modbus TCP",
                "RTU over TCP",
                "Modbus UDP",
                "Modbus/TCP Security",
                "serial master port",
                "MQTT"
            ]
        );
    }
}
