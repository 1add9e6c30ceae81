//! A bus's port across its outages: the back-off before each attempt to open it again, and which
//! of its ups and downs begin or end an outage, for the log. An outage begins when a port that
//! has served is lost, or when the first open fails or the first port is lost before serving; it
//! ends when a port serves: a request answered through it, or up for `reopen_delay_max` (what an
//! idle line can show). Only that resets the back-off: a device server that accepts and closes at
//! once (ser2net with its serial port missing) is connected ever less often, down to once per
//! `reopen_delay_max`, and its outage is one warn line when it begins and one info line when it
//! ends, with how many opens failed and how many ports were lost unserved in it.
//! Pure state over instants; knows nothing of ports, devices or logs.

use crate::metrics::PortLoss;
use std::time::Duration;
use tokio::time::Instant;

/// An outage so far.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Outage {
    /// When it began.
    pub(super) since: Instant,
    /// Opens (connects) that failed in it.
    pub(super) failed_opens: u32,
    /// Ports opened (connections made) in it and lost again before they served.
    pub(super) unserved: u32,
}

impl Outage {
    fn at(since: Instant) -> Outage {
        Outage {
            since,
            failed_opens: 0,
            unserved: 0,
        }
    }
}

/// An outage that a port serving has ended: what it was, and how long the line was down (until
/// that port opened).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Recovery {
    pub(super) outage: Outage,
    pub(super) down_for: Duration,
}

/// The port open now.
#[derive(Clone, Copy, Debug)]
struct Open {
    at: Instant,
    served: bool,
}

/// The bus's port between outages, and the wait before its next open.
#[derive(Debug)]
pub(super) struct Outages {
    /// The wait before the next open, once the port is down.
    delay: Duration,
    /// The outage under way, if any.
    outage: Option<Outage>,
    open: Option<Open>,
}

impl Outages {
    /// A bus that has not opened its port yet; its first wait will be `first`.
    pub(super) fn new(first: Duration) -> Outages {
        Outages {
            delay: first,
            outage: None,
            open: None,
        }
    }

    /// The port opened at `now`: the outage it opened in, if one is under way.
    pub(super) fn opened(&mut self, now: Instant) -> Option<Outage> {
        self.open = Some(Open {
            at: now,
            served: false,
        });
        self.outage
    }

    /// The open port served at `now` (a request was answered through it); the next wait is
    /// `first` again. The outage this ends, the first time.
    pub(super) fn served(&mut self, first: Duration) -> Option<Recovery> {
        let open = self.open.as_mut().filter(|open| !open.served)?;
        open.served = true;
        self.delay = first;
        let outage = self.outage.take()?;
        Some(Recovery {
            outage,
            down_for: open.at.saturating_duration_since(outage.since),
        })
    }

    /// As [`Outages::served`] if the open port has been up for `long` at `now`.
    pub(super) fn up_for(
        &mut self,
        now: Instant,
        long: Duration,
        first: Duration,
    ) -> Option<Recovery> {
        let open = self.open?;
        if open.served || now.saturating_duration_since(open.at) < long {
            return None;
        }
        self.served(first)
    }

    /// The open port was lost at `now`.
    pub(super) fn lost(&mut self, now: Instant) -> PortLoss {
        let served = self.open.take().is_some_and(|open| open.served);
        match (served, &mut self.outage) {
            (false, Some(outage)) => {
                outage.unserved += 1;
                PortLoss::AgainUnserved {
                    unserved: outage.unserved,
                }
            }
            (false, None) => {
                self.outage = Some(Outage {
                    unserved: 1,
                    ..Outage::at(now)
                });
                PortLoss::Unserved
            }
            (true, _) => {
                self.outage = Some(Outage::at(now));
                PortLoss::Served
            }
        }
    }

    /// An open failed at `now`: whether that began an outage.
    pub(super) fn open_failed(&mut self, now: Instant) -> bool {
        let began = self.outage.is_none();
        self.outage
            .get_or_insert_with(|| Outage::at(now))
            .failed_opens += 1;
        began
    }

    /// How long to wait before the next open; the wait after it is twice as long, up to `max`.
    pub(super) fn next_wait(&mut self, max: Duration) -> Duration {
        let wait = self.delay;
        self.delay = (wait * 2).min(max);
        wait
    }

    /// A new configuration: the port open, if any, is closed, and the next wait is `first`.
    pub(super) fn restart(&mut self, first: Duration) {
        self.open = None;
        self.delay = first;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FIRST: Duration = Duration::from_millis(100);
    const MAX: Duration = Duration::from_millis(800);
    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn ports_lost_before_serving_double_the_wait_and_make_one_outage() {
        let mut outages = Outages::new(FIRST);
        let start = Instant::now();
        let mut waits = Vec::new();
        for n in 0..6 {
            let at = start + n * MS;
            assert_eq!(
                outages.opened(at).is_some(),
                n > 0,
                "in an outage after the first"
            );
            let loss = outages.lost(at);
            let expected = if n == 0 {
                PortLoss::Unserved
            } else {
                PortLoss::AgainUnserved { unserved: n + 1 }
            };
            assert_eq!(loss, expected);
            waits.push(outages.next_wait(MAX));
        }
        assert_eq!(waits, [100, 200, 400, 800, 800, 800].map(|ms| ms * MS));
        // One that serves ends the outage, and the wait starts again from the first.
        outages.opened(start + 10 * MS);
        let ended = outages.served(FIRST).expect("an outage ended");
        assert_eq!(ended.outage.unserved, 6);
        assert_eq!(ended.down_for, 10 * MS);
        assert_eq!(outages.served(FIRST), None, "ended once");
        assert_eq!(outages.lost(start + 20 * MS), PortLoss::Served);
        assert_eq!(outages.next_wait(MAX), FIRST);
    }

    #[test]
    fn a_port_up_for_the_longest_wait_has_served_though_nobody_asked_anything() {
        let mut outages = Outages::new(FIRST);
        let start = Instant::now();
        assert!(outages.open_failed(start));
        assert!(!outages.open_failed(start + MS), "the same outage");
        outages.next_wait(MAX);
        outages.next_wait(MAX);
        outages.opened(start + 2 * MS);
        assert_eq!(outages.up_for(start + 2 * MS + MAX - MS, MAX, FIRST), None);
        let ended = outages.up_for(start + 2 * MS + MAX, MAX, FIRST);
        let outage = Outage {
            since: start,
            failed_opens: 2,
            unserved: 0,
        };
        let down_for = 2 * MS;
        assert_eq!(ended, Some(Recovery { outage, down_for }));
        assert_eq!(outages.next_wait(MAX), FIRST);
    }
}
