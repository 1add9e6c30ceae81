//! The bounded, fair queue in front of one line. Each master (a connection, or a Modbus UDP
//! source) has its own FIFO and the line serves them in turn, so a master that pipelines many
//! requests cannot starve one that sends a request at a time; masters in `server.priority` have a
//! ring of their own, served first up to `priority_share` of the line, and the gateway's own polls
//! of plant values the last one. A master that leaves takes its queued requests with it. Knows
//! nothing of lines or metrics: what it takes out or hands back, the bus answers.
//!
//! Here: the [`FairQueue`] and its state; by concern, `rings` (turns, the priority share,
//! admission to a full queue), `coalesce` (reads joining an identical one) and `cache` (write
//! epochs and cached answers).

mod cache;
mod coalesce;
mod rings;
#[cfg(test)]
mod testing;

pub(crate) use cache::Epoch;

use super::Waiter;
use crate::master::{Class, MasterId};
use crate::pdu;
use cache::Cached;
use coalesce::Leaders;
use rings::{ring, Held, Place, Ring, Share, POLLS, RINGS};
use std::collections::{hash_map, HashMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Duration;
use tokio::sync::Notify;

/// A request waiting for the line: its own master's, and the identical reads that joined it.
#[derive(Debug)]
pub(crate) struct Job {
    /// Its own master.
    pub waiter: Waiter,
    pub slave: u8,
    pub pdu: Vec<u8>,
    /// Identical reads may join it (a read, with `coalesce_reads` on for its slave).
    pub coalesce: bool,
    /// Identical reads of other masters that joined it while it waited, in arrival order.
    pub followers: Vec<Waiter>,
    /// Its slave's write epoch when it was queued: a cached answer is kept only if no write
    /// came since.
    pub epoch: Epoch,
}

impl Job {
    /// `waiter`'s request of `pdu` for `slave`.
    pub(crate) fn new(waiter: Waiter, slave: u8, pdu: Vec<u8>) -> Job {
        Job {
            waiter,
            slave,
            pdu,
            coalesce: false,
            followers: Vec::new(),
            epoch: 0,
        }
    }

    pub(crate) fn master(&self) -> MasterId {
        self.waiter.origin.master
    }

    /// Whose share and turn it takes ([`Origin::admission`](crate::master::Origin::admission)).
    pub(crate) fn admission(&self) -> MasterId {
        self.waiter.origin.admission
    }

    /// From a master in `server.priority`.
    pub(crate) fn priority(&self) -> bool {
        self.waiter.origin.class == Class::Priority
    }

    /// Which ring it waits in.
    pub(crate) fn class(&self) -> Class {
        self.waiter.origin.class
    }

    /// Nobody waits for its answer any more: its master and every follower left.
    pub(crate) fn abandoned(&self) -> bool {
        self.waiter.is_gone() && self.followers.iter().all(Waiter::is_gone)
    }

    pub(crate) fn function(&self) -> u8 {
        self.pdu.first().copied().unwrap_or(0)
    }

    /// The same request for `waiter`, one of its followers, to lead in its place.
    pub(crate) fn led_by(&self, waiter: Waiter) -> Job {
        Job {
            waiter,
            slave: self.slave,
            pdu: self.pdu.clone(),
            coalesce: self.coalesce,
            followers: Vec::new(),
            epoch: self.epoch,
        }
    }
}

/// What became of a pushed job.
#[derive(Debug)]
pub(crate) enum Pushed {
    /// In its master's FIFO.
    Queued,
    /// Joined an identical read of another master.
    Joined,
    /// Not queued: the cache holds its answer, this. The job comes back to be answered.
    Cached(Job, Vec<u8>),
}

/// One master's jobs, in its own order, and where it stands in the rotation (from its first).
struct Fifo {
    jobs: VecDeque<Job>,
    ring: usize,
    key: MasterId,
}

pub(crate) struct FairQueue {
    inner: Mutex<Inner>,
    ready: Notify,
    capacity: AtomicUsize,
}

struct Inner {
    /// Exactly the masters with queued jobs.
    queues: HashMap<MasterId, Fifo>,
    /// Exactly the masters with queued jobs, in serving order, per ring.
    turn: [Ring; RINGS],
    /// Exactly the masters whose head others' reads may join.
    leaders: Leaders,
    /// Jobs and followers waiting.
    len: usize,
    /// Jobs and followers waiting, by whose share they count against; only keys holding some.
    held: HashMap<MasterId, Held>,
    /// Closed for good: pushes are refused.
    closed: bool,
    /// Per slave: bumped by every write queued to it (all of them by a broadcast).
    epochs: Box<[Epoch; 256]>,
    /// Masters with a read following another's: their next jobs wait until it is taken, so
    /// that a master's requests reach the line in its own order.
    following: HashMap<MasterId, usize>,
    share: Share,
    /// The admission keys that were waiting when the last poll went and have not had their turn
    /// since: the next poll waits for them, so no request waits behind two polls.
    owed: HashSet<MasterId>,
    /// Answers of reads to slaves with a `cache`, by (slave, PDU).
    cache: HashMap<(u8, Vec<u8>), Cached>,
}

impl FairQueue {
    pub(crate) fn new(capacity: usize) -> Self {
        FairQueue {
            inner: Mutex::new(Inner {
                queues: HashMap::new(),
                turn: Default::default(),
                leaders: Leaders::default(),
                len: 0,
                held: HashMap::new(),
                closed: false,
                epochs: Box::new([0; 256]),
                following: HashMap::new(),
                share: Share::new(crate::config::defaults::PRIORITY_SHARE),
                owed: HashSet::new(),
                cache: HashMap::new(),
            }),
            ready: Notify::new(),
            capacity: AtomicUsize::new(capacity),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The most share of the line priority masters get while others wait (`priority_share`).
    pub(crate) fn set_priority_share(&self, share: f64) {
        self.lock().share.priority = share;
    }

    /// Queue `job` behind its master's earlier ones, join it to an identical read waiting at the
    /// head of another master's FIFO (if `job.coalesce`), or answer it from the cache if an
    /// answer younger than `cache` is there. A full queue takes it only in place of the newest
    /// job of another master (`rings`: one holding more than its share, or, each holding one,
    /// when `job`'s holds nothing), which comes back with it, to be refused; otherwise a full or
    /// closed queue hands `job` back.
    // The job handed back is moved, not boxed: a box would cost an allocation per request.
    #[allow(clippy::result_large_err)]
    pub(crate) fn push(&self, mut job: Job, cache: Duration) -> Result<(Pushed, Option<Job>), Job> {
        let (pushed, evicted) = {
            let mut inner = self.lock();
            if inner.closed {
                return Err(job);
            }
            let capacity = self.capacity.load(Ordering::Relaxed);
            // A poll takes no master's place: a full queue refuses it.
            if inner.len >= capacity && job.class() == Class::Poll {
                return Err(job);
            }
            let victim = if inner.len >= capacity {
                match inner.victim(&job.waiter.origin, capacity) {
                    Some(victim) => Some(victim),
                    None => return Err(job),
                }
            } else {
                None
            };
            let read = pdu::is_read_only(&job.pdu);
            if read {
                job.epoch = inner.epochs[usize::from(job.slave)];
                if let Some(answer) = inner.cached(&job, cache) {
                    return Ok((Pushed::Cached(job, answer), None));
                }
            }
            let evicted = match victim {
                Some(victim) => match inner.evict(victim) {
                    Some(evicted) => Some(evicted),
                    None => return Err(job),
                },
                None => None,
            };
            if !read {
                inner.new_epoch(job.slave);
                job.epoch = inner.epochs[usize::from(job.slave)];
            }
            inner.hold(&job.waiter.origin);
            let pushed = match inner.join(job) {
                Ok(()) => Pushed::Joined,
                Err(job) => {
                    inner.enqueue(job, false);
                    Pushed::Queued
                }
            };
            (pushed, evicted)
        };
        if matches!(pushed, Pushed::Queued) {
            self.ready.notify_one();
        }
        Ok((pushed, evicted))
    }

    /// The next job: from the priority ring first, up to its share of the line while others
    /// wait, then round robin across admission keys within a ring, and across a key's masters
    /// within its turns; a poll when no master waits, or when each master waiting has had its
    /// turn since the last poll. Its followers come with it; from now on nothing joins it.
    pub(crate) fn try_pop(&self) -> Option<Job> {
        let mut inner = self.lock();
        let next = [0, 1, POLLS].map(|r| inner.ready_master(r));
        let inner = &mut *inner;
        let waiting = |key: &MasterId| {
            inner.turn[..POLLS]
                .iter()
                .any(|r| r.masters.contains_key(key))
        };
        inner.owed.retain(waiting);
        let r = match next.map(|next| next.is_some()) {
            [false, false, false] => return None,
            [false, false, true] => POLLS,
            [_, _, true] if inner.owed.is_empty() => POLLS,
            [true, true, _] => ring(Class::of_master(inner.share.priority_next())),
            [false, true, _] => 1,
            [true, false, _] => 0,
        };
        let (place, master) = next[r]?;
        let queue = inner.queues.get_mut(&master)?;
        if r == POLLS {
            let keys = inner.turn[..POLLS].iter().flat_map(|r| r.keys.iter());
            inner.owed = keys.copied().collect();
        } else {
            inner.share.picked(r == 1);
            inner.owed.remove(&queue.key);
        }
        let job = queue.jobs.pop_front();
        if let Some(job) = &job {
            inner.leaders.remove(queue.ring, job);
        }
        if let Some(head) = queue.jobs.front() {
            inner.leaders.add(queue.ring, head);
        }
        let more = !queue.jobs.is_empty();
        if !more {
            inner.queues.remove(&master);
        }
        inner.turn[r].served(place, more);
        let job = job?;
        inner.release(job.admission(), job.priority());
        for follower in &job.followers {
            let priority = follower.origin.class == Class::Priority;
            inner.release(follower.origin.admission, priority);
            inner.unfollow(follower.origin.master);
        }
        Some(job)
    }

    /// Wait for the next job. Cancel-safe.
    pub(crate) async fn pop(&self) -> Job {
        loop {
            let ready = self.ready.notified();
            if let Some(job) = self.try_pop() {
                return job;
            }
            ready.await;
        }
    }

    /// Take every queued job (with its followers).
    pub(crate) fn drain(&self) -> Vec<Job> {
        let mut inner = self.lock();
        let jobs = inner.queues.drain().flat_map(|(_, q)| q.jobs).collect();
        inner.turn = Default::default();
        inner.leaders = Leaders::default();
        inner.following.clear();
        inner.len = 0;
        inner.held.clear();
        jobs
    }

    /// Hold up to `capacity` jobs from now on; jobs already queued stay.
    pub(crate) fn set_capacity(&self, capacity: usize) {
        self.capacity.store(capacity, Ordering::Relaxed);
    }

    /// Refuse every later push, and take every queued job.
    pub(crate) fn close(&self) -> Vec<Job> {
        self.lock().closed = true;
        self.drain()
    }

    pub(crate) fn is_closed(&self) -> bool {
        self.lock().closed
    }

    /// Take out the jobs of a master that has gone, and the reads it had following others'.
    /// Reads of others that followed its jobs stay queued, the first of them in its place.
    pub(crate) fn forget(&self, master: MasterId) -> Vec<Job> {
        let mut inner = self.lock();
        let mut gone = Vec::new();
        if let Some(queue) = inner.queues.remove(&master) {
            inner.turn[queue.ring].remove(queue.key, master);
            if let Some(head) = queue.jobs.front() {
                inner.leaders.remove(queue.ring, head);
            }
            for mut job in queue.jobs {
                inner.release(job.admission(), job.priority());
                let followers = std::mem::take(&mut job.followers);
                inner.promote(&job, followers);
                gone.push(job);
            }
        }
        if inner.following.remove(&master).is_some() {
            let mut left = Vec::new();
            for queue in inner.queues.values_mut() {
                for job in queue.jobs.iter_mut() {
                    let (mine, others) = std::mem::take(&mut job.followers)
                        .into_iter()
                        .partition(|f: &Waiter| f.origin.master == master);
                    job.followers = others;
                    left.extend(mine.into_iter().map(|f| job.led_by(f)));
                }
            }
            for job in &left {
                inner.release(job.admission(), job.priority());
            }
            gone.extend(left);
        }
        if !gone.is_empty() {
            self.ready.notify_one();
        }
        gone
    }

    /// Requests waiting, followers included.
    pub(crate) fn len(&self) -> usize {
        self.lock().len
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Inner {
    /// Queue `job` last in its master's FIFO, or (`first`) at its head; a master with nothing
    /// queued so far takes its place in the rotation.
    fn enqueue(&mut self, job: Job, first: bool) {
        match self.queues.entry(job.master()) {
            hash_map::Entry::Occupied(queue) if first => {
                let queue = queue.into_mut();
                if let Some(head) = queue.jobs.front() {
                    self.leaders.remove(queue.ring, head);
                }
                self.leaders.add(queue.ring, &job);
                queue.jobs.push_front(job);
            }
            hash_map::Entry::Occupied(queue) => queue.into_mut().jobs.push_back(job),
            hash_map::Entry::Vacant(queue) => {
                let (r, key) = (job.class().index(), job.admission());
                self.turn[r].push(key, job.master());
                self.leaders.add(r, &job);
                queue.insert(Fifo {
                    jobs: VecDeque::from([job]),
                    ring: r,
                    key,
                });
            }
        }
    }

    /// Who in ring `r` is the next master to serve: the first whose head may go now (one with a
    /// read following another's waits for it).
    fn ready_master(&self, r: usize) -> Option<(Place, MasterId)> {
        self.turn[r].next(|master| !self.following.contains_key(&master))
    }
}

#[cfg(test)]
mod tests {
    use super::testing::*;
    use super::*;
    use crate::error::{Answer, Outcome};
    use crate::master::Origin;
    use tokio::sync::oneshot;

    #[test]
    fn under_random_pushes_pops_and_departures_every_request_is_answered_once_to_its_own_master() {
        const CAPACITY: usize = 6;
        let mut rng = fastrand::Rng::with_seed(25);
        let q = FairQueue::new(CAPACITY);
        // Masters 1-6 connections (1 a priority one), 7-12 ports of two UDP addresses.
        let origin_of = |master: MasterId| Origin {
            admission: match master {
                1..=6 => master,
                _ => ADDRESS + master % 2,
            },
            ..origin(master, master == 1)
        };
        let answer = |waiter: Waiter| {
            let master = waiter.origin.master;
            waiter.reply(Ok(Answer::Reply(vec![master as u8])));
        };
        let settle = |job: Job| {
            job.followers.into_iter().for_each(answer);
            answer(job.waiter);
        };
        let mut waiting: Vec<(MasterId, oneshot::Receiver<Outcome>)> = Vec::new();
        for _ in 0..5000 {
            // Answers so far: each to its own master; what waits is what the queue holds.
            waiting.retain_mut(|(master, rx)| match rx.try_recv() {
                Ok(outcome) => {
                    assert_eq!(outcome.unwrap(), Answer::Reply(vec![*master as u8]));
                    false
                }
                Err(oneshot::error::TryRecvError::Empty) => true,
                Err(oneshot::error::TryRecvError::Closed) => panic!("master {master}: lost"),
            });
            assert_eq!(q.len(), waiting.len());
            match rng.u8(0..10) {
                0..=5 => {
                    let master = rng.u64(1..=12);
                    let pdu = [0x03, 0x00, rng.u8(0..3), 0x00, 0x01];
                    let pdu = if rng.u8(0..8) == 0 { WRITE } else { pdu };
                    let (j, rx) = request(origin_of(master), rng.u8(1..=2), &pdu);
                    let key = j.admission();
                    let mut held: HashMap<MasterId, usize> = HashMap::new();
                    for (m, _) in &waiting {
                        *held.entry(origin_of(*m).admission).or_default() += 1;
                    }
                    let holding = held.get(&key).copied().unwrap_or(0);
                    let share = (CAPACITY / (held.len() + usize::from(holding == 0))).max(1);
                    let over = held.values().any(|&h| h > share);
                    // Holding nothing, it gets in if the queue holds a job it may displace:
                    // the priority master's only for itself.
                    let displaceable = |k: MasterId| master == 1 || k != 1;
                    let newcomer = holding == 0 && held.keys().any(|&k| displaceable(k));
                    let room = waiting.len() < CAPACITY || holding < share && over || newcomer;
                    waiting.push((master, rx));
                    match q.push(j, NONE) {
                        Ok((_, evicted)) => {
                            assert!(room, "admitted without room");
                            if let Some(evicted) = evicted {
                                let victim = evicted.admission();
                                let most = held.values().max().copied().unwrap_or(0);
                                if over {
                                    assert!(held[&victim] > share);
                                } else {
                                    assert!(newcomer && displaceable(victim));
                                    assert_eq!(held[&victim], most);
                                }
                                assert_ne!(victim, key);
                                settle(evicted);
                            }
                        }
                        Err(refused) => {
                            assert!(!room, "master {master} refused with room");
                            settle(refused);
                        }
                    }
                    assert!(q.len() <= CAPACITY);
                }
                6..=8 => {
                    if let Some(job) = q.try_pop() {
                        settle(job);
                    }
                }
                _ => q.forget(rng.u64(1..=12)).into_iter().for_each(settle),
            }
            consistent(&q);
        }
        q.drain().into_iter().for_each(settle);
        for (master, mut rx) in waiting {
            assert!(rx.try_recv().is_ok(), "master {master}: unanswered");
        }
    }

    #[test]
    fn a_master_that_leaves_takes_its_jobs_and_its_turn() {
        let q = FairQueue::new(16);
        let mut keep = Vec::new();
        for (master, tag) in [(1, 0), (2, 1), (1, 2), (2, 3)] {
            let (j, rx) = job(master, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        assert_eq!(q.forget(1).len(), 2);
        assert_eq!(q.forget(1).len(), 0);
        assert_eq!(q.len(), 2);
        assert_eq!(order(&q), [(2, 1), (2, 3)]);
    }

    #[test]
    fn a_closed_queue_hands_back_what_it_held_and_refuses_more() {
        let q = FairQueue::new(4);
        let (a, _ra) = job(1, 0);
        q.push(a, NONE).unwrap();
        assert_eq!(q.close().len(), 1);
        let (b, _rb) = job(2, 0);
        assert!(q.push(b, NONE).is_err());
        assert!(q.is_closed() && q.is_empty());
    }

    #[tokio::test]
    async fn pop_waits_for_a_push() {
        let q = std::sync::Arc::new(FairQueue::new(4));
        let waiter = tokio::spawn({
            let q = q.clone();
            async move { q.pop().await.master() }
        });
        tokio::task::yield_now().await;
        let (j, _rx) = job(7, 0);
        q.push(j, NONE).unwrap();
        assert_eq!(waiter.await.unwrap(), 7);
    }
}
