//! The metrics of one bus and the events of its line that log and count from one call site: a
//! transaction's round trip and retries, a slave's state as `bus::health` reports it, a port
//! opened, lost or failing to open, what went over the line. Its series' families are defined in
//! `families`; what it reports of a device server's link and a USB adapter is in `link`.

mod families;
mod link;
mod observed;

pub(super) use families::BusFamilies;
use link::LinkSnapshot;
pub(crate) use observed::Discarded;
use observed::ObservedFamilies;

use super::labels::{decimal, seconds_since_epoch, Fate, LinkDrop, OTHER};
use super::{RequestCounters, BUS_EVENTS};
use crate::config;
use crate::error::{Answer, Outcome, RequestError};
use crate::line::LineCounters;
use crate::master::{Class, Protocol};
use prometheus::core::Collector;
use prometheus::{
    Counter, Gauge, GaugeVec, Histogram, IntCounter, IntCounterVec, IntGauge, IntGaugeVec,
};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tracing::{debug, info, warn};

/// Round trips kept per slave for the status page's median.
const RECENT_ROUND_TRIPS: usize = 32;

/// A slave's own series, and its last round trips.
pub(super) struct SlaveMetrics {
    up: IntGauge,
    last_success: Gauge,
    retries: IntCounter,
    coalesced: IntCounter,
    cache_hits: IntCounter,
    round_trips: Mutex<VecDeque<Duration>>,
    /// The gateway's polls of its plant values, for the status page.
    pub(super) polls: AtomicU64,
}

/// What the status page shows of a slave, as its metrics have it.
pub struct SlaveSnapshot {
    pub address: u8,
    pub up: bool,
    /// Its last answer, normal or exception.
    pub last_answer: Option<SystemTime>,
    pub(crate) round_trip_p50: Option<Duration>,
    /// Its requests by outcome label.
    pub requests: BTreeMap<String, u64>,
    /// The gateway's own polls of its plant values.
    pub polls: u64,
}

/// The metrics of one bus, label values resolved once. Shared by its handle and its task.
pub struct BusMetrics {
    pub(super) name: Arc<str>,
    pub(super) info: IntGaugeVec,
    /// The framing, format and transport labels of the bus's info series, to remove when they
    /// change.
    pub(super) info_labels: Mutex<Option<[String; 4]>>,
    pub(super) queue_capacity: IntGauge,
    /// Seconds per character on the line, to turn bytes into busy time.
    pub(super) char_time: f64,
    pub(super) counters: RequestCounters,
    pub(super) round_trip: Histogram,
    /// Per class, in the order of [`Class::ALL`].
    pub(super) queue_wait: [Histogram; 3],
    pub(super) busy: Counter,
    pub(super) sent: IntCounter,
    pub(super) received: IntCounter,
    pub(super) discarded_frames: IntCounter,
    pub(super) stray_bytes: IntCounter,
    pub(super) port_up: IntGauge,
    pub(super) port_reopens: IntCounter,
    pub(super) port_open_errors: IntCounter,
    pub(super) link_dropped: IntCounterVec,
    pub(super) latency_timer: GaugeVec,
    pub(super) link_round_trip: GaugeVec,
    pub(super) link_budget: GaugeVec,
    /// The device server's connection as last reported, for the status page.
    pub(super) link: Mutex<Option<LinkSnapshot>>,
    /// The line is behind a device server: its port events are told as connections.
    pub(super) network: AtomicBool,
    pub(super) retries: IntCounterVec,
    pub(super) coalesced: IntCounterVec,
    pub(super) cache_hits: IntCounterVec,
    pub(super) slave_up: IntGaugeVec,
    pub(super) slave_last_success: GaugeVec,
    pub(super) polls: IntCounterVec,
    pub(super) poll_errors: IntCounterVec,
    pub(super) slaves: Box<[OnceLock<SlaveMetrics>; 256]>,
    /// What a listen-only line hears.
    pub(super) observed: ObservedFamilies,
}

impl BusMetrics {
    /// No slave's series made yet.
    pub(super) fn no_slaves() -> Box<[OnceLock<SlaveMetrics>; 256]> {
        Box::new(std::array::from_fn(|_| OnceLock::new()))
    }

    /// The addresses whose series have been made: the known slaves.
    pub(super) fn known_slaves(&self) -> impl Iterator<Item = u8> + '_ {
        (0..=u8::MAX).filter(|a| self.is_known(*a))
    }

    /// A slave is known once it is configured (`[[bus.slave]]`, simulated) or has answered: only
    /// known slaves have series of their own and their address as a label value, so a master
    /// asking every unit id makes no series for the addresses where nobody answers.
    fn is_known(&self, address: u8) -> bool {
        self.slaves[usize::from(address)].get().is_some()
    }

    /// The `slave` label of requests to `address`: the address of a known slave or of the
    /// broadcast, else `other`.
    fn slave_label(&self, address: u8) -> &'static str {
        if address == crate::line::BROADCAST || self.is_known(address) {
            decimal(address)
        } else {
            OTHER
        }
    }

    /// The series of `address` if it is a known slave.
    pub(super) fn known(&self, address: u8) -> Option<&SlaveMetrics> {
        self.slaves[usize::from(address)].get()
    }

    /// The series of `address`, made now if it was not known.
    fn slave(&self, address: u8) -> &SlaveMetrics {
        self.slaves[usize::from(address)].get_or_init(|| {
            let labels = &[&*self.name, decimal(address)];
            let slave = SlaveMetrics {
                up: self.slave_up.with_label_values(labels),
                last_success: self.slave_last_success.with_label_values(labels),
                retries: self.retries.with_label_values(labels),
                coalesced: self.coalesced.with_label_values(labels),
                cache_hits: self.cache_hits.with_label_values(labels),
                round_trips: Mutex::new(VecDeque::with_capacity(RECENT_ROUND_TRIPS)),
                polls: AtomicU64::new(0),
            };
            slave.up.set(0);
            slave
        })
    }

    /// The bus's settings, at start or after a reload: its queue capacity, and series at zero for
    /// its known slaves (`[[bus.slave]]` and simulated ones).
    pub fn reconfigured(&self, settings: &config::Bus) {
        let transport = settings.transport();
        self.network
            .store(transport.is_network(), Ordering::Relaxed);
        for reason in LinkDrop::ALL
            .into_iter()
            .filter(|r| r.transport() == transport)
        {
            self.link_dropped
                .with_label_values(&[&*self.name, reason.label()]);
        }
        self.set_info(Some([
            settings.framing.name().to_owned(),
            settings.format_label(),
            transport.label().to_owned(),
            settings.mode.name().to_owned(),
        ]));
        if settings.mode == config::BusMode::Listen {
            self.observed.start(&self.name);
        }
        self.queue_capacity
            .set(i64::try_from(settings.queue_depth).unwrap_or(i64::MAX));
        let sim_slaves = settings.sim_slave.iter().flat_map(|s| s.address.iter());
        for address in settings.slave.iter().map(|s| s.address).chain(sim_slaves) {
            self.slave(address);
        }
    }

    /// Replace the bus's info series with one of `labels` (framing, format, transport, mode), or
    /// none.
    fn set_info(&self, labels: Option<[String; 4]>) {
        let mut current = self
            .info_labels
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if *current == labels {
            return;
        }
        if let Some([framing, format, transport, mode]) = current.take() {
            let _ =
                self.info
                    .remove_label_values(&[&*self.name, &framing, &format, &transport, &mode]);
        }
        if let Some([framing, format, transport, mode]) = &labels {
            self.info
                .with_label_values(&[&*self.name, framing, format, transport, mode])
                .set(1);
        }
        *current = labels;
    }

    /// Count a request's outcome; `None` if it was dropped unsent because its master left.
    pub fn request(&self, slave: u8, function: u8, protocol: Protocol, outcome: Option<&Outcome>) {
        let slave = self.slave_label(slave);
        self.counters
            .count(&self.name, slave, function, protocol, outcome);
    }

    /// The line took a request after it waited `wait` in the queue; `priority` if it came from
    /// a master in `server.priority`.
    pub(crate) fn dequeued(&self, wait: Duration, class: Class) {
        self.queue_wait[class.index()].observe(wait.as_secs_f64());
    }

    /// A read to `slave` joined another master's identical one.
    pub fn coalesced(&self, slave: u8) {
        if let Some(slave) = self.known(slave) {
            slave.coalesced.inc();
        }
    }

    /// A read to `slave` was answered from its cache.
    pub(crate) fn cache_hit(&self, slave: u8) {
        if let Some(slave) = self.known(slave) {
            slave.cache_hits.inc();
        }
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
        // An answer makes the slave known; a request nobody answered makes no series.
        let answered = matches!(outcome, Ok(Answer::Reply(_) | Answer::Malformed(_)));
        let metrics = if answered {
            self.slave(slave)
        } else {
            match self.known(slave) {
                Some(metrics) => metrics,
                None => return,
            }
        };
        if let Some(round_trip) = round_trip {
            let mut recent = metrics
                .round_trips
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            if recent.len() == RECENT_ROUND_TRIPS {
                recent.pop_front();
            }
            recent.push_back(round_trip);
        }
        metrics
            .retries
            .inc_by(u64::from(attempts.saturating_sub(1)));
        if answered {
            metrics.last_success.set(seconds_since_epoch());
        }
    }

    /// `slave` answered validly, for the first time or `again` after failing or being down
    /// (`bus::health` decides).
    pub(crate) fn slave_answering(&self, slave: u8, again: bool) {
        self.slave(slave).up.set(1);
        if again {
            info!(target: BUS_EVENTS, bus = &*self.name, slave, "slave answering again");
        }
    }

    /// `slave` stopped giving valid replies with the transaction that ended in `outcome`.
    /// Logged at warn for a known slave; an address nobody has answered at is only a master's
    /// guess, logged at debug.
    pub(crate) fn slave_failing(&self, slave: u8, outcome: &Outcome) {
        let bus = &*self.name;
        let label = Fate::of(outcome).0.label();
        let Some(metrics) = self.known(slave) else {
            debug!(target: BUS_EVENTS, bus, slave, outcome = label, "no valid reply at an address no slave has answered at");
            return;
        };
        metrics.up.set(0);
        if let Err(error @ RequestError::NoResponse { attempts, .. }) = outcome {
            warn!(target: BUS_EVENTS, bus, slave, attempts, outcome = label, %error, "slave gives no valid reply");
        }
    }

    /// `slave` timed out `timeouts` times in a row: its requests are answered 0x0B unsent (and
    /// counted `slave_down`) but for one probe per `probe_interval`. Logged at warn for a known
    /// slave, at debug for an address nobody has answered at.
    pub(crate) fn slave_down(&self, slave: u8, timeouts: u32, probe_interval: Duration) {
        let bus = &*self.name;
        let probe_interval = humantime::format_duration(probe_interval).to_string();
        let Some(metrics) = self.known(slave) else {
            debug!(target: BUS_EVENTS, bus, slave, timeouts, probe_interval, "no slave answers at this address; answering 0x0B without sending, probing once per interval");
            return;
        };
        metrics.up.set(0);
        warn!(target: BUS_EVENTS, bus, slave, timeouts, probe_interval, "slave down; answering 0x0B without sending, probing once per interval");
    }

    /// Seconds characters were on the line since the bus started.
    pub(crate) fn busy_seconds(&self) -> f64 {
        self.busy.get()
    }

    /// Transactions on the line since the bus started.
    pub fn transactions(&self) -> u64 {
        self.round_trip.get_sample_count()
    }

    /// Every known slave (configured, simulated, or that has answered), by address, as its series and
    /// recent round trips have it.
    pub fn slaves(&self) -> Vec<SlaveSnapshot> {
        let mut requests = self.requests_by_slave();
        self.known_slaves()
            .filter_map(|address| {
                let slave = self.slaves[usize::from(address)].get()?;
                let last = slave.last_success.get();
                let round_trips = slave
                    .round_trips
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner);
                Some(SlaveSnapshot {
                    address,
                    up: slave.up.get() == 1,
                    last_answer: (last > 0.0).then(|| UNIX_EPOCH + Duration::from_secs_f64(last)),
                    round_trip_p50: super::median::median(round_trips.iter().copied()),
                    requests: requests.remove(&address).unwrap_or_default(),
                    polls: slave.polls.load(Ordering::Relaxed),
                })
            })
            .collect()
    }

    /// This bus's request counts by slave and outcome, summed over functions and protocols.
    fn requests_by_slave(&self) -> HashMap<u8, BTreeMap<String, u64>> {
        let mut by_slave: HashMap<u8, BTreeMap<String, u64>> = HashMap::new();
        for family in self.counters.requests.collect() {
            for metric in family.get_metric() {
                let label = |name: &str| {
                    metric
                        .get_label()
                        .iter()
                        .find(|pair| pair.name() == name)
                        .map(|pair| pair.value())
                };
                if label("bus") != Some(&*self.name) {
                    continue;
                }
                let (Some(Ok(slave)), Some(outcome)) =
                    (label("slave").map(str::parse::<u8>), label("outcome"))
                else {
                    continue;
                };
                // Counters hold whole numbers.
                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                let count = metric.get_counter().get_value() as u64;
                *by_slave
                    .entry(slave)
                    .or_default()
                    .entry(outcome.to_owned())
                    .or_default() += count;
            }
        }
        by_slave
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
}
