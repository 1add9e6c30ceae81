//! Which reads poll a slave's values: values due at the same interval, in the same table and
//! contiguous (or overlapping), in one read up to the slave's limit of registers per read (of
//! bits, Modbus's 2000). Gaps are never read across, since devices answer a read that touches
//! an unmapped register with an exception. Pure.

use crate::config::{Table, Value, MAX_READ_BITS};
use std::collections::BTreeMap;
use std::time::Duration;

/// One read that polls values.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Read {
    pub(crate) slave: u8,
    pub(crate) table: Table,
    pub(crate) first: u16,
    pub(crate) count: u16,
    pub(crate) interval: Duration,
    /// The values it reads: their place in the caller's list, and their first register's
    /// distance from `first`.
    pub(crate) values: Vec<(usize, u16)>,
}

/// The reads of `slave`'s `values` (each with its place in the caller's list and its
/// interval), at most `max_registers` registers each.
pub(crate) fn plan(
    slave: u8,
    values: &[(usize, &Value, Duration)],
    max_registers: u16,
) -> Vec<Read> {
    let mut groups: BTreeMap<(Table, Duration), Vec<(usize, &Value)>> = BTreeMap::new();
    for &(place, value, interval) in values {
        groups
            .entry((value.table, interval))
            .or_default()
            .push((place, value));
    }
    let mut reads = Vec::new();
    for ((table, interval), mut members) in groups {
        let most = if table.is_bits() {
            MAX_READ_BITS
        } else {
            max_registers
        };
        members.sort_by_key(|(place, value)| (value.register, *place));
        let mut current: Option<Read> = None;
        for (place, value) in members {
            // Checked at load: a register and its width end by 65535.
            let start = u16::try_from(value.register).unwrap_or(u16::MAX);
            let end = u32::from(start) + u32::from(value.width());
            if let Some(read) = &mut current {
                let read_end = u32::from(read.first) + u32::from(read.count);
                let new_end = read_end.max(end);
                let fits = u32::from(start) <= read_end
                    && new_end - u32::from(read.first) <= u32::from(most);
                if fits {
                    read.count = u16::try_from(new_end - u32::from(read.first)).unwrap_or(most);
                    read.values.push((place, start - read.first));
                    continue;
                }
                reads.extend(current.take());
            }
            current = Some(Read {
                slave,
                table,
                first: start,
                count: value.width(),
                interval,
                values: vec![(place, 0)],
            });
        }
        reads.extend(current);
    }
    reads
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(register: u32, kind: &str, table: &str) -> Value {
        toml::from_str(&format!(
            "name = \"v{register}\"\nregister = {register}\ntype = \"{kind}\"\ntable = \"{table}\"\n"
        ))
        .expect("a value")
    }

    const TEN_S: Duration = Duration::from_secs(10);

    fn spans(reads: &[Read]) -> Vec<(Table, u16, u16)> {
        reads.iter().map(|r| (r.table, r.first, r.count)).collect()
    }

    #[test]
    fn contiguous_values_share_a_read_up_to_the_limit_and_a_gap_starts_another() {
        // 3000H-3004H contiguous (a u32 at 3003H), then 3010H after a gap.
        let values = [
            value(0x3000, "u16", "holding"),
            value(0x3001, "u16", "holding"),
            value(0x3002, "i16", "holding"),
            value(0x3003, "u32", "holding"),
            value(0x3010, "u16", "holding"),
        ];
        let listed: Vec<_> = values
            .iter()
            .enumerate()
            .map(|(i, v)| (i, v, TEN_S))
            .collect();
        let reads = plan(1, &listed, 16);
        assert_eq!(
            spans(&reads),
            [(Table::Holding, 0x3000, 5), (Table::Holding, 0x3010, 1)]
        );
        assert_eq!(reads[0].values, [(0, 0), (1, 1), (2, 2), (3, 3)]);
        assert_eq!(reads[1].values, [(4, 0)]);
        // A limit of 3 registers cuts the first run, never a value.
        let reads = plan(1, &listed, 3);
        assert_eq!(
            spans(&reads),
            [
                (Table::Holding, 0x3000, 3),
                (Table::Holding, 0x3003, 2),
                (Table::Holding, 0x3010, 1)
            ]
        );
    }

    #[test]
    fn tables_and_intervals_are_read_apart_and_overlapping_values_once() {
        let values = [
            value(0, "u16", "holding"),
            value(0, "u16", "input"),
            value(1, "u16", "holding"),
            value(0, "u32", "holding"),
            value(5, "bool", "coil"),
            value(6, "bool", "coil"),
        ];
        let mut listed: Vec<_> = values
            .iter()
            .enumerate()
            .map(|(i, v)| (i, v, TEN_S))
            .collect();
        listed[2].2 = Duration::from_secs(1);
        let reads = plan(7, &listed, 125);
        assert_eq!(
            spans(&reads),
            [
                (Table::Holding, 1, 1),
                (Table::Holding, 0, 2),
                (Table::Input, 0, 1),
                (Table::Coil, 5, 2),
            ]
        );
        assert_eq!(reads[1].values, [(0, 0), (3, 0)]);
        assert!(reads.iter().all(|r| r.slave == 7));
    }
}
