//! Whether each slave is alive: the one state machine that decides it, read by the bus (which
//! requests to send) and rendered by metrics and logs (its [`Change`]s), never recomputed there.
//!
//! A slave is answering after a valid reply (normal, exception or malformed), failing after a
//! timeout that counts or a corrupt reply, and down after `slave_down_after` timeouts in a row:
//! its requests are answered 0x0B at once without touching the line, but for one probe per
//! `slave_probe_interval` (a single attempt, no retries), so a dead drive costs the line one
//! timeout per interval instead of one per poll, and the healthy slaves keep the line. Any reply
//! brings it back. Corrupt replies neither count nor clear the timeouts: something is answering.
//! A line too busy to send on says nothing of the slave.
//!
//! Only a timeout that says the slave is gone counts: one for a function code the slave has
//! answered before (an exception is an answer), or any while it has answered nothing yet. Many
//! real slaves stay silent for function codes they do not implement or requests they find
//! malformed; such a silence says nothing of the slave, so it changes nothing (nor, for a probe,
//! puts off the next one), and one master's odd requests cannot make a slave down for every other
//! master. Pure: the time comes in as an argument.

use std::time::Duration;
use tokio::time::Instant;

/// `slave_down_after` and `slave_probe_interval`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct DownPolicy {
    /// 0: a slave is never down.
    pub after: u32,
    pub(crate) probe_interval: Duration,
}

/// What to do with the next request to a slave.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Admission {
    Send,
    /// The slave is down and its probe is due: one attempt, no retries.
    Probe,
    /// The slave is down: answer 0x0B without sending. `timeouts` in a row so far.
    Skip {
        timeouts: u32,
    },
}

/// How a transaction with a slave ended, as far as its health goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Response {
    /// A reply, normal or exception.
    Answered,
    /// Nothing came, retries included.
    TimedOut,
    /// A corrupt or incomplete reply: something answered, but not validly.
    Garbled,
    /// Never sent: the line was too busy. Says nothing of the slave.
    Unsent,
}

/// A change worth telling the operator: each is one log line (but the first answer) and one
/// move of `slave_up`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Change {
    None,
    /// Answered for the first time.
    Answering,
    /// Stopped giving valid replies, not (yet) down.
    Failing,
    /// Just went down after this many timeouts in a row.
    Down {
        timeouts: u32,
    },
    /// Was failing or down, and answered.
    Up,
}

/// Whether a slave gives valid replies, as far as its transactions tell.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
enum Liveness {
    /// Not asked yet, or only asked what it may ignore.
    #[default]
    Unknown,
    Answering,
    /// Its last transaction that tells of it got no valid reply.
    Failing,
}

/// A set of function codes, one bit each.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Functions([u64; 4]);

impl Functions {
    fn insert(&mut self, function: u8) {
        self.0[usize::from(function / 64)] |= 1 << (function % 64);
    }

    fn contains(&self, function: u8) -> bool {
        self.0[usize::from(function / 64)] & (1 << (function % 64)) != 0
    }

    fn is_empty(&self) -> bool {
        self.0 == [0; 4]
    }
}

#[derive(Clone, Copy, Debug, Default)]
struct SlaveHealth {
    timeouts: u32,
    next_probe: Option<Instant>,
    /// Function codes it has answered, normally or with an exception.
    answered: Functions,
    liveness: Liveness,
}

pub(crate) struct Health {
    slaves: Box<[SlaveHealth; 256]>,
}

impl Default for Health {
    fn default() -> Self {
        Health {
            slaves: Box::new([SlaveHealth::default(); 256]),
        }
    }
}

impl Health {
    fn is_down(slave: &SlaveHealth, policy: DownPolicy) -> bool {
        policy.after > 0 && slave.timeouts >= policy.after
    }

    pub(crate) fn admit(&self, address: u8, now: Instant, policy: DownPolicy) -> Admission {
        let slave = &self.slaves[usize::from(address)];
        if !Self::is_down(slave, policy) {
            return Admission::Send;
        }
        match slave.next_probe {
            Some(at) if now < at => Admission::Skip {
                timeouts: slave.timeouts,
            },
            _ => Admission::Probe,
        }
    }

    /// Whether a timeout of a request for `function` says that `address` is gone: it has
    /// answered that function code before, or nothing at all yet. Otherwise the slave may just
    /// ignore that kind of request.
    pub(crate) fn timeout_counts(&self, address: u8, function: u8) -> bool {
        let answered = &self.slaves[usize::from(address)].answered;
        answered.is_empty() || answered.contains(function)
    }

    /// Record how a transaction for `function` with `address` ended at `now`, and say what
    /// changed.
    pub(crate) fn record(
        &mut self,
        address: u8,
        function: u8,
        response: Response,
        now: Instant,
        policy: DownPolicy,
    ) -> Change {
        let counts = self.timeout_counts(address, function);
        let slave = &mut self.slaves[usize::from(address)];
        let was_down = Self::is_down(slave, policy);
        let was = slave.liveness;
        match response {
            Response::Answered => {
                slave.answered.insert(function);
                slave.timeouts = 0;
                slave.next_probe = None;
                slave.liveness = Liveness::Answering;
                match was {
                    Liveness::Unknown => Change::Answering,
                    Liveness::Answering => Change::None,
                    Liveness::Failing => Change::Up,
                }
            }
            Response::TimedOut if counts => {
                slave.timeouts = slave.timeouts.saturating_add(1);
                slave.liveness = Liveness::Failing;
                if Self::is_down(slave, policy) {
                    slave.next_probe = Some(now + policy.probe_interval);
                    if !was_down {
                        return Change::Down {
                            timeouts: slave.timeouts,
                        };
                    }
                }
                Self::failing_since(was)
            }
            Response::Garbled => {
                slave.liveness = Liveness::Failing;
                Self::failing_since(was)
            }
            Response::TimedOut | Response::Unsent => Change::None,
        }
    }

    /// The change for a slave that fails now and was `was` before.
    fn failing_since(was: Liveness) -> Change {
        if was == Liveness::Failing {
            Change::None
        } else {
            Change::Failing
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const POLICY: DownPolicy = DownPolicy {
        after: 3,
        probe_interval: Duration::from_secs(5),
    };

    const READ: u8 = 0x03;
    /// A user-defined function code that many slaves ignore.
    const UNKNOWN: u8 = 0x41;

    fn timed_out(health: &mut Health, slave: u8, times: u32, now: Instant) -> Vec<Change> {
        (0..times)
            .map(|_| health.record(slave, READ, Response::TimedOut, now, POLICY))
            .collect()
    }

    #[test]
    fn a_slave_is_down_after_the_configured_timeouts_in_a_row_and_others_are_not() {
        let mut health = Health::default();
        let now = Instant::now();
        let changes = timed_out(&mut health, 7, 3, now);
        assert_eq!(
            changes,
            [Change::Failing, Change::None, Change::Down { timeouts: 3 }]
        );
        assert_eq!(
            health.admit(7, now, POLICY),
            Admission::Skip { timeouts: 3 }
        );
        assert_eq!(health.admit(8, now, POLICY), Admission::Send);
    }

    #[test]
    fn an_answer_between_timeouts_starts_the_count_again() {
        let mut health = Health::default();
        let now = Instant::now();
        timed_out(&mut health, 1, 2, now);
        assert_eq!(
            health.record(1, READ, Response::Answered, now, POLICY),
            Change::Up
        );
        timed_out(&mut health, 1, 2, now);
        assert_eq!(health.admit(1, now, POLICY), Admission::Send);
    }

    #[test]
    fn garbled_replies_neither_count_nor_clear_timeouts() {
        let mut health = Health::default();
        let now = Instant::now();
        timed_out(&mut health, 1, 2, now);
        for _ in 0..10 {
            health.record(1, READ, Response::Garbled, now, POLICY);
        }
        assert_eq!(health.admit(1, now, POLICY), Admission::Send);
        timed_out(&mut health, 1, 1, now);
        assert_eq!(
            health.admit(1, now, POLICY),
            Admission::Skip { timeouts: 3 }
        );
    }

    #[test]
    fn a_down_slave_is_probed_once_per_interval_and_an_answer_brings_it_back() {
        let mut health = Health::default();
        let start = Instant::now();
        timed_out(&mut health, 4, 3, start);
        let almost = start + POLICY.probe_interval - Duration::from_millis(1);
        assert!(matches!(
            health.admit(4, almost, POLICY),
            Admission::Skip { .. }
        ));
        let due = start + POLICY.probe_interval;
        assert_eq!(health.admit(4, due, POLICY), Admission::Probe);
        // The probe times out: the next one is a whole interval after it.
        let probed = due + Duration::from_secs(1);
        assert_eq!(
            health.record(4, READ, Response::TimedOut, probed, POLICY),
            Change::None
        );
        assert!(matches!(
            health.admit(4, probed + Duration::from_secs(4), POLICY),
            Admission::Skip { timeouts: 4 }
        ));
        let next = probed + POLICY.probe_interval;
        assert_eq!(health.admit(4, next, POLICY), Admission::Probe);
        assert_eq!(
            health.record(4, READ, Response::Answered, next, POLICY),
            Change::Up
        );
        assert_eq!(health.admit(4, next, POLICY), Admission::Send);
    }

    #[test]
    fn timeouts_of_a_function_the_slave_never_answered_neither_count_nor_clear() {
        let mut health = Health::default();
        let now = Instant::now();
        assert_eq!(
            health.record(1, READ, Response::Answered, now, POLICY),
            Change::Answering
        );
        timed_out(&mut health, 1, 2, now);
        for _ in 0..10 {
            assert!(!health.timeout_counts(1, UNKNOWN));
            health.record(1, UNKNOWN, Response::TimedOut, now, POLICY);
        }
        assert_eq!(health.admit(1, now, POLICY), Admission::Send);
        // The third timeout of a read it used to answer does count.
        assert_eq!(
            timed_out(&mut health, 1, 1, now),
            [Change::Down { timeouts: 3 }]
        );
    }

    #[test]
    fn a_probe_the_slave_may_just_ignore_does_not_put_off_the_next_probe() {
        let mut health = Health::default();
        let start = Instant::now();
        health.record(5, READ, Response::Answered, start, POLICY);
        timed_out(&mut health, 5, 3, start);
        let due = start + POLICY.probe_interval;
        assert_eq!(health.admit(5, due, POLICY), Admission::Probe);
        // One master's probe asks for a function the slave never answered: its silence says
        // nothing, so another master's read, next, is probed at once.
        health.record(5, UNKNOWN, Response::TimedOut, due, POLICY);
        assert_eq!(health.admit(5, due, POLICY), Admission::Probe);
        assert_eq!(
            health.record(5, READ, Response::Answered, due, POLICY),
            Change::Up
        );
    }

    #[test]
    fn a_slave_that_never_answered_anything_is_down_whatever_it_was_asked() {
        let mut health = Health::default();
        let now = Instant::now();
        for function in [UNKNOWN, UNKNOWN] {
            assert!(health.timeout_counts(2, function));
            health.record(2, function, Response::TimedOut, now, POLICY);
        }
        assert_eq!(
            health.record(2, READ, Response::TimedOut, now, POLICY),
            Change::Down { timeouts: 3 }
        );
    }

    #[test]
    fn an_exception_counts_as_an_answer_of_its_function() {
        let mut health = Health::default();
        let now = Instant::now();
        health.record(3, UNKNOWN, Response::Answered, now, POLICY);
        assert!(health.timeout_counts(3, UNKNOWN));
        assert!(!health.timeout_counts(3, READ));
        assert!(health.timeout_counts(4, READ), "another slave is apart");
    }

    #[test]
    fn a_corrupt_reply_makes_an_answering_slave_failing_once_and_a_busy_line_changes_nothing() {
        let mut health = Health::default();
        let now = Instant::now();
        health.record(6, READ, Response::Answered, now, POLICY);
        assert_eq!(
            health.record(6, READ, Response::Unsent, now, POLICY),
            Change::None
        );
        assert_eq!(
            health.record(6, READ, Response::Garbled, now, POLICY),
            Change::Failing
        );
        assert_eq!(
            health.record(6, READ, Response::Garbled, now, POLICY),
            Change::None
        );
        assert_eq!(
            health.record(6, READ, Response::Answered, now, POLICY),
            Change::Up
        );
    }

    #[test]
    fn a_slave_that_answered_and_times_out_is_failing_then_down_each_told_once() {
        let mut health = Health::default();
        let now = Instant::now();
        health.record(8, READ, Response::Answered, now, POLICY);
        assert_eq!(
            timed_out(&mut health, 8, 4, now),
            [
                Change::Failing,
                Change::None,
                Change::Down { timeouts: 3 },
                Change::None
            ]
        );
    }

    #[test]
    fn function_sets_hold_every_code_apart() {
        let mut set = Functions::default();
        for function in [0x00, 0x3F, 0x40, 0x7F, 0x80, 0xFF] {
            assert!(!set.contains(function));
            set.insert(function);
            assert!(set.contains(function));
        }
        assert!(!set.contains(0x41));
    }

    #[test]
    fn with_slave_down_after_0_a_slave_is_never_down() {
        let policy = DownPolicy { after: 0, ..POLICY };
        let mut health = Health::default();
        let now = Instant::now();
        let changes: Vec<Change> = (0..100)
            .map(|_| health.record(2, READ, Response::TimedOut, now, policy))
            .collect();
        assert_eq!(changes[0], Change::Failing);
        assert!(changes[1..].iter().all(|&c| c == Change::None));
        assert_eq!(health.admit(2, now, policy), Admission::Send);
    }
}
