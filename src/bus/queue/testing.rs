//! What the queue's tests share: requests of a master, and a check that the queue's indexes
//! agree with what it holds.

use super::coalesce::{Leaders, ReadKey};
use super::rings::{ring, RINGS};
use super::{FairQueue, Job, Pushed, Waiter};
use crate::error::Outcome;
use crate::master::{Class, MasterId, Origin, Protocol};
use crate::pdu;
use std::collections::HashMap;
use std::time::Duration;
use tokio::sync::oneshot;
use tokio::time::Instant;

pub(super) const READ: [u8; 5] = [0x03, 0x00, 0x10, 0x00, 0x02];
pub(super) const WRITE: [u8; 5] = [0x06, 0x00, 0x10, 0x12, 0x34];
pub(super) const NONE: Duration = Duration::ZERO;

pub(super) fn origin(master: MasterId, priority: bool) -> Origin {
    Origin {
        master,
        admission: master,
        protocol: Protocol::Tcp,
        class: Class::of_master(priority),
    }
}

/// What became of a pushed job, whatever it displaced: [`Pushed`] without the job.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum Went {
    Queued,
    Joined,
    Cached(Vec<u8>),
}

pub(super) fn pushed(result: Result<(Pushed, Option<Job>), Job>) -> Option<Went> {
    result.ok().map(|(pushed, _)| match pushed {
        Pushed::Queued => Went::Queued,
        Pushed::Joined => Went::Joined,
        Pushed::Cached(_, answer) => Went::Cached(answer),
    })
}

pub(super) fn request(origin: Origin, slave: u8, pdu: &[u8]) -> (Job, oneshot::Receiver<Outcome>) {
    let far = Instant::now() + Duration::from_secs(60);
    let (waiter, rx) = Waiter::new(origin, far);
    let mut job = Job::new(waiter, slave, pdu.to_vec());
    job.coalesce = pdu::is_read_only(pdu);
    (job, rx)
}

pub(super) fn job(master: MasterId, tag: u8) -> (Job, oneshot::Receiver<Outcome>) {
    request(origin(master, false), 1, &[0x03, tag])
}

/// The rotation holds exactly the masters with jobs queued, each once, under the ring and
/// key of its jobs; the counts are those of the jobs and followers queued.
pub(super) fn consistent(q: &FairQueue) {
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
                    (ring(j.class()), j.admission(), j.master()) == (r, *key, *master)
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

pub(super) fn order(q: &FairQueue) -> Vec<(MasterId, u8)> {
    std::iter::from_fn(|| q.try_pop())
        .map(|j| (j.master(), j.pdu[1]))
        .collect()
}

/// The ids the ports of two Modbus UDP source addresses share for admission.
pub(super) const ADDRESS: MasterId = 100;
pub(super) const OTHER_ADDRESS: MasterId = 101;

/// A request of a Modbus UDP master: `port` at the address with id `address`.
pub(super) fn datagram(
    port: MasterId,
    address: MasterId,
    tag: u8,
) -> (Job, oneshot::Receiver<Outcome>) {
    let origin = Origin {
        admission: address,
        protocol: Protocol::Udp,
        ..origin(port, false)
    };
    request(origin, 1, &[0x03, tag])
}
