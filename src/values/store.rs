//! The plant values as last read: one entry per configured value of a slave, its last good
//! reading or why the last poll failed, and its good readings of the last minutes for the status
//! page's plot. Rendered for Prometheus (a collector in the gateway's registry: a value whose
//! last poll failed is left out, so its series goes stale) and as JSON for `GET /values`.
//! Plain data behind one lock; knows nothing of polling or HTTP.

use prometheus::core::{Collector, Desc};
use prometheus::proto::{Gauge, LabelPair, Metric, MetricFamily, MetricType};
use serde::Serialize;
use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::time::Instant;

/// How far back a value's readings are kept for its plot.
pub(crate) const HISTORY: Duration = Duration::from_secs(600);
/// The most readings kept per value: a value polled every second keeps its last two minutes.
const HISTORY_POINTS: usize = 120;

/// What a value is, as configured: whose, what it is called and how it is shown.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct ValueSpec {
    pub(crate) bus: Arc<str>,
    pub(crate) slave: u8,
    pub(crate) name: String,
    pub(crate) help: String,
    pub(crate) unit: Option<String>,
    pub(crate) labels: BTreeMap<String, String>,
}

/// A value's entry: what it is, and what its polls found.
#[derive(Debug)]
struct Entry {
    spec: ValueSpec,
    /// The last good reading, if the last poll was good.
    value: Option<f64>,
    /// When the last good poll was, even if a later one failed.
    read_at: Option<SystemTime>,
    /// The same, on the gateway's clock: how old the reading is.
    fresh_at: Option<Instant>,
    /// Why the last poll failed, if it did.
    error: Option<&'static str>,
    /// Good readings of the last [`HISTORY`], oldest first: Unix milliseconds and value.
    history: VecDeque<(u64, f64)>,
}

impl Entry {
    fn new(spec: ValueSpec) -> Entry {
        Entry {
            spec,
            value: None,
            read_at: None,
            fresh_at: None,
            error: None,
            history: VecDeque::new(),
        }
    }
}

/// Every configured value and what was read of it.
#[derive(Default)]
pub(crate) struct Store {
    entries: Mutex<Vec<Entry>>,
    /// Counts the configurations: an entry's place means something only in its own.
    generation: AtomicU64,
    /// Told of every poll's outcome and every new configuration (the MQTT publisher waits on
    /// it).
    changed: tokio::sync::Notify,
}

/// What one value is now, for the MQTT publisher: its last good reading if its last poll was
/// good, and whether its last poll failed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Sample {
    pub(crate) value: Option<f64>,
    pub(crate) failed: bool,
}

/// What was last read of one value, for a virtual unit's answer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Reading {
    /// The last good reading, if the last poll was good.
    pub(crate) value: Option<f64>,
    /// When that was, on the gateway's clock.
    pub(crate) fresh_at: Option<Instant>,
}

/// The store held still while a virtual unit's answer is made of it: every reading of one
/// answer from one moment.
pub(crate) struct Readings<'a> {
    entries: MutexGuard<'a, Vec<Entry>>,
    generation: u64,
}

impl Readings<'_> {
    /// The configuration the entries' places are of.
    pub(crate) fn generation(&self) -> u64 {
        self.generation
    }

    /// Entry `at`'s reading.
    pub(crate) fn get(&self, at: usize) -> Reading {
        self.entries.get(at).map_or(
            Reading {
                value: None,
                fresh_at: None,
            },
            |e| Reading {
                value: e.value,
                fresh_at: e.fresh_at,
            },
        )
    }
}

/// Which values `GET /values` asks for.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct ValueQuery {
    pub(crate) bus: Option<String>,
    pub(crate) slave: Option<u8>,
    pub(crate) history: bool,
}

/// One value as `GET /values` gives it, borrowed from its entry while the listing is written.
#[derive(Serialize)]
struct Shown<'a> {
    bus: &'a str,
    slave: u8,
    name: &'a str,
    /// What the value is, in words: its `help`, or its name if it has none.
    help: &'a str,
    labels: &'a BTreeMap<String, String>,
    value: Option<f64>,
    unit: Option<&'a str>,
    read_at: Option<String>,
    error: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    history: Option<&'a VecDeque<(u64, f64)>>,
}

/// `GET /values`.
#[derive(Serialize)]
struct Listing<'a> {
    values: Vec<Shown<'a>>,
}

fn unix_ms(time: SystemTime) -> u64 {
    let since = time.duration_since(UNIX_EPOCH).unwrap_or_default();
    u64::try_from(since.as_millis()).unwrap_or(u64::MAX)
}

impl Store {
    fn lock(&self) -> MutexGuard<'_, Vec<Entry>> {
        self.entries.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Configure the values anew as `specs` (a reload): an entry that stays the same keeps what
    /// was read of it; the others start unread. Returns nothing: entries are addressed by their
    /// place in `specs` from now on.
    pub(crate) fn configure(&self, specs: Vec<ValueSpec>) {
        let mut entries = self.lock();
        self.generation.fetch_add(1, Ordering::Relaxed);
        let mut old: Vec<Option<Entry>> = entries.drain(..).map(Some).collect();
        for spec in specs {
            let kept = old
                .iter_mut()
                .find(|e| e.as_ref().is_some_and(|e| e.spec == spec))
                .and_then(Option::take);
            entries.push(kept.unwrap_or_else(|| Entry::new(spec)));
        }
        drop(entries);
        self.changed.notify_one();
    }

    /// Wait until a poll ended or the values were configured anew since the last wait ended.
    pub(crate) async fn changed(&self) {
        self.changed.notified().await;
    }

    /// Every value's [`Sample`] into `out` (cleared first), and the configuration its places
    /// are of.
    pub(crate) fn samples(&self, out: &mut Vec<Sample>) -> u64 {
        let readings = self.readings();
        out.clear();
        out.extend(readings.entries.iter().map(|e| Sample {
            value: e.value,
            failed: e.error.is_some(),
        }));
        readings.generation
    }

    /// What every value is, in the store's order, and the configuration that order is of.
    pub(crate) fn specs(&self) -> (u64, Vec<ValueSpec>) {
        let readings = self.readings();
        let specs = readings.entries.iter().map(|e| e.spec.clone()).collect();
        (readings.generation, specs)
    }

    /// Value `at` read `value` at `when`.
    pub(crate) fn read(&self, at: usize, value: f64, when: SystemTime) {
        let mut entries = self.lock();
        let Some(entry) = entries.get_mut(at) else {
            return;
        };
        entry.value = Some(value);
        entry.read_at = Some(when);
        entry.fresh_at = Some(Instant::now());
        entry.error = None;
        let now = unix_ms(when);
        let horizon = now.saturating_sub(u64::try_from(HISTORY.as_millis()).unwrap_or(0));
        while entry
            .history
            .front()
            .is_some_and(|&(t, _)| t < horizon || entry.history.len() >= HISTORY_POINTS)
        {
            entry.history.pop_front();
        }
        entry.history.push_back((now, value));
        drop(entries);
        self.changed.notify_one();
    }

    /// The poll of value `at` failed as `outcome`: it is not exported until a good one.
    pub(crate) fn failed(&self, at: usize, outcome: &'static str) {
        if let Some(entry) = self.lock().get_mut(at) {
            entry.value = None;
            entry.error = Some(outcome);
        }
        self.changed.notify_one();
    }

    /// The readings as they are now, held still until the guard is dropped.
    pub(crate) fn readings(&self) -> Readings<'_> {
        let entries = self.lock();
        Readings {
            generation: self.generation.load(Ordering::Relaxed),
            entries,
        }
    }

    /// Where each of `series` (bus, slave, name, labels) is in the store, and the
    /// configuration those places are of.
    pub(crate) fn locate<'a>(
        &self,
        series: impl Iterator<Item = (&'a str, u8, &'a str, &'a BTreeMap<String, String>)>,
    ) -> (u64, Vec<Option<usize>>) {
        let readings = self.readings();
        let places = series
            .map(|(bus, slave, name, labels)| {
                readings.entries.iter().position(|e| {
                    *e.spec.bus == *bus
                        && e.spec.slave == slave
                        && e.spec.name == name
                        && e.spec.labels == *labels
                })
            })
            .collect();
        (readings.generation, places)
    }

    /// The values `filter` asks for, in configuration order, as `GET /values`'s JSON: written
    /// from the entries themselves, so a listing with every value's history copies none of it.
    pub(crate) fn listing(&self, filter: &ValueQuery) -> serde_json::Result<String> {
        let entries = self.lock();
        let chosen = entries.iter().filter(|e| {
            filter.bus.as_deref().is_none_or(|bus| *e.spec.bus == *bus)
                && filter.slave.is_none_or(|slave| e.spec.slave == slave)
        });
        let listing = Listing {
            values: chosen
                .map(|e| Shown {
                    bus: &e.spec.bus,
                    slave: e.spec.slave,
                    name: &e.spec.name,
                    help: &e.spec.help,
                    labels: &e.spec.labels,
                    value: e.value,
                    unit: e.spec.unit.as_deref(),
                    read_at: e
                        .read_at
                        .map(|t| humantime::format_rfc3339_millis(t).to_string()),
                    error: e.error,
                    history: filter.history.then_some(&e.history),
                })
                .collect(),
        };
        serde_json::to_string(&listing)
    }

    /// How many values are configured.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.lock().len()
    }
}

/// The store as the gateway's registry collects it.
pub(crate) struct Exported(pub(crate) Arc<Store>);

impl Collector for Exported {
    fn desc(&self) -> Vec<&Desc> {
        Vec::new()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        self.0.collect()
    }
}

/// A label pair of the exposition.
fn label(name: &str, value: &str) -> LabelPair {
    let mut pair = LabelPair::default();
    pair.set_name(name.to_owned());
    pair.set_value(value.to_owned());
    pair
}

/// The values with a good last reading, as one gauge family per name: `bus`, `slave` and the
/// value's own labels. The store describes no metric up front: its names change with the
/// configuration, and the gateway's registry checks them at load instead.
impl Collector for Store {
    fn desc(&self) -> Vec<&Desc> {
        Vec::new()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        let entries = self.lock();
        let mut families: BTreeMap<&str, MetricFamily> = BTreeMap::new();
        for entry in entries.iter() {
            let Some(value) = entry.value else {
                continue;
            };
            let spec = &entry.spec;
            let family = families.entry(&spec.name).or_insert_with(|| {
                let mut family = MetricFamily::default();
                family.set_name(spec.name.clone());
                family.set_help(spec.help.clone());
                family.set_field_type(MetricType::GAUGE);
                family
            });
            let mut labels = vec![
                label("bus", &spec.bus),
                label("slave", &spec.slave.to_string()),
            ];
            labels.extend(spec.labels.iter().map(|(k, v)| label(k, v)));
            let mut gauge = Gauge::default();
            gauge.set_value(value);
            let mut metric = Metric::default();
            metric.set_label(labels);
            metric.set_gauge(gauge);
            family.mut_metric().push(metric);
        }
        families.into_values().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(slave: u8, name: &str) -> ValueSpec {
        ValueSpec {
            bus: "line".into(),
            slave,
            name: name.to_owned(),
            help: format!("{name}'s help"),
            unit: Some("Hz".to_owned()),
            labels: BTreeMap::new(),
        }
    }

    fn listed(store: &Store, filter: &ValueQuery) -> serde_json::Value {
        serde_json::from_str(&store.listing(filter).unwrap()).unwrap()
    }

    fn at(seconds: u64) -> SystemTime {
        UNIX_EPOCH + Duration::from_secs(seconds)
    }

    #[test]
    fn a_value_is_exported_while_its_last_poll_was_good_and_listed_either_way() {
        let store = Store::default();
        store.configure(vec![
            spec(1, "drive_output_frequency_hertz"),
            spec(2, "drive_output_frequency_hertz"),
        ]);
        store.read(0, 37.5, at(100));
        store.read(1, 50.0, at(100));
        let families = store.collect();
        assert_eq!(families.len(), 1);
        assert_eq!(families[0].get_metric().len(), 2);
        store.failed(1, "timeout");
        let families = store.collect();
        assert_eq!(
            families[0].get_metric().len(),
            1,
            "slave 2's series goes stale"
        );
        let listing = listed(&store, &ValueQuery::default());
        assert_eq!(listing["values"][1]["value"], serde_json::Value::Null);
        assert_eq!(listing["values"][1]["error"], "timeout");
        assert_eq!(listing["values"][1]["read_at"], "1970-01-01T00:01:40.000Z");
        assert_eq!(listing["values"][0]["value"], 37.5);
        assert_eq!(
            listing["values"][0]["help"],
            "drive_output_frequency_hertz's help"
        );
        assert!(listing["values"][0].get("history").is_none());
    }

    #[test]
    fn history_keeps_the_last_ten_minutes_and_at_most_its_points() {
        let store = Store::default();
        store.configure(vec![spec(1, "a")]);
        for s in 0..700u32 {
            store.read(0, f64::from(s), at(1000 + u64::from(s) * 10));
        }
        let filter = ValueQuery {
            history: true,
            ..ValueQuery::default()
        };
        let listing = listed(&store, &filter);
        let history = listing["values"][0]["history"].as_array().unwrap().clone();
        // Every 10 s: ten minutes are 61 readings.
        assert_eq!(history.len(), 61);
        assert_eq!(history.last().unwrap()[1], 699.0);
        for s in 0..300 {
            store.read(0, 1.0, at(8000 + s));
        }
        let listing = listed(&store, &filter);
        assert_eq!(
            listing["values"][0]["history"].as_array().unwrap().len(),
            HISTORY_POINTS
        );
    }

    #[test]
    fn a_reload_keeps_what_was_read_of_values_that_stay() {
        let store = Store::default();
        store.configure(vec![spec(1, "a"), spec(1, "b")]);
        store.read(1, 2.0, at(5));
        store.configure(vec![spec(1, "b"), spec(1, "c")]);
        let listing = listed(&store, &ValueQuery::default());
        assert_eq!(listing["values"][0]["value"], 2.0);
        assert_eq!(listing["values"][1]["value"], serde_json::Value::Null);
        assert_eq!(store.len(), 2);
    }
}
