//! The bounded, fair queue in front of one serial line. Each master (connection) has its own
//! FIFO and the line serves them in turn, so a master that pipelines many requests cannot starve
//! one that sends a request at a time. A master that leaves takes its queued requests with it.

use crate::error::Outcome;
use crate::metrics::Protocol;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};
use tokio::sync::{oneshot, Notify};
use tokio::time::Instant;

/// One TCP connection.
pub type MasterId = u64;

/// A request waiting for the line.
#[derive(Debug)]
pub struct Job {
    pub master: MasterId,
    /// How the master talks to the gateway, for the requests' `protocol` label.
    pub protocol: Protocol,
    pub slave: u8,
    pub pdu: Vec<u8>,
    /// When it was queued.
    pub queued_at: Instant,
    /// If the line has not started it by then, the master has been answered 0x06 instead.
    pub deadline: Instant,
    pub reply: oneshot::Sender<Outcome>,
}

impl Job {
    pub fn function(&self) -> u8 {
        self.pdu.first().copied().unwrap_or(0)
    }
}

pub struct FairQueue {
    inner: Mutex<Inner>,
    ready: Notify,
    capacity: AtomicUsize,
}

#[derive(Default)]
struct Inner {
    queues: HashMap<MasterId, VecDeque<Job>>,
    /// Exactly the masters with queued jobs, in serving order.
    turn: VecDeque<MasterId>,
    len: usize,
    /// Closed for good: pushes are refused.
    closed: bool,
}

impl FairQueue {
    pub fn new(capacity: usize) -> Self {
        FairQueue {
            inner: Mutex::new(Inner::default()),
            ready: Notify::new(),
            capacity: AtomicUsize::new(capacity),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Queue `job` behind its master's earlier ones; a full or closed queue hands it back.
    pub fn push(&self, job: Job) -> Result<(), Job> {
        {
            let mut inner = self.lock();
            if inner.len >= self.capacity.load(Ordering::Relaxed) || inner.closed {
                return Err(job);
            }
            let master = job.master;
            let queue = inner.queues.entry(master).or_default();
            queue.push_back(job);
            if queue.len() == 1 {
                inner.turn.push_back(master);
            }
            inner.len += 1;
        }
        self.ready.notify_one();
        Ok(())
    }

    /// The next job in round-robin order across masters.
    pub fn try_pop(&self) -> Option<Job> {
        let mut inner = self.lock();
        let master = inner.turn.pop_front()?;
        let queue = inner.queues.get_mut(&master)?;
        let job = queue.pop_front();
        if queue.is_empty() {
            inner.queues.remove(&master);
        } else {
            inner.turn.push_back(master);
        }
        inner.len -= usize::from(job.is_some());
        job
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

    /// Take every queued job.
    pub fn drain(&self) -> Vec<Job> {
        let mut inner = self.lock();
        let jobs = inner.queues.drain().flat_map(|(_, q)| q).collect();
        inner.turn.clear();
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

    /// Take out the jobs of a master that has gone.
    pub fn forget(&self, master: MasterId) -> VecDeque<Job> {
        let mut inner = self.lock();
        let Some(queue) = inner.queues.remove(&master) else {
            return VecDeque::new();
        };
        inner.turn.retain(|&m| m != master);
        inner.len -= queue.len();
        queue
    }

    pub fn len(&self) -> usize {
        self.lock().len
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(master: MasterId, tag: u8) -> (Job, oneshot::Receiver<Outcome>) {
        let (reply, rx) = oneshot::channel();
        let job = Job {
            master,
            protocol: Protocol::Tcp,
            slave: 1,
            pdu: vec![0x03, tag],
            queued_at: Instant::now(),
            deadline: Instant::now(),
            reply,
        };
        (job, rx)
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
            q.push(j).unwrap();
            keep.push(rx);
        }
        for master in [2, 3] {
            let (j, rx) = job(master, 0);
            q.push(j).unwrap();
            keep.push(rx);
        }
        assert_eq!(order(&q), [(1, 0), (2, 0), (3, 0), (1, 1), (1, 2), (1, 3)]);
        assert!(q.is_empty());
    }

    #[test]
    fn a_full_queue_hands_the_job_back() {
        let q = FairQueue::new(2);
        let (a, _ra) = job(1, 0);
        let (b, _rb) = job(2, 0);
        let (c, _rc) = job(3, 0);
        q.push(a).unwrap();
        q.push(b).unwrap();
        let refused = q.push(c).unwrap_err();
        assert_eq!(refused.master, 3);
        assert_eq!(q.len(), 2);
    }

    #[test]
    fn a_master_that_leaves_takes_its_jobs_and_its_turn() {
        let q = FairQueue::new(16);
        let mut keep = Vec::new();
        for (master, tag) in [(1, 0), (2, 0), (1, 1), (2, 1)] {
            let (j, rx) = job(master, tag);
            q.push(j).unwrap();
            keep.push(rx);
        }
        assert_eq!(q.forget(1).len(), 2);
        assert_eq!(q.forget(1).len(), 0);
        assert_eq!(q.len(), 2);
        assert_eq!(order(&q), [(2, 0), (2, 1)]);
    }

    #[test]
    fn a_closed_queue_hands_back_what_it_held_and_refuses_more() {
        let q = FairQueue::new(4);
        let (a, _ra) = job(1, 0);
        q.push(a).unwrap();
        assert_eq!(q.close().len(), 1);
        let (b, _rb) = job(2, 0);
        assert!(q.push(b).is_err());
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
        q.push(j).unwrap();
        assert_eq!(waiter.await.unwrap(), 7);
    }
}
