//! The journal's lines: what the gateway writes and `modbus-gateway audit` reads back, one JSON
//! object a line, told apart by `kind`. A write has two lines sharing its `id`: the `write`,
//! written before anything is sent, and its `outcome`, written when it ends. Ids count from 1
//! when the gateway starts and are never reused while it runs; `open` is written when the
//! gateway opens a journal (at start, or a reload's new path), so the ids after an `open` that
//! starts a run count from 1 again. `gap` says how many writes went unrecorded, or were
//! refused, while the journal could not be written.

use serde::{Deserialize, Serialize};

/// One line of the journal.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub(crate) enum Line {
    Open(Opened),
    Write(Write),
    Outcome(Ended),
    Gap(Gap),
}

/// The gateway began a run on this journal.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct Opened {
    /// UTC, RFC 3339 with microseconds.
    pub(crate) time: String,
    pub(crate) pid: u32,
    pub(crate) version: String,
}

/// A write-class request, as it was decided: written before it is sent.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct Write {
    pub(crate) time: String,
    /// Counts from 1 in each run; its outcome line has the same.
    pub(crate) id: u64,
    /// The master's address and port.
    pub(crate) master: String,
    /// `tcp`, `rtu_over_tcp`, `udp` or `tls`.
    pub(crate) protocol: String,
    /// A TLS master's certificate subject.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) subject: Option<String>,
    /// A TLS master's certificate role, as written in it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) role: Option<String>,
    pub(crate) unit: u8,
    /// The bus and slave address the unit routes to; none without a route.
    #[serde(default)]
    pub(crate) bus: Option<String>,
    #[serde(default)]
    pub(crate) slave: Option<u8>,
    /// The virtual unit it was made to, or whose register it writes through.
    #[serde(default, rename = "virtual", skip_serializing_if = "Option::is_none")]
    pub(crate) virtual_unit: Option<String>,
    pub(crate) function: u8,
    /// The table and addresses it writes, when its bytes say (`coil`, `holding`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) table: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) start: Option<u16>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) count: Option<u32>,
    /// The values written, hex, as on the wire; for a function that names no registers, every
    /// byte after the function code.
    pub(crate) values: String,
    /// The rule that decided: a `[[rule]]`'s name (`rule N` without one), `server.read_only`,
    /// or `server.tls.roles.NAME`; none when no rule matched.
    #[serde(default)]
    pub(crate) rule: Option<String>,
    /// `allow`, `deny` or `acknowledge`.
    pub(crate) action: String,
}

/// How a write ended: written when it does.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct Ended {
    pub(crate) time: String,
    pub(crate) id: u64,
    pub(crate) outcome: WriteOutcome,
    /// Whether the slave did it: `yes`, `no`, or `maybe` (sent, and no reply says).
    pub(crate) carried_out: Carried,
    /// The exception code the master got (the slave's, the gateway's or the rule's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) exception: Option<u8>,
    /// Why, in words.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) detail: Option<String>,
}

/// Writes the journal could not record: with `on_error = "allow"` they went on unrecorded,
/// with `"deny_writes"` they were refused (0x0A). Written once it can be again.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct Gap {
    pub(crate) time: String,
    /// When the first entry could not be written.
    pub(crate) since: String,
    pub(crate) unrecorded: u64,
    pub(crate) refused: u64,
    /// Outcome lines of writes that could not be written: those writes read "no outcome
    /// recorded".
    #[serde(default)]
    pub(crate) lost_outcomes: u64,
    /// The first error.
    pub(crate) error: String,
}

/// How a write ended; the `outcome` label of `modbus_gateway_writes_total`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum WriteOutcome {
    /// The slave's normal reply.
    Answered,
    /// The slave's exception.
    SlaveException,
    /// The gateway answered with its own exception, unsent (no route, queue full, port down,
    /// bad length...), or after a lost port cut it off.
    GatewayException,
    /// A rule, `server.read_only` or a TLS role refused it, unsent.
    Denied,
    /// An `acknowledge` rule answered it with its normal reply, unsent.
    Acknowledged,
    /// Sent, and no valid reply came: it may have been carried out.
    Timeout,
    /// Sent to every slave (address 0), which never answer: it may have been carried out.
    Broadcast,
    /// Its master left before it was sent.
    Cancelled,
}

impl WriteOutcome {
    pub(crate) const ALL: [WriteOutcome; 8] = [
        WriteOutcome::Answered,
        WriteOutcome::SlaveException,
        WriteOutcome::GatewayException,
        WriteOutcome::Denied,
        WriteOutcome::Acknowledged,
        WriteOutcome::Timeout,
        WriteOutcome::Broadcast,
        WriteOutcome::Cancelled,
    ];

    pub(crate) fn label(self) -> &'static str {
        match self {
            WriteOutcome::Answered => "answered",
            WriteOutcome::SlaveException => "slave_exception",
            WriteOutcome::GatewayException => "gateway_exception",
            WriteOutcome::Denied => "denied",
            WriteOutcome::Acknowledged => "acknowledged",
            WriteOutcome::Timeout => "timeout",
            WriteOutcome::Broadcast => "broadcast",
            WriteOutcome::Cancelled => "cancelled",
        }
    }
}

/// Whether a write was carried out, as far as the gateway can know.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum Carried {
    Yes,
    No,
    Maybe,
}

/// The time now as the journal writes it: UTC, RFC 3339, microseconds.
pub(crate) fn now() -> String {
    humantime::format_rfc3339_micros(std::time::SystemTime::now()).to_string()
}

/// `bytes` as upper-case hex, no separators.
pub(crate) fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write as _;
    bytes
        .iter()
        .fold(String::with_capacity(bytes.len() * 2), |mut out, b| {
            let _ = write!(out, "{b:02X}");
            out
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_write_and_its_outcome_are_one_json_object_a_line_that_reads_back_the_same() {
        let write = Line::Write(Write {
            time: "2026-11-28T10:15:02.123456Z".into(),
            id: 7,
            master: "192.168.20.5:50312".into(),
            protocol: "tls".into(),
            subject: Some("CN=hmi-1".into()),
            role: Some("operator".into()),
            unit: 3,
            bus: Some("line1".into()),
            slave: Some(3),
            virtual_unit: None,
            function: 0x10,
            table: Some("holding".into()),
            start: Some(0x2000),
            count: Some(2),
            values: hex(&[0x13, 0x88, 0x00, 0x32]),
            rule: Some("wallbox".into()),
            action: "allow".into(),
        });
        let text = serde_json::to_string(&write).unwrap();
        assert!(
            text.starts_with(r#"{"kind":"write","time":"2026-11-28T10:15:02.123456Z","id":7,"#),
            "{text}"
        );
        assert!(text.contains(r#""values":"13880032""#), "{text}");
        assert!(!text.contains('\n'));
        assert_eq!(serde_json::from_str::<Line>(&text).unwrap(), write);
        let ended = Line::Outcome(Ended {
            time: now(),
            id: 7,
            outcome: WriteOutcome::Timeout,
            carried_out: Carried::Maybe,
            exception: Some(0x0B),
            detail: Some("no valid reply after 1 attempt(s): no reply".into()),
        });
        let text = serde_json::to_string(&ended).unwrap();
        assert!(
            text.contains(r#""outcome":"timeout","carried_out":"maybe""#),
            "{text}"
        );
        assert_eq!(serde_json::from_str::<Line>(&text).unwrap(), ended);
        assert!(now().ends_with('Z') && now().len() == "2026-11-28T10:15:02.123456Z".len());
    }
}
