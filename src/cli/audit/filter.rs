//! The filters of the command line (`--since`, `--master`, `--outcome`...), checked, and which
//! items they select.

use super::join::{End, Listed, Record};
use super::Options;
use crate::audit::entry::{Write, WriteOutcome};
use crate::config::UnitSet;
use ipnet::IpNet;
use std::net::{IpAddr, SocketAddr};
use std::time::SystemTime;

/// Which outcomes `--outcome` selects.
#[derive(Clone, Debug, Default, PartialEq)]
struct Outcomes {
    recorded: Vec<WriteOutcome>,
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
    pub(crate) fn shows(&self, item: &Listed) -> bool {
        match item {
            Listed::Write(record) => self.matches(record),
            Listed::Gap(gap) => {
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
                    End::Stopped | End::Lost | End::Waiting => wanted.pending,
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
pub(super) fn span(write: &Write) -> Option<(u32, u32)> {
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
        } else if let Some(outcome) = WriteOutcome::ALL.into_iter().find(|o| o.label() == word) {
            outcomes.recorded.push(outcome);
        } else {
            let valid: Vec<&str> = WriteOutcome::ALL.iter().map(|o| o.label()).collect();
            return Err(format!(
                "`{word}` is not an outcome; the outcomes are {}, {PENDING}",
                valid.join(", ")
            ));
        }
    }
    Ok(outcomes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::audit::fixtures::*;

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
}
