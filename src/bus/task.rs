//! The bus task's life: open the port, serve it (`serve`, or `pipelined` with `max_in_flight`
//! above 1) until it is lost or a new device is configured, answer 0x0A while it is down and
//! reopen it with backoff (`outage` says how long to wait and what each open and loss is to the
//! log), and once stopped answer whatever is still queued.

use super::device::net::Dropped;
use super::device::serial::latency::{self, SYSFS};
use super::health::Health;
use super::outage::{Outages, Recovery};
use super::reconfigure::{Current, Updates};
use super::{
    BusHandle, BusUpdates, Device, FairQueue, Heartbeat, Intake, Port, Reconfigure, HEARTBEAT,
};
use crate::config;
use crate::error::RequestError;
use crate::line::LineMaster;
use crate::metrics::Metrics;
use crate::shutdown::Stopping;
use crate::timer::coarse_sleep_until;
use crate::trace::BusTap;
use std::io;
use std::path::Path;
use std::pin::pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;
use tokio::time::{sleep, Instant};
use tracing::info;

/// Why the bus task stopped serving an open port.
pub(super) enum Served {
    Lost(io::Error),
    Stopped,
    /// The configuration names another device or format: open again.
    Reopen,
}

/// After connecting to a device server, how long the line must have been quiet (on top of the
/// link budget) before the first request: bytes the converter held while nobody was connected
/// (a reply to a request of before the outage) come at once, and are discarded.
const CONNECT_SETTLE: Duration = Duration::from_millis(100);

/// How an attempt to open the port ended. One per open, moved once: its size costs nothing.
#[allow(clippy::large_enum_variant)]
enum Opening {
    Done(io::Result<Port>),
    Stopped,
    /// A new configuration named another device: open that instead.
    Reopen,
}

/// How a wait with the port down ended.
enum Waited {
    /// Time to try to open the port again.
    TryAgain,
    Stopped,
    /// A new configuration came: open it at once.
    Reopen,
}

/// One RS-485 line's task and everything it needs, derived from its configuration.
pub struct BusTask {
    pub(super) current: Current,
    pub(super) handle: BusHandle,
    pub(super) updates: Updates,
    pub(super) health: Health,
    /// Where the line's frames go while someone watches.
    pub(super) trace: BusTap,
    /// The device's Modbus TCP answers have been logged on this connection.
    pub(super) told_wrong_mode: bool,
    /// A Modbus TCP device's wrong transaction ids have been logged on this connection.
    pub(super) told_mismatch: bool,
    /// The late-reply windows open when the port was lost: a reply to a request of before may
    /// still come through the reopened port.
    pub(super) windows_at_loss: Vec<(u8, Instant)>,
    /// The port's outages, and the wait before its next open.
    outages: Outages,
}

impl BusTask {
    /// A bus whose metrics are registered in `metrics`.
    pub fn new(settings: config::Bus, device: Device, metrics: &Metrics) -> Self {
        let current = Current::new(settings.clone(), device.clone());
        let queue = Arc::new(FairQueue::new(settings.queue_depth));
        let depth = metrics.queue_depth(&settings.name);
        let weak: Weak<FairQueue> = Arc::downgrade(&queue);
        metrics.on_scrape(move || {
            let len = weak.upgrade().map_or(0, |queue| queue.len());
            depth.set(i64::try_from(len).unwrap_or(i64::MAX));
        });
        let name: Arc<str> = settings.name.as_str().into();
        let trace = metrics.trace.register(name.clone());
        let handle = BusHandle {
            name,
            queue,
            up: Arc::new(AtomicBool::new(false)),
            intake: Arc::new(Mutex::new(Intake::of(&settings))),
            metrics: metrics.bus(&settings),
            heartbeat: Arc::new(Heartbeat {
                last: Mutex::new(Instant::now()),
                stall_limit: Mutex::new(current.derived.stall_limit),
            }),
            attempted: Arc::new(tokio::sync::Notify::new()),
            poll_time: Arc::default(),
            shadow: (settings.mode == config::BusMode::Listen)
                .then(|| Arc::new(super::shadow::Shadow::new(settings.max_age))),
        };
        BusTask {
            outages: Outages::new(settings.reopen_delay),
            current,
            handle,
            updates: Updates::new(Reconfigure { settings, device }),
            health: Health::default(),
            trace,
            told_wrong_mode: false,
            told_mismatch: false,
            windows_at_loss: Vec::new(),
        }
    }

    /// Where new configurations for this bus go; take it before running the bus.
    pub(crate) fn updates(&mut self) -> BusUpdates {
        self.updates.sender()
    }

    pub fn handle(&self) -> BusHandle {
        self.handle.clone()
    }

    fn set_up(&self, up: bool) {
        self.handle.up.store(up, Ordering::Release);
    }

    /// Take a new configuration if one came. Returns whether the port must be reopened.
    pub(super) fn take_update(&mut self) -> Option<bool> {
        let update = self.updates.take()?;
        Some(self.current.apply(update, &self.handle))
    }

    /// Run until `stopping`: open the port, serve it until it is lost, answer 0x0A while it is
    /// down, reopen with backoff. Once stopped, whatever is still queued is answered 0x0A.
    pub async fn run(mut self, mut stopping: Stopping) {
        loop {
            let opened = match self.open(&mut stopping).await {
                Opening::Done(opened) => opened,
                Opening::Stopped => break,
                Opening::Reopen => continue,
            };
            self.set_up(opened.is_ok());
            self.handle.attempted.notify_one();
            match opened {
                Ok(port) => match self.serve_port(port, &mut stopping).await {
                    Served::Lost(error) => self.lost(&error),
                    Served::Stopped => break,
                    // Straight to the new device, as a first open.
                    Served::Reopen => {
                        self.handle.metrics.link(None);
                        self.outages.restart(self.current.settings.reopen_delay);
                        continue;
                    }
                },
                Err(error) => {
                    let first = self.outages.open_failed(Instant::now());
                    let device = &self.current.settings.device;
                    self.handle.metrics.open_failed(device, &error, first);
                }
            }
            let wait = self
                .outages
                .next_wait(self.current.settings.reopen_delay_max);
            match self
                .refuse_until(Instant::now() + wait, &mut stopping)
                .await
            {
                Waited::Stopped => break,
                Waited::Reopen => self.outages.restart(self.current.settings.reopen_delay),
                Waited::TryAgain => {}
            }
        }
        self.finish();
    }

    /// Serve the freshly opened `port` until it is lost, a stop or a new device.
    async fn serve_port(&mut self, port: Port, stopping: &mut Stopping) -> Served {
        let again = self.outages.opened(Instant::now()).is_some();
        let metrics = &self.handle.metrics;
        metrics.port_opened(&self.current.settings.device, again);
        metrics.link(port.link());
        self.adjust_latency_timer();
        self.told_wrong_mode = false;
        self.told_mismatch = false;
        let end = if let Some(shadow) = self.handle.shadow.clone() {
            self.serve_listening(port, &shadow, stopping).await
        } else if self.current.settings.max_in_flight > 1 {
            self.serve_pipelined(port, stopping).await
        } else {
            let master = self.master_on(port);
            self.serve(master, stopping).await
        };
        self.set_up(false);
        end
    }

    /// The open port was lost with `error`: the outage it begins or continues, logged and
    /// counted as such, with why the gateway closed it if it did.
    fn lost(&mut self, error: &io::Error) {
        // A port up as long as the longest wait has served, even if no check saw it yet.
        self.beat();
        let loss = self.outages.lost(Instant::now());
        let device = &self.current.settings.device;
        let metrics = &self.handle.metrics;
        metrics.port_lost(device, error, loss, Dropped::of(error));
    }

    /// The open port has served: a request was answered through it. Ends the outage it opened
    /// in, if any.
    pub(super) fn served(&mut self) {
        let ended = self.outages.served(self.current.settings.reopen_delay);
        self.port_back(ended);
    }

    /// Show the task is running, and end the outage the open port opened in if it has been up
    /// as long as the longest wait between opens (`reopen_delay_max`).
    pub(super) fn beat(&mut self) {
        self.handle.beat();
        let settings = &self.current.settings;
        let (long, first) = (settings.reopen_delay_max, settings.reopen_delay);
        let ended = self.outages.up_for(Instant::now(), long, first);
        self.port_back(ended);
    }

    fn port_back(&self, ended: Option<Recovery>) {
        if let Some(Recovery { outage, down_for }) = ended {
            let device = &self.current.settings.device;
            let (failed, unserved) = (outage.failed_opens, outage.unserved);
            let metrics = &self.handle.metrics;
            metrics.port_back(device, down_for, failed, unserved);
        }
    }

    /// The line's master on a freshly opened `port`, configured. A slave that may still answer a
    /// request of before the port was lost keeps its late-reply window; a device server's line
    /// is kept quiet a while first, since what its converter held while nobody was connected
    /// comes at once.
    /// `connect_delay` after a connect, as a device may need, comes on top. A Modbus TCP
    /// device's connection carries nothing of an earlier one, so it needs neither.
    fn master_on(&mut self, port: Port) -> LineMaster<Port> {
        let derived = &self.current.derived;
        let serial = derived.framing.broadcasts();
        let mut master = LineMaster::new(port, derived.framing, derived.timing);
        self.current.configure(&mut master);
        for (slave, until) in self.windows_at_loss.drain(..).filter(|_| serial) {
            master.expect_late_reply(slave, until);
        }
        if let Some((_, budget, _)) = master.port().link() {
            let settle = if serial {
                budget + CONNECT_SETTLE
            } else {
                Duration::ZERO
            };
            let delay = self.current.settings.connect_delay;
            master.keep_quiet_until(Instant::now() + settle.max(delay));
        }
        master
    }

    /// Open the configured device, showing a heartbeat meanwhile (a connect to a device server
    /// takes a while): ends early on a stop, or on a new configuration that names another device.
    async fn open(&mut self, stopping: &mut Stopping) -> Opening {
        let device = self.current.device.clone();
        let framing = self.current.derived.framing;
        let listening = self.handle.shadow.is_some();
        let opening = async move {
            if listening {
                device.open_to_listen(framing).await
            } else {
                device.open_for(framing).await
            }
        };
        let mut opening = pin!(opening);
        loop {
            self.handle.beat();
            tokio::select! {
                biased;
                _ = stopping.requested() => {
                    self.handle.attempted.notify_one();
                    return Opening::Stopped;
                }
                () = self.updates.changed() => {
                    if self.take_update() == Some(true) {
                        return Opening::Reopen;
                    }
                }
                opened = &mut opening => return Opening::Done(opened),
                () = sleep(HEARTBEAT) => {}
            }
        }
    }

    /// Read the USB adapter's latency timer, set it if configured, and report it.
    fn adjust_latency_timer(&self) {
        let device = &self.current.device;
        if let (Some(path), Some(driver)) = (device.path(), device.driver()) {
            let timer = latency::adjust(Path::new(SYSFS), Path::new(path), driver.latency_timer);
            let found = timer.as_ref().map(|t| (t.value, t.file.as_path()));
            let refused = timer.as_ref().and_then(|t| t.refused.as_ref());
            self.handle
                .metrics
                .latency_timer(path, &driver.key, found, refused);
        }
    }

    /// Stopped: nothing more is queued, and what was gets 0x0A.
    fn finish(&mut self) {
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
    /// until `until`, a new configuration or a stop.
    async fn refuse_until(&mut self, until: Instant, stopping: &mut Stopping) -> Waited {
        for job in self.handle.queue.drain() {
            self.handle.answer(job, Err(RequestError::PortDown));
        }
        loop {
            self.handle.beat();
            if self.take_update().is_some() {
                return Waited::Reopen;
            }
            tokio::select! {
                biased;
                _ = stopping.requested() => return Waited::Stopped,
                () = self.updates.changed() => {}
                job = self.handle.queue.pop() => {
                    self.handle.answer(job, Err(RequestError::PortDown));
                }
                () = coarse_sleep_until(until) => return Waited::TryAgain,
                () = sleep(HEARTBEAT) => {}
            }
        }
    }
}
