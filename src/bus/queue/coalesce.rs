//! Reads coalesce here: a read identical (slave, PDU) to one waiting at the head of another
//! master's FIFO joins it as a follower and is answered by its transaction, which starts after
//! the follower arrived (the leader is taken from the queue only when the line is ready for its
//! frame). No read joins a leader from an earlier write epoch (`cache`). The heads reads may
//! join are indexed by (slave, epoch, PDU), so that neither a push nor a pop looks at every
//! master's FIFO. A leader that goes unsent (its master left, or it was refused) leaves its
//! followers queued, the first of them leading in its place.

use super::cache::Epoch;
use super::rings::RINGS;
use super::{Inner, Job, Waiter};
use crate::master::{Class, MasterId};
use std::collections::{hash_map, HashMap};

/// A read others may join, as [`Leaders`] knows it: its slave, that slave's write epoch when it
/// was queued, and its PDU.
pub(super) type ReadKey = (u8, Epoch, Vec<u8>);

/// Per ring, the masters whose head is a read others may join, by that read, so that a read
/// finds one to join without looking at every master's head.
#[derive(Default)]
pub(super) struct Leaders(pub(super) [HashMap<ReadKey, Vec<MasterId>>; RINGS]);

impl Leaders {
    pub(super) fn key(job: &Job) -> ReadKey {
        (job.slave, job.epoch, job.pdu.clone())
    }

    /// `head` is at the head of its master's FIFO in ring `r` now.
    pub(super) fn add(&mut self, r: usize, head: &Job) {
        if head.coalesce {
            self.0[r]
                .entry(Self::key(head))
                .or_default()
                .push(head.master());
        }
    }

    /// `head` is at the head of its master's FIFO in ring `r` no more.
    pub(super) fn remove(&mut self, r: usize, head: &Job) {
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
    /// such a one. A poll joins any read, another poll's last; a master's read never joins a
    /// poll, whose ring would hold it back.
    pub(super) fn find(&self, job: &Job) -> Option<MasterId> {
        let rings: &[usize] = match job.class() {
            Class::Priority => &[1],
            Class::Normal => &[1, 0],
            Class::Poll => &[1, 0, 2],
        };
        let key = Self::key(job);
        rings
            .iter()
            .find_map(|&r| self.0[r].get(&key).and_then(|masters| masters.first()))
            .copied()
    }
}

impl Inner {
    /// Make `job` a follower of an identical read at the head of another master's FIFO, if it
    /// may: a coalescing read, of a master with nothing else waiting, the leader from the same
    /// epoch, and (for a priority master) a priority leader.
    // The job handed back is moved, not boxed: a box would cost an allocation per request.
    #[allow(clippy::result_large_err)]
    pub(super) fn join(&mut self, job: Job) -> Result<(), Job> {
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

    pub(super) fn unfollow(&mut self, master: MasterId) {
        if let Some(count) = self.following.get_mut(&master) {
            *count -= 1;
            if *count == 0 {
                self.following.remove(&master);
            }
        }
    }

    /// The leader `job` is gone unsent: its first follower takes its place at the head of its
    /// own master's FIFO, with the others following it. They all still wait, as they did.
    pub(super) fn promote(&mut self, job: &Job, followers: Vec<Waiter>) {
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
    use super::super::testing::*;
    use super::super::*;
    use crate::master::Origin;

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
}
