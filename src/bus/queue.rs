//! The bounded, fair queue in front of one serial line. Each master (connection) has its own
//! FIFO and the line serves them in turn, so a master that pipelines many requests cannot starve
//! one that sends a request at a time; masters in `server.priority` have a ring of their own,
//! served first up to `priority_share` of the line. A master that leaves takes its queued
//! requests with it.
//!
//! The turns go round robin over [`Origin::admission`] keys, and within a key over its masters:
//! a connection is a key of its own, while all the ports of one Modbus UDP source address share
//! one turn (ports cost a sender nothing). So 40 ports of one host flooding the line take one
//! transaction in two while a connection waits, not 40 in 41; each port still has its own FIFO,
//! order and replies, and its turns come in rotation among its address's ports.
//!
//! Reads coalesce here: a read identical (slave, PDU) to one waiting at the head of another
//! master's FIFO joins it as a [`Follower`] and is answered by its transaction, which starts
//! after the follower arrived (the leader is taken from the queue only when the line is ready
//! for its frame). A write to a slave starts a new epoch for it: no read joins a leader from an
//! earlier epoch, and a cached answer (the opt-in per-slave cache kept here, under the same
//! lock as the epochs) dies with its epoch. The heads reads may join are indexed by (slave,
//! epoch, PDU), so that neither a push nor a pop looks at every master's FIFO.
//!
//! Admission is fair as well. `queue_depth` bounds the requests waiting for the line (followers
//! included) over all masters, and while there is room every request goes in. Once the queue is
//! full, a request still goes in if its master holds less than its *share* while another holds
//! more than its own: the share is `queue_depth` divided among the masters with requests
//! waiting, the newcomer included, rounded down and at least one. The newest request of the
//! master holding the most is refused (0x06) to make room; a master in `server.priority` loses
//! one only when no other master holds more than its share. So a master with nothing waiting
//! gets in whenever another holds more than its share, a master within its share is never
//! refused for another, and none can win a place back from the one that took it. When more
//! masters wait than the queue holds, each holds at most one and a newcomer waits for room.
//! What counts as one master here is a request's [`Origin::admission`]: a connection, or all
//! the ports of one Modbus UDP source address. A follower counts against its own master; a
//! refused leader's followers stay queued, the first of them leading in its place.

use super::Waiter;
use crate::line::BROADCAST;
use crate::master::MasterId;
use crate::pdu;
use std::cmp::Reverse;
use std::collections::{hash_map, HashMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Duration;
use tokio::sync::Notify;
use tokio::time::Instant;

/// A request waiting for the line: its own master's, and the identical reads that joined it.
#[derive(Debug)]
pub struct Job {
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

/// A slave's count of writes queued to it. It wraps: two epochs are compared only within the
/// wait of one request, and a `u32` keeps a [`Job`] small enough to move by value.
pub type Epoch = u32;

impl Job {
    /// `waiter`'s request of `pdu` for `slave`.
    pub fn new(waiter: Waiter, slave: u8, pdu: Vec<u8>) -> Job {
        Job {
            waiter,
            slave,
            pdu,
            coalesce: false,
            followers: Vec::new(),
            epoch: 0,
        }
    }

    pub fn master(&self) -> MasterId {
        self.waiter.origin.master
    }

    /// Whose share and turn it takes ([`Origin::admission`]).
    pub fn admission(&self) -> MasterId {
        self.waiter.origin.admission
    }

    /// From a master in `server.priority`.
    pub fn priority(&self) -> bool {
        self.waiter.origin.priority
    }

    /// Nobody waits for its answer any more: its master and every follower left.
    pub fn abandoned(&self) -> bool {
        self.waiter.is_gone() && self.followers.iter().all(Waiter::is_gone)
    }

    pub fn function(&self) -> u8 {
        self.pdu.first().copied().unwrap_or(0)
    }

    /// The same request for `waiter`, one of its followers, to lead in its place.
    pub fn led_by(&self, waiter: Waiter) -> Job {
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
pub enum Pushed {
    /// In its master's FIFO.
    Queued,
    /// Joined an identical read of another master.
    Joined,
    /// Not queued: the cache holds its answer, this. The job comes back to be answered.
    Cached(Job, Vec<u8>),
}

/// A cached answer to one read.
struct Cached {
    at: Instant,
    pdu: Vec<u8>,
}

/// How the line is shared between the two rings: counts of the recent transactions of each
/// (halved now and then, so that the recent past decides). When both rings wait, the priority
/// ring goes unless it has had `priority` of them already: a priority master that uses little
/// of the line always goes first, and saturating ones leave the others the rest.
#[derive(Default)]
struct Share {
    /// Most share of contested picks the priority ring gets; 1.0 serves it always first.
    priority: f64,
    priority_picks: u32,
    other_picks: u32,
}

impl Share {
    const MEMORY: u32 = 1000;

    /// Whether the priority ring goes next when both rings wait.
    fn priority_next(&self) -> bool {
        // Only if its share stays within `priority` with this pick, so the others' floor
        // holds; with no history, the priority ring.
        let total = f64::from(self.priority_picks + self.other_picks + 1);
        total == 1.0 || f64::from(self.priority_picks + 1) <= self.priority * total
    }

    fn picked(&mut self, priority: bool) {
        if priority {
            self.priority_picks += 1;
        } else {
            self.other_picks += 1;
        }
        if self.priority_picks + self.other_picks > Self::MEMORY {
            self.priority_picks /= 2;
            self.other_picks /= 2;
        }
    }
}

/// The normal ring, then the priority ring.
const RINGS: usize = 2;
fn ring(priority: bool) -> usize {
    usize::from(priority)
}

/// The masters with jobs queued in one ring, in serving order: round robin over admission keys,
/// and within a key over its masters.
#[derive(Default)]
struct Ring {
    /// Exactly the keys with a master here, the next to serve first.
    keys: VecDeque<MasterId>,
    /// By key in `keys`: exactly its masters here, the next to serve first.
    masters: HashMap<MasterId, VecDeque<MasterId>>,
}

/// Where a master to serve stands in its [`Ring`]: its key's place, and its own within the key.
#[derive(Clone, Copy)]
struct Place {
    key: usize,
    master: usize,
}

impl Ring {
    /// `master` of `key` has jobs now: served after the others of its key, and a key new here
    /// after every other key.
    fn push(&mut self, key: MasterId, master: MasterId) {
        match self.masters.entry(key) {
            hash_map::Entry::Occupied(mut masters) => masters.get_mut().push_back(master),
            hash_map::Entry::Vacant(masters) => {
                masters.insert(VecDeque::from([master]));
                self.keys.push_back(key);
            }
        }
    }

    /// The next master to serve: the first that may go (`ready`) of the first key that has one.
    fn next(&self, ready: impl Fn(MasterId) -> bool) -> Option<(Place, MasterId)> {
        self.keys.iter().enumerate().find_map(|(key, id)| {
            let masters = self.masters.get(id)?;
            let master = masters.iter().position(|&m| ready(m))?;
            Some((Place { key, master }, masters[master]))
        })
    }

    /// The master at `place` was served: its key goes last, and it goes last within its key if
    /// it has `more` jobs, or leaves the ring.
    fn served(&mut self, place: Place, more: bool) {
        let Some(key) = self.keys.remove(place.key) else {
            return;
        };
        let hash_map::Entry::Occupied(mut masters) = self.masters.entry(key) else {
            return;
        };
        let master = masters.get_mut().remove(place.master);
        if let (true, Some(master)) = (more, master) {
            masters.get_mut().push_back(master);
        }
        if masters.get().is_empty() {
            masters.remove();
        } else {
            self.keys.push_back(key);
        }
    }

    /// `master` of `key` has no jobs any more (it left, or its last one was refused).
    fn remove(&mut self, key: MasterId, master: MasterId) {
        let hash_map::Entry::Occupied(mut masters) = self.masters.entry(key) else {
            return;
        };
        masters.get_mut().retain(|&m| m != master);
        if masters.get().is_empty() {
            masters.remove();
            self.keys.retain(|&k| k != key);
        }
    }
}

/// A read others may join, as [`Leaders`] knows it: its slave, that slave's write epoch when it
/// was queued, and its PDU.
type ReadKey = (u8, Epoch, Vec<u8>);

/// Per ring, the masters whose head is a read others may join, by that read, so that a read
/// finds one to join without looking at every master's head.
#[derive(Default)]
struct Leaders([HashMap<ReadKey, Vec<MasterId>>; RINGS]);

impl Leaders {
    fn key(job: &Job) -> ReadKey {
        (job.slave, job.epoch, job.pdu.clone())
    }

    /// `head` is at the head of its master's FIFO in ring `r` now.
    fn add(&mut self, r: usize, head: &Job) {
        if head.coalesce {
            self.0[r]
                .entry(Self::key(head))
                .or_default()
                .push(head.master());
        }
    }

    /// `head` is at the head of its master's FIFO in ring `r` no more.
    fn remove(&mut self, r: usize, head: &Job) {
        if !head.coalesce {
            return;
        }
        if let hash_map::Entry::Occupied(mut masters) = self.0[r].entry(Self::key(head)) {
            masters.get_mut().retain(|&m| m != head.master());
            if masters.get().is_empty() {
                masters.remove();
            }
        }
    }

    /// A master whose head `job` may join: a priority one first, and for a priority job only
    /// such a one.
    fn find(&self, job: &Job) -> Option<MasterId> {
        let rings: &[usize] = if job.priority() { &[1] } else { &[1, 0] };
        let key = Self::key(job);
        rings
            .iter()
            .find_map(|&r| self.0[r].get(&key).and_then(|masters| masters.first()))
            .copied()
    }
}

/// One master's jobs, in its own order, and where it stands in the rotation (from its first).
struct Fifo {
    jobs: VecDeque<Job>,
    ring: usize,
    key: MasterId,
}

pub struct FairQueue {
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
    /// Answers of reads to slaves with a `cache`, by (slave, PDU).
    cache: HashMap<(u8, Vec<u8>), Cached>,
}

/// What one admission key has waiting.
#[derive(Clone, Copy, Default)]
struct Held {
    requests: usize,
    /// Of those, from masters in `server.priority`.
    priority: usize,
}

/// Most answers a bus keeps cached; the oldest go first.
const CACHE_ENTRIES: usize = 1024;

impl FairQueue {
    pub fn new(capacity: usize) -> Self {
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
                share: Share {
                    priority: crate::config::defaults::PRIORITY_SHARE,
                    ..Share::default()
                },
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
    pub fn set_priority_share(&self, share: f64) {
        self.lock().share.priority = share;
    }

    /// Queue `job` behind its master's earlier ones, join it to an identical read waiting at the
    /// head of another master's FIFO (if `job.coalesce`), or answer it from the cache if an
    /// answer younger than `cache` is there. A full queue takes it only in place of the newest
    /// job of a master holding more than its share, which comes back with it, to be refused;
    /// otherwise a full or closed queue hands `job` back.
    pub fn push(&self, mut job: Job, cache: Duration) -> Result<(Pushed, Option<Job>), Job> {
        let (pushed, evicted) = {
            let mut inner = self.lock();
            if inner.closed {
                return Err(job);
            }
            let capacity = self.capacity.load(Ordering::Relaxed);
            let victim = if inner.len >= capacity {
                match inner.victim(job.admission(), capacity) {
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
            inner.hold(job.admission(), job.priority());
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
    /// within its turns. Its followers come with it; from now on nothing joins it.
    pub fn try_pop(&self) -> Option<Job> {
        let mut inner = self.lock();
        let next = [0, 1].map(|r| inner.ready_master(r));
        let priority = match next.map(|next| next.is_some()) {
            [true, true] => inner.share.priority_next(),
            [false, true] => true,
            [true, false] => false,
            [false, false] => return None,
        };
        inner.share.picked(priority);
        let r = ring(priority);
        let (place, master) = next[r]?;
        let inner = &mut *inner;
        let queue = inner.queues.get_mut(&master)?;
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
            inner.release(follower.origin.admission, follower.origin.priority);
            inner.unfollow(follower.origin.master);
        }
        Some(job)
    }

    /// Wait for the next job. Cancel-safe.
    pub async fn pop(&self) -> Job {
        loop {
            let ready = self.ready.notified();
            if let Some(job) = self.try_pop() {
                return job;
            }
            ready.await;
        }
    }

    /// Take every queued job (with its followers).
    pub fn drain(&self) -> Vec<Job> {
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
    pub fn set_capacity(&self, capacity: usize) {
        self.capacity.store(capacity, Ordering::Relaxed);
    }

    /// Refuse every later push, and take every queued job.
    pub fn close(&self) -> Vec<Job> {
        self.lock().closed = true;
        self.drain()
    }

    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }

    /// Take out the jobs of a master that has gone, and the reads it had following others'.
    /// Reads of others that followed its jobs stay queued, the first of them in its place.
    pub fn forget(&self, master: MasterId) -> Vec<Job> {
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
    pub fn len(&self) -> usize {
        self.lock().len
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Keep `answer` to `job`'s read for `cache`-configured slaves, unless a write to its slave
    /// was queued since the job was.
    pub fn remember(&self, job: &Job, answer: &[u8]) {
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
    fn new_epoch(&mut self, slave: u8) {
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
    fn cached(&self, job: &Job, max_age: Duration) -> Option<Vec<u8>> {
        if max_age.is_zero() || !pdu::is_read_only(&job.pdu) {
            return None;
        }
        let cached = self.cache.get(&(job.slave, job.pdu.clone()))?;
        (cached.at.elapsed() < max_age).then(|| cached.pdu.clone())
    }

    /// Make `job` a follower of an identical read at the head of another master's FIFO, if it
    /// may: a coalescing read, of a master with nothing else waiting, the leader from the same
    /// epoch, and (for a priority master) a priority leader.
    fn join(&mut self, job: Job) -> Result<(), Job> {
        let master_busy =
            self.queues.contains_key(&job.master()) || self.following.contains_key(&job.master());
        if !job.coalesce || master_busy {
            return Err(job);
        }
        let head = self
            .leaders
            .find(&job)
            .and_then(|leader| self.queues.get_mut(&leader))
            .and_then(|queue| queue.jobs.front_mut())
            .filter(|head| {
                head.coalesce
                    && head.slave == job.slave
                    && head.epoch == job.epoch
                    && head.pdu == job.pdu
            });
        let Some(head) = head else {
            return Err(job);
        };
        *self.following.entry(job.master()).or_default() += 1;
        head.followers.push(job.waiter);
        Ok(())
    }

    /// One more request waits, counted against `key`.
    fn hold(&mut self, key: MasterId, priority: bool) {
        self.len += 1;
        let held = self.held.entry(key).or_default();
        held.requests += 1;
        held.priority += usize::from(priority);
    }

    /// A request counted against `key` waits no more.
    fn release(&mut self, key: MasterId, priority: bool) {
        self.len = self.len.saturating_sub(1);
        if let hash_map::Entry::Occupied(mut entry) = self.held.entry(key) {
            let held = entry.get_mut();
            held.requests = held.requests.saturating_sub(1);
            held.priority = held.priority.saturating_sub(usize::from(priority));
            if held.requests == 0 {
                entry.remove();
            }
        }
    }

    /// The key whose newest request a full queue of `capacity` refuses to admit one of
    /// `newcomer`, if any: `newcomer` holds less than its share and the key more than its own;
    /// the one holding the most, a priority master's only if no other qualifies.
    fn victim(&self, newcomer: MasterId, capacity: usize) -> Option<MasterId> {
        let holding = self.held.get(&newcomer).map_or(0, |held| held.requests);
        let sharing = self.held.len() + usize::from(holding == 0);
        let share = (capacity / sharing.max(1)).max(1);
        if holding >= share {
            return None;
        }
        self.held
            .iter()
            .filter(|(_, held)| held.requests > share)
            .min_by_key(|&(&key, held)| (held.priority > 0, Reverse(held.requests), key))
            .map(|(&key, _)| key)
    }

    /// Take out the newest request counted against `key`, to be refused: the last job of its
    /// master with the most queued (one that no read follows, if there is such a master), or
    /// else a read of it that follows another's. A refused leader's followers stay queued.
    fn evict(&mut self, key: MasterId) -> Option<Job> {
        let busiest = self
            .queues
            .iter()
            .filter(|(_, queue)| queue.jobs.back().is_some_and(|job| job.admission() == key))
            .max_by_key(|&(&master, queue)| {
                let led = queue
                    .jobs
                    .back()
                    .is_some_and(|job| !job.followers.is_empty());
                (!led, queue.jobs.len(), Reverse(master))
            })
            .map(|(&master, _)| master);
        if let Some(master) = busiest {
            let queue = self.queues.get_mut(&master)?;
            let mut job = queue.jobs.pop_back()?;
            if queue.jobs.is_empty() {
                self.leaders.remove(queue.ring, &job);
                self.turn[queue.ring].remove(queue.key, master);
                self.queues.remove(&master);
            }
            self.release(job.admission(), job.priority());
            let followers = std::mem::take(&mut job.followers);
            self.promote(&job, followers);
            return Some(job);
        }
        let job = self
            .queues
            .values_mut()
            .flat_map(|queue| queue.jobs.iter_mut())
            .find_map(|leader| {
                let at = leader
                    .followers
                    .iter()
                    .rposition(|f| f.origin.admission == key)?;
                let follower = leader.followers.remove(at);
                Some(leader.led_by(follower))
            })?;
        self.unfollow(job.master());
        self.release(job.admission(), job.priority());
        Some(job)
    }

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
                let (r, key) = (ring(job.priority()), job.admission());
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

    fn unfollow(&mut self, master: MasterId) {
        if let Some(count) = self.following.get_mut(&master) {
            *count -= 1;
            if *count == 0 {
                self.following.remove(&master);
            }
        }
    }

    /// The leader `job` is gone unsent: its first follower takes its place at the head of its
    /// own master's FIFO, with the others following it. They all still wait, as they did.
    fn promote(&mut self, job: &Job, followers: Vec<Waiter>) {
        let mut followers = followers.into_iter();
        let Some(first) = followers.next() else {
            return;
        };
        self.unfollow(first.origin.master);
        let mut promoted = job.led_by(first);
        promoted.followers = followers.collect();
        self.enqueue(promoted, true);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::{Answer, Outcome};
    use crate::master::{Origin, Protocol};
    use tokio::sync::oneshot;

    const READ: [u8; 5] = [0x03, 0x00, 0x10, 0x00, 0x02];
    const WRITE: [u8; 5] = [0x06, 0x00, 0x10, 0x12, 0x34];
    const NONE: Duration = Duration::ZERO;

    fn origin(master: MasterId, priority: bool) -> Origin {
        Origin {
            master,
            admission: master,
            protocol: Protocol::Tcp,
            priority,
        }
    }

    /// What became of a pushed job, whatever it displaced: [`Pushed`] without the job.
    #[derive(Debug, PartialEq, Eq)]
    enum Went {
        Queued,
        Joined,
        Cached(Vec<u8>),
    }

    fn pushed(result: Result<(Pushed, Option<Job>), Job>) -> Option<Went> {
        result.ok().map(|(pushed, _)| match pushed {
            Pushed::Queued => Went::Queued,
            Pushed::Joined => Went::Joined,
            Pushed::Cached(_, answer) => Went::Cached(answer),
        })
    }

    fn request(origin: Origin, slave: u8, pdu: &[u8]) -> (Job, oneshot::Receiver<Outcome>) {
        let far = Instant::now() + Duration::from_secs(60);
        let (waiter, rx) = Waiter::new(origin, far);
        let mut job = Job::new(waiter, slave, pdu.to_vec());
        job.coalesce = pdu::is_read_only(pdu);
        (job, rx)
    }

    fn job(master: MasterId, tag: u8) -> (Job, oneshot::Receiver<Outcome>) {
        request(origin(master, false), 1, &[0x03, tag])
    }

    /// The rotation holds exactly the masters with jobs queued, each once, under the ring and
    /// key of its jobs; the counts are those of the jobs and followers queued.
    fn consistent(q: &FairQueue) {
        let inner = q.lock();
        let mut placed = std::collections::HashSet::new();
        for (r, rotation) in inner.turn.iter().enumerate() {
            let keys: std::collections::HashSet<_> = rotation.keys.iter().collect();
            assert_eq!(keys.len(), rotation.keys.len(), "a key once");
            assert_eq!(keys.len(), rotation.masters.len());
            for (key, masters) in &rotation.masters {
                assert!(keys.contains(key) && !masters.is_empty());
                for master in masters {
                    let queue = &inner.queues[master];
                    assert_eq!((queue.ring, queue.key), (r, *key));
                    assert!(queue.jobs.iter().all(|j| {
                        (ring(j.priority()), j.admission(), j.master()) == (r, *key, *master)
                    }));
                    assert!(placed.insert(*master), "master {master} once");
                }
            }
        }
        assert_eq!(placed.len(), inner.queues.len());
        // The leaders are exactly the joinable heads, each under its own read and ring.
        let mut heads: Vec<(usize, ReadKey, MasterId)> = inner
            .queues
            .values()
            .filter_map(|queue| Some((queue.ring, queue.jobs.front()?)))
            .filter(|(_, head)| head.coalesce)
            .map(|(r, head)| (r, Leaders::key(head), head.master()))
            .collect();
        let mut leaders: Vec<(usize, ReadKey, MasterId)> = (0..RINGS)
            .flat_map(|r| {
                inner.leaders.0[r].iter().flat_map(move |(key, masters)| {
                    assert!(!masters.is_empty());
                    masters.iter().map(move |&m| (r, key.clone(), m))
                })
            })
            .collect();
        heads.sort_unstable();
        leaders.sort_unstable();
        assert_eq!(heads, leaders);
        let mut held: HashMap<MasterId, usize> = HashMap::new();
        for job in inner.queues.values().flat_map(|queue| &queue.jobs) {
            *held.entry(job.admission()).or_default() += 1;
            for follower in &job.followers {
                *held.entry(follower.origin.admission).or_default() += 1;
            }
        }
        assert_eq!(inner.len, held.values().sum::<usize>());
        let counted: HashMap<MasterId, usize> =
            inner.held.iter().map(|(&k, h)| (k, h.requests)).collect();
        assert_eq!(counted, held);
    }

    fn order(q: &FairQueue) -> Vec<(MasterId, u8)> {
        std::iter::from_fn(|| q.try_pop())
            .map(|j| (j.master(), j.pdu[1]))
            .collect()
    }

    #[test]
    fn masters_are_served_in_turn_whatever_they_queued() {
        let q = FairQueue::new(16);
        let mut keep = Vec::new();
        for tag in 0..4 {
            let (j, rx) = job(1, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        for master in [2, 3] {
            let (j, rx) = job(master, 0x10 + master as u8);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        assert_eq!(
            order(&q),
            [(1, 0), (2, 0x12), (3, 0x13), (1, 1), (1, 2), (1, 3)]
        );
        assert!(q.is_empty());
    }

    /// The ids the ports of two Modbus UDP source addresses share for admission.
    const ADDRESS: MasterId = 100;
    const OTHER_ADDRESS: MasterId = 101;

    /// A request of a Modbus UDP master: `port` at the address with id `address`.
    fn datagram(port: MasterId, address: MasterId, tag: u8) -> (Job, oneshot::Receiver<Outcome>) {
        let origin = Origin {
            admission: address,
            protocol: Protocol::Udp,
            ..origin(port, false)
        };
        request(origin, 1, &[0x03, tag])
    }

    #[test]
    fn forty_ports_of_one_udp_address_take_one_turn_so_another_masters_job_goes_within_two_pops() {
        let q = FairQueue::new(1024);
        let mut keep = Vec::new();
        for _ in 0..4 {
            for port in 10..50 {
                // Reads of a register of its own: none joins another.
                let udp = Origin {
                    admission: ADDRESS,
                    protocol: Protocol::Udp,
                    ..origin(port, false)
                };
                let (j, rx) = request(udp, 1, &[0x04, 0x00, port as u8, 0x00, 0x01]);
                q.push(j, NONE).unwrap();
                keep.push(rx);
            }
        }
        for tag in 0..4 {
            let (j, rx) = job(1, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        let served: Vec<MasterId> = std::iter::from_fn(|| q.try_pop())
            .map(|j| j.master())
            .collect();
        let connection: Vec<usize> = (0..served.len()).filter(|&at| served[at] == 1).collect();
        assert_eq!(connection, [1, 3, 5, 7], "{served:?}");
        // Within the address's turns its ports go round robin, each in its own order.
        let ports: Vec<MasterId> = served.iter().copied().filter(|&m| m != 1).collect();
        assert_eq!(ports.len(), 160);
        assert!(ports
            .chunks(40)
            .all(|round| round.iter().copied().eq(10..50)));
    }

    #[test]
    fn the_ports_of_one_udp_address_take_turns_within_its_turn() {
        let q = FairQueue::new(16);
        let mut keep = Vec::new();
        for (port, address, tag) in [(10, ADDRESS, 0), (10, ADDRESS, 1), (11, ADDRESS, 2)] {
            let (j, rx) = datagram(port, address, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        for (master, tag) in [(1, 3), (1, 4)] {
            let (j, rx) = job(master, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        let (j, rx) = datagram(20, OTHER_ADDRESS, 5);
        q.push(j, NONE).unwrap();
        keep.push(rx);
        assert_eq!(
            order(&q),
            [(10, 0), (1, 3), (20, 5), (11, 2), (1, 4), (10, 1)]
        );
        // A port that leaves takes only its own jobs; its address keeps its turn.
        for (port, tag) in [(10, 6), (11, 7), (10, 8)] {
            let (j, rx) = datagram(port, ADDRESS, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        let (j, rx) = job(1, 9);
        q.push(j, NONE).unwrap();
        keep.push(rx);
        assert_eq!(q.forget(10).len(), 2);
        assert_eq!(order(&q), [(11, 7), (1, 9)]);
    }

    #[test]
    fn a_full_queue_admits_a_newcomer_in_place_of_the_newest_job_of_the_master_holding_most() {
        let q = FairQueue::new(6);
        let mut keep = Vec::new();
        for (master, tag) in [(1, 0), (1, 1), (1, 2), (1, 3), (2, 4), (2, 5)] {
            let (j, rx) = job(master, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        // Three masters: a share of two each. Master 1 holds four.
        let (newcomer, _r) = job(3, 6);
        let (pushed, evicted) = q.push(newcomer, NONE).expect("admitted");
        assert!(matches!(pushed, Pushed::Queued));
        let evicted = evicted.expect("a job refused for it");
        assert_eq!(
            (evicted.master(), evicted.pdu[1]),
            (1, 3),
            "master 1's newest"
        );
        assert_eq!(q.len(), 6, "queue_depth stays the total");
        // Master 1, still above its share, cannot win the place back.
        let (again, _r) = job(1, 7);
        assert_eq!(q.push(again, NONE).unwrap_err().master(), 1);
        assert_eq!(order(&q), [(1, 0), (2, 4), (3, 6), (1, 1), (2, 5), (1, 2)]);
    }

    #[test]
    fn a_full_queue_refuses_a_master_at_its_share_and_one_when_nobody_holds_more_than_theirs() {
        let q = FairQueue::new(4);
        let mut keep = Vec::new();
        for (master, tag) in [(1, 0), (1, 1), (2, 2), (2, 3)] {
            let (j, rx) = job(master, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        // Two masters, two each: at their share.
        let (more, _r) = job(2, 4);
        assert_eq!(q.push(more, NONE).unwrap_err().master(), 2);
        // More masters than places: one each, and a newcomer waits for room.
        let q = FairQueue::new(2);
        for master in [1, 2] {
            let (j, rx) = job(master, 0);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        let (newcomer, _r) = job(3, 0);
        assert_eq!(q.push(newcomer, NONE).unwrap_err().master(), 3);
        assert_eq!(q.len(), 2);
    }

    #[test]
    fn the_ports_of_one_udp_address_share_one_share_of_a_full_queue() {
        let q = FairQueue::new(4);
        let mut keep = Vec::new();
        for port in 10..14 {
            let (j, rx) = datagram(port, ADDRESS, port as u8);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        // A fifth port is no newcomer: its address holds the whole queue already.
        let (port, _r) = datagram(14, ADDRESS, 0);
        assert!(q.push(port, NONE).is_err());
        // Another address and a connection are: the address keeps two.
        let (other, _r) = datagram(20, OTHER_ADDRESS, 1);
        let (_, evicted) = q.push(other, NONE).expect("another address");
        assert!((10..14).contains(&evicted.expect("a port's job").master()));
        let (connection, _r) = job(1, 2);
        let (_, evicted) = q.push(connection, NONE).expect("a connection");
        assert!((10..14).contains(&evicted.expect("a port's job").master()));
        let masters: Vec<MasterId> = order(&q).iter().map(|&(m, _)| m).collect();
        assert_eq!(
            masters.iter().filter(|&&m| (10..14).contains(&m)).count(),
            2
        );
        assert!(masters.contains(&20) && masters.contains(&1));
    }

    #[test]
    fn a_refused_leaders_followers_stay_queued_and_the_first_leads_in_its_place() {
        let q = FairQueue::new(4);
        let other = [0x03, 0x00, 0x20, 0x00, 0x01];
        // Master 1 follows master 3's read, then leads a read that master 2 follows: it holds two,
        // its newest a leader.
        let (lead, _r3) = request(origin(3, false), 6, &other);
        q.push(lead, NONE).unwrap();
        let (follows, _r1a) = request(origin(1, false), 6, &other);
        assert_eq!(pushed(q.push(follows, NONE)), Some(Went::Joined));
        let (leads, _r1b) = request(origin(1, false), 5, &READ);
        assert_eq!(pushed(q.push(leads, NONE)), Some(Went::Queued));
        let (joins, _r2) = request(origin(2, false), 5, &READ);
        assert_eq!(pushed(q.push(joins, NONE)), Some(Went::Joined));
        // Four masters, a share of one each.
        let (newcomer, _r4) = request(origin(4, false), 7, &READ);
        let (_, evicted) = q.push(newcomer, NONE).expect("admitted");
        let evicted = evicted.expect("master 1's read refused");
        assert_eq!((evicted.master(), evicted.slave), (1, 5));
        assert!(evicted.followers.is_empty(), "its follower stays");
        assert_eq!(q.len(), 4);
        // Each request once: master 3's read with master 1 following, master 2's in its place.
        let mut served: Vec<(MasterId, u8, Vec<MasterId>)> = std::iter::from_fn(|| q.try_pop())
            .map(|j| {
                (
                    j.master(),
                    j.slave,
                    j.followers.iter().map(|f| f.origin.master).collect(),
                )
            })
            .collect();
        served.sort_unstable();
        assert_eq!(served, [(2, 5, vec![]), (3, 6, vec![1]), (4, 7, vec![])]);
        assert!(q.is_empty());
    }

    #[test]
    fn when_an_address_holds_only_followers_one_of_them_is_refused() {
        let q = FairQueue::new(3);
        let (lead, _r1) = request(origin(1, false), 5, &READ);
        q.push(lead, NONE).unwrap();
        let mut keep = Vec::new();
        for port in [10, 11] {
            let udp = Origin {
                admission: ADDRESS,
                ..origin(port, false)
            };
            let (follows, rx) = request(udp, 5, &READ);
            assert_eq!(pushed(q.push(follows, NONE)), Some(Went::Joined));
            keep.push(rx);
        }
        let (newcomer, _r2) = job(2, 0);
        let (_, evicted) = q.push(newcomer, NONE).expect("admitted");
        let evicted = evicted.expect("a follower refused");
        assert!([10, 11].contains(&evicted.master()));
        assert_eq!((evicted.slave, &evicted.pdu[..]), (5, &READ[..]));
        let leader = q.try_pop().unwrap();
        assert_eq!(leader.master(), 1);
        assert_eq!(leader.followers.len(), 1);
        assert_ne!(leader.followers[0].origin.master, evicted.master());
        assert_eq!(q.try_pop().unwrap().master(), 2);
        assert!(q.is_empty() && q.try_pop().is_none());
    }

    #[test]
    fn a_priority_master_loses_a_place_only_when_no_other_master_holds_more_than_its_share() {
        let q = FairQueue::new(7);
        let mut keep = Vec::new();
        for (master, priority, n) in [(1, true, 4), (2, false, 3)] {
            for tag in 0..n {
                let (j, rx) = request(origin(master, priority), 1, &[0x03, tag]);
                q.push(j, NONE).unwrap();
                keep.push(rx);
            }
        }
        // Shares of two, then of one: master 2 gives way first though master 1 holds more.
        let mut refused = Vec::new();
        for newcomer in [3, 4, 5] {
            let (j, _r) = job(newcomer, 9);
            let (_, evicted) = q.push(j, NONE).expect("admitted");
            refused.push(evicted.expect("one refused").master());
        }
        assert_eq!(refused, [2, 2, 1]);
        assert_eq!(q.len(), 7);
    }

    #[test]
    fn under_random_pushes_pops_and_departures_every_request_is_answered_once_to_its_own_master() {
        const CAPACITY: usize = 8;
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
                    let room = waiting.len() < CAPACITY
                        || holding < share && held.values().any(|&h| h > share);
                    waiting.push((master, rx));
                    match q.push(j, NONE) {
                        Ok((_, evicted)) => {
                            assert!(room, "admitted without room");
                            if let Some(evicted) = evicted {
                                assert!(held[&evicted.admission()] > share);
                                assert_ne!(evicted.admission(), key);
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
    fn a_full_queue_hands_the_job_back() {
        let q = FairQueue::new(2);
        let (a, _ra) = job(1, 0);
        let (b, _rb) = job(2, 1);
        let (c, _rc) = job(3, 2);
        q.push(a, NONE).unwrap();
        q.push(b, NONE).unwrap();
        let refused = q.push(c, NONE).unwrap_err();
        assert_eq!(refused.master(), 3);
        assert_eq!(q.len(), 2);
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

    #[test]
    fn identical_reads_of_other_masters_join_the_one_waiting_and_leave_with_it() {
        let q = FairQueue::new(16);
        let (leader, _r1) = request(origin(1, false), 5, &READ);
        assert_eq!(pushed(q.push(leader, NONE)), Some(Went::Queued));
        let (same, _r2) = request(origin(2, false), 5, &READ);
        assert_eq!(pushed(q.push(same, NONE)), Some(Went::Joined));
        // Another slave, another register: a request of its own.
        let (other_slave, _r3) = request(origin(3, false), 6, &READ);
        assert_eq!(pushed(q.push(other_slave, NONE)), Some(Went::Queued));
        let (other_block, _r4) = request(origin(4, false), 5, &[0x03, 0x00, 0x11, 0x00, 0x02]);
        assert_eq!(pushed(q.push(other_block, NONE)), Some(Went::Queued));
        assert_eq!(q.len(), 4, "a follower waits too");
        let first = q.try_pop().unwrap();
        assert_eq!(first.master(), 1);
        let followers: Vec<MasterId> = first.followers.iter().map(|f| f.origin.master).collect();
        assert_eq!(followers, [2]);
        assert_eq!(q.len(), 2);
        // Taken: a read arriving now starts a transaction of its own.
        let (late, _r5) = request(origin(5, false), 5, &READ);
        assert_eq!(pushed(q.push(late, NONE)), Some(Went::Queued));
    }

    #[test]
    fn no_read_joins_across_a_write_to_its_slave_but_one_to_another_slave_does_not_matter() {
        let q = FairQueue::new(16);
        let (leader, _r1) = request(origin(1, false), 5, &READ);
        q.push(leader, NONE).unwrap();
        let (elsewhere, _r2) = request(origin(2, false), 6, &WRITE);
        q.push(elsewhere, NONE).unwrap();
        let (joins, _r3) = request(origin(3, false), 5, &READ);
        assert_eq!(pushed(q.push(joins, NONE)), Some(Went::Joined));
        let (write, _r4) = request(origin(4, false), 5, &WRITE);
        q.push(write, NONE).unwrap();
        let (after_write, _r5) = request(origin(5, false), 5, &READ);
        assert_eq!(
            pushed(q.push(after_write, NONE)),
            Some(Went::Queued),
            "after the write"
        );
        let (broadcast, _r6) = request(origin(6, false), 0, &WRITE);
        q.push(broadcast, NONE).unwrap();
        let (after_broadcast, _r7) = request(origin(7, false), 5, &READ);
        assert_eq!(pushed(q.push(after_broadcast, NONE)), Some(Went::Queued));
    }

    #[test]
    fn a_master_with_requests_waiting_keeps_its_own_order_and_does_not_join() {
        let q = FairQueue::new(16);
        let (leader, _r1) = request(origin(1, false), 5, &READ);
        q.push(leader, NONE).unwrap();
        // Master 2 pipelines a write to slave 6, then the read: the read may not overtake it.
        let (write, _r2) = request(origin(2, false), 6, &WRITE);
        q.push(write, NONE).unwrap();
        let (read, _r3) = request(origin(2, false), 5, &READ);
        assert_eq!(pushed(q.push(read, NONE)), Some(Went::Queued));
    }

    #[test]
    fn a_followers_next_request_waits_until_the_read_it_follows_is_taken() {
        let q = FairQueue::new(16);
        let (a, _r1) = request(origin(1, false), 5, &[0x03, 0x00, 0x00, 0x00, 0x01]);
        q.push(a, NONE).unwrap();
        let (leader, _r2) = request(origin(2, false), 5, &READ);
        q.push(leader, NONE).unwrap();
        let (follows, _r3) = request(origin(3, false), 5, &READ);
        assert_eq!(pushed(q.push(follows, NONE)), Some(Went::Joined));
        let (next, _r4) = request(origin(3, false), 5, &WRITE);
        q.push(next, NONE).unwrap();
        let masters: Vec<(MasterId, usize)> = std::iter::from_fn(|| q.try_pop())
            .map(|j| (j.master(), j.followers.len()))
            .collect();
        assert_eq!(
            masters,
            [(1, 0), (2, 1), (3, 0)],
            "3's write after its read"
        );
    }

    #[test]
    fn when_a_leaders_master_leaves_its_first_follower_leads_in_its_place() {
        let q = FairQueue::new(16);
        let (leader, _r1) = request(origin(1, false), 5, &READ);
        q.push(leader, NONE).unwrap();
        let mut keep = Vec::new();
        for master in [2, 3] {
            let (follows, rx) = request(origin(master, false), 5, &READ);
            q.push(follows, NONE).unwrap();
            keep.push(rx);
        }
        let gone = q.forget(1);
        assert_eq!(gone.len(), 1);
        assert!(gone[0].followers.is_empty());
        assert_eq!(q.len(), 2);
        let next = q.try_pop().unwrap();
        assert_eq!(next.master(), 2);
        assert_eq!(next.pdu, READ);
        assert_eq!(next.followers.len(), 1);
        assert_eq!(next.followers[0].origin.master, 3);
        assert!(q.is_empty());
        // A follower that leaves goes alone.
        let (leader, _r4) = request(origin(4, false), 5, &READ);
        q.push(leader, NONE).unwrap();
        let (follows, _r5) = request(origin(5, false), 5, &READ);
        q.push(follows, NONE).unwrap();
        assert_eq!(q.forget(5).len(), 1);
        assert!(q.try_pop().unwrap().followers.is_empty());
    }

    #[test]
    fn priority_masters_go_first_up_to_their_share_and_the_others_still_get_the_rest() {
        let q = FairQueue::new(4096);
        q.set_priority_share(0.75);
        let mut keep = Vec::new();
        for n in 0..200u8 {
            for (master, priority) in [(1, true), (2, false)] {
                let (j, rx) = request(origin(master, priority), 1, &[0x41, n]);
                q.push(j, NONE).unwrap();
                keep.push(rx);
            }
        }
        let first: Vec<MasterId> = (0..100).map(|_| q.try_pop().unwrap().master()).collect();
        let priority = first.iter().filter(|&&m| m == 1).count();
        assert_eq!(priority, 75, "{first:?}");
        assert_eq!(&first[..5], [1, 2, 1, 1, 2]);
        // Alone, the priority ring takes the whole line, and so do the others.
        let q = FairQueue::new(16);
        q.set_priority_share(0.5);
        let (j, _r) = request(origin(1, false), 1, &[0x41, 0]);
        q.push(j, NONE).unwrap();
        assert_eq!(q.try_pop().unwrap().master(), 1);
    }

    #[test]
    fn a_priority_read_joins_only_a_priority_masters_read() {
        let q = FairQueue::new(16);
        let (normal, _r1) = request(origin(1, false), 5, &READ);
        q.push(normal, NONE).unwrap();
        let (urgent, _r2) = request(origin(2, true), 5, &READ);
        assert_eq!(pushed(q.push(urgent, NONE)), Some(Went::Queued));
        let (normal_too, _r3) = request(origin(3, false), 5, &READ);
        assert_eq!(pushed(q.push(normal_too, NONE)), Some(Went::Joined));
        assert_eq!(q.try_pop().unwrap().master(), 2, "the priority read first");
        // Master 3's read followed the priority one, the first identical read waiting.
        assert_eq!(q.try_pop().unwrap().followers.len(), 0);
    }

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
