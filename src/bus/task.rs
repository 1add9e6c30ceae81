//! The bus task's life: open the port, serve it until it is lost or a new device is configured,
//! answer 0x0A while it is down and reopen it with backoff, and once stopped answer whatever is
//! still queued.

use super::device::net::Dropped;
use super::device::serial::latency::{self, SYSFS};
use super::health::Health;
use super::reconfigure::{Current, Updates};
use super::{
    BusHandle, BusUpdates, Device, FairQueue, Heartbeat, Intake, Port, Reconfigure, HEARTBEAT,
};
use crate::config;
use crate::error::RequestError;
use crate::line::LineMaster;
use crate::metrics::Metrics;
use crate::shutdown::Stopping;
use crate::trace::BusTap;
use std::io;
use std::path::Path;
use std::pin::pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;
use tokio::time::{sleep, sleep_until, Instant};
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
        };
        BusTask {
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
        let metrics = self.handle.metrics.clone();
        let mut delay = self.current.settings.reopen_delay;
        // Since when the port is down, and how many opens have failed since.
        let mut down_since: Option<(Instant, u32)> = None;
        loop {
            let opened = match self.open(&mut stopping).await {
                Opening::Done(opened) => opened,
                Opening::Stopped => break,
                Opening::Reopen => continue,
            };
            self.set_up(opened.is_ok());
            self.handle.attempted.notify_one();
            let device = &self.current.settings.device;
            match opened {
                Ok(port) => {
                    let down = down_since
                        .take()
                        .map(|(since, failed_opens)| (since.elapsed(), failed_opens));
                    metrics.port_opened(device, down);
                    metrics.link(port.link());
                    self.adjust_latency_timer();
                    self.told_wrong_mode = false;
                    self.told_mismatch = false;
                    delay = self.current.settings.reopen_delay;
                    let pipelined = self.current.settings.max_in_flight > 1;
                    let end = if pipelined {
                        self.serve_pipelined(port, &mut stopping).await
                    } else {
                        let master = self.master_on(port);
                        self.serve(master, &mut stopping).await
                    };
                    self.set_up(false);
                    match end {
                        Served::Lost(error) => {
                            let dropped = Dropped::of(&error);
                            metrics.port_lost(&self.current.settings.device, &error, dropped);
                        }
                        Served::Stopped => break,
                        // Straight to the new device, as a first open.
                        Served::Reopen => {
                            metrics.link(None);
                            continue;
                        }
                    }
                    down_since = Some((Instant::now(), 0));
                }
                Err(error) => {
                    metrics.open_failed(device, &error, down_since.is_none());
                    let (_, failed_opens) = down_since.get_or_insert((Instant::now(), 0));
                    *failed_opens += 1;
                }
            }
            match self
                .refuse_until(Instant::now() + delay, &mut stopping)
                .await
            {
                Waited::Stopped => break,
                Waited::Reopen => {
                    delay = self.current.settings.reopen_delay;
                    continue;
                }
                Waited::TryAgain => {}
            }
            delay = (delay * 2).min(self.current.settings.reopen_delay_max);
        }
        self.finish();
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
        let opening = device.open_for(self.current.derived.framing);
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
                () = sleep_until(until) => return Waited::TryAgain,
                () = sleep(HEARTBEAT) => {}
            }
        }
    }
}
