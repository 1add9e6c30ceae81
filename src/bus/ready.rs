//! The one step between the fair queue and the wire, which both serving loops (`serve`, one
//! request at a time; `pipelined`, several in flight) take for every request: answer at once who
//! no longer waits or waited too long, wait for the journal's entry of a write to be on record
//! (and refuse a write it could not record), refuse a request to a slave that is down (or let
//! it through as its probe), and decide how many tries it gets. A gate every request must pass
//! before it goes out belongs here, so that neither loop can skip it. Also the one count of the
//! line's traffic for the metrics.

use super::health::Admission;
use super::task::BusTask;
use super::{Job, Waiter};
use crate::error::RequestError;
use crate::line::{LineCounters, BROADCAST};
use crate::pdu;
use std::time::Duration;
use tokio::time::Instant;

/// A request cleared for the wire.
pub(super) struct Cleared {
    pub(super) job: Job,
    /// Tries after the first one, should it time out or be garbled.
    pub(super) retries: u32,
    /// Sent to every slave of a serial line (address 0): no slave answers it.
    pub(super) broadcast: bool,
}

impl BusTask {
    /// `job`, if it may go out now; answered here, and `None`, if it may not.
    pub(super) async fn ready(&mut self, job: Job) -> Option<Cleared> {
        let job = self.settle_waiters(job)?;
        if !job.waiter.durable().await {
            let refusal = RequestError::Unrecorded(job.function());
            self.handle.answer(job, Err(refusal));
            return None;
        }
        let admission = if self.is_broadcast(&job) {
            Admission::Send
        } else {
            self.health
                .admit(job.slave, Instant::now(), self.current.derived.down)
        };
        let probe = match admission {
            Admission::Skip { timeouts } => {
                let refusal = RequestError::SlaveDown { timeouts };
                self.handle.answer(job, Err(refusal));
                return None;
            }
            Admission::Probe => true,
            Admission::Send => false,
        };
        Some(self.clear(job, probe))
    }

    /// `job` as the line carries it: a broadcast, or a request with its tries. The retry rule:
    /// reads are retried, writes only with `retry_writes` (a write whose reply was lost may have
    /// been carried out), a `probe` of a slave that is down never.
    pub(super) fn clear(&self, job: Job, probe: bool) -> Cleared {
        let settings = &self.current.settings;
        let retries = if probe {
            0
        } else if pdu::is_read_only(&job.pdu) || settings.retry_writes {
            settings.retries
        } else {
            0
        };
        Cleared {
            broadcast: self.is_broadcast(&job),
            job,
            retries,
        }
    }

    /// Whether `job` goes to every slave of a serial line (address 0), which none answers.
    fn is_broadcast(&self, job: &Job) -> bool {
        job.slave == BROADCAST && self.current.derived.framing.broadcasts()
    }

    /// Answer at once who no longer waits for `job`, or waited too long: its own master and
    /// each follower. The job, if anyone is left for the line to answer: led by the first
    /// follower still waiting if its own master is settled.
    fn settle_waiters(&self, mut job: Job) -> Option<Job> {
        let now = Instant::now();
        let (slave, function) = (job.slave, job.function());
        job.followers = std::mem::take(&mut job.followers)
            .into_iter()
            .filter_map(|follower| self.settle(follower, now, slave, function))
            .collect();
        match self.settle(job.waiter, now, slave, function) {
            Some(waiter) => Some(Job { waiter, ..job }),
            None if job.followers.is_empty() => None,
            None => {
                let first = job.followers.remove(0);
                Some(Job {
                    waiter: first,
                    ..job
                })
            }
        }
    }

    /// `waiter`, if it still waits for the line: answered at once if its master left or its
    /// deadline passed before `now`.
    fn settle(&self, waiter: Waiter, now: Instant, slave: u8, function: u8) -> Option<Waiter> {
        let tally = self.handle.tally();
        if waiter.is_gone() {
            waiter.left(tally, slave, function);
            return None;
        }
        let metrics = &self.handle.metrics;
        metrics.dequeued(waiter.queued_at.elapsed(), waiter.origin.class);
        if now > waiter.deadline {
            waiter.answer(tally, slave, function, Err(RequestError::Expired));
            return None;
        }
        Some(waiter)
    }

    /// Pass what went over the line since `counted` (the line's counters `now`) to the metrics,
    /// and a device server's `link` as now measured with it.
    pub(super) fn count_traffic(
        &self,
        now: LineCounters,
        counted: &mut LineCounters,
        link: Option<(&str, Duration, Option<Duration>)>,
    ) {
        self.handle.metrics.line(&now.since(counted));
        *counted = now;
        if let Some(link) = link {
            self.handle.metrics.link(Some(link));
        }
    }
}
