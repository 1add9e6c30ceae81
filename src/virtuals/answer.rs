//! What a virtual unit answers: a read's reply, made from one moment of the store, or the
//! exception it gets; a write's translation into writes of the source slaves' registers, each
//! in its source value's encoding, or the exception it gets. Every check comes before anything
//! is sent: a write refused for one register sends nothing.

use super::{table_index, too_old, Placed, Units, Virtual};
use crate::config::Table;
use crate::pdu::{broadcast_response, ExceptionCode};
use crate::routing::Target;
use crate::values::{decode, encode, write_request};
use tokio::time::Instant;

/// The exception a virtual unit answers a request with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Declined(pub(crate) ExceptionCode);

/// A write to one source slave, to send as any master's write is sent.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct SourceWrite {
    pub(crate) target: Target,
    pub(crate) pdu: Vec<u8>,
}

/// A request's table, first address and quantity, as its function code and bytes say.
fn span(pdu: &[u8]) -> Result<(Table, u16, u16), Declined> {
    let word = |at: usize| {
        pdu.get(at..at + 2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
    };
    let (table, single) = match pdu.first() {
        Some(0x01) => (Table::Coil, false),
        Some(0x02) => (Table::Discrete, false),
        Some(0x03) => (Table::Holding, false),
        Some(0x04) => (Table::Input, false),
        Some(0x05) => (Table::Coil, true),
        Some(0x06) => (Table::Holding, true),
        Some(0x0F) => (Table::Coil, false),
        Some(0x10) => (Table::Holding, false),
        _ => return Err(Declined(ExceptionCode::IllegalFunction)),
    };
    let first = word(1).ok_or(Declined(ExceptionCode::IllegalDataValue))?;
    let count = if single {
        1
    } else {
        word(3).ok_or(Declined(ExceptionCode::IllegalDataValue))?
    };
    // Modbus Application Protocol V1.1b3, 6.1-6.4, 6.11, 6.12: the quantities a request may ask.
    let most = match pdu[0] {
        0x01 | 0x02 => 2000,
        0x03 | 0x04 => 125,
        0x0F => 0x07B0,
        0x10 => 123,
        _ => 1,
    };
    if count == 0 || count > most {
        return Err(Declined(ExceptionCode::IllegalDataValue));
    }
    if u32::from(first) + u32::from(count) > 0x1_0000 {
        return Err(Declined(ExceptionCode::IllegalDataAddress));
    }
    Ok((table, first, count))
}

impl Virtual {
    /// The registers of `table` that `first..=last` touches, every address of it laid out;
    /// 0x02 if one is not.
    fn touched(&self, table: Table, first: u16, last: u16) -> Result<&[Placed], Declined> {
        let placed = &self.tables[table_index(table)];
        // Laid out without overlaps (bits of one register apart), so their ends are in order.
        let from = placed.partition_point(|p| p.slot.last() < first);
        let to = placed.partition_point(|p| p.slot.first() <= last);
        let touched = &placed[from..to.max(from)];
        let mut next = u32::from(first);
        for p in touched {
            if u32::from(p.slot.first()) > next {
                return Err(Declined(ExceptionCode::IllegalDataAddress));
            }
            next = next.max(u32::from(p.slot.last()) + 1);
        }
        if next <= u32::from(last) {
            return Err(Declined(ExceptionCode::IllegalDataAddress));
        }
        Ok(touched)
    }
}

impl Units {
    /// The reply to the read `pdu` (FC 01-04) of `unit` at `now`, or its exception.
    pub(crate) fn read(
        &self,
        unit: &Virtual,
        pdu: &[u8],
        now: Instant,
    ) -> Result<Vec<u8>, Declined> {
        let (table, first, count) = span(pdu)?;
        if !matches!(pdu[0], 0x01..=0x04) {
            return Err(Declined(ExceptionCode::IllegalFunction));
        }
        let last = first + (count - 1);
        let touched = unit.touched(table, first, last)?;
        let readings = self.store.readings();
        if readings.generation() != self.generation {
            // The configuration is being replaced: the places are of the other one.
            return Err(Declined(ExceptionCode::ServerDeviceBusy));
        }
        let stale = Declined(ExceptionCode::GatewayTargetFailedToRespond);
        let mut words = vec![0u16; usize::from(count)];
        for placed in touched {
            let slot = &placed.slot;
            let reading = placed.entry.map(|at| readings.get(at)).ok_or(stale)?;
            let value = reading.value.ok_or(stale)?;
            if too_old(reading.fresh_at, now, slot.max_age) {
                return Err(stale);
            }
            let held = encode(&slot.encoding, value).ok_or(stale)?;
            for (i, word) in held.into_iter().enumerate() {
                let address = u32::from(slot.first()) + u32::try_from(i).unwrap_or(u32::MAX);
                let Some(at) = address.checked_sub(u32::from(first)) else {
                    continue;
                };
                if let Some(w) = words.get_mut(usize::try_from(at).unwrap_or(usize::MAX)) {
                    *w |= word;
                }
            }
        }
        drop(readings);
        Ok(reply(pdu[0], table, &words))
    }

    /// What the write `pdu` (FC 05, 06, 0F, 10) to `unit` becomes: one write per register it
    /// covers, each to its source slave in its source value's encoding, in address order, and
    /// the normal reply the master gets once they are done; or its exception, nothing sent.
    pub(crate) fn write(
        &self,
        unit: &Virtual,
        pdu: &[u8],
    ) -> Result<(Vec<SourceWrite>, Vec<u8>), Declined> {
        let (table, first, count) = span(pdu)?;
        let words = written(pdu, count)?;
        let last = first + (count - 1);
        let touched = unit.touched(table, first, last)?;
        let mut writes = Vec::new();
        for placed in touched {
            let slot = &placed.slot;
            let (Some(found), Some(target), true) = (&slot.source, placed.target, slot.writable)
            else {
                return Err(Declined(ExceptionCode::IllegalFunction));
            };
            // A write carries whole values: none begins before it or ends after it.
            if slot.first() < first || slot.last() > last {
                return Err(Declined(ExceptionCode::IllegalDataAddress));
            }
            let from = usize::from(slot.first() - first);
            let mine = &words[from..from + usize::from(slot.encoding.width())];
            let number =
                decode(&slot.encoding, mine).ok_or(Declined(ExceptionCode::IllegalDataValue))?;
            let held =
                encode(&found.value, number).ok_or(Declined(ExceptionCode::IllegalDataValue))?;
            let register = u16::try_from(found.value.register).unwrap_or(u16::MAX);
            writes.push(SourceWrite {
                target,
                pdu: write_request(found.value.table, register, &held),
            });
        }
        let normal = broadcast_response(pdu).ok_or(Declined(ExceptionCode::IllegalFunction))?;
        Ok((writes, normal))
    }
}

/// The registers (or coils as 0 and 1) a write of `count` carries.
fn written(pdu: &[u8], count: u16) -> Result<Vec<u16>, Declined> {
    let bad = Declined(ExceptionCode::IllegalDataValue);
    let count = usize::from(count);
    match pdu[0] {
        0x05 => match pdu.get(3..5) {
            Some([0xFF, 0x00]) => Ok(vec![1]),
            Some([0x00, 0x00]) => Ok(vec![0]),
            _ => Err(bad),
        },
        0x06 => Ok(vec![u16::from_be_bytes([pdu[3], pdu[4]])]),
        0x0F => {
            let data = pdu.get(6..6 + count.div_ceil(8)).ok_or(bad)?;
            Ok((0..count)
                .map(|i| u16::from((data[i / 8] >> (i % 8)) & 1))
                .collect())
        }
        _ => {
            let data = pdu.get(6..6 + 2 * count).ok_or(bad)?;
            Ok(data
                .chunks_exact(2)
                .map(|w| u16::from_be_bytes([w[0], w[1]]))
                .collect())
        }
    }
}

/// The normal reply to read `function` of `table`, its data `words` (bits as 0 and 1).
fn reply(function: u8, table: Table, words: &[u16]) -> Vec<u8> {
    if table.is_bits() {
        let mut bytes = vec![0u8; words.len().div_ceil(8)];
        for (i, word) in words.iter().enumerate() {
            if *word != 0 {
                bytes[i / 8] |= 1 << (i % 8);
            }
        }
        let mut pdu = vec![function, u8::try_from(bytes.len()).unwrap_or(0)];
        pdu.extend(bytes);
        pdu
    } else {
        let mut pdu = Vec::with_capacity(2 + 2 * words.len());
        pdu.push(function);
        pdu.push(u8::try_from(2 * words.len()).unwrap_or(0));
        pdu.extend(words.iter().flat_map(|w| w.to_be_bytes()));
        pdu
    }
}
