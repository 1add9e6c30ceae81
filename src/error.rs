//! What fails one request (a connection's own failures are `net::session`'s), what answers it,
//! and the one place such a failure becomes the exception code the master sees.

pub use crate::line::NoReply;
use crate::line::Reply;
use crate::pdu::ExceptionCode;

/// What a request gets: an [`Answer`] to send back, or a failure the gateway answers itself.
pub type Outcome = Result<Answer, RequestError>;

/// What goes back to the master when the line gave an answer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Answer {
    /// The slave's reply PDU, normal or exception, byte for byte; for a broadcast, the normal
    /// response to the write (`broadcast_reply = true`).
    Reply(Vec<u8>),
    /// The slave's reply PDU, byte for byte, though it does not have the shape the request asks
    /// for (a byte count or echo that does not match): the slave's own answer all the same.
    Malformed(Vec<u8>),
    /// Nothing: a broadcast with `broadcast_reply = false`.
    Nothing,
    /// The normal reply to a write, made by the gateway for an `acknowledge` rule: the write
    /// was never sent.
    Acknowledged(Vec<u8>),
}

impl Answer {
    /// The PDU the master gets, if any.
    pub fn into_pdu(self) -> Option<Vec<u8>> {
        match self {
            Answer::Reply(pdu) | Answer::Malformed(pdu) | Answer::Acknowledged(pdu) => Some(pdu),
            Answer::Nothing => None,
        }
    }
}

impl From<Reply> for Answer {
    fn from(reply: Reply) -> Self {
        match reply {
            Reply::Fits(pdu) => Answer::Reply(pdu),
            Reply::Malformed(pdu) => Answer::Malformed(pdu),
        }
    }
}

/// What failed one request: a value to copy to every master that shared its transaction. A lost
/// port is no request's failure: its `io::Error` stays with the bus that lost it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum RequestError {
    #[error("function code {0:#04x} is not valid in a request")]
    InvalidFunction(u8),
    #[error(
        "a function {function:#04x} request of {len} bytes: not the length its function gives it"
    )]
    BadLength { function: u8, len: usize },
    #[error("function code {0:#04x} refused: its length cannot be checked, and the master's TLS role may address only some units")]
    Unverifiable(u8),
    #[error("function code {0:#04x} may change the slave, and the master is read-only")]
    ReadOnly(u8),
    #[error("function code {0:#04x} refused: the master's TLS role allows nothing")]
    NoAccess(u8),
    #[error("unit {0} refused: the master's TLS role may not address it")]
    UnitNotPermitted(u8),
    #[error("function code {function:#04x} refused by a [[rule]]")]
    Denied { function: u8, registers: bool },
    #[error("function code {0:#04x} refused: the audit journal cannot be written (audit.on_error = \"deny_writes\")")]
    Unrecorded(u8),
    #[error("no route for unit {0}")]
    NoRoute(u8),
    /// A virtual unit's own exception: what it does not lay out (0x02), answer (0x01) or hold
    /// (0x03), or a value too old (0x0B). Nothing was sent.
    #[error("the virtual unit answers it with exception {0:?}; nothing was sent")]
    Emulated(ExceptionCode),
    /// A listen-only line's answer to anything that is not a read: nothing is sent on it.
    #[error("function code {0:#04x} refused: the line is listen-only (mode = \"listen\"); nothing is sent on it")]
    ListenOnly(u8),
    /// A listen-only line's answer to a read of registers its other master has not read within
    /// `max_age`, or never.
    #[error("not seen on the listen-only line within its max_age; nothing was sent")]
    Unseen,
    /// A listen-only line's answer to a read of no registers or more than a read may take.
    #[error("function code {0:#04x}: a read of a quantity no slave answers; nothing was sent")]
    Unreadable(u8),
    #[error("function code {0:#04x} cannot be broadcast")]
    NotBroadcastable(u8),
    #[error("serial port is down")]
    PortDown,
    #[error("the port was lost during the transaction: the request may have reached the slave")]
    PortLost,
    #[error("bus queue is full")]
    QueueFull,
    #[error("not sent within the queue timeout")]
    Expired,
    #[error("the gateway is shutting down")]
    ShuttingDown,
    #[error("slave is down (timed out {timeouts} times in a row); not sent")]
    SlaveDown { timeouts: u32 },
    #[error("no valid reply after {attempts} attempt(s): {last}")]
    NoResponse { attempts: u32, last: NoReply },
}

impl RequestError {
    /// The exception the gateway answers with. Everything the gateway refuses on its own goes
    /// through here.
    pub fn exception_code(&self) -> ExceptionCode {
        match self {
            RequestError::InvalidFunction(_)
            | RequestError::NotBroadcastable(_)
            | RequestError::ReadOnly(_)
            | RequestError::NoAccess(_)
            | RequestError::Unverifiable(_)
            | RequestError::UnitNotPermitted(_)
            | RequestError::ListenOnly(_) => ExceptionCode::IllegalFunction,
            RequestError::Unreadable(_) => ExceptionCode::IllegalDataValue,
            RequestError::Denied {
                registers: false, ..
            } => ExceptionCode::IllegalFunction,
            RequestError::Denied {
                registers: true, ..
            } => ExceptionCode::IllegalDataAddress,
            RequestError::BadLength { .. } => ExceptionCode::IllegalDataValue,
            RequestError::Emulated(code) => *code,
            RequestError::NoRoute(_)
            | RequestError::PortDown
            | RequestError::PortLost
            | RequestError::Unrecorded(_)
            | RequestError::ShuttingDown => ExceptionCode::GatewayPathUnavailable,
            RequestError::QueueFull | RequestError::Expired => ExceptionCode::ServerDeviceBusy,
            RequestError::NoResponse { .. }
            | RequestError::SlaveDown { .. }
            | RequestError::Unseen => ExceptionCode::GatewayTargetFailedToRespond,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::TxError;

    #[test]
    fn a_failed_try_keeps_its_message_and_a_lost_port_its_io_error() {
        let tries = [
            TxError::Timeout,
            TxError::Check,
            TxError::Frame,
            TxError::LineBusy,
            TxError::Echo,
        ];
        for error in tries {
            let message = error.to_string();
            assert_eq!(
                NoReply::try_from(error).expect("no reply").to_string(),
                message
            );
        }
        let lost = TxError::PortLost(std::io::Error::other("unplugged"));
        assert_eq!(
            NoReply::try_from(lost).expect_err("port lost").to_string(),
            "unplugged"
        );
    }
}
