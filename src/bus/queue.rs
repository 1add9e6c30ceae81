//! The bounded, fair queue in front of one serial line. Each master (connection) has its own
//! FIFO and the line serves them in turn, so a master that pipelines many requests cannot starve
//! one that sends a request at a time; masters in `server.priority` have a ring of their own,
//! served first up to `priority_share` of the line. A master that leaves takes its queued
//! requests with it.
//!
//! Reads coalesce here: a read identical (slave, PDU) to one waiting at the head of another
//! master's FIFO joins it as a [`Follower`] and is answered by its transaction, which starts
//! after the follower arrived (the leader is taken from the queue only when the line is ready
//! for its frame). A write to a slave starts a new epoch for it: no read joins a leader from an
//! earlier epoch, and a cached answer (the opt-in per-slave cache kept here, under the same
//! lock as the epochs) dies with its epoch.

use crate::error::{Answer, Outcome};
use crate::line::BROADCAST;
use crate::metrics::Protocol;
use crate::pdu;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Duration;
use tokio::sync::{oneshot, Notify};
use tokio::time::Instant;

/// One TCP connection.
pub type MasterId = u64;

/// Who a request comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Origin {
    pub master: MasterId,
    /// How the master talks to the gateway, for the requests' `protocol` label.
    pub protocol: Protocol,
    /// Served before the others (`server.priority`).
    pub priority: bool,
}

/// A request waiting for the line.
#[derive(Debug)]
pub struct Job {
    pub master: MasterId,
    /// How the master talks to the gateway, for the requests' `protocol` label.
    pub protocol: Protocol,
    /// From a master in `server.priority`.
    pub priority: bool,
    pub slave: u8,
    pub pdu: Vec<u8>,
    /// When it was queued.
    pub queued_at: Instant,
    /// If the line has not started it by then, the master has been answered 0x06 instead.
    pub deadline: Instant,
    pub reply: oneshot::Sender<Outcome>,
    /// Identical reads may join it (a read, with `coalesce_reads` on for its slave).
    pub coalesce: bool,
    /// Identical reads of other masters that joined it while it waited, in arrival order.
    pub followers: Vec<Follower>,
    /// Its slave's write epoch when it was queued: a cached answer is kept only if no write
    /// came since.
    pub epoch: u64,
    /// Its own master has been answered already (it expired or left); its followers have not.
    pub answered: bool,
}

/// A read answered by another master's identical one.
#[derive(Debug)]
pub struct Follower {
    pub master: MasterId,
    pub protocol: Protocol,
    pub priority: bool,
    pub queued_at: Instant,
    pub deadline: Instant,
    pub reply: oneshot::Sender<Outcome>,
}

impl Job {
    /// A request of `origin` for `slave`, queued now, given up at `deadline`.
    pub fn new(
        origin: Origin,
        slave: u8,
        pdu: Vec<u8>,
        deadline: Instant,
        reply: oneshot::Sender<Outcome>,
    ) -> Job {
        Job {
            master: origin.master,
            protocol: origin.protocol,
            priority: origin.priority,
            slave,
            pdu,
            queued_at: Instant::now(),
            deadline,
            reply,
            coalesce: false,
            followers: Vec::new(),
            epoch: 0,
            answered: false,
        }
    }

    /// Nobody waits for its answer any more: its master and every follower left.
    pub fn abandoned(&self) -> bool {
        (self.answered || self.reply.is_closed())
            && self.followers.iter().all(|f| f.reply.is_closed())
    }

    pub fn function(&self) -> u8 {
        self.pdu.first().copied().unwrap_or(0)
    }

    fn follower(self) -> Follower {
        Follower {
            master: self.master,
            protocol: self.protocol,
            priority: self.priority,
            queued_at: self.queued_at,
            deadline: self.deadline,
            reply: self.reply,
        }
    }
}

impl Follower {
    /// The follower's own request, as a job like `leader`.
    fn leading(self, leader: &Job) -> Job {
        Job {
            master: self.master,
            protocol: self.protocol,
            priority: self.priority,
            slave: leader.slave,
            pdu: leader.pdu.clone(),
            queued_at: self.queued_at,
            deadline: self.deadline,
            reply: self.reply,
            coalesce: leader.coalesce,
            followers: Vec::new(),
            epoch: leader.epoch,
            answered: false,
        }
    }
}

/// What became of a pushed job.
#[derive(Debug, PartialEq, Eq)]
pub enum Pushed {
    /// In its master's FIFO.
    Queued,
    /// Joined an identical read of another master.
    Joined,
    /// Answered from the cache, with this.
    Cached(Vec<u8>),
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

pub struct FairQueue {
    inner: Mutex<Inner>,
    ready: Notify,
    capacity: AtomicUsize,
}

struct Inner {
    queues: HashMap<MasterId, VecDeque<Job>>,
    /// Exactly the masters with queued jobs, in serving order, per ring.
    turn: [VecDeque<MasterId>; RINGS],
    /// Jobs and followers waiting.
    len: usize,
    /// Closed for good: pushes are refused.
    closed: bool,
    /// Per slave: bumped by every write queued to it (all of them by a broadcast).
    epochs: Box<[u64; 256]>,
    /// Masters with a read following another's: their next jobs wait until it is taken, so
    /// that a master's requests reach the line in its own order.
    following: HashMap<MasterId, usize>,
    share: Share,
    /// Answers of reads to slaves with a `cache`, by (slave, PDU).
    cache: HashMap<(u8, Vec<u8>), Cached>,
}

/// Most answers a bus keeps cached; the oldest go first.
const CACHE_ENTRIES: usize = 1024;

impl FairQueue {
    pub fn new(capacity: usize) -> Self {
        FairQueue {
            inner: Mutex::new(Inner {
                queues: HashMap::new(),
                turn: Default::default(),
                len: 0,
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
    /// answer younger than `cache` is there. A full or closed queue hands it back.
    pub fn push(&self, mut job: Job, cache: Duration) -> Result<Pushed, Job> {
        let pushed = {
            let mut inner = self.lock();
            if inner.len >= self.capacity.load(Ordering::Relaxed) || inner.closed {
                return Err(job);
            }
            if !pdu::is_read_only(&job.pdu) {
                inner.new_epoch(job.slave);
            }
            job.epoch = inner.epochs[usize::from(job.slave)];
            if let Some(answer) = inner.cached(&job, cache) {
                let _ = job.reply.send(Ok(Answer::Reply(answer.clone())));
                return Ok(Pushed::Cached(answer));
            }
            inner.len += 1;
            match inner.join(job) {
                Ok(()) => Pushed::Joined,
                Err(job) => {
                    inner.enqueue(job);
                    Pushed::Queued
                }
            }
        };
        if pushed == Pushed::Queued {
            self.ready.notify_one();
        }
        Ok(pushed)
    }

    /// The next job: from the priority ring first, up to its share of the line while others
    /// wait, then round robin across masters within a ring. Its followers come with it; from
    /// now on nothing joins it.
    pub fn try_pop(&self) -> Option<Job> {
        let mut inner = self.lock();
        let waiting = [0, 1].map(|r| inner.ready_master(r).is_some());
        let priority = match waiting {
            [true, true] => inner.share.priority_next(),
            [false, true] => true,
            [true, false] => false,
            [false, false] => return None,
        };
        inner.share.picked(priority);
        let at = inner.ready_master(ring(priority))?;
        let master = inner.turn[ring(priority)].remove(at)?;
        let queue = inner.queues.get_mut(&master)?;
        let job = queue.pop_front();
        if queue.is_empty() {
            inner.queues.remove(&master);
        } else {
            inner.turn[ring(priority)].push_back(master);
        }
        let job = job?;
        inner.len -= 1 + job.followers.len();
        for follower in &job.followers {
            inner.unfollow(follower.master);
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
        let jobs = inner.queues.drain().flat_map(|(_, q)| q).collect();
        inner.turn = Default::default();
        inner.following.clear();
        inner.len = 0;
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
            for turn in &mut inner.turn {
                turn.retain(|&m| m != master);
            }
            for mut job in queue {
                inner.len -= 1;
                let followers = std::mem::take(&mut job.followers);
                inner.len -= followers.len();
                inner.promote(&job, followers);
                gone.push(job);
            }
        }
        if inner.following.remove(&master).is_some() {
            let mut left = Vec::new();
            for queue in inner.queues.values_mut() {
                for job in queue.iter_mut() {
                    let (mine, others) = std::mem::take(&mut job.followers)
                        .into_iter()
                        .partition(|f: &Follower| f.master == master);
                    job.followers = others;
                    left.extend(mine.into_iter().map(|f| f.leading(job)));
                }
            }
            inner.len -= left.len();
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

    /// The write epoch of `slave` now.
    pub fn epoch(&self, slave: u8) -> u64 {
        self.lock().epochs[usize::from(slave)]
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
            self.epochs.iter_mut().for_each(|epoch| *epoch += 1);
            self.cache.clear();
        } else {
            self.epochs[usize::from(slave)] += 1;
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
            self.queues.contains_key(&job.master) || self.following.contains_key(&job.master);
        if !job.coalesce || master_busy {
            return Err(job);
        }
        let rings: &[usize] = if job.priority { &[1] } else { &[1, 0] };
        let leader = rings.iter().find_map(|&r| {
            self.turn[r].iter().find(|master| {
                self.queues
                    .get(master)
                    .and_then(VecDeque::front)
                    .is_some_and(|head| {
                        head.coalesce
                            && head.slave == job.slave
                            && head.epoch == job.epoch
                            && head.pdu == job.pdu
                    })
            })
        });
        let Some(&leader) = leader else {
            return Err(job);
        };
        *self.following.entry(job.master).or_default() += 1;
        let head = self.queues.get_mut(&leader).and_then(VecDeque::front_mut);
        match head {
            Some(head) => {
                head.followers.push(job.follower());
                Ok(())
            }
            None => Err(job),
        }
    }

    fn enqueue(&mut self, job: Job) {
        let master = job.master;
        let priority = job.priority;
        let queue = self.queues.entry(master).or_default();
        queue.push_back(job);
        if queue.len() == 1 {
            self.turn[ring(priority)].push_back(master);
        }
    }

    /// Where in ring `r` the next master to serve is: the first whose head may go now (one
    /// with a read following another's waits for it).
    fn ready_master(&self, r: usize) -> Option<usize> {
        self.turn[r]
            .iter()
            .position(|master| !self.following.contains_key(master))
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
    /// own master's FIFO, with the others following it.
    fn promote(&mut self, job: &Job, followers: Vec<Follower>) {
        let mut followers = followers.into_iter();
        let Some(first) = followers.next() else {
            return;
        };
        self.unfollow(first.master);
        let mut promoted = first.leading(job);
        promoted.followers = followers.collect();
        self.len += 1 + promoted.followers.len();
        let (master, priority) = (promoted.master, promoted.priority);
        let queue = self.queues.entry(master).or_default();
        queue.push_front(promoted);
        if queue.len() == 1 {
            self.turn[ring(priority)].push_back(master);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const READ: [u8; 5] = [0x03, 0x00, 0x10, 0x00, 0x02];
    const WRITE: [u8; 5] = [0x06, 0x00, 0x10, 0x12, 0x34];
    const NONE: Duration = Duration::ZERO;

    fn origin(master: MasterId, priority: bool) -> Origin {
        Origin {
            master,
            protocol: Protocol::Tcp,
            priority,
        }
    }

    fn request(origin: Origin, slave: u8, pdu: &[u8]) -> (Job, oneshot::Receiver<Outcome>) {
        let (reply, rx) = oneshot::channel();
        let far = Instant::now() + Duration::from_secs(60);
        let mut job = Job::new(origin, slave, pdu.to_vec(), far, reply);
        job.coalesce = pdu::is_read_only(pdu);
        (job, rx)
    }

    fn job(master: MasterId, tag: u8) -> (Job, oneshot::Receiver<Outcome>) {
        request(origin(master, false), 1, &[0x03, tag])
    }

    fn order(q: &FairQueue) -> Vec<(MasterId, u8)> {
        std::iter::from_fn(|| q.try_pop())
            .map(|j| (j.master, j.pdu[1]))
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

    #[test]
    fn a_full_queue_hands_the_job_back() {
        let q = FairQueue::new(2);
        let (a, _ra) = job(1, 0);
        let (b, _rb) = job(2, 1);
        let (c, _rc) = job(3, 2);
        q.push(a, NONE).unwrap();
        q.push(b, NONE).unwrap();
        let refused = q.push(c, NONE).unwrap_err();
        assert_eq!(refused.master, 3);
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
            async move { q.pop().await.master }
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
        assert_eq!(q.push(leader, NONE).ok(), Some(Pushed::Queued));
        let (same, _r2) = request(origin(2, false), 5, &READ);
        assert_eq!(q.push(same, NONE).ok(), Some(Pushed::Joined));
        // Another slave, another register: a request of its own.
        let (other_slave, _r3) = request(origin(3, false), 6, &READ);
        assert_eq!(q.push(other_slave, NONE).ok(), Some(Pushed::Queued));
        let (other_block, _r4) = request(origin(4, false), 5, &[0x03, 0x00, 0x11, 0x00, 0x02]);
        assert_eq!(q.push(other_block, NONE).ok(), Some(Pushed::Queued));
        assert_eq!(q.len(), 4, "a follower waits too");
        let first = q.try_pop().unwrap();
        assert_eq!(first.master, 1);
        let followers: Vec<MasterId> = first.followers.iter().map(|f| f.master).collect();
        assert_eq!(followers, [2]);
        assert_eq!(q.len(), 2);
        // Taken: a read arriving now starts a transaction of its own.
        let (late, _r5) = request(origin(5, false), 5, &READ);
        assert_eq!(q.push(late, NONE).ok(), Some(Pushed::Queued));
    }

    #[test]
    fn no_read_joins_across_a_write_to_its_slave_but_one_to_another_slave_does_not_matter() {
        let q = FairQueue::new(16);
        let (leader, _r1) = request(origin(1, false), 5, &READ);
        q.push(leader, NONE).unwrap();
        let (elsewhere, _r2) = request(origin(2, false), 6, &WRITE);
        q.push(elsewhere, NONE).unwrap();
        let (joins, _r3) = request(origin(3, false), 5, &READ);
        assert_eq!(q.push(joins, NONE).ok(), Some(Pushed::Joined));
        let (write, _r4) = request(origin(4, false), 5, &WRITE);
        q.push(write, NONE).unwrap();
        let (after_write, _r5) = request(origin(5, false), 5, &READ);
        assert_eq!(
            q.push(after_write, NONE).ok(),
            Some(Pushed::Queued),
            "after the write"
        );
        let (broadcast, _r6) = request(origin(6, false), 0, &WRITE);
        q.push(broadcast, NONE).unwrap();
        let (after_broadcast, _r7) = request(origin(7, false), 5, &READ);
        assert_eq!(q.push(after_broadcast, NONE).ok(), Some(Pushed::Queued));
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
        assert_eq!(q.push(read, NONE).ok(), Some(Pushed::Queued));
    }

    #[test]
    fn a_followers_next_request_waits_until_the_read_it_follows_is_taken() {
        let q = FairQueue::new(16);
        let (a, _r1) = request(origin(1, false), 5, &[0x03, 0x00, 0x00, 0x00, 0x01]);
        q.push(a, NONE).unwrap();
        let (leader, _r2) = request(origin(2, false), 5, &READ);
        q.push(leader, NONE).unwrap();
        let (follows, _r3) = request(origin(3, false), 5, &READ);
        assert_eq!(q.push(follows, NONE).ok(), Some(Pushed::Joined));
        let (next, _r4) = request(origin(3, false), 5, &WRITE);
        q.push(next, NONE).unwrap();
        let masters: Vec<(MasterId, usize)> = std::iter::from_fn(|| q.try_pop())
            .map(|j| (j.master, j.followers.len()))
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
        assert_eq!(next.master, 2);
        assert_eq!(next.pdu, READ);
        assert_eq!(next.followers.len(), 1);
        assert_eq!(next.followers[0].master, 3);
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
        let first: Vec<MasterId> = (0..100).map(|_| q.try_pop().unwrap().master).collect();
        let priority = first.iter().filter(|&&m| m == 1).count();
        assert_eq!(priority, 75, "{first:?}");
        assert_eq!(&first[..5], [1, 2, 1, 1, 2]);
        // Alone, the priority ring takes the whole line, and so do the others.
        let q = FairQueue::new(16);
        q.set_priority_share(0.5);
        let (j, _r) = request(origin(1, false), 1, &[0x41, 0]);
        q.push(j, NONE).unwrap();
        assert_eq!(q.try_pop().unwrap().master, 1);
    }

    #[test]
    fn a_priority_read_joins_only_a_priority_masters_read() {
        let q = FairQueue::new(16);
        let (normal, _r1) = request(origin(1, false), 5, &READ);
        q.push(normal, NONE).unwrap();
        let (urgent, _r2) = request(origin(2, true), 5, &READ);
        assert_eq!(q.push(urgent, NONE).ok(), Some(Pushed::Queued));
        let (normal_too, _r3) = request(origin(3, false), 5, &READ);
        assert_eq!(q.push(normal_too, NONE).ok(), Some(Pushed::Joined));
        assert_eq!(q.try_pop().unwrap().master, 2, "the priority read first");
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
        let (again, mut answer) = request(origin(2, false), 5, &READ);
        assert_eq!(
            q.push(again, age).ok(),
            Some(Pushed::Cached(vec![0x03, 0x04, 0, 1, 0, 2]))
        );
        assert_eq!(
            answer.try_recv().unwrap().unwrap(),
            Answer::Reply(vec![0x03, 0x04, 0, 1, 0, 2])
        );
        tokio::time::advance(age).await;
        let (stale, _r3) = request(origin(3, false), 5, &READ);
        assert_eq!(q.push(stale, age).ok(), Some(Pushed::Queued), "too old");
        let stale = q.try_pop().unwrap();
        q.remember(&stale, &[0x03, 0x04, 0, 1, 0, 2]);
        let (write, _r4) = request(origin(4, false), 5, &WRITE);
        q.push(write, age).unwrap();
        let (after, _r5) = request(origin(5, false), 5, &READ);
        assert_eq!(
            q.push(after, age).ok(),
            Some(Pushed::Queued),
            "the write dropped it"
        );
        // An answer to a read queued before that write is not kept.
        q.remember(&stale, &[0x03, 0x04, 9, 9, 9, 9]);
        let (later, _r6) = request(origin(6, false), 5, &READ);
        assert_eq!(
            q.push(later, age).ok(),
            Some(Pushed::Joined),
            "it joins the read waiting; the answer from before the write is not there"
        );
    }
}
