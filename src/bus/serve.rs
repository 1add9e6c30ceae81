//! Serving an open port one request at a time: take the next request from the fair queue once
//! the line is ready for its frame (or a new configuration, a stop, stray bytes on the idle line),
//! clear it through the pre-send step (`ready`: who no longer waits, expiry, the journal, a slave
//! that is down), wait out its slave's late-reply window, and run it as one transaction.

use super::task::{BusTask, Served};
use super::transaction::Ran;
use super::{Job, Port, HEARTBEAT};
use crate::error::RequestError;
use crate::line::{LineCounters, LineMaster};
use crate::shutdown::Stopping;
use std::io;
use std::pin::Pin;
use tokio::time::{sleep, Instant, Sleep};

/// What the serving loop does next.
enum Next {
    Run(Job),
    /// Look again: a stop was asked for, a configuration came, the line was idle.
    Again,
    End(Served),
}

/// The serving loop's own state between requests.
struct Serving<'a> {
    master: LineMaster<Port>,
    stopping: &'a mut Stopping,
    /// Once a stop is asked for: no new request starts after this.
    deadline: Option<Instant>,
    /// Line counters already passed to the metrics.
    counted: LineCounters,
    /// Re-armed only when it fires: a new one per request would be due before the runtime's
    /// planned wake-up each time, and tokio answers that with a wake-up of its own driver.
    heartbeat: Pin<Box<Sleep>>,
    /// No request is taken before this: the end of the gap after the last transaction, as it
    /// ended. Stray bytes that push the gap back later do not hold the next request here; the
    /// transaction deals with a line that stays busy.
    take_after: Option<Instant>,
}

impl BusTask {
    /// Serve requests on an open port until it is lost, or, once a stop is asked for, until the
    /// queue is empty or the stop's deadline has passed.
    pub(super) async fn serve(
        &mut self,
        master: LineMaster<Port>,
        stopping: &mut Stopping,
    ) -> Served {
        let mut serving = Serving {
            counted: master.counters(),
            master,
            deadline: stopping.deadline(),
            stopping,
            heartbeat: Box::pin(sleep(HEARTBEAT)),
            take_after: None,
        };
        loop {
            self.beat();
            match self.take_update() {
                Some(true) => return Served::Reopen,
                Some(false) => self.current.configure(&mut serving.master),
                None => {}
            }
            let job = match self.next_job(&mut serving).await {
                Next::Run(job) => job,
                Next::Again => continue,
                Next::End(end) => return self.end_serving(&serving, end),
            };
            if let Some(end) = self.run_job(&mut serving, job).await {
                return self.end_serving(&serving, end);
            }
        }
    }

    /// Serving ends as `end`; a lost port leaves its late-reply windows to the next one.
    fn end_serving(&mut self, serving: &Serving<'_>, end: Served) -> Served {
        if matches!(end, Served::Lost(_)) {
            self.windows_at_loss = serving.master.late_reply_windows();
        }
        end
    }

    /// Wait for the next request, or for whatever else needs the loop's attention.
    async fn next_job(&mut self, serving: &mut Serving<'_>) -> Next {
        if let Some(deadline) = serving.deadline {
            // Draining: no new request starts after the deadline.
            if Instant::now() >= deadline {
                return Next::End(Served::Stopped);
            }
            return self
                .handle
                .queue
                .try_pop()
                .map_or(Next::End(Served::Stopped), Next::Run);
        }
        // The next request is taken when the line is ready for its frame, not before: identical
        // reads arriving meanwhile still join it, and a priority master's request still goes
        // first.
        let take_after = *serving
            .take_after
            .get_or_insert_with(|| serving.master.quiet_until());
        let line_ready = Instant::now() >= take_after;
        tokio::select! {
            biased;
            at = serving.stopping.requested() => {
                serving.deadline = Some(at);
                Next::Again
            }
            () = self.updates.changed() => Next::Again,
            () = crate::timer::sleep_until(take_after), if !line_ready => Next::Again,
            job = self.handle.queue.pop(), if line_ready => {
                serving.take_after = None;
                Next::Run(job)
            }
            idle = serving.master.watch_idle() => {
                self.count_serving(serving);
                match idle {
                    Ok(_) => Next::Again,
                    Err(error) => Next::End(Served::Lost(error)),
                }
            }
            () = &mut serving.heartbeat => {
                serving.heartbeat.as_mut().reset(Instant::now() + HEARTBEAT);
                Next::Again
            }
        }
    }

    /// Pass what went over the line since the last look to the metrics.
    fn count_serving(&self, serving: &mut Serving<'_>) {
        let now = serving.master.counters();
        self.count_traffic(now, &mut serving.counted, serving.master.port().link());
    }

    /// Answer `job`: from the line, or at once if nobody waits for it, it expired or its slave
    /// is down. Returns why serving ends, if it does.
    async fn run_job(&mut self, serving: &mut Serving<'_>, job: Job) -> Option<Served> {
        let cleared = self.ready(job).await?;
        // The slave's reply to an earlier, timed-out request may still come: let it arrive
        // (and be discarded) before this request goes out.
        if let Some(until) = serving.master.late_reply_window(cleared.job.slave) {
            crate::timer::sleep_until(until).await;
        }
        let ran = self
            .execute(&mut serving.master, &cleared, serving.deadline)
            .await;
        let broadcast = cleared.broadcast;
        let job = cleared.job;
        self.count_serving(serving);
        match ran {
            Ran::Done(outcome) => {
                self.remember(&job, &outcome);
                self.handle.answer(job, outcome);
                None
            }
            Ran::Reset(outcome) => {
                self.handle.answer(job, outcome);
                Some(Served::Lost(io::Error::other(
                    "reset after a timeout: with match_transaction_id = false a late answer \
                     could not be told from the next request's",
                )))
            }
            Ran::PortLost(error) => {
                // The request may have reached the slave, which may still answer.
                let timeout = self.current.derived.timeouts[usize::from(job.slave)];
                if !broadcast {
                    serving
                        .master
                        .expect_late_reply(job.slave, Instant::now() + timeout);
                }
                self.handle.answer(job, Err(RequestError::PortLost));
                Some(Served::Lost(error))
            }
        }
    }

    /// Keep a slave's normal reply to a read for its `cache`, if it has one.
    pub(super) fn remember(&self, job: &Job, outcome: &crate::error::Outcome) {
        let Ok(crate::error::Answer::Reply(pdu)) = outcome else {
            return;
        };
        let normal = pdu
            .first()
            .is_some_and(|f| f & crate::pdu::EXCEPTION_BIT == 0);
        let cache = self.current.derived.cached[usize::from(job.slave)];
        if normal && cache && crate::pdu::is_read_only(&job.pdu) {
            self.handle.queue.remember(job, pdu);
        }
    }
}
