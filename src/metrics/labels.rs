//! The label values of the gateway's metrics: what became of a request (`outcome`), who made
//! an exception (`source`), why a connection was refused or ended (`reason`, a device server's
//! too), and the addresses and codes as strings made once. Bounded sets, all of them; nothing
//! here counts.

use crate::error::{Answer, NoReply, Outcome, RequestError};
use crate::line::framing::TransportKind;
use crate::line::{Reply, TxError};
use std::sync::OnceLock;
use std::time::{SystemTime, UNIX_EPOCH};

/// What became of one request: the `outcome` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Fate {
    /// The slave's normal reply (or, for a broadcast, the frame went out).
    Ok,
    /// The slave's own exception reply.
    Exception,
    /// The slave's reply, forwarded as it came, though it does not have the shape the request
    /// asks for (byte count, echo).
    MalformedReply,
    /// No reply to this request within the response timeout, retries included.
    Timeout,
    /// The last reply failed its check: its CRC, or its LRC on an ASCII bus.
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
    /// A request longer or shorter than its function code says; never sent (0x03).
    BadLength,
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
    /// A request from a master whose TLS role allows nothing, or not that unit, or (limited to
    /// some units) a request whose length the gateway cannot check; never sent (0x01).
    NoAccess,
    /// The slave is down (timed out again and again) and it was not its probe's turn; never
    /// sent (0x0B).
    SlaveDown,
    /// Refused by a `[[rule]]`; never sent (0x01, or 0x02 from a rule with registers).
    Denied,
    /// A write answered by an `acknowledge` rule with its normal reply; never sent.
    Acknowledged,
    /// A write refused because the audit journal cannot be written; never sent (0x0A).
    Unrecorded,
}

impl Fate {
    pub(crate) fn label(self) -> &'static str {
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
            Fate::BadLength => "bad_length",
            Fate::QueueFull => "queue_full",
            Fate::Expired => "expired",
            Fate::PortDown => "port_down",
            Fate::Shutdown => "shutdown",
            Fate::Dropped => "dropped",
            Fate::ReadOnly => "read_only",
            Fate::NoAccess => "no_access",
            Fate::SlaveDown => "slave_down",
            Fate::Denied => "denied",
            Fate::Acknowledged => "acknowledged",
            Fate::Unrecorded => "unrecorded",
        }
    }

    /// The fate of an answered request, with the exception code in its answer and who made it.
    pub(crate) fn of(outcome: &Outcome) -> (Fate, Option<(ExceptionSource, u8)>) {
        match outcome {
            Ok(Answer::Reply(pdu))
                if pdu
                    .first()
                    .is_some_and(|f| f & crate::pdu::EXCEPTION_BIT != 0) =>
            {
                (
                    Fate::Exception,
                    Some((ExceptionSource::Slave, pdu.get(1).copied().unwrap_or(0))),
                )
            }
            Ok(Answer::Malformed(_)) => (Fate::MalformedReply, None),
            Ok(Answer::Acknowledged(_)) => (Fate::Acknowledged, None),
            Ok(_) => (Fate::Ok, None),
            Err(error) => {
                let fate = match error {
                    RequestError::InvalidFunction(_)
                    | RequestError::NotBroadcastable(_)
                    | RequestError::Emulated(_)
                    | RequestError::ListenOnly(_)
                    | RequestError::Unseen
                    | RequestError::Unreadable(_) => Fate::Refused,
                    RequestError::ReadOnly(_) => Fate::ReadOnly,
                    RequestError::BadLength { .. } => Fate::BadLength,
                    RequestError::NoAccess(_)
                    | RequestError::UnitNotPermitted(_)
                    | RequestError::Unverifiable(_) => Fate::NoAccess,
                    RequestError::SlaveDown { .. } => Fate::SlaveDown,
                    RequestError::Denied { .. } => Fate::Denied,
                    RequestError::Unrecorded(_) => Fate::Unrecorded,
                    RequestError::NoRoute(_) => Fate::NoRoute,
                    RequestError::PortDown | RequestError::PortLost => Fate::PortDown,
                    RequestError::QueueFull => Fate::QueueFull,
                    RequestError::Expired => Fate::Expired,
                    RequestError::ShuttingDown => Fate::Shutdown,
                    RequestError::NoResponse { last, .. } => Fate::of_no_reply(*last),
                };
                (
                    fate,
                    Some((ExceptionSource::Gateway, error.exception_code() as u8)),
                )
            }
        }
    }
}

impl Fate {
    /// The fate of one try on the line (a request may take several), as the trace shows it.
    pub(crate) fn of_try(result: &Result<Reply, TxError>) -> Fate {
        match result {
            Ok(Reply::Fits(pdu))
                if pdu
                    .first()
                    .is_some_and(|f| f & crate::pdu::EXCEPTION_BIT != 0) =>
            {
                Fate::Exception
            }
            Ok(Reply::Fits(_)) => Fate::Ok,
            Ok(Reply::Malformed(_)) => Fate::MalformedReply,
            Err(error) => Fate::of_failed_try(error),
        }
    }

    /// The fate of a request whose last try got no valid reply.
    pub(crate) fn of_no_reply(last: NoReply) -> Fate {
        match last {
            NoReply::Timeout => Fate::Timeout,
            NoReply::Check => Fate::CrcError,
            NoReply::Frame | NoReply::Echo | NoReply::ModbusTcp => Fate::FrameError,
            NoReply::LineBusy => Fate::LineBusy,
        }
    }

    /// The fate of a try that got no answer.
    pub(crate) fn of_failed_try(error: &TxError) -> Fate {
        match error {
            TxError::Timeout => Fate::Timeout,
            TxError::Check => Fate::CrcError,
            TxError::Frame | TxError::Echo | TxError::ModbusTcp => Fate::FrameError,
            TxError::LineBusy => Fate::LineBusy,
            TxError::PortLost(_) => Fate::PortDown,
        }
    }
}

/// Who made an exception reply: the `source` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ExceptionSource {
    Slave,
    Gateway,
}

impl ExceptionSource {
    pub(crate) fn label(self) -> &'static str {
        match self {
            ExceptionSource::Slave => "slave",
            ExceptionSource::Gateway => "gateway",
        }
    }
}

/// Why the gateway closed a device server's connection itself: the `reason` label of
/// `modbus_gateway_link_dropped_total`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum LinkDrop {
    /// An RFC 2217 converter's option negotiation asked for more Telnet answers between two
    /// frames than the gateway keeps.
    TelnetAnswers,
}

impl LinkDrop {
    pub(crate) const ALL: [LinkDrop; 1] = [LinkDrop::TelnetAnswers];

    pub(crate) fn label(self) -> &'static str {
        match self {
            LinkDrop::TelnetAnswers => "telnet_answers",
        }
    }

    /// The transport on which it can happen: its series is there, at zero, from the start.
    pub(crate) fn transport(self) -> TransportKind {
        match self {
            LinkDrop::TelnetAnswers => TransportKind::Rfc2217,
        }
    }
}

/// Why a TCP connection was refused at accept: the `reason` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rejection {
    /// `max_connections` open, none of them evictable (or `when_full = "refuse"`).
    MaxConnections,
    /// `max_connections_per_address` open from the peer's address.
    MaxConnectionsPerAddress,
    /// The peer's address is outside `server.allow`.
    NotAllowed,
    /// The TLS handshake failed or did not finish within `server.tls.handshake_timeout`.
    TlsHandshake,
}

impl Rejection {
    /// The refusals every TCP listener may make (a TLS handshake only fails on a TLS one).
    pub(crate) const ALL: [Rejection; 3] = [
        Rejection::MaxConnections,
        Rejection::MaxConnectionsPerAddress,
        Rejection::NotAllowed,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Rejection::MaxConnections => "max_connections",
            Rejection::MaxConnectionsPerAddress => "max_connections_per_address",
            Rejection::NotAllowed => "not_allowed",
            Rejection::TlsHandshake => "tls_handshake",
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
    /// Closed to make room for a new master at `max_connections` (see `when_full`).
    Evicted,
    /// A reply waited `frame_timeout` for the master to read: it does not read its replies.
    WriteTimeout,
}

impl Closing {
    pub(crate) const ALL: [Closing; 8] = [
        Closing::ByMaster,
        Closing::ProtocolError,
        Closing::Idle,
        Closing::IoError,
        Closing::Shutdown,
        Closing::FrameTimeout,
        Closing::Evicted,
        Closing::WriteTimeout,
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
            Closing::WriteTimeout => "write_timeout",
        }
    }
}

/// The label value of what a master chose and the configuration does not bound: a unit id
/// nobody answers at, a function code the gateway does not know.
pub(in crate::metrics) const OTHER: &str = "other";

/// The `function` label of a request: its code, as the spec writes it, if the gateway knows
/// the function, else [`OTHER`]; so no master can make more series than the table has rows.
pub(in crate::metrics) fn function(code: u8) -> &'static str {
    if crate::pdu::function(code).is_some() {
        hex(code)
    } else {
        OTHER
    }
}

/// Label values for addresses and codes, made once: the request path formats nothing.
pub(in crate::metrics) fn decimal(n: u8) -> &'static str {
    static TABLE: OnceLock<Vec<String>> = OnceLock::new();
    &TABLE.get_or_init(|| (0..=u8::MAX).map(|n| n.to_string()).collect())[usize::from(n)]
}

/// `0x03`, as the Modbus spec writes function and exception codes.
pub(in crate::metrics) fn hex(n: u8) -> &'static str {
    static TABLE: OnceLock<Vec<String>> = OnceLock::new();
    &TABLE.get_or_init(|| (0..=u8::MAX).map(|n| format!("0x{n:02X}")).collect())[usize::from(n)]
}

pub(super) fn seconds_since_epoch() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs_f64()
}
