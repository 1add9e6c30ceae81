//! How an item reads: one line for a terminal, or one JSON object. Every string of the journal
//! is shown as the gateway's log shows its text fields, escaped (see [`field`]): the journal
//! carries what masters sent and their certificates say, and none of it may reach a terminal
//! as anything but text, nor pass for another field of the line.

use super::filter::span;
use super::join::{End, Listed, Record};
use crate::audit::entry::{Carried, Ended, Gap, Write};
use crate::pdu;
use serde::Serialize;
use std::borrow::Cow;
use std::fmt::Write as _;
use std::io;

/// `text` as one field of a line: as it is when it is a plain word; otherwise quoted and
/// escaped exactly as the gateway's log writes a text field (tracing's text format writes them
/// with Rust's `{:?}`): `"` and `\` escaped, and every character that is not printable as
/// `\u{...}`, among them the controls (Cc), the format characters (Cf: the bidi controls
/// U+202A-U+202E and U+2066-U+2069, U+200B, U+FEFF...), the separators but the space and the
/// combining marks. So no value can close its quotes early, run into the next field, or make a
/// terminal reorder, hide or colour the line.
pub(super) fn field(text: &str) -> Cow<'_, str> {
    let plain = |b: u8| b.is_ascii_graphic() && b != b'"' && b != b'\\';
    if !text.is_empty() && text.bytes().all(plain) {
        return Cow::Borrowed(text);
    }
    let quoted = format!("{text:?}");
    let unchanged = quoted.len() == text.len() + 2;
    if unchanged && !text.is_empty() && !text.contains(char::is_whitespace) {
        Cow::Borrowed(text)
    } else {
        Cow::Owned(quoted)
    }
}

/// `text` that ends a line or a clause (an outcome's detail, a gap's error): escaped as
/// [`field`] escapes, without the quotes; it may hold spaces.
pub(super) fn prose(text: &str) -> String {
    let quoted = format!("{text:?}");
    let inner = quoted.strip_prefix('"').and_then(|q| q.strip_suffix('"'));
    inner.unwrap_or(&quoted).to_owned()
}

/// Whether [`field`] shows `c` escaped (`"` and `\` aside, which have escapes of their own).
fn hidden(c: char) -> bool {
    !matches!(c, '"' | '\\' | '\'') && c.escape_debug().len() > 1
}

/// One line for a terminal.
pub(crate) fn describe(item: &Listed) -> String {
    match item {
        Listed::Write(record) => describe_write(record),
        Listed::Gap(gap) => describe_gap(gap),
    }
}

/// `TIME  gap: the journal could not be written from SINCE: ERROR; WHAT WENT MISSING`.
fn describe_gap(gap: &Gap) -> String {
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
        field(&gap.time),
        field(&gap.since),
        prose(&gap.error),
        went.join(", ")
    )
}

fn writes(n: u64) -> String {
    if n == 1 {
        "1 write".to_owned()
    } else {
        format!("{n} writes")
    }
}

/// `TIME  MASTER PROTOCOL [subject "S"] [role R]  unit U -> BUS slave S  FUNCTION [TABLE RANGE]
/// [= VALUES]  rule R: ACTION  OUTCOME`.
fn describe_write(record: &Record) -> String {
    let write = &record.write;
    let mut line = format!(
        "{}  {} {}",
        field(&write.time),
        field(&write.master),
        field(&write.protocol)
    );
    if let Some(subject) = &write.subject {
        // Always quoted: a subject has spaces (`CN=hmi-1, O=Plant`).
        let _ = write!(line, " subject {subject:?}");
    }
    if let Some(role) = &write.role {
        let _ = write!(line, " role {}", field(role));
    }
    let _ = write!(line, "  unit {} -> ", write.unit);
    match (&write.bus, write.slave) {
        (Some(bus), Some(slave)) => {
            let _ = write!(line, "{} slave {slave}", field(bus));
        }
        (Some(bus), None) => line.push_str(&field(bus)),
        (None, Some(slave)) => {
            let _ = write!(line, "slave {slave}");
        }
        (None, None) => match &write.virtual_unit {
            Some(name) => {
                let _ = write!(line, "virtual {}", field(name));
            }
            None => line.push_str("no route"),
        },
    }
    if let (Some(name), Some(_)) = (&write.virtual_unit, write.slave) {
        let _ = write!(line, " (through virtual {})", field(name));
    }
    line.push_str("  ");
    line.push_str(&what(write));
    let action = field(&write.action);
    match &write.rule {
        Some(rule) => {
            let _ = write!(line, "  rule {}: {action}", field(rule));
        }
        None => {
            let _ = write!(line, "  no rule: {action}");
        }
    }
    line.push_str("  ");
    line.push_str(&ending(record));
    line
}

/// `FUNCTION [TABLE RANGE] [= VALUES]`.
fn what(write: &Write) -> String {
    let function = write.function;
    let mut what = match pdu::function(function) {
        Some(known) => format!("{} (0x{function:02X})", known.name),
        None => format!("function 0x{function:02X}"),
    };
    if let (Some(table), Some((first, last))) = (&write.table, span(write)) {
        let _ = write!(what, " {} 0x{first:04X}", field(table));
        if last > first {
            let _ = write!(what, "-0x{last:04X}");
        }
    }
    let values = &write.values;
    if values.bytes().all(|b| b.is_ascii_hexdigit()) {
        if !values.is_empty() {
            // Registers as the words they are; anything else (packed coils, a user-defined
            // function's bytes) byte by byte.
            let digits = if write.table.as_deref() == Some("holding") {
                4
            } else {
                2
            };
            let groups: Vec<&str> = values
                .as_bytes()
                .chunks(digits)
                .filter_map(|group| std::str::from_utf8(group).ok())
                .collect();
            let _ = write!(what, " = {}", groups.join(" "));
        }
    } else {
        // Not what the gateway writes (an edited journal): shown whole, as a field.
        let _ = write!(what, " = {}", field(values));
    }
    what
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
                    let _ = write!(text, ": {}", prose(detail));
                }
                None if ended.carried_out == Carried::Maybe => {
                    text.push_str(": may have been carried out");
                }
                None => {}
            }
            return text;
        }
        End::Stopped => "the gateway stopped before its outcome",
        End::Lost => "its outcome line was lost: see the gap after it",
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

/// One JSON object. Its strings read back as the journal has them; the characters [`field`]
/// escapes are written as JSON escapes (`\u202e`), so that the line too is harmless on a
/// terminal.
pub(crate) fn as_json(item: &Listed) -> String {
    let mut bytes = Vec::new();
    let mut out = serde_json::Serializer::with_formatter(&mut bytes, Harmless);
    let done = match item {
        Listed::Write(record) => {
            let (outcome, pending) = match &record.end {
                End::Recorded(ended) => (Some(ended), None),
                End::Stopped => (None, Some("gateway_stopped")),
                End::Lost => (None, Some("outcome_lost")),
                End::Waiting => (None, Some("no_outcome_yet")),
            };
            let write = WriteJson {
                kind: "write",
                write: &record.write,
                outcome,
                pending,
            };
            write.serialize(&mut out)
        }
        Listed::Gap(gap) => GapJson { kind: "gap", gap }.serialize(&mut out),
    };
    let text = done
        .map_err(|e| e.to_string())
        .and_then(|()| String::from_utf8(bytes).map_err(|e| e.to_string()));
    // Strings and numbers only: it cannot fail, but a line saying so beats a panic.
    text.unwrap_or_else(|e| serde_json::json!({ "kind": "error", "error": e }).to_string())
}

/// serde_json's compact format, with the characters [`field`] escapes (but those JSON escapes
/// already) as `\uXXXX`.
struct Harmless;

impl serde_json::ser::Formatter for Harmless {
    fn write_string_fragment<W: ?Sized + io::Write>(
        &mut self,
        writer: &mut W,
        fragment: &str,
    ) -> io::Result<()> {
        let mut shown = 0;
        for (at, c) in fragment.char_indices().filter(|&(_, c)| hidden(c)) {
            writer.write_all(&fragment.as_bytes()[shown..at])?;
            let mut units = [0; 2];
            for unit in c.encode_utf16(&mut units) {
                write!(writer, "\\u{unit:04x}")?;
            }
            shown = at + c.len_utf8();
        }
        writer.write_all(&fragment.as_bytes()[shown..])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::audit::entry::WriteOutcome;
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
            outcome: WriteOutcome::Timeout,
            carried_out: Carried::Maybe,
            exception: Some(0x0B),
            detail: None,
        });
        let line = describe(&Listed::Write(Box::new(tls.clone())));
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
            outcome: WriteOutcome::SlaveException,
            carried_out: Carried::No,
            exception: Some(0x02),
            detail: Some("the slave refused it: illegal data address".into()),
        });
        tls.write.role = Some("op\u{1b}[2J".into());
        let line = describe(&Listed::Write(Box::new(tls)));
        assert!(
            line.ends_with("  slave_exception (0x02): the slave refused it: illegal data address"),
            "{line}"
        );
        assert!(line.contains(" role \"op\\u{1b}[2J\"  unit 3"), "{line}");
        let custom = record(
            r#"{"kind":"write","time":"2026-11-28T10:15:02Z","id":5,"master":"10.0.0.1:40000","protocol":"udp","unit":7,"bus":null,"slave":null,"function":65,"values":"0102A0","rule":null,"action":"deny"}"#,
        );
        assert_eq!(
            describe(&Listed::Write(Box::new(Record {
                end: End::Waiting,
                ..custom
            }))),
            "2026-11-28T10:15:02Z  10.0.0.1:40000 udp  unit 7 -> no route  function 0x41 = 01 02 A0  \
             no rule: deny  no outcome recorded: not sent (action deny) (no outcome yet)"
        );
    }

    /// A TLS master's write, its subject and role as `change` makes them, answered.
    fn tls_write(change: impl FnOnce(&mut Write)) -> Record {
        let mut record = record(&write(4, "2026-11-28T10:15:02.123456Z"));
        record.write.protocol = "tls".into();
        change(&mut record.write);
        record
    }

    #[test]
    fn a_subject_with_a_quote_cannot_pass_for_a_role_it_does_not_have() {
        let record = tls_write(|w| w.subject = Some("CN=maint\" role operator".into()));
        let line = describe(&Listed::Write(Box::new(record)));
        assert!(
            line.contains(r#" tls subject "CN=maint\" role operator"  unit 3 -> line1"#),
            "{line}"
        );
        let spaced = tls_write(|w| w.role = Some("operator  unit 9".into()));
        let line = describe(&Listed::Write(Box::new(spaced)));
        assert!(
            line.contains(r#" tls role "operator  unit 9"  unit 3 -> "#),
            "a role with spaces is quoted: {line}"
        );
    }

    #[test]
    fn bidi_and_invisible_characters_print_escaped_in_every_field_and_text() {
        let mut record = tls_write(|w| {
            w.subject = Some("CN=\u{202E}nimda".into());
            w.role = Some("op\u{2066}x".into());
            w.bus = Some("line\u{200B}1".into());
            w.rule = Some("wall\u{202E}box".into());
            w.master = "10.0.0.1:1\u{FEFF}".into();
        });
        record.end = End::Recorded(Ended {
            time: "2026-11-28T10:15:03Z".into(),
            id: 4,
            outcome: WriteOutcome::Denied,
            carried_out: Carried::No,
            exception: Some(0x01),
            detail: Some("rule \"wall\u{202E}box\" denies it".into()),
        });
        let line = describe(&Listed::Write(Box::new(record)));
        assert!(!line.contains(hidden), "{line:?}");
        assert!(
            line.contains(
                r#"  "10.0.0.1:1\u{feff}" tls subject "CN=\u{202e}nimda" role "op\u{2066}x"  unit 3 -> "line\u{200b}1" slave 3  "#
            ),
            "{line}"
        );
        assert!(
            line.ends_with(
                r#"  rule "wall\u{202e}box": allow  denied (0x01): rule \"wall\u{202e}box\" denies it"#
            ),
            "{line}"
        );
        let gap = Gap {
            time: "2026-11-28T10:20:00Z".into(),
            since: "2026-11-28T10:16:00Z".into(),
            unrecorded: 1,
            refused: 0,
            lost_outcomes: 0,
            error: "disk\u{2067} full\n".into(),
        };
        let line = describe(&Listed::Gap(gap));
        assert!(
            line.contains(r#"10:16:00Z: disk\u{2067} full\n; 1 write went"#),
            "{line}"
        );
    }

    #[test]
    fn json_escapes_the_characters_the_text_escapes_and_reads_back_the_same() {
        let record = tls_write(|w| {
            w.subject = Some("CN=\u{202E}nimda \u{1F600} caf\u{E9}".into());
            w.role = Some("op\u{E0041}\u{7F}\u{85}".into());
        });
        let text = as_json(&Listed::Write(Box::new(record.clone())));
        assert!(!text.contains(hidden), "{text:?}");
        let printable = "\"subject\":\"CN=\\u202enimda \u{1F600} caf\u{E9}\"";
        assert!(text.contains(printable), "printable stays as it is: {text}");
        assert!(
            text.contains(r#""role":"op\udb40\udc41\u007f\u0085""#),
            "{text}"
        );
        let back: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(back["subject"].as_str(), record.write.subject.as_deref());
        assert_eq!(back["role"].as_str(), record.write.role.as_deref());
    }
}
