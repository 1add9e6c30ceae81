//! How an item reads: one line for a terminal, or one JSON object.

use super::filter::span;
use super::join::{End, Item, Record};
use crate::audit::entry::{Carried, Ended, Gap, Write};
use crate::pdu;
use serde::Serialize;
use std::fmt::Write as _;

/// One line for a terminal. Control characters in the journal's strings (a certificate's
/// subject, an error, a line someone edited) are shown escaped, never sent to the terminal.
pub(crate) fn describe(item: &Item) -> String {
    let line = match item {
        Item::Write(record) => describe_write(record),
        Item::Gap(gap) => {
            let mut went = Vec::new();
            if gap.unrecorded > 0 {
                went.push(format!("{} went unrecorded", writes(gap.unrecorded)));
            }
            if gap.refused > 0 {
                went.push(format!("{} refused (0x0A)", writes(gap.refused)));
            }
            match gap.lost_outcomes {
                0 => {}
                1 => went.push("1 outcome line lost".to_owned()),
                n => went.push(format!("{n} outcome lines lost")),
            }
            if went.is_empty() {
                went.push("no write missed".to_owned());
            }
            format!(
                "{}  gap: the journal could not be written from {}: {}; {}",
                gap.time,
                gap.since,
                gap.error,
                went.join(", ")
            )
        }
    };
    if !line.contains(char::is_control) {
        return line;
    }
    line.chars()
        .fold(String::with_capacity(line.len()), |mut shown, c| {
            if c.is_control() {
                shown.extend(c.escape_default());
            } else {
                shown.push(c);
            }
            shown
        })
}

fn writes(n: u64) -> String {
    if n == 1 {
        "1 write".to_owned()
    } else {
        format!("{n} writes")
    }
}

/// `TIME  MASTER PROTOCOL [subject S] [role R]  unit U -> BUS slave S  FUNCTION [TABLE RANGE]
/// [= VALUES]  rule R: ACTION  OUTCOME`.
fn describe_write(record: &Record) -> String {
    let write = &record.write;
    let mut line = format!("{}  {} {}", write.time, write.master, write.protocol);
    if let Some(subject) = &write.subject {
        let _ = write!(line, " subject \"{subject}\"");
    }
    if let Some(role) = &write.role {
        let _ = write!(line, " role {role}");
    }
    let _ = write!(line, "  unit {} -> ", write.unit);
    match (&write.bus, write.slave) {
        (Some(bus), Some(slave)) => {
            let _ = write!(line, "{bus} slave {slave}");
        }
        (Some(bus), None) => line.push_str(bus),
        (None, Some(slave)) => {
            let _ = write!(line, "slave {slave}");
        }
        (None, None) => line.push_str("no route"),
    }
    let function = write.function;
    match pdu::function(function) {
        Some(known) => {
            let _ = write!(line, "  {} (0x{function:02X})", known.name);
        }
        None => {
            let _ = write!(line, "  function 0x{function:02X}");
        }
    }
    if let (Some(table), Some((first, last))) = (&write.table, span(write)) {
        let _ = write!(line, " {table} 0x{first:04X}");
        if last > first {
            let _ = write!(line, "-0x{last:04X}");
        }
    }
    if !write.values.is_empty() {
        // Registers as the words they are; anything else (packed coils, a user-defined
        // function's bytes) byte by byte.
        let digits = if write.table.as_deref() == Some("holding") {
            4
        } else {
            2
        };
        let groups: Vec<&str> = write
            .values
            .as_bytes()
            .chunks(digits)
            .filter_map(|group| std::str::from_utf8(group).ok())
            .collect();
        let _ = write!(line, " = {}", groups.join(" "));
    }
    match &write.rule {
        Some(rule) => {
            let _ = write!(line, "  rule {rule}: {}", write.action);
        }
        None => {
            let _ = write!(line, "  no rule: {}", write.action);
        }
    }
    line.push_str("  ");
    line.push_str(&ending(record));
    line
}

/// How the write ended, in words.
pub(super) fn ending(record: &Record) -> String {
    let why = match &record.end {
        End::Recorded(ended) => {
            let mut text = ended.outcome.label().to_owned();
            if let Some(code) = ended.exception {
                let _ = write!(text, " (0x{code:02X})");
            }
            match &ended.detail {
                Some(detail) => {
                    let _ = write!(text, ": {detail}");
                }
                None if ended.carried_out == Carried::Maybe => {
                    text.push_str(": may have been carried out");
                }
                None => {}
            }
            return text;
        }
        End::Stopped => "the gateway stopped before its outcome",
        End::Waiting => "no outcome yet",
    };
    // A write its rule refused or acknowledged is never sent, outcome or not.
    let sent = match record.write.action.as_str() {
        "deny" | "acknowledge" => format!("not sent (action {})", record.write.action),
        _ => "may have been carried out".to_owned(),
    };
    format!("no outcome recorded: {sent} ({why})")
}

/// A write as `--json` prints it: its journal fields, `kind` `write`, and `outcome`, the
/// outcome line's fields or null; a null outcome's `pending` says why.
#[derive(Serialize)]
struct WriteJson<'a> {
    kind: &'static str,
    #[serde(flatten)]
    write: &'a Write,
    outcome: Option<&'a Ended>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pending: Option<&'static str>,
}

#[derive(Serialize)]
struct GapJson<'a> {
    kind: &'static str,
    #[serde(flatten)]
    gap: &'a Gap,
}

/// One JSON object.
pub(crate) fn as_json(item: &Item) -> String {
    let text = match item {
        Item::Write(record) => {
            let (outcome, pending) = match &record.end {
                End::Recorded(ended) => (Some(ended), None),
                End::Stopped => (None, Some("gateway_stopped")),
                End::Waiting => (None, Some("no_outcome_yet")),
            };
            serde_json::to_string(&WriteJson {
                kind: "write",
                write: &record.write,
                outcome,
                pending,
            })
        }
        Item::Gap(gap) => serde_json::to_string(&GapJson { kind: "gap", gap }),
    };
    // Strings and numbers only: it cannot fail, but a line saying so beats a panic.
    text.unwrap_or_else(|e| format!("{{\"kind\":\"error\",\"error\":\"{e}\"}}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::audit::entry::Outcome;
    use crate::cli::audit::fixtures::*;

    #[test]
    fn a_tls_master_an_exception_and_a_user_defined_function_are_described() {
        let mut tls = record(&write(4, "2026-11-28T10:15:02.123456Z"));
        tls.write.protocol = "tls".into();
        tls.write.subject = Some("CN=hmi-1, O=Plant".into());
        tls.write.role = Some("operator".into());
        tls.end = End::Recorded(Ended {
            time: "2026-11-28T10:15:03.123456Z".into(),
            id: 4,
            outcome: Outcome::Timeout,
            carried_out: Carried::Maybe,
            exception: Some(0x0B),
            detail: None,
        });
        let line = describe(&Item::Write(Box::new(tls.clone())));
        assert!(
            line.contains(
                "192.168.20.5:50312 tls subject \"CN=hmi-1, O=Plant\" role operator  unit 3"
            ),
            "{line}"
        );
        assert!(
            line.ends_with("  timeout (0x0B): may have been carried out"),
            "{line}"
        );
        tls.end = End::Recorded(Ended {
            time: "2026-11-28T10:15:03.123456Z".into(),
            id: 4,
            outcome: Outcome::SlaveException,
            carried_out: Carried::No,
            exception: Some(0x02),
            detail: Some("the slave refused it: illegal data address".into()),
        });
        tls.write.role = Some("op\u{1b}[2J".into());
        let line = describe(&Item::Write(Box::new(tls)));
        assert!(
            line.ends_with("  slave_exception (0x02): the slave refused it: illegal data address"),
            "{line}"
        );
        assert!(line.contains(" role op\\u{1b}[2J  unit 3"), "{line}");
        let custom = record(
            r#"{"kind":"write","time":"2026-11-28T10:15:02Z","id":5,"master":"10.0.0.1:40000","protocol":"udp","unit":7,"bus":null,"slave":null,"function":65,"values":"0102A0","rule":null,"action":"deny"}"#,
        );
        assert_eq!(
            describe(&Item::Write(Box::new(Record {
                end: End::Waiting,
                ..custom
            }))),
            "2026-11-28T10:15:02Z  10.0.0.1:40000 udp  unit 7 -> no route  function 0x41 = 01 02 A0  \
             no rule: deny  no outcome recorded: not sent (action deny) (no outcome yet)"
        );
    }
}
