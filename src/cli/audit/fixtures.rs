//! Journal lines and joined items the `audit` modules' unit tests share: a run's `open`, a
//! routed Write Multiple Registers and its outcome, and the filters of a command line.

use super::filter::Filter;
use super::join::{End, Joiner, Listed, Record, Unreadable};
use super::print::ending;
use super::Options;
use crate::audit::entry::{Carried, Ended, Line, Write, WriteOutcome};
use std::time::SystemTime;

pub(super) const OPEN: &str =
    r#"{"kind":"open","time":"2026-11-28T10:00:00.000000Z","pid":812,"version":"0.1.0"}"#;

/// The `open` line of a run of the process `pid`.
pub(super) fn open(pid: u32) -> String {
    format!(
        r#"{{"kind":"open","time":"2026-11-28T11:00:00.000000Z","pid":{pid},"version":"0.1.0"}}"#
    )
}

/// A `write` line: Write Multiple Registers from 192.168.20.5 to unit 3, line1 slave 3.
pub(super) fn write(id: u64, time: &str) -> String {
    format!(
        r#"{{"kind":"write","time":"{time}","id":{id},"master":"192.168.20.5:50312","protocol":"tcp","unit":3,"bus":"line1","slave":3,"function":16,"table":"holding","start":8192,"count":2,"values":"13880032","rule":"wallbox","action":"allow"}}"#
    )
}

pub(super) fn outcome(id: u64, outcome: &str) -> String {
    format!(
        r#"{{"kind":"outcome","time":"2026-11-28T10:15:02.200000Z","id":{id},"outcome":"{outcome}","carried_out":"yes"}}"#
    )
}

/// Every item of `files` (oldest first), and the `file:line` of each unreadable line.
pub(super) fn join(files: &[&str]) -> (Vec<Listed>, Vec<String>) {
    let mut joiner = Joiner::default();
    let (mut items, mut unreadable) = (Vec::new(), Vec::new());
    for (n, text) in files.iter().enumerate() {
        for (number, line) in text.lines().enumerate() {
            if joiner.feed(line.as_bytes()) == Err(Unreadable) {
                unreadable.push(format!("file{n}:{}", number + 1));
            }
            items.extend(joiner.ready());
        }
    }
    let (rest, _) = joiner.finish();
    items.extend(rest);
    (items, unreadable)
}

pub(super) fn ids_and_ends(items: &[Listed]) -> Vec<(u64, String)> {
    items
        .iter()
        .filter_map(|item| match item {
            Listed::Write(record) => Some((record.write.id, ending(record))),
            Listed::Gap(_) => None,
        })
        .collect()
}

pub(super) fn now() -> SystemTime {
    humantime::parse_rfc3339("2026-11-28T12:00:00Z").unwrap()
}

/// A record of `write` (as the line would say), answered.
pub(super) fn record(line: &str) -> Record {
    let Ok(Line::Write(write)) = serde_json::from_str(line) else {
        panic!("{line}");
    };
    Record {
        write,
        end: End::Recorded(Ended {
            time: "2026-11-28T10:15:02.200000Z".into(),
            id: 1,
            outcome: WriteOutcome::Answered,
            carried_out: Carried::Yes,
            exception: None,
            detail: None,
        }),
    }
}

pub(super) fn record_with(record: &Record, change: impl FnOnce(&mut Write)) -> Record {
    let mut record = record.clone();
    change(&mut record.write);
    record
}

/// The options of the command line `--FLAG VALUE...`.
pub(super) fn given(flags: &[(&str, &str)]) -> Options {
    let mut options = Options::default();
    for &(flag, value) in flags {
        let value = Some(value.to_owned());
        match flag {
            "since" => options.since = value,
            "until" => options.until = value,
            "master" => options.master = value,
            "unit" => options.unit = value,
            "register" => options.register = value,
            "bus" => options.bus = value,
            "outcome" => options.outcome.extend(value),
            _ => panic!("no --{flag}"),
        }
    }
    options
}

pub(super) fn filter(flags: &[(&str, &str)]) -> Result<Filter, Vec<String>> {
    Filter::parse(&given(flags), now())
}
