//! The plant's values for Prometheus: the values each slave lists (its own and its device
//! template's) read by the gateway itself, through the bus's queue below every master, and
//! exported as gauges on `/metrics`, as JSON on `/values` and on the status page. Here: what the
//! configuration asks to poll (`layout`), and the pollers' lives across reloads; by concern,
//! `decode` (a reply's registers, a value's number), `plan` (which reads), `poller` (one task
//! per bus), `store` (what was read). Knows nothing of HTTP, and of the line only the bus's
//! handle.

mod decode;
mod follow;
mod plan;
mod poller;
mod store;

pub(crate) use decode::{decode, encode, write_request};
pub(crate) use store::{Exported, Sample, Store, ValueQuery, ValueSpec};

use crate::bus::BusHandle;
use crate::config::{Config, Value};
use poller::Poll;
use std::sync::{Arc, Mutex, PoisonError};
use tokio::task::JoinHandle;

/// What a configuration asks to poll: every value's entry, and per bus its reads and share.
struct Layout {
    specs: Vec<ValueSpec>,
    /// By bus name: its polls and `poll_share`.
    buses: Vec<(String, Vec<Poll>, f64)>,
    /// By listen line's name: its values, which are never polled.
    listened: Vec<(String, Vec<follow::Followed>)>,
}

/// The values of `config`'s slaves, in configuration order (a slave's template's first, then
/// its own), and the reads that poll them.
fn layout(config: &Config) -> Layout {
    let mut specs = Vec::new();
    let mut buses = Vec::new();
    let mut listened = Vec::new();
    for bus in &config.bus {
        let listening = bus.mode == crate::config::BusMode::Listen;
        let mut followed = Vec::new();
        let name: Arc<str> = bus.name.as_str().into();
        let mut polls = Vec::new();
        for slave in &bus.slave {
            let template = slave
                .template
                .as_deref()
                .and_then(|t| config.templates.get(t));
            let with_intervals = config
                .values_of(&bus.name, slave.address)
                .unwrap_or_default();
            if with_intervals.is_empty() {
                continue;
            }
            let values: Vec<&Value> = with_intervals.iter().map(|(v, _)| *v).collect();
            let first = specs.len();
            let listed: Vec<(usize, &Value, std::time::Duration)> = with_intervals
                .iter()
                .enumerate()
                .map(|(i, (v, interval))| (first + i, *v, *interval))
                .collect();
            specs.extend(values.iter().map(|v| ValueSpec {
                bus: name.clone(),
                slave: slave.address,
                name: v.name.clone(),
                help: v.help_text().to_owned(),
                unit: v.unit.clone(),
                labels: v.labels.clone(),
            }));
            if listening {
                let values = listed.iter().map(|&(entry, v, _)| (entry, v.clone()));
                followed.extend(values.map(|(e, v)| follow::Followed::new(e, slave.address, v)));
                continue;
            }
            let max = slave.read_limit(template);
            polls.extend(
                plan::plan(slave.address, &listed, max)
                    .into_iter()
                    .map(|read| Poll {
                        values: read
                            .values
                            .iter()
                            .map(|&(entry, offset)| (entry, offset, values[entry - first].clone()))
                            .collect(),
                        read,
                    }),
            );
        }
        if listening {
            listened.push((bus.name.clone(), followed));
        } else {
            buses.push((bus.name.clone(), polls, bus.poll_share));
        }
    }
    Layout {
        specs,
        buses,
        listened,
    }
}

/// The plant values of a running gateway: what was read, and the pollers reading them.
pub(crate) struct Values {
    store: Arc<Store>,
    pollers: Mutex<Vec<JoinHandle<()>>>,
}

impl Values {
    /// Nothing configured yet; its store is to be registered with the metrics.
    pub(crate) fn new() -> Values {
        Values {
            store: Arc::new(Store::default()),
            pollers: Mutex::new(Vec::new()),
        }
    }

    pub(crate) fn store(&self) -> &Arc<Store> {
        &self.store
    }

    /// Poll what `config` asks for on `buses` (by name) from now on: the pollers of an earlier
    /// configuration stop, and values that stay keep what was read of them.
    pub(crate) fn apply(&self, config: &Config, buses: &[BusHandle]) {
        let mut pollers = self.pollers.lock().unwrap_or_else(PoisonError::into_inner);
        for poller in pollers.drain(..) {
            poller.abort();
        }
        let layout = layout(config);
        self.store.configure(layout.specs);
        for (name, followed) in layout.listened {
            if let Some(bus) = buses.iter().find(|b| b.name() == name) {
                let store = self.store.clone();
                pollers.push(tokio::spawn(follow::run(bus.clone(), followed, store)));
            }
        }
        for (name, polls, share) in layout.buses {
            let Some(bus) = buses.iter().find(|b| b.name() == name) else {
                continue;
            };
            if polls.is_empty() {
                continue;
            }
            for poll in &polls {
                bus.metrics().will_poll(poll.read.slave);
            }
            pollers.push(tokio::spawn(poller::run(
                bus.clone(),
                polls,
                self.store.clone(),
                share,
            )));
        }
    }
}

impl Drop for Values {
    fn drop(&mut self) {
        let pollers = self
            .pollers
            .get_mut()
            .unwrap_or_else(PoisonError::into_inner);
        for poller in pollers.drain(..) {
            poller.abort();
        }
    }
}

#[cfg(test)]
mod tests;
