//! Whose turn it is, and who gets in. The turns go round robin over [`Origin::admission`]
//! keys, and within a key over its masters: a connection is a key of its own, while all the
//! ports of one Modbus UDP source address share one turn (ports cost a sender nothing). So 40
//! ports of one host flooding the line take one transaction in two while a connection waits,
//! not 40 in 41; each port still has its own FIFO, order and replies, and its turns come in
//! rotation among its address's ports. Masters in `server.priority` have a ring of their own,
//! served first up to `priority_share` of the line. The gateway's polls of plant values have the
//! last ring: a poll goes when no master is ready, or once every master that was waiting when
//! the last poll went has had its turn (or left), so that no request waits behind two polls
//! (how much of the line polling takes in all, `poll_share`, the poller keeps to itself).
//!
//! Admission is fair as well. `queue_depth` bounds the requests waiting for the line (followers
//! included) over all masters, and while there is room every request goes in. Once the queue is
//! full, a request still goes in if its master holds less than its *share* while another holds
//! more than its own: the share is `queue_depth` divided among the masters with requests
//! waiting, the newcomer included, rounded down and at least one. It goes in too if its master
//! holds nothing, when more masters wait than the queue holds and each holds its one. The
//! newest request of the master holding the most is refused (0x06) to make room; of masters
//! holding as many, the gateway's polls give way first, then Modbus UDP sources (a datagram's
//! source costs nothing, and is new again each time it is answered), then connections, and of
//! those the newest master (ids are handed out as masters come). A master in `server.priority`
//! loses one only when no other master holds more than its share, and its only one to no master
//! outside `server.priority`. So a master with nothing waiting gets in whenever the queue holds
//! others' requests (all priority masters' only ones excepted), a master within its share is
//! refused for another only when each holds one, and one that lost a request for holding more
//! than its share cannot win the place back. When each holds one, a connection waiting keeps
//! its place while thousands of UDP sources take each other's. What counts as one
//! master here is a request's [`Origin::admission`]: a connection, or all the ports of one
//! Modbus UDP source address. A follower counts against its own master; a refused leader's
//! followers stay queued, the first of them leading in its place.
//!
//! [`Origin::admission`]: crate::master::Origin::admission

use super::{Inner, Job};
use crate::master::{Class, MasterId, Origin};
use std::cmp::Reverse;
use std::collections::{hash_map, HashMap, VecDeque};

/// How the line is shared between the two rings: counts of the recent transactions of each
/// (halved now and then, so that the recent past decides). When both rings wait, the priority
/// ring goes unless it has had `priority` of them already: a priority master that uses little
/// of the line always goes first, and saturating ones leave the others the rest.
#[derive(Default)]
pub(super) struct Share {
    /// Most share of contested picks the priority ring gets; 1.0 serves it always first.
    pub(super) priority: f64,
    priority_picks: u32,
    other_picks: u32,
}

impl Share {
    const MEMORY: u32 = 1000;

    /// No history yet, and `priority` of contested picks for the priority ring.
    pub(super) fn new(priority: f64) -> Share {
        Share {
            priority,
            ..Share::default()
        }
    }

    /// Whether the priority ring goes next when both rings wait.
    pub(super) fn priority_next(&self) -> bool {
        // Only if its share stays within `priority` with this pick, so the others' floor
        // holds; with no history, the priority ring.
        let total = f64::from(self.priority_picks + self.other_picks + 1);
        total == 1.0 || f64::from(self.priority_picks + 1) <= self.priority * total
    }

    pub(super) fn picked(&mut self, priority: bool) {
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

/// The normal ring, the priority ring and the polls' ring, in [`Class::ALL`]'s order.
pub(super) const RINGS: usize = Class::ALL.len();
/// The polls' ring.
pub(super) const POLLS: usize = 2;
pub(super) fn ring(class: Class) -> usize {
    class.index()
}

/// The masters with jobs queued in one ring, in serving order: round robin over admission keys,
/// and within a key over its masters.
#[derive(Default)]
pub(super) struct Ring {
    /// Exactly the keys with a master here, the next to serve first.
    pub(super) keys: VecDeque<MasterId>,
    /// By key in `keys`: exactly its masters here, the next to serve first.
    pub(super) masters: HashMap<MasterId, VecDeque<MasterId>>,
}

/// Where a master to serve stands in its [`Ring`]: its key's place, and its own within the key.
#[derive(Clone, Copy)]
pub(super) struct Place {
    key: usize,
    master: usize,
}

impl Ring {
    /// `master` of `key` has jobs now: served after the others of its key, and a key new here
    /// after every other key.
    pub(super) fn push(&mut self, key: MasterId, master: MasterId) {
        match self.masters.entry(key) {
            hash_map::Entry::Occupied(mut masters) => masters.get_mut().push_back(master),
            hash_map::Entry::Vacant(masters) => {
                masters.insert(VecDeque::from([master]));
                self.keys.push_back(key);
            }
        }
    }

    /// The next master to serve: the first that may go (`ready`) of the first key that has one.
    pub(super) fn next(&self, ready: impl Fn(MasterId) -> bool) -> Option<(Place, MasterId)> {
        self.keys.iter().enumerate().find_map(|(key, id)| {
            let masters = self.masters.get(id)?;
            let master = masters.iter().position(|&m| ready(m))?;
            Some((Place { key, master }, masters[master]))
        })
    }

    /// The master at `place` was served: its key goes last, and it goes last within its key if
    /// it has `more` jobs, or leaves the ring.
    pub(super) fn served(&mut self, place: Place, more: bool) {
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
    pub(super) fn remove(&mut self, key: MasterId, master: MasterId) {
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

/// Which of the keys holding as many requests gives up a place first: the gateway's own polls,
/// then Modbus UDP sources (a datagram's source address is unproven and costs nothing, and it
/// is a new key each time it has nothing pending), then connections (each proved its address
/// with a handshake, and `max_connections` bounds them).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
enum Standing {
    #[default]
    Poll,
    Datagram,
    Connection,
}

impl Standing {
    fn of(origin: &Origin) -> Standing {
        match (origin.class, origin.protocol.transport().is_stream()) {
            (Class::Poll, _) => Standing::Poll,
            (_, false) => Standing::Datagram,
            (_, true) => Standing::Connection,
        }
    }
}

/// What one admission key has waiting.
#[derive(Clone, Copy, Default)]
pub(super) struct Held {
    pub(super) requests: usize,
    /// Of those, from masters in `server.priority`.
    priority: usize,
    /// The same for every request of a key: one kind of master has it.
    standing: Standing,
}

impl Held {
    /// Which of two keys gives up a place first (the lesser): one outside `server.priority`,
    /// holding the most, the lowest [`Standing`], the newest (master ids are handed out as
    /// masters come, so the highest is the newest).
    fn yields(&self, key: MasterId) -> impl Ord {
        let priority = self.priority > 0;
        (
            priority,
            Reverse(self.requests),
            self.standing,
            Reverse(key),
        )
    }
}

/// Of `keys`, the one that gives up a place first.
fn first_to_yield<'a>(keys: impl Iterator<Item = (&'a MasterId, &'a Held)>) -> Option<MasterId> {
    keys.min_by_key(|&(&key, held)| held.yields(key))
        .map(|(&key, _)| key)
}

impl Inner {
    /// One more request waits, counted against its origin's admission key.
    pub(super) fn hold(&mut self, origin: &Origin) {
        self.len += 1;
        let held = self.held.entry(origin.admission).or_insert_with(|| Held {
            standing: Standing::of(origin),
            ..Held::default()
        });
        held.requests += 1;
        held.priority += usize::from(origin.class == Class::Priority);
    }

    /// A request counted against `key` waits no more.
    pub(super) fn release(&mut self, key: MasterId, priority: bool) {
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
    /// `newcomer`, if any: `newcomer` holds less than its share and the key more than its own,
    /// or (every key holding one) `newcomer` holds nothing and the key is not a priority
    /// master's unless `newcomer` is one too; of those, the first to yield ([`Held::yields`]).
    pub(super) fn victim(&self, newcomer: &Origin, capacity: usize) -> Option<MasterId> {
        let holding = self
            .held
            .get(&newcomer.admission)
            .map_or(0, |held| held.requests);
        let sharing = self.held.len() + usize::from(holding == 0);
        let share = (capacity / sharing.max(1)).max(1);
        if holding >= share {
            return None;
        }
        let over = first_to_yield(self.held.iter().filter(|(_, held)| held.requests > share));
        if over.is_some() || holding > 0 {
            return over;
        }
        let priority = newcomer.class == Class::Priority;
        first_to_yield(
            self.held
                .iter()
                .filter(|(_, held)| priority || held.priority == 0),
        )
    }

    /// Take out the newest request counted against `key`, to be refused: the last job of its
    /// master with the most queued (one that no read follows, if there is such a master), or
    /// else a read of it that follows another's. A refused leader's followers stay queued.
    pub(super) fn evict(&mut self, key: MasterId) -> Option<Job> {
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
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;
    use crate::master::{Origin, Protocol};

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
    fn a_full_queue_refuses_a_master_that_holds_its_share() {
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
        // More masters than places, one each: one holding its one gets no second.
        let q = FairQueue::new(2);
        for master in [1, 2] {
            let (j, rx) = job(master, 0);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        let (second, _r) = job(1, 1);
        assert_eq!(q.push(second, NONE).unwrap_err().master(), 1);
        assert_eq!(q.len(), 2);
    }

    #[test]
    fn a_newcomer_where_each_master_holds_one_displaces_the_newest_masters_job() {
        let q = FairQueue::new(3);
        let mut keep = Vec::new();
        for master in [1, 2, 3] {
            let (j, rx) = job(master, master as u8);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        // Master 4 holds nothing: it gets in, and master 3, the newest holding one, gives way.
        let (newcomer, _r4) = job(4, 4);
        let (pushed, evicted) = q.push(newcomer, NONE).expect("admitted");
        assert!(matches!(pushed, Pushed::Queued));
        let evicted = evicted.expect("one refused for it");
        assert_eq!((evicted.master(), evicted.pdu[1]), (3, 3));
        assert_eq!(q.len(), 3, "queue_depth stays the total");
        // Master 3, holding nothing now, gets back in the same way; masters 1 and 2 keep theirs.
        let (again, _r3) = job(3, 5);
        let (_, evicted) = q.push(again, NONE).expect("admitted");
        assert_eq!(evicted.expect("one refused for it").master(), 4);
        consistent(&q);
        assert_eq!(order(&q), [(1, 1), (2, 2), (3, 5)]);
    }

    #[test]
    fn of_masters_holding_one_a_poll_gives_way_then_a_udp_source_then_a_connection() {
        let q = FairQueue::new(4);
        let mut keep = Vec::new();
        // An older connection, a UDP source, a newer connection and a poll.
        let poll = Origin {
            class: Class::Poll,
            ..origin(MasterId::MAX, false)
        };
        let queued = [
            job(1, 1),
            datagram(10, ADDRESS, 2),
            job(200, 3),
            request(poll, 1, &[0x04, 4]),
        ];
        for (j, rx) in queued {
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        let mut refused = Vec::new();
        for newcomer in [300, 301, 302] {
            let (j, rx) = job(newcomer, newcomer as u8);
            keep.push(rx);
            let (_, evicted) = q.push(j, NONE).expect("admitted");
            refused.push(evicted.expect("one refused for it").master());
        }
        // The poll, the datagram source, then the newest connection (a newcomer before).
        assert_eq!(refused, [MasterId::MAX, 10, 301]);
        consistent(&q);
        let masters: Vec<MasterId> = order(&q).iter().map(|&(m, _)| m).collect();
        assert_eq!(masters, [1, 200, 300, 302]);
    }

    #[test]
    fn a_priority_masters_only_job_gives_way_to_no_newcomer_outside_server_priority() {
        let q = FairQueue::new(2);
        let mut keep = Vec::new();
        for master in [1, 2] {
            let (j, rx) = request(origin(master, true), 1, &[0x03, master as u8]);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        let (normal, _r) = job(3, 3);
        assert_eq!(q.push(normal, NONE).unwrap_err().master(), 3);
        // Another priority master holding nothing gets in, in place of the newest.
        let (priority, _r) = request(origin(4, true), 1, &[0x03, 4]);
        let (_, evicted) = q.push(priority, NONE).expect("admitted");
        assert_eq!(evicted.expect("one refused for it").master(), 2);
        // Beside a normal master holding one, the normal one gives way.
        let q = FairQueue::new(2);
        let (j, _r1) = request(origin(1, true), 1, &[0x03, 1]);
        q.push(j, NONE).unwrap();
        let (j, _r2) = job(2, 2);
        q.push(j, NONE).unwrap();
        let (j, _r3) = request(origin(3, true), 1, &[0x03, 3]);
        let (_, evicted) = q.push(j, NONE).expect("admitted");
        assert_eq!(evicted.expect("one refused for it").master(), 2);
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
    fn a_full_queue_hands_the_job_back() {
        let q = FairQueue::new(2);
        let (a, _ra) = job(1, 0);
        let (b, _rb) = job(2, 1);
        let (c, _rc) = job(2, 2);
        q.push(a, NONE).unwrap();
        q.push(b, NONE).unwrap();
        let refused = q.push(c, NONE).unwrap_err();
        assert_eq!((refused.master(), refused.pdu[1]), (2, 2));
        assert_eq!(q.len(), 2);
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
}

#[cfg(test)]
mod poll_tests {
    use super::super::testing::*;
    use super::super::*;
    use crate::master::Origin;

    /// The poller's origin: a master of its own in the polls' ring.
    fn poll_origin() -> Origin {
        Origin {
            class: Class::Poll,
            ..origin(99, false)
        }
    }

    #[test]
    fn a_poll_waits_until_every_master_waiting_has_had_a_turn_since_the_last_poll() {
        let q = FairQueue::new(64);
        let mut keep = Vec::new();
        // Three masters with two reads each, and two polls: the first poll goes first (no poll
        // yet), the second after the three masters' turns.
        for tag in 0..2 {
            for master in 1..=3 {
                // A function of its own: nothing coalesces.
                let (j, rx) = request(origin(master, false), 1, &[0x41, tag]);
                q.push(j, NONE).unwrap();
                keep.push(rx);
            }
        }
        for tag in [10, 11] {
            let (j, rx) = request(poll_origin(), 1, &[0x04, tag]);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        consistent(&q);
        assert_eq!(
            order(&q),
            [
                (99, 10),
                (1, 0),
                (2, 0),
                (3, 0),
                (99, 11),
                (1, 1),
                (2, 1),
                (3, 1)
            ]
        );
    }

    #[test]
    fn with_no_master_waiting_polls_go_back_to_back() {
        let q = FairQueue::new(64);
        let mut keep = Vec::new();
        for tag in 0..3 {
            let (j, rx) = request(poll_origin(), 1, &[0x04, tag]);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        assert_eq!(order(&q), [(99, 0), (99, 1), (99, 2)]);
    }

    #[test]
    fn a_poll_rides_on_a_masters_identical_read_but_no_master_waits_behind_a_poll() {
        let q = FairQueue::new(64);
        let (master_read, _m) = request(origin(1, false), 1, &READ);
        q.push(master_read, NONE).unwrap();
        let (poll, _p) = request(poll_origin(), 1, &READ);
        assert_eq!(pushed(q.push(poll, NONE)), Some(Went::Joined));
        let taken = q.try_pop().unwrap();
        assert_eq!((taken.master(), taken.followers.len()), (1, 1));
        // The other way round: the master's read does not join the poll's.
        let (poll, _p) = request(poll_origin(), 1, &READ);
        assert_eq!(pushed(q.push(poll, NONE)), Some(Went::Queued));
        let (master_read, _m) = request(origin(2, false), 1, &READ);
        assert_eq!(pushed(q.push(master_read, NONE)), Some(Went::Queued));
        consistent(&q);
    }

    #[test]
    fn a_full_queue_refuses_a_poll_and_never_makes_room_for_it() {
        let q = FairQueue::new(2);
        let mut keep = Vec::new();
        for tag in 0..2 {
            let (j, rx) = job(1, tag);
            q.push(j, NONE).unwrap();
            keep.push(rx);
        }
        let (poll, _p) = request(poll_origin(), 1, &READ);
        assert!(q.push(poll, NONE).is_err(), "refused");
        assert_eq!(order(&q), [(1, 0), (1, 1)]);
    }
}
