//! The publisher: what goes to the broker and when. A value is published when it changed by
//! more than its deadband (any change with none) since it was last published, and again at
//! least every `publish_interval`; a value whose poll failed publishes nothing, and its slave's
//! availability turns `offline`. What waits for the broker is one message per topic, the newest
//! (an older one replaced unsent is counted `dropped`), so the broker down or slow costs a
//! bounded memory and the buses never wait for it. At every connection everything is published
//! anew: the status, the discovery configs, every value and availability.

use super::catalogue::Catalogue;
use super::link::{self, FromBroker};
use super::set::{self, Set};
use crate::config::Mqtt;
use crate::dispatch::Client;
use crate::metrics::{MqttMessage, MqttMetrics};
use crate::net::server::Shared;
use crate::values::{Sample, Store};
use rumqttc::{AsyncClient, Publish, QoS};
use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, watch};
use tokio::time::Instant;
use tracing::debug;

/// The least time between two looks at the store: polls ending close together are published
/// together.
const SCAN_GAP: Duration = Duration::from_millis(50);
/// How soon a message the client could not take yet is offered again.
const RETRY: Duration = Duration::from_millis(20);
/// A set's result waiting to be published.
const RESULTS: usize = 64;

/// One message per topic, the newest, in the order the topics first waited.
#[derive(Default)]
pub(super) struct Outbox {
    order: VecDeque<Arc<str>>,
    waiting: HashMap<Arc<str>, (String, bool)>,
}

impl Outbox {
    /// `payload` to wait for the broker at `topic`, retained or not; `true` if it replaced an
    /// unsent one.
    pub(super) fn put(&mut self, topic: Arc<str>, payload: String, retain: bool) -> bool {
        match self.waiting.insert(topic.clone(), (payload, retain)) {
            Some(_) => true,
            None => {
                self.order.push_back(topic);
                false
            }
        }
    }

    pub(super) fn len(&self) -> usize {
        self.order.len()
    }

    /// Forget, unsent and uncounted, every message `keep` says no to.
    fn keep(&mut self, keep: impl Fn(&str, &str) -> bool) {
        self.waiting
            .retain(|topic, (payload, _)| keep(topic, payload));
        let waiting = &self.waiting;
        self.order.retain(|topic| waiting.contains_key(topic));
    }

    /// Hand the waiting messages to `send` in order, until it takes no more.
    fn drain(&mut self, mut send: impl FnMut(&str, &str, bool) -> bool) {
        while let Some(topic) = self.order.front() {
            let Some((payload, retain)) = self.waiting.get(topic) else {
                self.order.pop_front();
                continue;
            };
            if !send(topic, payload, *retain) {
                return;
            }
            let topic = self.order.pop_front().expect("a front");
            self.waiting.remove(&topic);
        }
    }
}

/// Whether a value now `value`, last published as `last` (value and when), is due for
/// publishing at `now`.
pub(super) fn due(
    deadband: f64,
    last: Option<(f64, Instant)>,
    value: f64,
    now: Instant,
    interval: Duration,
) -> bool {
    let Some((was, at)) = last else {
        return true;
    };
    let changed = if deadband > 0.0 {
        (value - was).abs() > deadband
    } else {
        value != was
    };
    changed || now.duration_since(at) >= interval
}

/// What was said of each of `now`'s topics, carried from `said` of the same topic among
/// `before`'s; `None` for a topic that is new.
fn carried<T: Copy>(before: &[Arc<str>], said: &[Option<T>], now: &[Arc<str>]) -> Vec<Option<T>> {
    let said: HashMap<&Arc<str>, Option<T>> = before.iter().zip(said.iter().copied()).collect();
    now.iter()
        .map(|topic| said.get(topic).copied().flatten())
        .collect()
}

/// A value's payload: the plain decimal number (0 or 1 for a bit).
pub(super) fn payload(value: f64, is_bool: bool) -> String {
    if is_bool {
        return if value != 0.0 { "1" } else { "0" }.to_owned();
    }
    if value == 0.0 {
        return "0".to_owned();
    }
    format!("{value}")
}

/// What the publisher is made of, besides its state.
pub(super) struct Parts {
    pub(super) settings: Mqtt,
    pub(super) client: AsyncClient,
    pub(super) store: Arc<Store>,
    pub(super) catalogues: watch::Receiver<Arc<Catalogue>>,
    pub(super) shared: Arc<Shared>,
    pub(super) master: Arc<Client>,
    pub(super) metrics: MqttMetrics,
}

struct Publisher {
    parts: Parts,
    qos: QoS,
    catalogue: Arc<Catalogue>,
    connected: bool,
    outbox: Outbox,
    /// Per value: what was last published, and when.
    last: Vec<Option<(f64, Instant)>>,
    /// Per slave: online, offline, or not said yet.
    availability: Vec<Option<bool>>,
    samples: Vec<Sample>,
    results: mpsc::Sender<(Arc<str>, String)>,
    /// When the first value is due again by `publish_interval`.
    next_due: Instant,
}

/// Publish for as long as the gateway runs, hearing the connection on `link`.
pub(super) async fn run(mut parts: Parts, mut link: mpsc::Receiver<FromBroker>) {
    let store = parts.store.clone();
    let mut catalogues = parts.catalogues.clone();
    let catalogue = parts.catalogues.borrow_and_update().clone();
    let (results, mut finished) = mpsc::channel(RESULTS);
    let parts_interval = parts.settings.publish_interval;
    let mut publisher = Publisher {
        qos: link::qos(&parts.settings),
        parts,
        catalogue: Arc::new(Catalogue::empty()),
        connected: false,
        outbox: Outbox::default(),
        last: Vec::new(),
        availability: Vec::new(),
        samples: Vec::new(),
        results,
        next_due: Instant::now() + parts_interval,
    };
    publisher.reconfigure(catalogue);
    let (mut scan_due, mut next_scan) = (true, Instant::now());
    loop {
        let waiting = publisher.connected && publisher.outbox.len() > 0;
        tokio::select! {
            event = link.recv() => match event {
                Some(event) => publisher.heard(event),
                None => return,
            },
            Ok(()) = catalogues.changed() => {
                let catalogue = catalogues.borrow_and_update().clone();
                publisher.reconfigure(catalogue);
                scan_due = true;
            }
            () = store.changed(), if !scan_due => scan_due = true,
            // The first value due again by `publish_interval`, unchanged.
            () = crate::timer::coarse_sleep_until(publisher.next_due), if !scan_due => {
                scan_due = true;
            }
            () = crate::timer::coarse_sleep_until(next_scan), if scan_due => {
                publisher.scan();
                scan_due = false;
                next_scan = Instant::now() + SCAN_GAP;
            }
            Some((topic, result)) = finished.recv() => {
                publisher.put(topic, result, false);
            }
            () = tokio::time::sleep(RETRY), if waiting => {}
        }
        publisher.flush();
    }
}

impl Publisher {
    fn put(&mut self, topic: Arc<str>, payload: String, retain: bool) {
        if self.outbox.put(topic, payload, retain) {
            self.parts.metrics.count(MqttMessage::Dropped, 1);
        }
    }

    /// Hand the client what waits, while connected.
    fn flush(&mut self) {
        if !self.connected {
            return;
        }
        let (client, qos) = (&self.parts.client, self.qos);
        self.outbox.drain(|topic, payload, retain| {
            client
                .try_publish(topic, qos, retain, payload.as_bytes().to_vec())
                .is_ok()
        });
    }

    fn heard(&mut self, event: FromBroker) {
        match event {
            FromBroker::Up => self.up(),
            FromBroker::Down => self.connected = false,
            FromBroker::Message(message) => self.message(&message),
        }
    }

    /// Connected (again): subscribe, and publish everything anew.
    fn up(&mut self) {
        self.connected = true;
        // What the broker is told anew is made again below; a set's result and a removed
        // value's clearing are not: they wait on.
        self.outbox
            .keep(|topic, payload| payload.is_empty() || topic.ends_with("/set/result"));
        let settings = &self.parts.settings;
        let prefix = &settings.topic_prefix;
        let client = &self.parts.client;
        // At most once: a write must never be carried out twice.
        if settings.writes {
            for filter in [
                format!("{prefix}/+/+/+/set"),
                format!("{prefix}/+/+/+/+/set"),
            ] {
                let _ = client.try_subscribe(filter, QoS::AtMostOnce);
            }
        }
        // The broker hands over the retained discovery configs at the subscription; the
        // unsubscription right after it (in order on the connection) spares the gateway the echo
        // of its own configs, and later traffic of other integrations'.
        if settings.home_assistant {
            for component in ["sensor", "binary_sensor"] {
                let filter = format!("{}/{component}/+/+/config", settings.discovery_prefix);
                let _ = client.try_subscribe(filter.clone(), QoS::AtMostOnce);
                let _ = client.try_unsubscribe(filter);
            }
        }
        self.outbox
            .put(self.catalogue.status.clone(), "online".to_owned(), true);
        self.announce();
        self.scan();
    }

    /// Every discovery config, and every value and availability due at the next look.
    fn announce(&mut self) {
        for (topic, config) in &self.catalogue.discovery {
            self.outbox.put(topic.clone(), config.clone(), true);
        }
        self.last.iter_mut().for_each(|l| *l = None);
        self.availability.iter_mut().for_each(|a| *a = None);
    }

    /// Publish what `catalogue` says from now on; clear what the one before published and this
    /// one does not.
    fn reconfigure(&mut self, catalogue: Arc<Catalogue>) {
        let old = std::mem::replace(&mut self.catalogue, catalogue.clone());
        for topic in old.retained.difference(&catalogue.retained) {
            self.put(topic.clone(), String::new(), true);
        }
        // What stays the same keeps what was published of it: a reload that changes nothing
        // publishes nothing.
        let values = |c: &Catalogue| c.values.iter().map(|v| v.topic.clone()).collect::<Vec<_>>();
        let slaves = |c: &Catalogue| {
            c.slaves
                .iter()
                .map(|s| s.availability.clone())
                .collect::<Vec<_>>()
        };
        self.last = carried(&values(&old), &self.last, &values(&catalogue));
        self.availability = carried(&slaves(&old), &self.availability, &slaves(&catalogue));
        if self.connected {
            let before: HashMap<&str, &str> = old
                .discovery
                .iter()
                .map(|(topic, config)| (&**topic, config.as_str()))
                .collect();
            for (topic, config) in &catalogue.discovery {
                if before.get(&**topic) != Some(&config.as_str()) {
                    self.outbox.put(topic.clone(), config.clone(), true);
                }
            }
        }
    }

    /// Look at the store: the values due, the availabilities changed.
    fn scan(&mut self) {
        let generation = self.parts.store.samples(&mut self.samples);
        let catalogue = self.catalogue.clone();
        let now = Instant::now();
        let interval = self.parts.settings.publish_interval;
        if generation != catalogue.generation {
            // The new configuration's catalogue is on its way, and its arrival looks again.
            self.next_due = now + interval;
            return;
        }
        let retain = self.parts.settings.retain;
        let mut failed = vec![false; catalogue.slaves.len()];
        let mut good = vec![false; catalogue.slaves.len()];
        let samples = std::mem::take(&mut self.samples);
        let mut next_due = now + interval;
        for (at, (item, sample)) in catalogue.values.iter().zip(&samples).enumerate() {
            failed[item.owner] |= sample.failed;
            let Some(value) = sample.value else { continue };
            good[item.owner] = true;
            if due(item.deadband, self.last[at], value, now, interval) {
                self.last[at] = Some((value, now));
                self.put(item.topic.clone(), payload(value, item.is_bool()), retain);
            } else if let Some((_, at)) = self.last[at] {
                next_due = next_due.min(at + interval);
            }
        }
        self.samples = samples;
        self.next_due = next_due;
        for (at, slave) in catalogue.slaves.iter().enumerate() {
            let state = if failed[at] {
                Some(false)
            } else {
                good[at].then_some(true)
            };
            if state.is_some() && state != self.availability[at] {
                self.availability[at] = state;
                let said = if state == Some(true) {
                    "online"
                } else {
                    "offline"
                };
                self.put(slave.availability.clone(), said.to_owned(), true);
            }
        }
    }

    /// A message from the broker: a `set`, or a retained discovery config.
    fn message(&mut self, message: &Publish) {
        if message.topic.ends_with("/set") {
            self.set(message);
        } else if message.retain
            && !message.payload.is_empty()
            && self.catalogue.is_ours(&message.topic, &message.payload)
            && !self.catalogue.configs.contains(message.topic.as_str())
        {
            // A value no longer configured: its config is cleared, and Home Assistant drops it.
            self.put(message.topic.as_str().into(), String::new(), true);
        }
    }

    fn set(&mut self, message: &Publish) {
        let metrics = &self.parts.metrics;
        metrics.count(MqttMessage::SetReceived, 1);
        let Some(&at) = self.catalogue.sets.get(&message.topic) else {
            metrics.count(MqttMessage::SetRefused, 1);
            debug!(target: "modbus_gateway::mqtt", topic = %message.topic, "a set for no writable value refused");
            return;
        };
        let item = &self.catalogue.values[at];
        let topic: Arc<str> = format!("{}/result", message.topic).into();
        let dispatcher = &self.parts.shared.dispatcher;
        match set::set(
            dispatcher,
            &self.parts.master,
            item,
            &message.payload,
            message.retain,
        ) {
            Set::Refused(why) => {
                metrics.count(MqttMessage::SetRefused, 1);
                self.put(topic, set::refused(&why), false);
            }
            Set::Sent {
                value,
                rule,
                outcome,
            } => {
                let results = self.results.clone();
                tokio::spawn(async move {
                    let ended = outcome
                        .await
                        .unwrap_or(Err(crate::error::RequestError::ShuttingDown));
                    let result = set::result(value, rule.as_deref(), ended);
                    let _ = results.send((topic, result)).await;
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_value_is_due_when_it_moved_past_its_deadband_or_its_interval_passed() {
        let start = Instant::now();
        let minute = Duration::from_secs(60);
        assert!(due(0.0, None, 1.0, start, minute), "never published");
        let last = Some((50.0, start));
        assert!(!due(0.0, last, 50.0, start, minute), "unchanged");
        assert!(
            due(0.0, last, 50.01, start, minute),
            "any change without a deadband"
        );
        assert!(!due(0.5, last, 50.5, start, minute), "within the deadband");
        assert!(due(0.5, last, 50.51, start, minute), "past it");
        assert!(due(0.5, last, 49.4, start, minute), "past it downwards");
        assert!(
            due(0.5, last, 50.0, start + minute, minute),
            "the interval passed"
        );
    }

    #[test]
    fn payloads_are_plain_decimal_numbers() {
        assert_eq!(payload(50.0, false), "50");
        assert_eq!(payload(0.1 + 0.2, false), "0.30000000000000004");
        assert_eq!(payload(-0.0, false), "0");
        assert_eq!(payload(1e21, false), "1000000000000000000000");
        assert_eq!(payload(1.0, true), "1");
        assert_eq!(payload(0.0, true), "0");
    }

    #[test]
    fn the_outbox_keeps_the_newest_message_of_a_topic_in_its_first_place() {
        let mut outbox = Outbox::default();
        assert!(!outbox.put("a".into(), "1".into(), true));
        assert!(!outbox.put("b".into(), "2".into(), true));
        assert!(outbox.put("a".into(), "3".into(), true), "replaced unsent");
        let mut sent = Vec::new();
        outbox.drain(|t, p, _| {
            sent.push(format!("{t}={p}"));
            false
        });
        assert_eq!(sent, ["a=3"]);
        assert_eq!(outbox.len(), 2, "refused: still waiting");
        let mut rest = Vec::new();
        outbox.drain(|t, p, _| {
            rest.push(format!("{t}={p}"));
            true
        });
        assert_eq!(rest, ["a=3", "b=2"]);
        assert_eq!(outbox.len(), 0);
    }
}
