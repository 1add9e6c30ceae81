//! Write epochs and the opt-in per-slave cache, kept under the queue's lock. A write to a
//! slave starts a new epoch for it: no read joins a leader from an earlier epoch, and a cached
//! answer dies with its epoch.

use super::{FairQueue, Inner, Job};
use crate::line::BROADCAST;
use crate::pdu;
use std::time::Duration;
use tokio::time::Instant;

/// A slave's count of writes queued to it. It wraps: two epochs are compared only within the
/// wait of one request, and a `u32` keeps a [`Job`] small enough to move by value.
pub(crate) type Epoch = u32;

/// A cached answer to one read.
pub(super) struct Cached {
    at: Instant,
    pdu: Vec<u8>,
}

/// Most answers a bus keeps cached; the oldest go first.
const CACHE_ENTRIES: usize = 1024;

impl FairQueue {
    /// Keep `answer` to `job`'s read for `cache`-configured slaves, unless a write to its slave
    /// was queued since the job was.
    pub(crate) fn remember(&self, job: &Job, answer: &[u8]) {
        let mut inner = self.lock();
        if inner.epochs[usize::from(job.slave)] != job.epoch {
            return;
        }
        if inner.cache.len() >= CACHE_ENTRIES {
            let oldest = inner
                .cache
                .iter()
                .min_by_key(|(_, cached)| cached.at)
                .map(|(key, _)| key.clone());
            if let Some(key) = oldest {
                inner.cache.remove(&key);
            }
        }
        inner.cache.insert(
            (job.slave, job.pdu.clone()),
            Cached {
                at: Instant::now(),
                pdu: answer.to_vec(),
            },
        );
    }
}

impl Inner {
    /// A write to `slave` is queued: reads after it join nothing before it, and its cached
    /// answers are gone.
    pub(super) fn new_epoch(&mut self, slave: u8) {
        if slave == BROADCAST {
            self.epochs
                .iter_mut()
                .for_each(|epoch| *epoch = epoch.wrapping_add(1));
            self.cache.clear();
        } else {
            let epoch = &mut self.epochs[usize::from(slave)];
            *epoch = epoch.wrapping_add(1);
            self.cache.retain(|(cached, _), _| *cached != slave);
        }
    }

    /// The cached answer to `job`, if younger than `max_age`.
    pub(super) fn cached(&self, job: &Job, max_age: Duration) -> Option<Vec<u8>> {
        if max_age.is_zero() || !pdu::is_read_only(&job.pdu) {
            return None;
        }
        let cached = self.cache.get(&(job.slave, job.pdu.clone()))?;
        (cached.at.elapsed() < max_age).then(|| cached.pdu.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;
    use std::time::Duration;

    #[tokio::test(start_paused = true)]
    async fn a_cached_answer_serves_within_its_age_and_a_write_to_the_slave_drops_it() {
        let q = FairQueue::new(16);
        let age = Duration::from_millis(500);
        let (read, _r1) = request(origin(1, false), 5, &READ);
        q.push(read, age).unwrap();
        let read = q.try_pop().unwrap();
        q.remember(&read, &[0x03, 0x04, 0, 1, 0, 2]);
        let (again, _r2) = request(origin(2, false), 5, &READ);
        match q.push(again, age) {
            Ok((Pushed::Cached(job, answer), None)) => {
                assert_eq!(answer, [0x03, 0x04, 0, 1, 0, 2]);
                assert_eq!(job.master(), 2, "back to be answered by the bus");
            }
            _ => panic!("not answered from the cache"),
        }
        assert!(q.is_empty());
        tokio::time::advance(age).await;
        let (stale, _r3) = request(origin(3, false), 5, &READ);
        assert_eq!(pushed(q.push(stale, age)), Some(Went::Queued), "too old");
        let stale = q.try_pop().unwrap();
        q.remember(&stale, &[0x03, 0x04, 0, 1, 0, 2]);
        let (write, _r4) = request(origin(4, false), 5, &WRITE);
        q.push(write, age).unwrap();
        let (after, _r5) = request(origin(5, false), 5, &READ);
        assert_eq!(
            pushed(q.push(after, age)),
            Some(Went::Queued),
            "the write dropped it"
        );
        // An answer to a read queued before that write is not kept.
        q.remember(&stale, &[0x03, 0x04, 9, 9, 9, 9]);
        let (later, _r6) = request(origin(6, false), 5, &READ);
        assert_eq!(
            pushed(q.push(later, age)),
            Some(Went::Joined),
            "it joins the read waiting; the answer from before the write is not there"
        );
    }
}
