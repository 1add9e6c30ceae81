//! One task per RS-485 line, the only owner of its port. It takes requests from a fair queue
//! ([`queue`]), skips those whose master has gone or whose deadline passed, runs each through the
//! RTU master with the slave's timeout and the retry policy, sends broadcasts, and when the port
//! is lost answers 0x0A at once while it reopens the port with backoff. A slave that keeps timing
//! out is left alone but for probes ([`health`]). Knows nothing of TCP.

pub mod health;
pub mod port;
pub mod queue;

pub use port::{Device, Port};
pub use queue::{FairQueue, Job, MasterId};

use crate::config;
use crate::error::{Answer, Outcome, RequestError};
use crate::line::{Framing, LineMaster, MasterTiming, ReplyForm, TxError};
use crate::metrics::{BusMetrics, Metrics};
use crate::pdu;
use crate::rtu::frame::{BROADCAST, MAX_FRAME_LEN};
use crate::shutdown::Stopping;
use health::{Admission, Change, DownPolicy, Health, Response};
use std::io;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError, Weak};
use std::time::Duration;
use tokio::sync::{oneshot, watch};
use tokio::time::{sleep, sleep_until, Instant};
use tracing::{debug, info};

/// How often an idle bus task shows it is still running.
const HEARTBEAT: Duration = Duration::from_secs(1);
/// Slack on top of the longest a bus task may legitimately go without a heartbeat.
const STALL_MARGIN: Duration = Duration::from_secs(1);

/// When a bus task last showed it was running, and how long it may go without doing so.
struct Heartbeat {
    last: Mutex<Instant>,
    stall_limit: Mutex<Duration>,
}

/// What the rest of the gateway holds of a bus: its queue, whether its port is open, whether its
/// task is making progress.
#[derive(Clone)]
pub struct BusHandle {
    name: Arc<str>,
    queue: Arc<FairQueue>,
    up: Arc<AtomicBool>,
    queue_timeout: Arc<Mutex<Duration>>,
    metrics: Arc<BusMetrics>,
    heartbeat: Arc<Heartbeat>,
    /// Signalled once the task has made its first attempt to open the port.
    attempted: Arc<tokio::sync::Notify>,
}

impl BusHandle {
    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn metrics(&self) -> &BusMetrics {
        &self.metrics
    }

    /// True while the bus holds an open port.
    pub fn is_up(&self) -> bool {
        self.up.load(Ordering::Acquire)
    }

    /// How long the bus task has gone without a heartbeat, if longer than any transaction or
    /// idle wait can take: the task is stuck (blocked thread, a driver that never returns).
    pub fn stalled_for(&self) -> Option<Duration> {
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
    pub async fn first_open_attempt(&self) {
        self.attempted.notified().await;
    }

    fn beat(&self) {
        *self
            .heartbeat
            .last
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Instant::now();
    }

    /// Queue `pdu` for `slave`. The receiver yields the outcome; refusals (port down, queue full)
    /// are in it at once.
    pub fn submit(&self, master: MasterId, slave: u8, pdu: Vec<u8>) -> oneshot::Receiver<Outcome> {
        let (reply, outcome) = oneshot::channel();
        let now = Instant::now();
        let job = Job {
            master,
            slave,
            pdu,
            queued_at: now,
            deadline: now
                + *self
                    .queue_timeout
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner),
            reply,
        };
        if !self.is_up() {
            self.answer(job, Err(RequestError::PortDown));
        } else if let Err(job) = self.queue.push(job) {
            let refusal = if self.queue.is_closed() {
                RequestError::ShuttingDown
            } else {
                RequestError::QueueFull
            };
            self.answer(job, Err(refusal));
        }
        outcome
    }

    /// Drop the queued requests of a master that has gone; they are never sent.
    pub fn forget(&self, master: MasterId) {
        for job in self.queue.forget(master) {
            self.metrics.request(job.slave, job.function(), None);
        }
    }

    /// Every request ends here, or in [`BusHandle::forget`]: counted by outcome, then answered.
    fn answer(&self, job: Job, outcome: Outcome) {
        self.metrics
            .request(job.slave, job.function(), Some(&outcome));
        let _ = job.reply.send(outcome);
    }
}

/// Why the bus task stopped serving an open port.
enum End {
    Lost(io::Error),
    Stopped,
    /// The configuration names another device or format: open again.
    Reopen,
}

/// A running bus's new configuration: its settings and the device they name.
#[derive(Clone)]
pub struct Reconfigure {
    pub settings: config::Bus,
    pub device: Device,
}

/// The gateway's side of a running bus: where new configurations go.
pub struct BusUpdates(watch::Sender<Option<Reconfigure>>);

impl BusUpdates {
    /// Apply `update` between transactions. Returns whether the port will be reopened (its
    /// device or serial format changed); otherwise the new settings apply on the open port.
    pub fn send(&self, update: Reconfigure) -> bool {
        let reopen = self
            .0
            .borrow()
            .as_ref()
            .is_none_or(|current| !current.device.same_as(&update.device));
        self.0.send_replace(Some(update));
        reopen
    }
}

/// What the bus task derives from its settings.
struct Derived {
    timing: MasterTiming,
    /// Response timeout per slave address, overrides applied.
    timeouts: Box<[Duration; 256]>,
    stall_limit: Duration,
    down: DownPolicy,
}

impl Derived {
    fn of(settings: &config::Bus) -> Derived {
        let timing = settings.master_timing();
        let mut timeouts = Box::new([settings.response_timeout; 256]);
        for slave in &settings.slave {
            if let Some(timeout) = slave.response_timeout {
                timeouts[usize::from(slave.address)] = timeout;
            }
        }
        // The longest a bus task may legitimately go between heartbeats: one attempt, whose gap
        // the line may hold busy for the timeout, then the timeout, two longest frames, the
        // silence that ends a reply and a broadcast's turnaround; or an idle heartbeat.
        let longest_timeout = timeouts.iter().copied().max().unwrap_or_default();
        let stall_limit = HEARTBEAT
            + longest_timeout * 2
            + timing.line.frame_time(MAX_FRAME_LEN) * 2
            + timing.silence
            + settings.turnaround_delay
            + STALL_MARGIN;
        Derived {
            timing,
            timeouts,
            stall_limit,
            down: DownPolicy {
                after: settings.slave_down_after,
                probe_interval: settings.slave_probe_interval,
            },
        }
    }
}

/// Everything the bus task needs, derived from its configuration.
pub struct Bus {
    settings: config::Bus,
    derived: Derived,
    device: Device,
    handle: BusHandle,
    updates: watch::Receiver<Option<Reconfigure>>,
    /// Kept so that `updates` never reports a closed channel when nobody reconfigures the bus.
    updates_sender: Option<watch::Sender<Option<Reconfigure>>>,
    /// Whoever reconfigured the bus is gone: stop listening for more.
    updates_closed: bool,
    health: Health,
}

impl Bus {
    /// A bus whose metrics are registered in `metrics`.
    pub fn new(settings: config::Bus, device: Device, metrics: &Metrics) -> Self {
        let derived = Derived::of(&settings);
        let queue = Arc::new(FairQueue::new(settings.queue_depth));
        let depth = metrics.queue_depth(&settings.name);
        let weak: Weak<FairQueue> = Arc::downgrade(&queue);
        metrics.on_scrape(move || {
            let len = weak.upgrade().map_or(0, |queue| queue.len());
            depth.set(i64::try_from(len).unwrap_or(i64::MAX));
        });
        let handle = BusHandle {
            name: settings.name.as_str().into(),
            queue,
            up: Arc::new(AtomicBool::new(false)),
            queue_timeout: Arc::new(Mutex::new(settings.queue_timeout)),
            metrics: metrics.bus(&settings),
            heartbeat: Arc::new(Heartbeat {
                last: Mutex::new(Instant::now()),
                stall_limit: Mutex::new(derived.stall_limit),
            }),
            attempted: Arc::new(tokio::sync::Notify::new()),
        };
        let (sender, updates) = watch::channel(Some(Reconfigure {
            settings: settings.clone(),
            device: device.clone(),
        }));
        Bus {
            settings,
            derived,
            device,
            handle,
            updates,
            updates_sender: Some(sender),
            updates_closed: false,
            health: Health::default(),
        }
    }

    /// Where new configurations for this bus go; take it before running the bus.
    pub fn updates(&mut self) -> BusUpdates {
        let sender = self
            .updates_sender
            .take()
            .unwrap_or_else(|| watch::channel(None).0);
        BusUpdates(sender)
    }

    pub fn handle(&self) -> BusHandle {
        self.handle.clone()
    }

    fn set_up(&self, up: bool) {
        self.handle.up.store(up, Ordering::Release);
    }

    /// Take a new configuration. Returns whether the port must be reopened.
    fn apply(&mut self, update: Reconfigure) -> bool {
        let reopen = !self.device.same_as(&update.device);
        self.derived = Derived::of(&update.settings);
        *self
            .handle
            .heartbeat
            .stall_limit
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = self.derived.stall_limit;
        *self
            .handle
            .queue_timeout
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = update.settings.queue_timeout;
        self.handle.queue.set_capacity(update.settings.queue_depth);
        self.handle.metrics.reconfigured(&update.settings);
        info!(bus = &*self.handle.name, reopen, "bus reconfigured");
        self.settings = update.settings;
        self.device = update.device;
        reopen
    }

    /// A new configuration, if one came since the last look (`changed`: `updates.changed()`
    /// has just said so, and marked it seen).
    fn update(&mut self, changed: bool) -> Option<Reconfigure> {
        if !changed && !self.updates.has_changed().unwrap_or(false) {
            return None;
        }
        self.updates.borrow_and_update().clone()
    }

    /// Set the master's timing and reply forms from the settings.
    fn configure(&self, master: &mut LineMaster<Port>) {
        master.set_timing(self.derived.timing);
        for address in 0..=u8::MAX {
            master.set_reply_form(address, ReplyForm::Standard);
        }
        for slave in self.settings.slave.iter().filter(|s| s.wide_read_count) {
            master.set_reply_form(slave.address, ReplyForm::WideReadCount);
        }
    }

    /// Run until `stopping`: open the port, serve it until it is lost, answer 0x0A while it is
    /// down, reopen with backoff. Once stopped, whatever is still queued is answered 0x0A.
    pub async fn run(mut self, mut stopping: Stopping) {
        let metrics = self.handle.metrics.clone();
        // The configuration it starts with is the one it was made with.
        self.updates.borrow_and_update();
        let mut delay = self.settings.reopen_delay;
        // Since when the port is down, and how many opens have failed since.
        let mut down_since: Option<(Instant, u32)> = None;
        loop {
            let opened = self.device.open();
            self.set_up(opened.is_ok());
            self.handle.attempted.notify_one();
            match opened {
                Ok(port) => {
                    let down = down_since
                        .take()
                        .map(|(since, failed_opens)| (since.elapsed(), failed_opens));
                    metrics.port_opened(&self.settings.device, down);
                    delay = self.settings.reopen_delay;
                    let mut master = LineMaster::new(port, Framing::Rtu, self.derived.timing);
                    self.configure(&mut master);
                    let end = self.serve(master, &mut stopping).await;
                    self.set_up(false);
                    match end {
                        End::Lost(error) => metrics.port_lost(&self.settings.device, &error),
                        End::Stopped => break,
                        // Straight to the new device, as a first open.
                        End::Reopen => continue,
                    }
                    down_since = Some((Instant::now(), 0));
                }
                Err(error) => {
                    let first = down_since.is_none();
                    metrics.open_failed(&self.settings.device, &error, first);
                    let (_, failed_opens) = down_since.get_or_insert((Instant::now(), 0));
                    *failed_opens += 1;
                }
            }
            match self
                .refuse_until(Instant::now() + delay, &mut stopping)
                .await
            {
                End::Stopped => break,
                End::Reopen => {
                    delay = self.settings.reopen_delay;
                    continue;
                }
                End::Lost(_) => {}
            }
            delay = (delay * 2).min(self.settings.reopen_delay_max);
        }
        self.set_up(false);
        let left = self.handle.queue.close();
        info!(
            bus = &*self.handle.name,
            unserved = left.len(),
            "bus stopped"
        );
        for job in left {
            self.handle.answer(job, Err(RequestError::ShuttingDown));
        }
    }

    /// While the port is down: answer everything queued, and everything that arrives, with 0x0A,
    /// until `until` (time to try again: `Lost`), a new configuration (`Reopen`: try it at once)
    /// or a stop.
    async fn refuse_until(&mut self, until: Instant, stopping: &mut Stopping) -> End {
        for job in self.handle.queue.drain() {
            self.handle.answer(job, Err(RequestError::PortDown));
        }
        let mut changed = false;
        loop {
            self.handle.beat();
            if let Some(update) = self.update(std::mem::take(&mut changed)) {
                self.apply(update);
                return End::Reopen;
            }
            tokio::select! {
                biased;
                _ = stopping.requested() => return End::Stopped,
                seen = self.updates.changed(), if !self.updates_closed => {
                    changed = seen.is_ok();
                    self.updates_closed = seen.is_err();
                }
                job = self.handle.queue.pop() => {
                    self.handle.answer(job, Err(RequestError::PortDown));
                }
                () = sleep_until(until) => return End::Lost(io::ErrorKind::NotConnected.into()),
                () = sleep(HEARTBEAT) => {}
            }
        }
    }

    /// Serve requests on an open port until it is lost, or, once a stop is asked for, until the
    /// queue is empty or the stop's deadline has passed.
    async fn serve(&mut self, mut master: LineMaster<Port>, stopping: &mut Stopping) -> End {
        let metrics = self.handle.metrics.clone();
        let mut counted = master.counters();
        let mut deadline = stopping.deadline();
        let mut changed = false;
        // Re-armed only when it fires: a new one per request would be due before the runtime's
        // planned wake-up each time, and tokio answers that with a wake-up of its own driver.
        let heartbeat = sleep(HEARTBEAT);
        tokio::pin!(heartbeat);
        loop {
            self.handle.beat();
            if let Some(update) = self.update(std::mem::take(&mut changed)) {
                if self.apply(update) {
                    return End::Reopen;
                }
                self.configure(&mut master);
            }
            let job = if let Some(deadline) = deadline {
                // Draining: no new request starts after the deadline.
                if Instant::now() >= deadline {
                    return End::Stopped;
                }
                match self.handle.queue.try_pop() {
                    Some(job) => job,
                    None => return End::Stopped,
                }
            } else {
                tokio::select! {
                    biased;
                    at = stopping.requested() => {
                        deadline = Some(at);
                        continue;
                    }
                    seen = self.updates.changed(), if !self.updates_closed => {
                        changed = seen.is_ok();
                        self.updates_closed = seen.is_err();
                        continue;
                    }
                    job = self.handle.queue.pop() => job,
                    idle = master.watch_idle() => {
                        let traffic = master.counters();
                        metrics.line(&traffic.since(&counted));
                        counted = traffic;
                        match idle {
                            Ok(_) => continue,
                            Err(error) => return End::Lost(error),
                        }
                    }
                    () = &mut heartbeat => {
                        heartbeat.as_mut().reset(Instant::now() + HEARTBEAT);
                        continue;
                    }
                }
            };
            if job.reply.is_closed() {
                metrics.request(job.slave, job.function(), None);
                continue;
            }
            metrics.dequeued(job.queued_at.elapsed());
            if Instant::now() > job.deadline {
                self.handle.answer(job, Err(RequestError::Expired));
                continue;
            }
            let admission = match job.slave {
                BROADCAST => Admission::Send,
                slave => self.health.admit(slave, Instant::now(), self.derived.down),
            };
            if let Admission::Skip { timeouts } = admission {
                self.handle
                    .answer(job, Err(RequestError::SlaveDown { timeouts }));
                continue;
            }
            // The slave's reply to an earlier, timed-out request may still come: let it arrive
            // (and be discarded) before this request goes out.
            if let Some(until) = master.late_reply_window(job.slave) {
                crate::timer::sleep_until(until).await;
            }
            let probe = admission == Admission::Probe;
            let result = self.execute(&mut master, &job, deadline, probe).await;
            let traffic = master.counters();
            metrics.line(&traffic.since(&counted));
            counted = traffic;
            match result {
                Ok(outcome) => self.handle.answer(job, outcome),
                Err(error) => {
                    self.handle.answer(job, Err(RequestError::PortDown));
                    return End::Lost(error);
                }
            }
        }
    }

    /// Run one request on the line; no retry starts after `stop_at`, none at all for a `probe`
    /// of a slave that is down. `Err` only when the port is lost.
    async fn execute(
        &mut self,
        master: &mut LineMaster<Port>,
        job: &Job,
        stop_at: Option<Instant>,
        probe: bool,
    ) -> Result<Outcome, io::Error> {
        let settings = &self.settings;
        if job.slave == BROADCAST {
            return match master
                .broadcast(
                    &job.pdu,
                    settings.turnaround_delay,
                    settings.response_timeout,
                )
                .await
            {
                Ok(()) => Ok(Ok(settings
                    .broadcast_reply
                    .then(|| pdu::broadcast_response(&job.pdu))
                    .flatten()
                    .map_or(Answer::Nothing, Answer::Reply))),
                Err(TxError::PortLost(error)) => Err(error),
                Err(last) => Ok(Err(RequestError::NoResponse { attempts: 1, last })),
            };
        }
        // A write whose reply was lost may have been carried out: sending it again could do it
        // twice, so writes are retried only when the configuration says so.
        let retries = if probe {
            0
        } else if pdu::is_read_only(&job.pdu) || settings.retry_writes {
            settings.retries
        } else {
            0
        };
        let timeout = self.derived.timeouts[usize::from(job.slave)];
        let mut attempts = 0;
        let mut first_sent_at = None;
        let outcome = loop {
            attempts += 1;
            self.handle.beat();
            let previous = master.sent_at();
            let result = master.transact(job.slave, &job.pdu, timeout).await;
            if master.sent_at() != previous {
                first_sent_at.get_or_insert(master.sent_at());
            }
            match result {
                Ok(reply) => break Ok(Answer::from(reply)),
                Err(TxError::PortLost(error)) => return Err(error),
                Err(last)
                    if attempts > retries
                        || job.reply.is_closed()
                        || stop_at.is_some_and(|at| Instant::now() >= at) =>
                {
                    break Err(RequestError::NoResponse { attempts, last });
                }
                Err(error) => {
                    debug!(bus = &*self.handle.name, slave = job.slave, attempts, %error, "retrying");
                }
            }
        };
        // A request the line was always too busy to send has no round trip.
        let round_trip = first_sent_at.map(|sent| sent.elapsed());
        let function = job.function();
        let timeout_counts = self.health.timeout_counts(job.slave, function);
        self.handle
            .metrics
            .transaction(job.slave, attempts, round_trip, &outcome, timeout_counts);
        let response = match &outcome {
            Ok(_) => Response::Answered,
            Err(RequestError::NoResponse {
                last: TxError::Timeout,
                ..
            }) => Response::TimedOut,
            Err(_) => Response::Garbled,
        };
        let down = self.derived.down;
        let change = self
            .health
            .record(job.slave, function, response, Instant::now(), down);
        if let Change::Down { timeouts } = change {
            self.handle
                .metrics
                .slave_down(job.slave, timeouts, down.probe_interval);
        }
        Ok(outcome)
    }
}
