//! The metrics of one bus and the events of its line that log and count from one call site: a
//! transaction's round trip and retries, a slave's state as `bus::health` reports it, a port
//! opened, lost or failing to open, what went over the line.

use super::labels::{decimal, seconds_since_epoch, Fate};
use super::{RequestCounters, BUS_EVENTS};
use crate::config;
use crate::error::{Answer, Outcome, RequestError};
use crate::line::LineCounters;
use prometheus::{
    Counter, Gauge, GaugeVec, Histogram, IntCounter, IntCounterVec, IntGauge, IntGaugeVec,
};
use std::fmt::Display;
use std::sync::{Arc, OnceLock};
use std::time::Duration;
use tracing::{debug, info, warn};

/// A slave's own series.
pub(super) struct SlaveMetrics {
    up: IntGauge,
    last_success: Gauge,
    retries: IntCounter,
}

/// The metrics of one bus, label values resolved once. Shared by its handle and its task.
pub struct BusMetrics {
    pub(super) name: Arc<str>,
    pub(super) queue_capacity: IntGauge,
    /// Seconds per character on the line, to turn bytes into busy time.
    pub(super) char_time: f64,
    pub(super) counters: RequestCounters,
    pub(super) round_trip: Histogram,
    pub(super) queue_wait: Histogram,
    pub(super) busy: Counter,
    pub(super) sent: IntCounter,
    pub(super) received: IntCounter,
    pub(super) discarded_frames: IntCounter,
    pub(super) stray_bytes: IntCounter,
    pub(super) port_up: IntGauge,
    pub(super) port_reopens: IntCounter,
    pub(super) port_open_errors: IntCounter,
    pub(super) retries: IntCounterVec,
    pub(super) slave_up: IntGaugeVec,
    pub(super) slave_last_success: GaugeVec,
    pub(super) slaves: Box<[OnceLock<SlaveMetrics>; 256]>,
}

impl BusMetrics {
    /// No slave's series made yet.
    pub(super) fn no_slaves() -> Box<[OnceLock<SlaveMetrics>; 256]> {
        Box::new(std::array::from_fn(|_| OnceLock::new()))
    }

    /// The addresses whose series have been made.
    pub(super) fn known_slaves(&self) -> impl Iterator<Item = u8> + '_ {
        (0..=u8::MAX).filter(|a| self.slaves[usize::from(*a)].get().is_some())
    }

    fn slave(&self, address: u8) -> &SlaveMetrics {
        self.slaves[usize::from(address)].get_or_init(|| {
            let labels = &[&*self.name, decimal(address)];
            let slave = SlaveMetrics {
                up: self.slave_up.with_label_values(labels),
                last_success: self.slave_last_success.with_label_values(labels),
                retries: self.retries.with_label_values(labels),
            };
            slave.up.set(0);
            slave
        })
    }

    /// The bus's settings, at start or after a reload: its queue capacity, and series at zero for
    /// its known slaves (`[[bus.slave]]` and simulated ones).
    pub fn reconfigured(&self, settings: &config::Bus) {
        self.queue_capacity
            .set(i64::try_from(settings.queue_depth).unwrap_or(i64::MAX));
        let sim_slaves = settings.sim_slave.iter().flat_map(|s| s.address.iter());
        for address in settings.slave.iter().map(|s| s.address).chain(sim_slaves) {
            self.slave(address);
        }
    }

    /// Count a request's outcome; `None` if it was dropped unsent because its master left.
    pub fn request(&self, slave: u8, function: u8, outcome: Option<&Outcome>) {
        self.counters.count(&self.name, slave, function, outcome);
    }

    /// The line took a request after it waited `wait` in the queue.
    pub fn dequeued(&self, wait: Duration) {
        self.queue_wait.observe(wait.as_secs_f64());
    }

    /// The line ran a request to `slave`: its round trip (`None` if it never got on the wire),
    /// how many attempts it took, and how it ended.
    pub fn transaction(
        &self,
        slave: u8,
        attempts: u32,
        round_trip: Option<Duration>,
        outcome: &Outcome,
    ) {
        if let Some(round_trip) = round_trip {
            self.round_trip.observe(round_trip.as_secs_f64());
        }
        let metrics = self.slave(slave);
        metrics
            .retries
            .inc_by(u64::from(attempts.saturating_sub(1)));
        if let Ok(Answer::Reply(_) | Answer::Malformed(_)) = outcome {
            metrics.last_success.set(seconds_since_epoch());
        }
    }

    /// `slave` answered validly, for the first time or `again` after failing or being down
    /// (`bus::health` decides).
    pub fn slave_answering(&self, slave: u8, again: bool) {
        self.slave(slave).up.set(1);
        if again {
            info!(target: BUS_EVENTS, bus = &*self.name, slave, "slave answering again");
        }
    }

    /// `slave` stopped giving valid replies with the transaction that ended in `outcome`.
    pub fn slave_failing(&self, slave: u8, outcome: &Outcome) {
        self.slave(slave).up.set(0);
        let bus = &*self.name;
        let label = Fate::of(outcome).0.label();
        if let Err(error @ RequestError::NoResponse { attempts, .. }) = outcome {
            warn!(target: BUS_EVENTS, bus, slave, attempts, outcome = label, %error, "slave gives no valid reply");
        }
    }

    /// `slave` timed out `timeouts` times in a row: its requests are answered 0x0B unsent (and
    /// counted `slave_down`) but for one probe per `probe_interval`.
    pub fn slave_down(&self, slave: u8, timeouts: u32, probe_interval: Duration) {
        self.slave(slave).up.set(0);
        let bus = &*self.name;
        let probe_interval = humantime::format_duration(probe_interval).to_string();
        warn!(target: BUS_EVENTS, bus, slave, timeouts, probe_interval, "slave down; answering 0x0B without sending, probing once per interval");
    }

    /// What went over the line since the last call.
    pub fn line(&self, traffic: &LineCounters) {
        self.sent.inc_by(traffic.sent_bytes);
        self.received.inc_by(traffic.received_bytes);
        self.discarded_frames.inc_by(traffic.foreign_frames);
        self.stray_bytes.inc_by(traffic.stray_bytes);
        let characters = traffic.sent_bytes + traffic.received_bytes;
        self.busy.inc_by(characters as f64 * self.char_time);
    }

    /// The port is open: for the first time (`down` is `None`), or again after `down` (how long,
    /// and how many opens failed meanwhile).
    pub fn port_opened(&self, device: &str, down: Option<(Duration, u32)>) {
        let bus = &*self.name;
        match down {
            None => info!(target: BUS_EVENTS, bus, device, "serial port open"),
            Some((down_for, failed_opens)) => {
                self.port_reopens.inc();
                info!(target: BUS_EVENTS,
                    bus,
                    device,
                    failed_opens,
                    down_s = down_for.as_secs_f64(),
                    "serial port reopened"
                );
            }
        }
        self.port_up.set(1);
    }

    pub fn port_lost(&self, device: &str, error: &dyn Display) {
        self.port_up.set(0);
        warn!(target: BUS_EVENTS, bus = &*self.name, device, %error, "serial port lost; answering 0x0A and reopening");
    }

    /// An open failed; only the first failure of an outage is logged above debug level.
    pub fn open_failed(&self, device: &str, error: &dyn Display, first: bool) {
        self.port_open_errors.inc();
        let bus = &*self.name;
        if first {
            warn!(target: BUS_EVENTS, bus, device, %error, "cannot open serial port; answering 0x0A and retrying");
        } else {
            debug!(target: BUS_EVENTS, bus, device, %error, "serial port still cannot be opened");
        }
    }
}
