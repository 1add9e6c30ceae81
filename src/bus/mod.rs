//! One task per line (an RS-485 line, or a Modbus TCP device's connection), the only owner of its
//! port. Others hold its [`BusHandle`]: they submit requests to its fair queue (`queue`) and read
//! whether it is up. The task (`task`) opens the port (`device`: a serial port with its RS-485 and
//! USB adapter settings, a device server's or Modbus TCP device's socket, or the simulated line),
//! answers 0x0A at once while it is down and reopens it with backoff, which only a port that
//! serves resets (`outage`, which also says what each open and loss is to the log). While it is
//! open one of two loops serves the queue: `serve`, one request at a time, or `pipelined`, several
//! in flight on a Modbus TCP device. Both take every request through the one pre-send step
//! (`ready`: who still waits, a write's journal entry on record, the slave's health, its tries),
//! then run it as one transaction (`transaction`: the slave's timeout, retries, broadcasts). A
//! slave that keeps timing out is left alone but for probes (`health`, the one place that decides
//! whether a slave is alive). Every request ends through its [`Waiter`] (`waiter`), counted and
//! answered once. New settings reach the task between transactions (`reconfigure`). Knows nothing
//! of TCP masters, nor of which transport carries a line.

pub(crate) mod device;
pub(crate) mod health;
mod listen;
mod outage;
mod pipelined;
pub(crate) mod queue;
mod ready;
mod reconfigure;
mod serve;
pub(crate) mod shadow;
mod task;
mod transaction;
mod waiter;

pub(crate) use device::TlsDevice;
pub use device::{Device, Port, SerialDriver};
pub(crate) use queue::{FairQueue, Job, Pushed};
pub(crate) use reconfigure::{longest_transaction, BusUpdates, Reconfigure};
pub use task::BusTask;
pub(crate) use waiter::Tally;
pub(crate) use waiter::Waiter;

use crate::config;
use crate::error::{Answer, Outcome, RequestError};
use crate::master::{Class, MasterId, Origin};
use crate::metrics::BusMetrics;
use crate::pdu;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::sync::oneshot;
use tokio::time::Instant;

/// How often an idle bus task shows it is still running.
const HEARTBEAT: Duration = Duration::from_secs(1);
/// Slack on top of the longest a bus task may legitimately go without a heartbeat.
const STALL_MARGIN: Duration = Duration::from_secs(1);

/// When a bus task last showed it was running, and how long it may go without doing so.
struct Heartbeat {
    last: Mutex<Instant>,
    stall_limit: Mutex<Duration>,
}

/// What a request meets as it is submitted, from the bus's settings: how long it may wait, and
/// per slave whether reads coalesce and how old a cached answer may be.
pub(crate) struct Intake {
    queue_timeout: Duration,
    /// Address 0 is a broadcast on this line (not on a Modbus TCP device's).
    broadcasts: bool,
    /// A broadcast write is answered with its normal reply.
    broadcast_reply: bool,
    coalesce: Box<[bool; 256]>,
    cache: Box<[Duration; 256]>,
}

impl Intake {
    pub(crate) fn of(settings: &config::Bus) -> Intake {
        let mut intake = Intake {
            queue_timeout: settings.queue_timeout,
            broadcasts: settings.framing.broadcasts(),
            broadcast_reply: settings.broadcast_reply,
            coalesce: Box::new([settings.coalesce_reads; 256]),
            cache: Box::new([Duration::ZERO; 256]),
        };
        for slave in &settings.slave {
            let at = usize::from(slave.address);
            intake.coalesce[at] = slave.coalesce_reads.unwrap_or(settings.coalesce_reads);
            intake.cache[at] = slave.cache;
        }
        intake
    }
}

/// What the rest of the gateway holds of a bus: its queue, whether its port is open, whether its
/// task is making progress.
#[derive(Clone)]
pub struct BusHandle {
    name: Arc<str>,
    queue: Arc<FairQueue>,
    up: Arc<AtomicBool>,
    intake: Arc<Mutex<Intake>>,
    metrics: Arc<BusMetrics>,
    heartbeat: Arc<Heartbeat>,
    /// Signalled once the task has made its first attempt to open the port.
    attempted: Arc<tokio::sync::Notify>,
    /// The line's time the gateway's polls have taken so far, in nanoseconds: what a poll led
    /// took from its first frame to its end, retries included.
    poll_time: Arc<AtomicU64>,
    /// A listen-only line's shadow of its slaves, which answers every request to it: such a
    /// line never queues anything.
    shadow: Option<Arc<shadow::Shadow>>,
}

impl BusHandle {
    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn metrics(&self) -> &BusMetrics {
        &self.metrics
    }

    /// A listen-only line's shadow, if this is one.
    pub(crate) fn shadow(&self) -> Option<&Arc<shadow::Shadow>> {
        self.shadow.as_ref()
    }

    /// Requests waiting in its queue now.
    pub fn queue_depth(&self) -> usize {
        self.queue.len()
    }

    /// True while the bus holds an open port.
    pub fn is_up(&self) -> bool {
        self.up.load(Ordering::Acquire)
    }

    /// How long the bus task has gone without a heartbeat, if longer than any transaction or
    /// idle wait can take: the task is stuck (blocked thread, a driver that never returns).
    pub(crate) fn stalled_for(&self) -> Option<Duration> {
        let last = *self
            .heartbeat
            .last
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let silent = last.elapsed();
        let limit = *self
            .heartbeat
            .stall_limit
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        (silent > limit).then_some(silent)
    }

    /// Wait until the bus task has tried once to open its port (successfully or not). Meant for
    /// one waiter, once.
    pub(crate) async fn first_open_attempt(&self) {
        self.attempted.notified().await;
    }

    /// The line's time the gateway's polls have taken since the bus started.
    pub(crate) fn poll_time(&self) -> Duration {
        Duration::from_nanos(self.poll_time.load(Ordering::Relaxed))
    }

    /// `job` ended after taking the line for `line_time`: counted if it is a poll.
    fn took_line(&self, job: &Job, line_time: Duration) {
        if job.class() == Class::Poll {
            let nanos = u64::try_from(line_time.as_nanos()).unwrap_or(u64::MAX);
            self.poll_time.fetch_add(nanos, Ordering::Relaxed);
        }
    }

    fn beat(&self) {
        *self
            .heartbeat
            .last
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Instant::now();
    }

    #[cfg(any(test, feature = "test-util"))]
    /// Queue `pdu` for `slave` from a Modbus TCP master. The receiver yields the outcome;
    /// refusals (port down, queue full) are in it at once.
    pub fn submit(&self, master: MasterId, slave: u8, pdu: Vec<u8>) -> oneshot::Receiver<Outcome> {
        let origin = Origin {
            master,
            admission: master,
            protocol: crate::master::Protocol::Tcp,
            class: Class::Normal,
        };
        self.submit_from(origin, slave, pdu)
    }

    /// Priority masters' requests go before the others' up to `share` of the line.
    pub fn set_priority_share(&self, share: f64) {
        self.queue.set_priority_share(share);
    }

    /// Whether a broadcast write is answered with its normal reply (`broadcast_reply`).
    pub(crate) fn broadcast_reply(&self) -> bool {
        self.intake
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .broadcast_reply
    }

    /// [`BusHandle::submit`] for a master of any protocol and class: a read may be answered
    /// from the cache, or join an identical one waiting. Admitted to a full queue in place of
    /// another master's request, that one is refused (queue full).
    pub fn submit_from(
        &self,
        origin: Origin,
        slave: u8,
        pdu: Vec<u8>,
    ) -> oneshot::Receiver<Outcome> {
        self.submit_journaled(origin, slave, pdu, None)
    }

    /// [`BusHandle::submit_from`] for a write whose journal entry (`pending`) is written: its
    /// outcome is written wherever the request ends.
    pub(crate) fn submit_journaled(
        &self,
        origin: Origin,
        slave: u8,
        pdu: Vec<u8>,
        pending: Option<crate::audit::Pending>,
    ) -> oneshot::Receiver<Outcome> {
        let (deadline, coalesce, cache) = {
            let intake = self.intake.lock().unwrap_or_else(PoisonError::into_inner);
            let at = usize::from(slave);
            (
                Instant::now() + intake.queue_timeout,
                intake.coalesce[at]
                    && (slave != crate::line::BROADCAST || !intake.broadcasts)
                    && pdu::is_read_only(&pdu),
                intake.cache[at],
            )
        };
        let (waiter, outcome) = Waiter::new(origin, deadline);
        let mut job = Job::new(waiter.journaled(pending), slave, pdu);
        if let Some(shadow) = &self.shadow {
            let answered = shadow.answer(slave, &job.pdu, Instant::now());
            self.answer(job, answered.map(Answer::Reply));
            return outcome;
        }
        job.coalesce = coalesce;
        if !self.is_up() {
            self.answer(job, Err(RequestError::PortDown));
            return outcome;
        }
        match self.queue.push(job, cache) {
            Ok((pushed, evicted)) => {
                if let Some(evicted) = evicted {
                    self.answer(evicted, Err(RequestError::QueueFull));
                }
                match pushed {
                    Pushed::Queued => {}
                    Pushed::Joined => self.metrics.coalesced(slave),
                    Pushed::Cached(job, answer) => {
                        self.metrics.cache_hit(slave);
                        self.answer(job, Ok(Answer::Reply(answer)));
                    }
                }
            }
            Err(job) => {
                let refusal = if self.queue.is_closed() {
                    RequestError::ShuttingDown
                } else {
                    RequestError::QueueFull
                };
                self.answer(job, Err(refusal));
            }
        }
        outcome
    }

    /// Drop the queued requests of a master that has gone; they are never sent.
    pub(crate) fn forget(&self, master: MasterId) {
        for job in self.queue.forget(master) {
            // Reads that followed it stay queued, the first leading in its place.
            debug_assert!(job.followers.is_empty());
            let function = job.function();
            job.waiter.left(self.tally(), job.slave, function);
        }
    }

    /// Where this bus counts how its requests end.
    pub(crate) fn tally(&self) -> Tally<'_> {
        Tally::Bus(&self.metrics)
    }

    /// `job` ends in `outcome`: its master is answered, and the reads that followed it get the
    /// same outcome (a follower whose master left is counted as dropped).
    fn answer(&self, job: Job, outcome: Outcome) {
        let (slave, function, tally) = (job.slave, job.function(), self.tally());
        for follower in job.followers {
            if follower.is_gone() {
                follower.left(tally, slave, function);
            } else {
                follower.answer(tally, slave, function, outcome.clone());
            }
        }
        job.waiter.answer(tally, slave, function, outcome);
    }
}

#[cfg(test)]
mod exits_tests;
#[cfg(test)]
mod outage_tests;
#[cfg(test)]
mod pipelined_tests;
#[cfg(test)]
mod tests;
