//! A running bus's settings and how new ones reach it: the gateway sends a [`Reconfigure`]
//! through [`BusUpdates`]; the task takes it between transactions, reopening the port only when
//! the device or its serial format, the framing or `max_in_flight` changed. Also what the task
//! derives from its settings, the longest one transaction can take among them.

use super::device::net::MAX_LINK_BUDGET;
use super::device::{Device, Port};
use super::{BusHandle, Intake, HEARTBEAT, STALL_MARGIN};
use crate::config;
use crate::line::{Framing, ReplyForm};
use crate::line::{LineMaster, MasterTiming};
use std::sync::PoisonError;
use std::time::Duration;
use tokio::sync::watch;
use tracing::info;

/// A running bus's new configuration: its settings and the device they name.
#[derive(Clone)]
pub(crate) struct Reconfigure {
    pub settings: config::Bus,
    pub device: Device,
}

/// The gateway's side of a running bus: where new configurations go.
pub(crate) struct BusUpdates(watch::Sender<Option<Reconfigure>>);

impl BusUpdates {
    /// Apply `update` between transactions. Returns whether the port will be reopened (its
    /// device or serial format changed); otherwise the new settings apply on the open port.
    pub(crate) fn send(&self, update: Reconfigure) -> bool {
        let reopen = self
            .0
            .borrow()
            .as_ref()
            .is_none_or(|current| needs_reopen(&current.device, &current.settings, &update));
        self.0.send_replace(Some(update));
        reopen
    }
}

/// Whether going from `current` to `update` takes the port closed and opened again: another
/// device or format, another framing, or another `max_in_flight` (one request at a time and
/// pipelining are two ways of serving a connection).
fn needs_reopen(device: &Device, settings: &config::Bus, update: &Reconfigure) -> bool {
    !device.same_as(&update.device)
        || settings.framing != update.settings.framing
        || settings.max_in_flight != update.settings.max_in_flight
}

/// The longest one transaction on a bus with `settings` can take: the gap before its frame,
/// which stray bytes may hold busy for as long as a response timeout, then the longest response
/// timeout, two longest frames, the RS-485 delays around the request, a device server's link and
/// packing timer (twice: the request's way and the reply's), the silence that ends a reply and a
/// broadcast's turnaround.
/// Whoever waits for a transaction to end adds its own margin to this.
pub(crate) fn longest_transaction(settings: &config::Bus) -> Duration {
    Derived::of(settings).longest_transaction(settings.turnaround_delay)
}

/// Response timeout per slave address, overrides applied.
fn timeouts(settings: &config::Bus) -> Box<[Duration; 256]> {
    let mut timeouts = Box::new([settings.response_timeout; 256]);
    for slave in &settings.slave {
        if let Some(timeout) = slave.response_timeout {
            timeouts[usize::from(slave.address)] = timeout;
        }
    }
    timeouts
}

/// What the bus task derives from its settings.
pub(super) struct Derived {
    pub(super) framing: Framing,
    pub(super) timing: MasterTiming,
    /// Response timeout per slave address, overrides applied.
    pub(super) timeouts: Box<[Duration; 256]>,
    /// Per slave address: its reads' answers are cached (`cache`).
    pub(super) cached: Box<[bool; 256]>,
    /// The longest the task may legitimately go between heartbeats: one transaction, or an
    /// idle heartbeat.
    pub(super) stall_limit: Duration,
    pub(super) down: super::health::DownPolicy,
    /// What the RS-485 direction control adds around each frame sent.
    driver_delays: Duration,
    /// Behind a device server: the most the link and the converter's packing timer add to a
    /// frame's time and to its reply's deadline.
    link: Duration,
}

impl Derived {
    pub(super) fn of(settings: &config::Bus) -> Derived {
        let mut derived = Derived {
            framing: settings.framing,
            timing: settings.master_timing(),
            timeouts: timeouts(settings),
            cached: Box::new(std::array::from_fn(|address| {
                settings
                    .slave
                    .iter()
                    .any(|s| usize::from(s.address) == address && !s.cache.is_zero())
            })),
            stall_limit: Duration::ZERO,
            driver_delays: settings.rs485.delay_before_send + settings.rs485.delay_after_send,
            link: if settings.transport().is_network() {
                MAX_LINK_BUDGET + settings.packing_delay
            } else {
                Duration::ZERO
            },
            down: super::health::DownPolicy {
                // A listen line sends no probes: a slave is answering or not, never left alone.
                after: if settings.mode == config::BusMode::Listen {
                    0
                } else {
                    settings.slave_down_after
                },
                probe_interval: settings.slave_probe_interval,
            },
        };
        derived.stall_limit =
            HEARTBEAT + derived.longest_transaction(settings.turnaround_delay) + STALL_MARGIN;
        derived
    }

    /// The longest response timeout of any slave on the line.
    pub(super) fn longest_timeout(&self) -> Duration {
        self.timeouts.iter().copied().max().unwrap_or_default()
    }

    fn longest_transaction(&self, turnaround: Duration) -> Duration {
        let longest_timeout = self.longest_timeout();
        let longest_frame = self.timing.line.frame_time(self.framing.max_frame_len());
        longest_timeout * 2
            + longest_frame * 2
            + self.driver_delays
            + self.link * 2
            + self.timing.silence
            + turnaround
    }
}

/// The settings the task runs with, what it derives from them, and the device they name.
pub(super) struct Current {
    pub(super) settings: config::Bus,
    pub(super) derived: Derived,
    pub(super) device: Device,
}

impl Current {
    pub(super) fn new(settings: config::Bus, device: Device) -> Self {
        Current {
            derived: Derived::of(&settings),
            settings,
            device,
        }
    }

    /// Take `update`, and pass on what others read of it through `handle`. Returns whether the
    /// port must be reopened.
    pub(super) fn apply(&mut self, mut update: Reconfigure, handle: &BusHandle) -> bool {
        // A line's mode is its task's for life (a change takes a restart).
        update.settings.mode = self.settings.mode;
        let reopen = needs_reopen(&self.device, &self.settings, &update);
        self.derived = Derived::of(&update.settings);
        *handle
            .heartbeat
            .stall_limit
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = self.derived.stall_limit;
        *handle.intake.lock().unwrap_or_else(PoisonError::into_inner) =
            Intake::of(&update.settings);
        handle.queue.set_capacity(update.settings.queue_depth);
        handle.metrics.reconfigured(&update.settings);
        info!(bus = &*handle.name, reopen, "bus reconfigured");
        self.settings = update.settings;
        self.device = update.device;
        reopen
    }

    /// Set the master's timing and reply forms from the settings.
    pub(super) fn configure(&self, master: &mut LineMaster<Port>) {
        master.set_timing(self.derived.timing);
        master.set_echo(self.settings.rs485.echo);
        master.set_match_transaction(self.settings.match_transaction_id);
        for address in 0..=u8::MAX {
            master.set_reply_form(address, ReplyForm::Standard);
        }
        for slave in self.settings.slave.iter().filter(|s| s.wide_read_count) {
            master.set_reply_form(slave.address, ReplyForm::WideReadCount);
        }
    }
}

/// The task's side of the updates channel.
pub(super) struct Updates {
    receiver: watch::Receiver<Option<Reconfigure>>,
    /// Kept so that `receiver` never reports a closed channel when nobody reconfigures the bus.
    sender: Option<watch::Sender<Option<Reconfigure>>>,
    /// Whoever reconfigured the bus is gone: stop listening for more.
    closed: bool,
    /// `changed()` has said a new configuration came, and marked it seen.
    pending: bool,
}

impl Updates {
    /// A channel that starts with `first`, already seen.
    pub(super) fn new(first: Reconfigure) -> Self {
        let (sender, mut receiver) = watch::channel(Some(first));
        receiver.borrow_and_update();
        Updates {
            receiver,
            sender: Some(sender),
            closed: false,
            pending: false,
        }
    }

    /// The gateway's side; the first call takes it, later ones get a channel nobody reads.
    pub(super) fn sender(&mut self) -> BusUpdates {
        BusUpdates(self.sender.take().unwrap_or_else(|| watch::channel(None).0))
    }

    /// A new configuration, if one came since the last look.
    pub(super) fn take(&mut self) -> Option<Reconfigure> {
        let pending = std::mem::take(&mut self.pending);
        if !pending && !self.receiver.has_changed().unwrap_or(false) {
            return None;
        }
        self.receiver.borrow_and_update().clone()
    }

    /// Wait until a new configuration comes (then [`Updates::take`] has it), or forever once
    /// the sending side is gone. Cancel-safe.
    pub(super) async fn changed(&mut self) {
        if self.closed {
            return std::future::pending().await;
        }
        match self.receiver.changed().await {
            Ok(()) => self.pending = true,
            Err(_) => self.closed = true,
        }
    }
}
