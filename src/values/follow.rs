//! The plant values of a listen-only line: no poll is ever sent; each value is taken from the
//! line's shadow as soon as a reply the other master asked for carries all its registers, with
//! the time it was heard, and goes stale (`"stale"`: not exported) once that is older than the
//! line's `max_age`. One task per listen line.

use super::decode;
use super::store::Store;
use crate::bus::BusHandle;
use crate::config::Value;
use crate::timer::coarse_sleep_until;
use std::sync::Arc;
use tokio::time::Instant;

/// One value of the line: its entry in the store, its slave, and how to decode it.
pub(crate) struct Followed {
    pub(crate) entry: usize,
    pub(crate) slave: u8,
    pub(crate) value: Value,
    /// When the registers it was last taken from were heard.
    heard_at: Option<Instant>,
    stale: bool,
}

impl Followed {
    pub(crate) fn new(entry: usize, slave: u8, value: Value) -> Followed {
        Followed {
            entry,
            slave,
            value,
            heard_at: None,
            stale: false,
        }
    }
}

/// Follow `values` in `bus`'s shadow into `store`, for ever.
pub(crate) async fn run(bus: BusHandle, mut values: Vec<Followed>, store: Arc<Store>) {
    let Some(shadow) = bus.shadow().cloned() else {
        return;
    };
    // What was heard before this configuration counts too.
    let mut slaves: Vec<u8> = values.iter().map(|v| v.slave).collect();
    slaves.dedup();
    loop {
        for followed in values.iter_mut().filter(|v| slaves.contains(&v.slave)) {
            take(followed, &shadow, &store);
        }
        let max_age = shadow.max_age();
        let now = Instant::now();
        let mut next = None::<Instant>;
        for followed in &mut values {
            let Some(heard) = followed.heard_at else {
                continue;
            };
            if now.saturating_duration_since(heard) > max_age {
                if !followed.stale {
                    followed.stale = true;
                    store.failed(followed.entry, "stale");
                }
            } else {
                let due = heard + max_age;
                next = Some(next.map_or(due, |n: Instant| n.min(due)));
            }
        }
        let wake = next.unwrap_or(now + max_age);
        tokio::select! {
            () = shadow.recorded() => {}
            () = coarse_sleep_until(wake) => {}
        }
        slaves = shadow.take_changed();
    }
}

/// `followed`'s registers, if the shadow holds all of them newer than it last took.
fn take(followed: &mut Followed, shadow: &crate::bus::shadow::Shadow, store: &Store) {
    let value = &followed.value;
    let Ok(first) = u16::try_from(value.register) else {
        return;
    };
    let Some(seen) = shadow.seen(followed.slave, value.table.function(), first, value.width())
    else {
        return;
    };
    if followed.heard_at.is_some_and(|at| at >= seen.at) {
        return;
    }
    followed.heard_at = Some(seen.at);
    followed.stale = false;
    match decode::decode(value, &seen.values) {
        Some(number) => store.read(followed.entry, number, seen.wall),
        None => store.failed(followed.entry, "bad_reply"),
    }
}
