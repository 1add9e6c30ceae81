//! Who a request comes from: the vocabulary every layer shares (a master's id, how it talks to
//! the gateway, what it may ask for, whose turn and share it takes). Plain values; imports
//! nothing from the crate, so every module may use it.

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
    /// Served before the others (`server.priority`).
    pub priority: bool,
}

/// How a master talks to the gateway: the `protocol` label of connections and requests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
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
}

impl Protocol {
    pub fn label(self) -> &'static str {
        match self {
            Protocol::Tcp => "tcp",
            Protocol::RtuOverTcp => "rtu_over_tcp",
            Protocol::Udp => "udp",
            Protocol::Tls => "tls",
        }
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
