//! Virtual units (`[[virtual]]`): units the gateway answers itself, from the values it polls.
//! Here: the table of every unit's registers, built from the configuration's layout and the
//! places of their values in the store, replaced whole on a reload; by concern, `answer` (what
//! a read gets, what a write becomes). A read is made from one moment of the store, and a read
//! touching a register whose value is too old, never read or failed gets 0x0B whole: a master
//! never gets a block half old. Knows nothing of sessions, rules or the journal: the dispatcher
//! decides whether a request may be made, and sends a write on to the source slaves.

mod answer;

pub(crate) use answer::{Declined, SourceWrite};

use crate::config::{Config, Slot, Table};
use crate::error::Outcome;
use crate::line::rtu;
use crate::master::VIRTUAL_TRACE_PREFIX;
use crate::metrics::{Metrics, VirtualOutcome};
use crate::pdu::exception_pdu;
use crate::routing::Target;
use crate::trace::{BusTap, Direction, TraceEvent, TraceHub};
use crate::values::Store;
use std::sync::Arc;
use std::time::{Duration, SystemTime};
use tokio::time::Instant;

/// One register (run, bit) of a unit, and where its value is in the store.
#[derive(Debug)]
struct Placed {
    slot: Slot,
    /// The value's place in the store; `None`: never (a template's value its source lacks).
    entry: Option<usize>,
    /// Where a write goes: the source slave.
    target: Option<Target>,
}

/// One virtual unit.
pub(crate) struct Virtual {
    pub(crate) id: u8,
    pub(crate) name: Arc<str>,
    /// Each table's registers by first address (holding, input, coil, discrete).
    tables: [Vec<Placed>; 4],
    /// Its requests and answers on the trace, as bus `virtual:NAME`.
    tap: BusTap,
}

impl Virtual {
    /// Show the request `pdu` that ended in `outcome` on the trace: `rx` the master's request,
    /// `tx` the answer, each as an RTU frame to the unit.
    pub(crate) fn trace(&self, pdu: &[u8], outcome: &Outcome) {
        let hub = self.tap.hub();
        if !hub.active() {
            return;
        }
        let function = pdu.first().copied().unwrap_or(0);
        let label = VirtualOutcome::of(function, outcome).label();
        let reply = match outcome {
            Ok(answer) => answer.clone().into_pdu().unwrap_or_default(),
            Err(error) => exception_pdu(function, error.exception_code()).to_vec(),
        };
        for (direction, pdu) in [(Direction::Rx, pdu), (Direction::Tx, &reply[..])] {
            hub.publish(TraceEvent {
                time: SystemTime::now(),
                bus: self.tap.bus().clone(),
                direction,
                slave: self.id,
                function: pdu.first().copied().unwrap_or(0),
                bytes: rtu::encode(self.id, pdu),
                framing: "rtu",
                outcome: label,
            });
        }
    }
}

fn table_index(table: Table) -> usize {
    match table {
        Table::Holding => 0,
        Table::Input => 1,
        Table::Coil => 2,
        Table::Discrete => 3,
    }
}

/// Every virtual unit of a configuration, and the store their values are read from.
pub(crate) struct Units {
    by_id: [Option<u16>; 256],
    list: Vec<Virtual>,
    store: Arc<Store>,
    /// The store's configuration the entries' places are of.
    generation: u64,
}

/// One register as `/status` and `check-config` show it.
#[derive(Clone, Debug, serde::Serialize)]
pub(crate) struct Shown {
    pub(crate) table: &'static str,
    pub(crate) register: u16,
    #[serde(rename = "type")]
    pub(crate) kind: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(crate) bit: Option<u8>,
    /// `BUS/SLAVE/NAME{labels}`; none for a template's value its source lacks.
    pub(crate) source: Option<String>,
    pub(crate) writable: bool,
    pub(crate) max_age_seconds: f64,
    pub(crate) value: Option<f64>,
    /// Seconds since its value was read; none if it never was.
    pub(crate) age_seconds: Option<f64>,
    /// Whether a read of it now is answered (not 0x0B).
    pub(crate) fresh: bool,
}

/// A unit as `/status` shows it.
#[derive(Clone, Debug, serde::Serialize)]
pub(crate) struct ShownUnit {
    pub(crate) unit: u8,
    pub(crate) name: String,
    pub(crate) registers: Vec<Shown>,
}

impl Units {
    /// None: for the tests of other parts.
    #[cfg(any(test, feature = "test-util"))]
    pub(crate) fn none(store: Arc<Store>) -> Units {
        Units {
            by_id: [None; 256],
            list: Vec::new(),
            store,
            generation: 0,
        }
    }

    /// The units `config` lays out (checked), their values found in `store` as it is configured
    /// for `config` now, their requests shown on `trace`.
    pub(crate) fn new(config: &Config, store: Arc<Store>, trace: &Arc<TraceHub>) -> Units {
        let mut list = Vec::new();
        let mut all: Vec<Vec<Slot>> = Vec::new();
        for at in 0..config.virtual_units.len() {
            all.push(config.virtual_layout(at).0);
        }
        let series = all.iter().flatten().map(|slot| match &slot.source {
            Some(found) => (
                found.at.bus.as_str(),
                found.at.slave,
                found.at.name.as_str(),
                &found.at.labels,
            ),
            // Found nowhere: no value has an empty name.
            None => ("", 0, "", &slot.encoding.labels),
        });
        let (generation, places) = store.locate(series);
        let mut places = places.into_iter();
        let mut by_id = [None; 256];
        for (at, (unit, slots)) in config.virtual_units.iter().zip(all).enumerate() {
            let mut tables: [Vec<Placed>; 4] = Default::default();
            for slot in slots {
                let entry = places.next().flatten();
                let target = slot.source.as_ref().and_then(|found| {
                    let bus = config.bus.iter().position(|b| b.name == found.at.bus)?;
                    Some(Target {
                        bus,
                        address: found.at.slave,
                        broadcast: false,
                    })
                });
                tables[table_index(slot.encoding.table)].push(Placed {
                    slot,
                    entry,
                    target,
                });
            }
            for table in &mut tables {
                table.sort_by_key(|p| p.slot.first());
            }
            by_id[usize::from(unit.unit)] = u16::try_from(at).ok();
            list.push(Virtual {
                id: unit.unit,
                name: unit.name.as_str().into(),
                tables,
                tap: trace.register(format!("{VIRTUAL_TRACE_PREFIX}{}", unit.name).into()),
            });
        }
        Units {
            by_id,
            list,
            store,
            generation,
        }
    }

    /// The units `config` lays out, their values found in `store` (configured for it), their
    /// requests on `metrics`' trace and their series declared: for a running gateway.
    pub(crate) fn serving(config: &Config, store: &Arc<Store>, metrics: &Metrics) -> Arc<Units> {
        let units = Units::new(config, store.clone(), &metrics.trace);
        for unit in &units.list {
            metrics.virtual_units.declare(unit.id, &unit.name);
        }
        Arc::new(units)
    }

    /// The virtual unit with id `unit`, if there is one.
    pub(crate) fn get(&self, unit: u8) -> Option<&Virtual> {
        let at = self.by_id[usize::from(unit)]?;
        self.list.get(usize::from(at))
    }

    /// Every unit and register as it stands `now`, for `/status`.
    pub(crate) fn shown(&self, now: Instant) -> Vec<ShownUnit> {
        let readings = self.store.readings();
        let current = readings.generation() == self.generation;
        self.list
            .iter()
            .map(|unit| ShownUnit {
                unit: unit.id,
                name: unit.name.to_string(),
                registers: unit
                    .tables
                    .iter()
                    .flatten()
                    .map(|placed| {
                        let reading = placed.entry.filter(|_| current).map(|at| readings.get(at));
                        let age = reading
                            .and_then(|r| r.fresh_at)
                            .map(|t| now.saturating_duration_since(t));
                        let slot = &placed.slot;
                        Shown {
                            table: slot.encoding.table.name(),
                            register: slot.first(),
                            kind: slot.encoding.kind().name(),
                            bit: slot.encoding.bit,
                            source: slot.source.as_ref().map(|f| f.at.to_string()),
                            writable: slot.writable,
                            max_age_seconds: slot.max_age.as_secs_f64(),
                            value: reading.and_then(|r| r.value),
                            age_seconds: age.map(|a| a.as_secs_f64()),
                            fresh: reading.is_some_and(|r| {
                                r.value.is_some() && age.is_some_and(|a| a <= slot.max_age)
                            }),
                        }
                    })
                    .collect(),
            })
            .collect()
    }
}

/// Whether a reading taken at `fresh_at` is too old at `now` for `max_age`.
fn too_old(fresh_at: Option<Instant>, now: Instant, max_age: Duration) -> bool {
    fresh_at.is_none_or(|t| now.saturating_duration_since(t) > max_age)
}

#[cfg(test)]
mod tests;
