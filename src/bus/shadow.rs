//! What a listen line's slaves last said: per slave and table (holding, input, coils, discrete),
//! the blocks their replies to the other master's reads carried, with when. A master's read of
//! a listen line is answered here, never on the wire: what was seen, no older than `max_age`;
//! otherwise, or for what was never seen, 0x0B; anything that is not a read, 0x01. Bounded: each
//! slave's table keeps its newest [`MAX_BLOCKS`] blocks. Plain data behind one lock; knows
//! nothing of ports or of how frames are heard.

use crate::config::{Table, MAX_READ_BITS, MAX_READ_REGISTERS};
use crate::error::RequestError;
use crate::pdu::code;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::{Duration, SystemTime};
use tokio::sync::Notify;
use tokio::time::Instant;

/// Blocks kept per slave and table: a master polling more distinct blocks than this from one
/// slave has its oldest forgotten, so a hostile line cannot grow the shadow.
pub(crate) const MAX_BLOCKS: usize = 64;
/// The tables, in the order of their read function codes (01 to 04): a table's place here is
/// its place in a slave's shadow.
const TABLES: [Table; 4] = [Table::Coil, Table::Discrete, Table::Holding, Table::Input];

/// The table a read function code (01 to 04) reads, and its place in [`TABLES`].
fn table_read_by(function: u8) -> Option<(Table, usize)> {
    TABLES
        .iter()
        .position(|t| t.function() == function)
        .map(|at| (TABLES[at], at))
}

/// One reply's worth of one table: registers, or bits as 0 and 1.
#[derive(Debug)]
struct Block {
    first: u16,
    values: Vec<u16>,
    at: Instant,
    wall: SystemTime,
}

impl Block {
    fn end(&self) -> u32 {
        u32::from(self.first) + u32::try_from(self.values.len()).unwrap_or(0)
    }

    fn get(&self, address: u32) -> Option<u16> {
        let at = address.checked_sub(u32::from(self.first))?;
        self.values.get(usize::try_from(at).ok()?).copied()
    }
}

/// What was seen of some registers: their values, when the oldest of them was seen.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Shadowed {
    pub(crate) values: Vec<u16>,
    pub(crate) at: Instant,
    pub(crate) wall: SystemTime,
}

#[derive(Default)]
struct State {
    /// By address, by table, newest last.
    tables: Vec<[Vec<Block>; 4]>,
    /// Addresses whose blocks changed since the values last looked.
    changed: Vec<u8>,
}

/// A listen line's shadow of its slaves.
pub(crate) struct Shadow {
    state: Mutex<State>,
    max_age: AtomicU64,
    /// Told when a reply was recorded.
    recorded: Notify,
}

impl Shadow {
    pub(crate) fn new(max_age: Duration) -> Shadow {
        let mut state = State::default();
        state.tables.resize_with(256, Default::default);
        Shadow {
            state: Mutex::new(state),
            max_age: AtomicU64::new(nanos(max_age)),
            recorded: Notify::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    pub(crate) fn set_max_age(&self, max_age: Duration) {
        self.max_age.store(nanos(max_age), Ordering::Relaxed);
    }

    pub(crate) fn max_age(&self) -> Duration {
        Duration::from_nanos(self.max_age.load(Ordering::Relaxed))
    }

    /// `slave` answered `request` with `reply` (normal, checked to fit it) at `at`: what a read
    /// carried goes into its table, replacing the blocks it covers.
    pub(crate) fn record(
        &self,
        slave: u8,
        request: &[u8],
        reply: &[u8],
        at: (Instant, SystemTime),
    ) {
        let Some(((table, place), first, count)) = read_of(request) else {
            return;
        };
        let Some(values) = carried(table, count, reply) else {
            return;
        };
        let block = Block {
            first,
            values,
            at: at.0,
            wall: at.1,
        };
        let mut state = self.lock();
        let blocks = &mut state.tables[usize::from(slave)][place];
        blocks.retain(|b| b.first < block.first || b.end() > block.end());
        blocks.push(block);
        if blocks.len() > MAX_BLOCKS {
            blocks.remove(0);
        }
        if !state.changed.contains(&slave) {
            state.changed.push(slave);
        }
        drop(state);
        self.recorded.notify_one();
    }

    /// Wait until a reply has been recorded since the last wait.
    pub(crate) async fn recorded(&self) {
        self.recorded.notified().await;
    }

    /// The slaves whose blocks changed since the last call.
    pub(crate) fn take_changed(&self) -> Vec<u8> {
        std::mem::take(&mut self.lock().changed)
    }

    /// `count` registers (or bits) of `slave`'s `function`'s table from `first`, if every one
    /// was seen, each from the newest block that holds it.
    pub(crate) fn seen(&self, slave: u8, function: u8, first: u16, count: u16) -> Option<Shadowed> {
        let (_, at) = table_read_by(function)?;
        let state = self.lock();
        let blocks = &state.tables[usize::from(slave)][at];
        let mut values = Vec::with_capacity(usize::from(count));
        let mut oldest: Option<&Block> = None;
        for address in u32::from(first)..u32::from(first) + u32::from(count) {
            let (value, block) = blocks
                .iter()
                .rev()
                .find_map(|b| b.get(address).map(|v| (v, b)))?;
            values.push(value);
            if oldest.is_none_or(|o| block.at < o.at) {
                oldest = Some(block);
            }
        }
        let oldest = oldest?;
        Some(Shadowed {
            values,
            at: oldest.at,
            wall: oldest.wall,
        })
    }

    /// A master's `pdu` to `slave`, answered from what was seen, at `now`.
    pub(crate) fn answer(
        &self,
        slave: u8,
        pdu: &[u8],
        now: Instant,
    ) -> Result<Vec<u8>, RequestError> {
        let function = pdu.first().copied().unwrap_or(0);
        let Some(((table, _), first, count)) =
            read_of(pdu).filter(|_| table_read_by(function).is_some())
        else {
            return Err(RequestError::ListenOnly(function));
        };
        let most = if table.is_bits() {
            MAX_READ_BITS
        } else {
            MAX_READ_REGISTERS
        };
        if count == 0 || count > most || u32::from(first) + u32::from(count) > 0x1_0000 {
            return Err(RequestError::Unreadable(function));
        }
        let seen = self
            .seen(slave, function, first, count)
            .ok_or(RequestError::Unseen)?;
        if now.saturating_duration_since(seen.at) > self.max_age() {
            return Err(RequestError::Unseen);
        }
        Ok(reply_of(function, table, &seen.values))
    }
}

fn nanos(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

/// The table, first register and count a request reads: 01 to 04, and 17's read half.
fn read_of(pdu: &[u8]) -> Option<((Table, usize), u16, u16)> {
    let word = |at: usize| Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]));
    let function = *pdu.first()?;
    let table = match function {
        code::READ_WRITE_MULTIPLE_REGISTERS => table_read_by(code::READ_HOLDING_REGISTERS)?,
        _ => table_read_by(function)?,
    };
    if function != code::READ_WRITE_MULTIPLE_REGISTERS && pdu.len() != 5 {
        return None;
    }
    Some((table, word(1)?, word(3)?))
}

/// The registers or bits a normal reply of `count` of `table` carries.
fn carried(table: Table, count: u16, reply: &[u8]) -> Option<Vec<u16>> {
    let (&bytes, data) = reply.get(1..)?.split_first()?;
    let count = usize::from(count);
    if table.is_bits() {
        if usize::from(bytes) != count.div_ceil(8) || data.len() != usize::from(bytes) {
            return None;
        }
        Some(
            (0..count)
                .map(|i| u16::from(data[i / 8] >> (i % 8) & 1))
                .collect(),
        )
    } else {
        if usize::from(bytes) != count * 2 || data.len() != count * 2 {
            return None;
        }
        Some(
            data.chunks_exact(2)
                .map(|w| u16::from_be_bytes([w[0], w[1]]))
                .collect(),
        )
    }
}

/// The normal reply of `function` carrying `values`.
fn reply_of(function: u8, table: Table, values: &[u16]) -> Vec<u8> {
    let mut pdu = vec![function, 0];
    if table.is_bits() {
        let mut bytes = vec![0u8; values.len().div_ceil(8)];
        for (i, &bit) in values.iter().enumerate() {
            if bit != 0 {
                bytes[i / 8] |= 1 << (i % 8);
            }
        }
        pdu.extend_from_slice(&bytes);
    } else {
        for value in values {
            pdu.extend_from_slice(&value.to_be_bytes());
        }
    }
    pdu[1] = u8::try_from(pdu.len() - 2).unwrap_or(u8::MAX);
    pdu
}

#[cfg(test)]
#[path = "shadow_tests.rs"]
mod tests;
