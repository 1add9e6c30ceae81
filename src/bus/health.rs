//! Which slaves are down. A slave whose requests timed out `slave_down_after` times in a row is
//! down: its requests are answered 0x0B at once without touching the line, but for one probe per
//! `slave_probe_interval` (a single attempt, no retries), so a dead drive costs the line one
//! timeout per interval instead of one per poll, and the healthy slaves keep the line. Any reply
//! brings it back. Corrupt replies neither count nor clear: something is answering.
//!
//! After a timeout, a slave's reply may still come. RTU frames carry no transaction id, so a late
//! reply would be taken as the answer to the next request of the same form to that slave, maybe
//! another master's: the next request to a slave that timed out waits out a late-reply window
//! (one more response timeout) first. Pure: the time comes in as an argument.

use std::time::Duration;
use tokio::time::Instant;

/// `slave_down_after` and `slave_probe_interval`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DownPolicy {
    /// 0: a slave is never down.
    pub after: u32,
    pub probe_interval: Duration,
}

/// What to do with the next request to a slave.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Admission {
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
pub enum Response {
    /// A reply, normal or exception.
    Answered,
    /// Nothing came, retries included.
    TimedOut,
    /// A corrupt or foreign reply, or a busy line.
    Garbled,
}

/// A change worth telling the operator.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Change {
    None,
    /// Just went down after this many timeouts in a row.
    Down {
        timeouts: u32,
    },
    /// Was down and answered.
    Up,
}

#[derive(Clone, Copy, Debug, Default)]
struct Slave {
    timeouts: u32,
    next_probe: Option<Instant>,
    /// Its last timed-out request may still be answered until then.
    late_until: Option<Instant>,
}

pub struct Health {
    slaves: Box<[Slave; 256]>,
}

impl Default for Health {
    fn default() -> Self {
        Health {
            slaves: Box::new([Slave::default(); 256]),
        }
    }
}

impl Health {
    fn is_down(slave: &Slave, policy: DownPolicy) -> bool {
        policy.after > 0 && slave.timeouts >= policy.after
    }

    pub fn admit(&self, address: u8, now: Instant, policy: DownPolicy) -> Admission {
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

    /// A request to `address` timed out; its reply may still come until `until`.
    pub fn expect_late_reply(&mut self, address: u8, until: Instant) {
        self.slaves[usize::from(address)].late_until = Some(until);
    }

    /// Until when a new request to `address` must wait, if a late reply may still come.
    pub fn late_reply_window(&self, address: u8, now: Instant) -> Option<Instant> {
        self.slaves[usize::from(address)]
            .late_until
            .filter(|&until| until > now)
    }

    /// Record how a transaction with `address` ended at `now`.
    pub fn record(
        &mut self,
        address: u8,
        response: Response,
        now: Instant,
        policy: DownPolicy,
    ) -> Change {
        let slave = &mut self.slaves[usize::from(address)];
        let was_down = Self::is_down(slave, policy);
        match response {
            Response::Answered => {
                slave.timeouts = 0;
                slave.next_probe = None;
                if was_down {
                    Change::Up
                } else {
                    Change::None
                }
            }
            Response::TimedOut => {
                slave.timeouts = slave.timeouts.saturating_add(1);
                if !Self::is_down(slave, policy) {
                    return Change::None;
                }
                slave.next_probe = Some(now + policy.probe_interval);
                if was_down {
                    Change::None
                } else {
                    Change::Down {
                        timeouts: slave.timeouts,
                    }
                }
            }
            Response::Garbled => Change::None,
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

    fn timed_out(health: &mut Health, slave: u8, times: u32, now: Instant) -> Vec<Change> {
        (0..times)
            .map(|_| health.record(slave, Response::TimedOut, now, POLICY))
            .collect()
    }

    #[test]
    fn a_slave_is_down_after_the_configured_timeouts_in_a_row_and_others_are_not() {
        let mut health = Health::default();
        let now = Instant::now();
        let changes = timed_out(&mut health, 7, 3, now);
        assert_eq!(
            changes,
            [Change::None, Change::None, Change::Down { timeouts: 3 }]
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
            health.record(1, Response::Answered, now, POLICY),
            Change::None
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
            health.record(1, Response::Garbled, now, POLICY);
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
            health.record(4, Response::TimedOut, probed, POLICY),
            Change::None
        );
        assert!(matches!(
            health.admit(4, probed + Duration::from_secs(4), POLICY),
            Admission::Skip { timeouts: 4 }
        ));
        let next = probed + POLICY.probe_interval;
        assert_eq!(health.admit(4, next, POLICY), Admission::Probe);
        assert_eq!(
            health.record(4, Response::Answered, next, POLICY),
            Change::Up
        );
        assert_eq!(health.admit(4, next, POLICY), Admission::Send);
    }

    #[test]
    fn a_late_reply_window_holds_only_that_slave_and_only_until_it_ends() {
        let mut health = Health::default();
        let now = Instant::now();
        let until = now + Duration::from_millis(100);
        health.expect_late_reply(3, until);
        assert_eq!(health.late_reply_window(3, now), Some(until));
        assert_eq!(health.late_reply_window(4, now), None);
        assert_eq!(health.late_reply_window(3, until), None);
    }

    #[test]
    fn with_slave_down_after_0_a_slave_is_never_down() {
        let policy = DownPolicy { after: 0, ..POLICY };
        let mut health = Health::default();
        let now = Instant::now();
        for _ in 0..100 {
            assert_eq!(
                health.record(2, Response::TimedOut, now, policy),
                Change::None
            );
        }
        assert_eq!(health.admit(2, now, policy), Admission::Send);
    }
}
