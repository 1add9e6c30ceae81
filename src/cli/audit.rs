//! The `audit` subcommand: read the journal of writes (`[audit]`) back, its rotated files oldest
//! first, join each write to its outcome, filter, and print one line (or JSON object) per write.
//! The lines' format is [`crate::audit::entry`]'s; knows nothing of how the gateway writes them.

use super::EXIT_CONFIG;
use crate::audit::entry::{Carried, Ended, Gap, Line, Outcome, Write};
use crate::config::{Config, UnitSet};
use crate::pdu;
use ipnet::IpNet;
use serde::Serialize;
use std::collections::{HashMap, VecDeque};
use std::fmt::Write as _;
use std::fs::File;
use std::io::{self, BufRead, BufReader, Write as _};
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::SystemTime;

/// What to print, as given on the command line: checked by [`Filter::parse`].
#[derive(Clone, Debug, Default)]
pub struct Options {
    pub since: Option<String>,
    pub until: Option<String>,
    pub master: Option<String>,
    pub unit: Option<String>,
    pub register: Option<String>,
    /// Outcome words, each maybe a comma list.
    pub outcome: Vec<String>,
    pub bus: Option<String>,
    pub json: bool,
}

/// The journal `audit.path` of the configuration read from `file`; without `[audit]`, says so
/// and gives the exit code.
pub fn journal_of(file: &Path, config: &Config) -> Result<PathBuf, ExitCode> {
    match &config.audit {
        Some(audit) => Ok(audit.path.clone()),
        None => {
            eprintln!(
                "modbus-gateway: audit: {}: has no [audit] table, so no journal to read; \
                 name one with --journal PATH",
                file.display()
            );
            Err(ExitCode::from(EXIT_CONFIG))
        }
    }
}

/// Print the writes of the journal at `path` (and its rotated files) that `options` select.
/// Exit 0 when it was read, matched or not; 1 when it cannot be read; 2 for bad options.
pub fn audit(path: &Path, options: &Options) -> ExitCode {
    let filter = match Filter::parse(options, SystemTime::now()) {
        Ok(filter) => filter,
        Err(errors) => {
            for e in errors {
                eprintln!("modbus-gateway: audit: {e}");
            }
            return ExitCode::from(EXIT_CONFIG);
        }
    };
    let files = match open(path) {
        Ok(files) => files,
        Err(e) => {
            eprintln!("modbus-gateway: audit: {e}");
            return ExitCode::FAILURE;
        }
    };
    let mut out = io::BufWriter::new(io::stdout().lock());
    let mut print = |item: &Item| -> io::Result<()> {
        if filter.shows(item) {
            let text = if options.json {
                as_json(item)
            } else {
                describe(item)
            };
            writeln!(out, "{text}")?;
        }
        Ok(())
    };
    let mut joiner = Joiner::default();
    let mut unreadable = 0u64;
    for (name, file) in files {
        let mut reader = BufReader::new(file);
        let mut bytes = Vec::new();
        let mut number = 0u64;
        loop {
            bytes.clear();
            match reader.read_until(b'\n', &mut bytes) {
                Ok(0) => break,
                Ok(_) => {}
                Err(e) => {
                    eprintln!("modbus-gateway: audit: cannot read {name}: {e}");
                    return ExitCode::FAILURE;
                }
            }
            number += 1;
            if joiner.feed(&bytes).is_err() {
                unreadable += 1;
                eprintln!("{name}:{number}: unreadable line");
            }
            for item in joiner.ready() {
                if let Err(e) = print(&item) {
                    return write_failed(&e);
                }
            }
        }
    }
    let (rest, orphans) = joiner.finish();
    for item in rest {
        if let Err(e) = print(&item) {
            return write_failed(&e);
        }
    }
    if let Err(e) = out.flush() {
        return write_failed(&e);
    }
    if unreadable > 0 {
        eprintln!("modbus-gateway: audit: {unreadable} unreadable line(s) skipped");
    }
    if orphans > 0 {
        eprintln!(
            "modbus-gateway: audit: {orphans} outcome line(s) name no write before them in \
             their run (the write is in a file no longer kept, or unreadable)"
        );
    }
    ExitCode::SUCCESS
}

/// A reader that went away (`| head`) ends the listing quietly.
fn write_failed(error: &io::Error) -> ExitCode {
    if super::reader_gone(error) {
        return ExitCode::SUCCESS;
    }
    eprintln!("modbus-gateway: audit: cannot write to stdout: {error}");
    ExitCode::FAILURE
}

/// The journal's files, oldest first: `PATH.k` ... `PATH.1` (up to the first number missing),
/// then `PATH`; each opened now, so that a rotation meanwhile moves none under the reader.
fn open(path: &Path) -> Result<Vec<(String, File)>, String> {
    let opened = |path: PathBuf| match File::open(&path) {
        Ok(file) => Ok(Some((path.display().to_string(), file))),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(format!("cannot read {}: {e}", path.display())),
    };
    let mut files = Vec::new();
    for n in 1.. {
        match opened(crate::audit::rotated(path, n))? {
            Some(file) => files.push(file),
            None => break,
        }
    }
    files.reverse();
    match opened(path.to_owned())? {
        Some(file) => files.push(file),
        None if files.is_empty() => {
            return Err(format!(
                "no journal at {} (nor a rotated {})",
                path.display(),
                crate::audit::rotated(path, 1).display()
            ));
        }
        // Between a rotation's rename and the new file, or after the gateway's last run.
        None => {}
    }
    Ok(files)
}

/// One thing to print, in the journal's order: a write, or a gap in the journal.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Item {
    Write(Box<Record>),
    Gap(Gap),
}

/// A write and how it ended, as far as the journal says.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Record {
    pub(crate) write: Write,
    pub(crate) end: End,
}

#[derive(Clone, Debug, PartialEq)]
pub(crate) enum End {
    Recorded(Ended),
    /// A later `open`: the gateway stopped before it wrote the outcome.
    Stopped,
    /// Nothing yet: its outcome may still come, or the gateway stopped with no run after.
    Waiting,
}

/// Joins each `write` line to its `outcome`, which may come many lines (and a rotation) later,
/// and hands the items back in the journal's order once each is whole: a write when it has its
/// outcome or its run ended, a gap at once (behind the writes before it).
#[derive(Default)]
pub(crate) struct Joiner {
    queue: VecDeque<Item>,
    /// How many items have left the queue: an item's number less this is its place in it.
    handed: u64,
    /// The writes of this run still waiting for their outcome, by id: their item's number.
    waiting: HashMap<u64, u64>,
    /// Outcome lines that name no waiting write of their run.
    orphans: u64,
    /// The process of this run, from its `open` line.
    pid: Option<u32>,
    /// The highest write id of this run so far.
    last_id: u64,
    /// An `open` by this run's process (or the first one met) came last: a reload that moved
    /// the journal back here, ids going on, or a restart that got the same pid (in a container,
    /// say), ids from 1 again. The next write's id tells which.
    reopened: bool,
}

/// A line that is not one of the journal's.
#[derive(Debug, PartialEq)]
pub(crate) struct Unreadable;

impl Joiner {
    /// Take one line of the journal (its newline optional).
    pub(crate) fn feed(&mut self, bytes: &[u8]) -> Result<(), Unreadable> {
        let bytes = bytes.strip_suffix(b"\n").unwrap_or(bytes);
        let line = serde_json::from_slice::<Line>(bytes).map_err(|_| Unreadable)?;
        match line {
            Line::Open(opened) => {
                if self.pid.is_some_and(|pid| pid != opened.pid) {
                    self.new_run();
                } else {
                    self.reopened = true;
                }
                self.pid = Some(opened.pid);
            }
            Line::Write(write) => {
                if std::mem::take(&mut self.reopened) && write.id <= self.last_id {
                    self.new_run();
                }
                self.last_id = self.last_id.max(write.id);
                let number = self.handed + self.queue.len() as u64;
                // The same id again in one run: its `open` line is missing, so the earlier
                // write's run ended without its outcome.
                if let Some(earlier) = self.waiting.insert(write.id, number) {
                    self.end(earlier, End::Stopped);
                }
                self.queue.push_back(Item::Write(Box::new(Record {
                    write,
                    end: End::Waiting,
                })));
            }
            Line::Outcome(ended) => match self.waiting.remove(&ended.id) {
                Some(number) => self.end(number, End::Recorded(ended)),
                None => self.orphans += 1,
            },
            Line::Gap(gap) => self.queue.push_back(Item::Gap(gap)),
        }
        Ok(())
    }

    /// A new run began: the writes of the last one still waiting never got their outcome.
    fn new_run(&mut self) {
        for (_, number) in std::mem::take(&mut self.waiting) {
            self.end(number, End::Stopped);
        }
        self.last_id = 0;
    }

    /// Say how the write numbered `number`, still queued, ended.
    fn end(&mut self, number: u64, end: End) {
        let place = number
            .checked_sub(self.handed)
            .and_then(|place| usize::try_from(place).ok());
        if let Some(Item::Write(record)) = place.and_then(|place| self.queue.get_mut(place)) {
            record.end = end;
        }
    }

    /// The items that are whole, from the front of the queue.
    pub(crate) fn ready(&mut self) -> Vec<Item> {
        let mut ready = Vec::new();
        while let Some(front) = self.queue.front() {
            if matches!(front, Item::Write(record) if record.end == End::Waiting) {
                break;
            }
            ready.extend(self.queue.pop_front());
            self.handed += 1;
        }
        ready
    }

    /// Every item left, at the end of the journal (writes still waiting have no outcome yet),
    /// and how many outcome lines named no write.
    pub(crate) fn finish(self) -> (Vec<Item>, u64) {
        (self.queue.into(), self.orphans)
    }
}

/// Which outcomes `--outcome` selects.
#[derive(Clone, Debug, Default, PartialEq)]
struct Outcomes {
    recorded: Vec<Outcome>,
    /// Writes without a recorded outcome.
    pending: bool,
}

/// Who `--master` selects.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Master {
    Ip(IpAddr),
    Address(SocketAddr),
    Network(IpNet),
}

/// The checked filters: a write is printed when it matches all that are set.
#[derive(Clone, Debug)]
pub(crate) struct Filter {
    since: Option<SystemTime>,
    until: Option<SystemTime>,
    master: Option<Master>,
    unit: Option<UnitSet>,
    /// First and last address.
    register: Option<(u16, u16)>,
    outcomes: Option<Outcomes>,
    bus: Option<String>,
}

/// The word `--outcome` takes for writes without a recorded outcome.
const PENDING: &str = "pending";

impl Filter {
    /// `options` checked, times ago counted back from `now`; or every problem, one each.
    pub(crate) fn parse(options: &Options, now: SystemTime) -> Result<Filter, Vec<String>> {
        let mut errors = Vec::new();
        let since = options.since.as_deref().map(|t| parse_time(t, now));
        let since = checked(&mut errors, "since", since);
        let until = options.until.as_deref().map(|t| parse_time(t, now));
        let until = checked(&mut errors, "until", until);
        let master = options.master.as_deref().map(parse_master);
        let master = checked(&mut errors, "master", master);
        let unit = options.unit.as_deref().map(str::parse::<UnitSet>);
        let unit = checked(&mut errors, "unit", unit);
        let register = options.register.as_deref().map(parse_registers);
        let register = checked(&mut errors, "register", register);
        let outcomes = (!options.outcome.is_empty()).then(|| parse_outcomes(&options.outcome));
        let outcomes = checked(&mut errors, "outcome", outcomes);
        if let (Some(since), Some(until)) = (since, until) {
            if since > until {
                errors.push("--since: is after --until, so no write could match".to_owned());
            }
        }
        if !errors.is_empty() {
            return Err(errors);
        }
        Ok(Filter {
            since,
            until,
            master,
            unit,
            register,
            outcomes,
            bus: options.bus.clone(),
        })
    }

    /// Whether to print `item`. A gap is printed when its time overlaps `--since`/`--until`,
    /// whatever the other filters: the writes it stands for could have matched them.
    pub(crate) fn shows(&self, item: &Item) -> bool {
        match item {
            Item::Write(record) => self.matches(record),
            Item::Gap(gap) => {
                let began = humantime::parse_rfc3339_weak(&gap.since).ok();
                let ended = humantime::parse_rfc3339_weak(&gap.time).ok();
                let after_since = match (self.since, ended) {
                    (Some(since), Some(ended)) => ended >= since,
                    _ => true,
                };
                let before_until = match (self.until, began) {
                    (Some(until), Some(began)) => began <= until,
                    _ => true,
                };
                after_since && before_until
            }
        }
    }

    fn matches(&self, record: &Record) -> bool {
        let write = &record.write;
        let time = humantime::parse_rfc3339_weak(&write.time).ok();
        let in_time = |bound: Option<SystemTime>, ok: fn(&SystemTime, &SystemTime) -> bool| {
            bound.is_none_or(|bound| time.is_some_and(|time| ok(&time, &bound)))
        };
        in_time(self.since, SystemTime::ge)
            && in_time(self.until, SystemTime::le)
            && self.master.is_none_or(|m| master_matches(m, &write.master))
            && self.unit.is_none_or(|units| units.contains(write.unit))
            && self.register.is_none_or(|(first, last)| {
                span(write)
                    .is_some_and(|(start, end)| start <= u32::from(last) && end >= u32::from(first))
            })
            && self
                .outcomes
                .as_ref()
                .is_none_or(|wanted| match &record.end {
                    End::Recorded(ended) => wanted.recorded.contains(&ended.outcome),
                    End::Stopped | End::Waiting => wanted.pending,
                })
            && self
                .bus
                .as_deref()
                .is_none_or(|bus| write.bus.as_deref() == Some(bus))
    }
}

/// A flag's value, if given and good; if bad, its problem is added to `errors`.
fn checked<T>(
    errors: &mut Vec<String>,
    flag: &str,
    parsed: Option<Result<T, String>>,
) -> Option<T> {
    match parsed? {
        Ok(value) => Some(value),
        Err(e) => {
            errors.push(format!("--{flag}: {e}"));
            None
        }
    }
}

/// The first and last address a write names, if it names any.
fn span(write: &Write) -> Option<(u32, u32)> {
    let start = u32::from(write.start?);
    // A count no write can have (the journal is a file anyone may edit) must not overflow.
    let count = write.count.unwrap_or(1).max(1);
    Some((start, start.saturating_add(count - 1)))
}

fn master_matches(wanted: Master, master: &str) -> bool {
    let Ok(address) = master.parse::<SocketAddr>() else {
        return false;
    };
    let ip = address.ip().to_canonical();
    match wanted {
        Master::Ip(want) => ip == want.to_canonical(),
        Master::Address(want) => ip == want.ip().to_canonical() && address.port() == want.port(),
        Master::Network(net) => net.contains(&ip),
    }
}

/// `2026-11-28T10:00:00Z`, `2026-11-28 10:00:00` (UTC), `2026-11-28` (its midnight, UTC), or
/// a duration ago (`1h`, `30m`, `2days`).
fn parse_time(text: &str, now: SystemTime) -> Result<SystemTime, String> {
    let text = text.trim();
    if let Ok(ago) = humantime::parse_duration(text) {
        return now
            .checked_sub(ago)
            .ok_or_else(|| format!("`{text}` ago is before any time this system can tell"));
    }
    let full = if text.len() == "2026-11-28".len() {
        format!("{text} 00:00:00")
    } else {
        text.to_owned()
    };
    humantime::parse_rfc3339_weak(&full).map_err(|_| {
        format!(
            "`{text}` is neither a UTC time (2026-11-28T10:00:00Z, 2026-11-28 10:00:00, \
             2026-11-28) nor a duration ago (1h, 30m)"
        )
    })
}

/// `192.168.20.5`, `192.168.20.5:50312`, `[fd00::5]:502`, `192.168.20.0/24`.
fn parse_master(text: &str) -> Result<Master, String> {
    let text = text.trim();
    if let Ok(address) = text.parse::<SocketAddr>() {
        return Ok(Master::Address(address));
    }
    if let Ok(ip) = text.parse::<IpAddr>() {
        return Ok(Master::Ip(ip));
    }
    text.parse::<IpNet>()
        .map(Master::Network)
        .map_err(|_| format!("`{text}` is not an IP address, IP:port or network (192.168.20.0/24)"))
}

/// `100`, `0x2000`, `0x2000-0x2001`, `100-199`: the first and last address.
fn parse_registers(text: &str) -> Result<(u16, u16), String> {
    let address = |s: &str| -> Result<u16, String> {
        let s = s.trim();
        let parsed = match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
            Some(hex) => u16::from_str_radix(hex, 16),
            None => s.parse::<u16>(),
        };
        parsed.map_err(|_| format!("`{s}` is not an address from 0 to 65535 (or 0x0000 to 0xFFFF)"))
    };
    let (first, last) = match text.split_once('-') {
        Some((first, last)) => (address(first)?, address(last)?),
        None => {
            let only = address(text)?;
            (only, only)
        }
    };
    if first > last {
        return Err(format!("range `{}` runs backwards", text.trim()));
    }
    Ok((first, last))
}

/// Outcome words, each value maybe a comma list.
fn parse_outcomes(values: &[String]) -> Result<Outcomes, String> {
    let mut outcomes = Outcomes::default();
    for word in values.iter().flat_map(|v| v.split(',')).map(str::trim) {
        let word = word.to_ascii_lowercase();
        if word == PENDING {
            outcomes.pending = true;
        } else if let Some(outcome) = Outcome::ALL.into_iter().find(|o| o.label() == word) {
            outcomes.recorded.push(outcome);
        } else {
            let valid: Vec<&str> = Outcome::ALL.iter().map(|o| o.label()).collect();
            return Err(format!(
                "`{word}` is not an outcome; the outcomes are {}, {PENDING}",
                valid.join(", ")
            ));
        }
    }
    Ok(outcomes)
}

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
fn ending(record: &Record) -> String {
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

    const OPEN: &str =
        r#"{"kind":"open","time":"2026-11-28T10:00:00.000000Z","pid":812,"version":"0.1.0"}"#;

    /// The `open` line of a run of the process `pid`.
    fn open(pid: u32) -> String {
        format!(
            r#"{{"kind":"open","time":"2026-11-28T11:00:00.000000Z","pid":{pid},"version":"0.1.0"}}"#
        )
    }

    /// A `write` line: Write Multiple Registers from 192.168.20.5 to unit 3, line1 slave 3.
    fn write(id: u64, time: &str) -> String {
        format!(
            r#"{{"kind":"write","time":"{time}","id":{id},"master":"192.168.20.5:50312","protocol":"tcp","unit":3,"bus":"line1","slave":3,"function":16,"table":"holding","start":8192,"count":2,"values":"13880032","rule":"wallbox","action":"allow"}}"#
        )
    }

    fn outcome(id: u64, outcome: &str) -> String {
        format!(
            r#"{{"kind":"outcome","time":"2026-11-28T10:15:02.200000Z","id":{id},"outcome":"{outcome}","carried_out":"yes"}}"#
        )
    }

    /// Every item of `files` (oldest first), and the `file:line` of each unreadable line.
    fn join(files: &[&str]) -> (Vec<Item>, Vec<String>) {
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

    fn ids_and_ends(items: &[Item]) -> Vec<(u64, String)> {
        items
            .iter()
            .filter_map(|item| match item {
                Item::Write(record) => Some((record.write.id, ending(record))),
                Item::Gap(_) => None,
            })
            .collect()
    }

    fn now() -> SystemTime {
        humantime::parse_rfc3339("2026-11-28T12:00:00Z").unwrap()
    }

    #[test]
    fn a_write_is_joined_to_its_outcome_in_the_next_file_after_a_rotation() {
        let older = format!(
            "{OPEN}\n{}\n{}\n",
            write(1, "2026-11-28T10:15:02.123456Z"),
            write(2, "2026-11-28T10:15:03.000000Z")
        );
        let newer = format!("{}\n{}\n", outcome(2, "answered"), outcome(1, "answered"));
        let (items, unreadable) = join(&[&older, &newer]);
        assert!(unreadable.is_empty());
        assert_eq!(
            ids_and_ends(&items),
            [(1, "answered".to_owned()), (2, "answered".to_owned())],
            "in the order of the write lines, each with its own outcome"
        );
        assert_eq!(
            describe(&items[0]),
            "2026-11-28T10:15:02.123456Z  192.168.20.5:50312 tcp  unit 3 -> line1 slave 3  \
             Write Multiple Registers (0x10) holding 0x2000-0x2001 = 1388 0032  rule wallbox: \
             allow  answered"
        );
    }

    #[test]
    fn a_run_restart_leaves_the_earlier_write_without_outcome_and_ids_start_again() {
        let text = format!(
            "{OPEN}\n{}\n{}\n{}\n{}\n{}\n{}\n",
            write(1, "2026-11-28T10:15:02.000000Z"),
            write(2, "2026-11-28T10:15:03.000000Z"),
            open(813),
            write(1, "2026-11-28T11:00:00.000000Z"),
            outcome(1, "answered"),
            write(2, "2026-11-28T11:00:01.000000Z"),
        );
        let (items, _) = join(&[&text]);
        let stopped = "no outcome recorded: may have been carried out \
                       (the gateway stopped before its outcome)";
        let not_yet = "no outcome recorded: may have been carried out (no outcome yet)";
        assert_eq!(
            ids_and_ends(&items),
            [
                (1, stopped.to_owned()),
                (2, stopped.to_owned()),
                (1, "answered".to_owned()),
                (2, not_yet.to_owned()),
            ],
            "the second run's outcome of id 1 is not the first run's"
        );
        let json: serde_json::Value = serde_json::from_str(&as_json(&items[0])).unwrap();
        assert_eq!(json["outcome"], serde_json::Value::Null);
        assert_eq!(json["pending"], "gateway_stopped");
        assert_eq!(json["id"], 1);
        assert_eq!(json["values"], "13880032");
    }

    #[test]
    fn an_open_by_the_same_process_goes_on_with_its_run_unless_the_ids_start_again() {
        // A reload moved the journal away and back: the same pid, the ids going on, and an
        // outcome of a write from before it.
        let reload = format!(
            "{OPEN}\n{}\n{}\n{}\n{}\n",
            write(1, "2026-11-28T10:15:02.000000Z"),
            open(812),
            write(7, "2026-11-28T11:00:01.000000Z"),
            outcome(1, "answered"),
        );
        let (items, _) = join(&[&reload]);
        let not_yet = "no outcome recorded: may have been carried out (no outcome yet)";
        assert_eq!(
            ids_and_ends(&items),
            [(1, "answered".to_owned()), (7, not_yet.to_owned())]
        );
        // A restart that got the same pid (pid 1 in a container): the ids start again.
        let restart = format!(
            "{}\n{}\n{}\n{}\n{}\n",
            open(1),
            write(1, "2026-11-28T10:15:02.000000Z"),
            write(2, "2026-11-28T10:15:03.000000Z"),
            open(1),
            write(1, "2026-11-28T11:00:01.000000Z"),
        );
        let (items, _) = join(&[&restart]);
        let stopped = "no outcome recorded: may have been carried out \
                       (the gateway stopped before its outcome)";
        assert_eq!(
            ids_and_ends(&items),
            [
                (1, stopped.to_owned()),
                (2, stopped.to_owned()),
                (1, not_yet.to_owned())
            ]
        );
    }

    #[test]
    fn a_write_waiting_for_its_outcome_holds_back_the_later_ones_until_it_ends() {
        let mut joiner = Joiner::default();
        joiner
            .feed(write(1, "2026-11-28T10:00:01Z").as_bytes())
            .unwrap();
        joiner
            .feed(write(2, "2026-11-28T10:00:02Z").as_bytes())
            .unwrap();
        joiner.feed(outcome(2, "answered").as_bytes()).unwrap();
        assert!(joiner.ready().is_empty(), "1 comes first");
        joiner.feed(outcome(1, "timeout").as_bytes()).unwrap();
        let ready = joiner.ready();
        assert_eq!(ids_and_ends(&ready).len(), 2);
        joiner.feed(outcome(9, "answered").as_bytes()).unwrap();
        assert_eq!(
            joiner.finish(),
            (Vec::new(), 1),
            "an outcome without its write"
        );
    }

    #[test]
    fn an_unreadable_line_is_counted_and_skipped() {
        let text = format!(
            "{OPEN}\n{}\nnot json\n{{\"kind\":\"write\",\"id\":2}}\n{{\"kind\":\"weird\"}}\n\n{}\n",
            write(1, "2026-11-28T10:15:02.000000Z"),
            outcome(1, "answered"),
        );
        let (items, unreadable) = join(&[&text]);
        assert_eq!(unreadable, ["file0:3", "file0:4", "file0:5", "file0:6"]);
        assert_eq!(ids_and_ends(&items), [(1, "answered".to_owned())]);
        let mut joiner = Joiner::default();
        assert_eq!(
            joiner.feed(&[0xFF, 0xFE, b'\n']),
            Err(Unreadable),
            "not UTF-8"
        );
    }

    #[test]
    fn a_gap_is_its_own_line_in_its_place() {
        let gap = r#"{"kind":"gap","time":"2026-11-28T10:20:00.000000Z","since":"2026-11-28T10:16:00.000000Z","unrecorded":0,"refused":3,"lost_outcomes":1,"error":"No space left on device (os error 28)"}"#;
        let text = format!(
            "{}\n{}\n{gap}\n{}\n{}\n",
            write(1, "2026-11-28T10:15:02.000000Z"),
            outcome(1, "answered"),
            write(2, "2026-11-28T10:21:00.000000Z"),
            outcome(2, "answered"),
        );
        let (items, _) = join(&[&text]);
        assert_eq!(items.len(), 3);
        assert_eq!(
            describe(&items[1]),
            "2026-11-28T10:20:00.000000Z  gap: the journal could not be written from \
             2026-11-28T10:16:00.000000Z: No space left on device (os error 28); 3 writes \
             refused (0x0A), 1 outcome line lost"
        );
        let json: serde_json::Value = serde_json::from_str(&as_json(&items[1])).unwrap();
        assert_eq!(json["kind"], "gap");
        assert_eq!(json["refused"], 3);
        // Shown whatever the other filters, when its time overlaps the window.
        let other = filter(&[("unit", "9"), ("since", "2026-11-28T10:19:00Z")]).unwrap();
        assert!(other.shows(&items[1]));
        assert!(!other.shows(&items[0]) && !other.shows(&items[2]), "unit 3");
        let after = filter(&[("since", "2026-11-28T10:20:01Z")]).unwrap();
        assert!(!after.shows(&items[1]));
        let before = filter(&[("until", "2026-11-28 10:15:59")]).unwrap();
        assert!(!before.shows(&items[1]));
        let during = filter(&[("until", "2026-11-28 10:17:00")]).unwrap();
        assert!(during.shows(&items[1]));
    }

    /// A record of `write` (as the line would say), answered.
    fn record(line: &str) -> Record {
        let Ok(Line::Write(write)) = serde_json::from_str(line) else {
            panic!("{line}");
        };
        Record {
            write,
            end: End::Recorded(Ended {
                time: "2026-11-28T10:15:02.200000Z".into(),
                id: 1,
                outcome: Outcome::Answered,
                carried_out: Carried::Yes,
                exception: None,
                detail: None,
            }),
        }
    }

    fn record_with(record: &Record, change: impl FnOnce(&mut Write)) -> Record {
        let mut record = record.clone();
        change(&mut record.write);
        record
    }

    /// The options of the command line `--FLAG VALUE...`.
    fn given(flags: &[(&str, &str)]) -> Options {
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

    fn filter(flags: &[(&str, &str)]) -> Result<Filter, Vec<String>> {
        Filter::parse(&given(flags), now())
    }

    fn selects(flags: &[(&str, &str)], record: &Record) -> bool {
        filter(flags).unwrap().matches(record)
    }

    #[test]
    fn since_and_until_take_utc_times_and_durations_ago_and_bound_the_write_time() {
        let record = record(&write(1, "2026-11-28T10:15:02.123456Z"));
        let within = |flags: &[(&str, &str)]| selects(flags, &record);
        assert!(within(&[("since", "2026-11-28T10:00:00Z")]));
        assert!(within(&[
            ("since", "2026-11-28 10:15:02"),
            ("until", "2026-11-28T10:15:03Z")
        ]));
        assert!(!within(&[("since", "2026-11-28T10:15:03Z")]));
        assert!(!within(&[("until", "2026-11-28 10:15:02")]));
        assert!(within(&[("since", "2026-11-28"), ("until", "2026-11-29")]));
        // now() is 12:00: 2h ago is 10:00, 1h30m ago is 10:30.
        assert!(within(&[("since", "2h"), ("until", "1h30m")]));
        assert!(!within(&[("since", "30m")]));
        let errors = filter(&[
            ("since", "yesterday"),
            ("until", "2026-11-28T10:00:00+02:00"),
        ])
        .unwrap_err();
        assert_eq!(errors.len(), 2, "{errors:?}");
        assert!(
            errors[0].starts_with("--since: `yesterday` is neither a UTC time"),
            "{errors:?}"
        );
        assert!(filter(&[("since", "1h"), ("until", "2h")]).is_err());
    }

    #[test]
    fn master_takes_an_address_an_address_and_port_or_a_network() {
        let record = record(&write(1, "2026-11-28T10:15:02Z"));
        let master = |m: &str| selects(&[("master", m)], &record);
        assert!(master("192.168.20.5"));
        assert!(master("192.168.20.5:50312"));
        assert!(!master("192.168.20.5:50313"));
        assert!(master("192.168.20.0/24"));
        assert!(!master("192.168.21.0/24"));
        assert!(!master("192.168.20.6"));
        assert!(
            master("::ffff:192.168.20.5"),
            "an IPv4-mapped address is the same master"
        );
        let mapped = record_with(&record, |w| {
            w.master = "[::ffff:192.168.20.5]:50312".into();
        });
        assert!(selects(&[("master", "192.168.20.0/24")], &mapped));
        assert!(filter(&[("master", "plc-1")]).is_err());
    }

    #[test]
    fn unit_and_bus_select_the_writes_to_them() {
        let record = record(&write(1, "2026-11-28T10:15:02Z"));
        let unit = |u: &str| selects(&[("unit", u)], &record);
        assert!(unit("3") && unit("1-4,7") && !unit("4-10"));
        assert!(filter(&[("unit", "300")]).is_err());
        let bus = |b: &str| selects(&[("bus", b)], &record);
        assert!(bus("line1") && !bus("line2"));
        let unrouted = record_with(&record, |w| w.bus = None);
        assert!(!selects(&[("bus", "line1")], &unrouted));
        assert!(
            selects(&[("unit", "3"), ("bus", "line1")], &record)
                && !selects(&[("unit", "3"), ("bus", "line2")], &record),
            "every filter must match"
        );
    }

    #[test]
    fn register_selects_the_writes_whose_addresses_overlap_it() {
        // Writes 0x2000-0x2001.
        let record = record(&write(1, "2026-11-28T10:15:02Z"));
        let register = |r: &str| selects(&[("register", r)], &record);
        assert!(register("0x2000") && register("0x2001") && register("8192"));
        assert!(register("0x1FF0-0x2000") && register("0x2001-0x2100") && register("0-65535"));
        assert!(!register("0x1FFF") && !register("0x2002-0x2003"));
        let no_range = record_with(&record, |w| {
            (w.table, w.start, w.count) = (None, None, None);
        });
        assert!(!selects(&[("register", "0-65535")], &no_range));
        let huge = record_with(&record, |w| w.count = Some(u32::MAX));
        assert!(
            selects(&[("register", "0xFFFF")], &huge),
            "seen whole, no overflow"
        );
        for bad in ["0x2001-0x2000", "70000", "0xZZ", ""] {
            assert!(filter(&[("register", bad)]).is_err(), "{bad}");
        }
    }

    #[test]
    fn outcome_takes_the_outcome_words_and_pending_and_refuses_others_naming_them() {
        let answered = record(&write(1, "2026-11-28T10:15:02Z"));
        let stopped = Record {
            end: End::Stopped,
            ..answered.clone()
        };
        let waiting = Record {
            end: End::Waiting,
            ..answered.clone()
        };
        assert!(selects(&[("outcome", "answered")], &answered));
        assert!(!selects(&[("outcome", "timeout,denied")], &answered));
        assert!(selects(
            &[("outcome", "timeout"), ("outcome", "Answered")],
            &answered
        ));
        assert!(!selects(&[("outcome", "answered")], &stopped));
        assert!(selects(&[("outcome", "timeout,pending")], &stopped));
        assert!(selects(&[("outcome", "pending")], &waiting));
        assert_eq!(
            filter(&[("outcome", "answered,done")]).unwrap_err(),
            [
                "--outcome: `done` is not an outcome; the outcomes are answered, slave_exception, \
              gateway_exception, denied, acknowledged, timeout, broadcast, cancelled, pending"
            ]
        );
    }

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
