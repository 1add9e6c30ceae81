//! `[[virtual]]`: a unit the gateway answers itself from the values it polls. Its keys, and its
//! layout: every register it answers, where the number in it comes from (a polled value of a
//! slave: bus, address, name and labels), how the register holds that number, and how old the
//! number may be. The layout is made here once, for the configuration's check and for the
//! running gateway alike, so what `check-config` prints is what is answered. Plain values; knows
//! nothing of requests.

use super::load::ConfigError;
use super::serde_adapters::{is_zero_f64, opt_duration};
use super::{Config, Order, Table, Value, ValueType};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Duration;

/// A unit answered from memory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VirtualUnit {
    /// The unit id masters address.
    pub unit: u8,
    /// What metrics, `/status` and the trace call it.
    pub name: String,
    /// Lay out registers as this template lays out its values, from `source`'s values.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub template: Option<String>,
    /// The slave whose values the template's registers take.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<VirtualSource>,
    /// How old a register's number may be when it is read; left out, three of its value's poll
    /// intervals.
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub max_age: Option<Duration>,
    /// Registers of its own.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub register: Vec<VirtualRegister>,
}

/// A slave of a bus.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VirtualSource {
    pub bus: String,
    pub slave: u8,
}

/// One register (coil, input) of a virtual unit's own, and the polled value it shows.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VirtualRegister {
    /// Its data address, 0-65535.
    pub register: u32,
    #[serde(default)]
    pub table: Table,
    /// `BUS/SLAVE/NAME` of a polled value, `NAME{label="v"}` to pick one series of several;
    /// with the unit's `source`, `NAME` alone is the source's.
    pub value: String,
    #[serde(default, rename = "type", skip_serializing_if = "Option::is_none")]
    pub kind: Option<ValueType>,
    #[serde(default, skip_serializing_if = "is_big")]
    pub word_order: Order,
    #[serde(default, skip_serializing_if = "is_big")]
    pub byte_order: Order,
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub scale: f64,
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub offset: f64,
    /// A write here is written to the source value's register.
    #[serde(default, skip_serializing_if = "is_false")]
    pub writable: bool,
}

fn one() -> f64 {
    1.0
}

#[allow(clippy::trivially_copy_pass_by_ref)] // serde's signature
fn is_one(value: &f64) -> bool {
    *value == 1.0
}

#[allow(clippy::trivially_copy_pass_by_ref)] // serde's signature
fn is_big(order: &Order) -> bool {
    *order == Order::Big
}

#[allow(clippy::trivially_copy_pass_by_ref)] // serde's signature
fn is_false(flag: &bool) -> bool {
    !*flag
}

/// A polled value of one slave: one series.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct ValueRef {
    pub(crate) bus: String,
    pub(crate) slave: u8,
    pub(crate) name: String,
    pub(crate) labels: BTreeMap<String, String>,
}

impl std::fmt::Display for ValueRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}/{}", self.bus, self.slave, self.name)?;
        if !self.labels.is_empty() {
            let labels: Vec<String> = self
                .labels
                .iter()
                .map(|(k, v)| format!("{k}=\"{v}\""))
                .collect();
            write!(f, "{{{}}}", labels.join(","))?;
        }
        Ok(())
    }
}

/// The polled value a register shows, as the configuration lists it.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Found {
    pub(crate) at: ValueRef,
    /// How the source slave's registers hold it: where a write goes, and in what encoding.
    pub(crate) value: Value,
}

/// One register (or run of registers, or bit) a virtual unit answers.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Slot {
    /// How the unit's register holds the number: table, first register, type, bit, orders,
    /// scale and offset (its `name` the value's).
    pub(crate) encoding: Value,
    /// The value it shows; `None`: its template's value the source does not have (read 0x0B).
    pub(crate) source: Option<Found>,
    /// Older than this, it reads 0x0B.
    pub(crate) max_age: Duration,
    pub(crate) writable: bool,
    /// The key it comes from: `virtual[0].register[1]`, `virtual[0].template (its value[3])`.
    pub(crate) key: String,
}

impl Slot {
    /// Its first address.
    pub(crate) fn first(&self) -> u16 {
        u16::try_from(self.encoding.register).unwrap_or(u16::MAX)
    }

    /// Its last address.
    pub(crate) fn last(&self) -> u16 {
        self.first().saturating_add(self.encoding.width() - 1)
    }
}

/// Parse `BUS/SLAVE/NAME{k="v",...}` (or `NAME{...}` of `source`).
fn parse_ref(text: &str, source: Option<&VirtualSource>) -> Result<ValueRef, String> {
    let (path, labels) = match text.split_once('{') {
        Some((path, rest)) => {
            let inner = rest
                .strip_suffix('}')
                .ok_or_else(|| format!("`{text}`: labels end with }}"))?;
            (
                path,
                parse_labels(inner).map_err(|why| format!("`{text}`: {why}"))?,
            )
        }
        None => (text, BTreeMap::new()),
    };
    let parts: Vec<&str> = path.split('/').collect();
    let (bus, slave, name) = match (parts.as_slice(), source) {
        ([bus, slave, name], _) => {
            let slave = slave
                .parse::<u8>()
                .map_err(|_| format!("`{text}`: `{slave}` is not a slave address 0-255"))?;
            ((*bus).to_owned(), slave, *name)
        }
        ([name], Some(source)) => (source.bus.clone(), source.slave, *name),
        _ => {
            return Err(format!(
                "`{text}` is not BUS/SLAVE/NAME (NAME alone only with the unit's `source`)"
            ))
        }
    };
    Ok(ValueRef {
        bus,
        slave,
        name: name.to_owned(),
        labels,
    })
}

/// `k="v",k2="v2"`.
fn parse_labels(text: &str) -> Result<BTreeMap<String, String>, String> {
    let mut labels = BTreeMap::new();
    for pair in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let (key, value) = pair
            .split_once('=')
            .ok_or_else(|| format!("`{pair}` is not label=\"value\""))?;
        let value = value
            .trim()
            .strip_prefix('"')
            .and_then(|v| v.strip_suffix('"'))
            .ok_or_else(|| format!("the value of label `{}` is not in quotes", key.trim()))?;
        labels.insert(key.trim().to_owned(), value.to_owned());
    }
    Ok(labels)
}

impl Config {
    /// The values of slave `slave` of bus `bus` (its template's, then its own), each with its
    /// poll interval; `None` if no such slave is configured.
    pub(crate) fn values_of(&self, bus: &str, slave: u8) -> Option<Vec<(&Value, Duration)>> {
        let bus = self.bus.iter().find(|b| b.name == bus)?;
        let slave = bus.slave.iter().find(|s| s.address == slave)?;
        let template = slave
            .template
            .as_deref()
            .and_then(|t| self.templates.get(t));
        let interval = slave.poll_interval();
        Some(
            template
                .into_iter()
                .flat_map(|t| &t.value)
                .chain(&slave.value)
                .map(|v| (v, v.poll_interval.unwrap_or(interval)))
                .collect(),
        )
    }

    /// The registers of `[[virtual]]` number `at`, in configuration order (its template's,
    /// then its own), and every problem found making them, by key.
    pub(crate) fn virtual_layout(&self, at: usize) -> (Vec<Slot>, Vec<ConfigError>) {
        let unit = &self.virtual_units[at];
        let mut slots = Vec::new();
        let mut errors = Vec::new();
        let mut fail = |key: String, reason: String| errors.push(ConfigError { key, reason });
        if let Some(name) = &unit.template {
            match (self.templates.get(name), &unit.source) {
                (None, _) => {
                    let known: Vec<&str> = self.templates.names().collect();
                    fail(
                        format!("virtual[{at}].template"),
                        format!("no template `{name}`: there are {}", known.join(", ")),
                    );
                }
                (Some(_), None) => fail(
                    format!("virtual[{at}].source"),
                    format!(
                        "template `{name}` lays out registers for a slave's values: give \
                         `source`, the bus and slave address of the slave"
                    ),
                ),
                (Some(template), Some(source)) => {
                    self.template_slots(at, unit, template, source, &mut slots, &mut fail);
                }
            }
        } else if unit.source.is_some() && unit.register.is_empty() {
            fail(
                format!("virtual[{at}].source"),
                "a source without a template lays out nothing: give `template` or \
                 [[virtual.register]]"
                    .to_owned(),
            );
        }
        for (j, register) in unit.register.iter().enumerate() {
            let key = format!("virtual[{at}].register[{j}]");
            if let Some(slot) = self.own_slot(unit, register, &key, &mut fail) {
                slots.push(slot);
            }
        }
        check_overlaps(&slots, &mut fail);
        (slots, errors)
    }

    /// The slots of `unit`'s template, each taking `source`'s value of its name and labels.
    fn template_slots(
        &self,
        at: usize,
        unit: &VirtualUnit,
        template: &super::Template,
        source: &VirtualSource,
        slots: &mut Vec<Slot>,
        fail: &mut impl FnMut(String, String),
    ) {
        let Some(values) = self.values_of(&source.bus, source.slave) else {
            fail(
                format!("virtual[{at}].source"),
                format!(
                    "bus `{}` has no [[bus.slave]] with address {}: a source is a slave whose \
                     values the gateway polls",
                    source.bus, source.slave
                ),
            );
            return;
        };
        for (k, laid) in template.value.iter().enumerate() {
            let found = values
                .iter()
                .find(|(v, _)| v.name == laid.name && v.labels == laid.labels);
            let max_age = found.map_or(Duration::ZERO, |(_, interval)| {
                unit.max_age.unwrap_or(*interval * 3)
            });
            slots.push(Slot {
                encoding: laid.clone(),
                source: found.map(|(value, _)| Found {
                    at: ValueRef {
                        bus: source.bus.clone(),
                        slave: source.slave,
                        name: value.name.clone(),
                        labels: value.labels.clone(),
                    },
                    value: (*value).clone(),
                }),
                max_age,
                writable: false,
                key: format!("virtual[{at}].template (its value[{k}])"),
            });
        }
    }

    /// A `[[virtual.register]]`'s slot, or its problems under `key`.
    fn own_slot(
        &self,
        unit: &VirtualUnit,
        register: &VirtualRegister,
        key: &str,
        fail: &mut impl FnMut(String, String),
    ) -> Option<Slot> {
        let mut problems = Vec::new();
        let encoding = Value {
            name: String::new(),
            register: register.register,
            table: register.table,
            kind: register.kind,
            bit: None,
            word_order: register.word_order,
            byte_order: register.byte_order,
            scale: register.scale,
            offset: register.offset,
            unit: None,
            help: None,
            labels: BTreeMap::new(),
            poll_interval: None,
            deadband: 0.0,
            writable: false,
        };
        encoding.check_encoding(key, &mut problems);
        let at = match parse_ref(&register.value, unit.source.as_ref()) {
            Ok(at) => Some(at),
            Err(why) => {
                fail(format!("{key}.value"), why);
                None
            }
        };
        let found = at.and_then(|at| self.find_value(at, key, fail));
        if let Some((found, _)) = &found {
            if register.writable {
                writable_problems(register, &found.value, key, fail);
            }
        }
        for problem in problems {
            fail(problem.key, problem.reason);
        }
        let (found, interval) = found?;
        Some(Slot {
            encoding: Value {
                name: found.value.name.clone(),
                ..encoding
            },
            source: Some(found),
            max_age: unit.max_age.unwrap_or(interval * 3),
            writable: register.writable,
            key: key.to_owned(),
        })
    }

    /// The configured value `at` names, with its poll interval, or why there is none.
    fn find_value(
        &self,
        at: ValueRef,
        key: &str,
        fail: &mut impl FnMut(String, String),
    ) -> Option<(Found, Duration)> {
        let Some(values) = self.values_of(&at.bus, at.slave) else {
            fail(
                format!("{key}.value"),
                format!(
                    "`{at}`: bus `{}` has no [[bus.slave]] with address {}",
                    at.bus, at.slave
                ),
            );
            return None;
        };
        let named: Vec<&(&Value, Duration)> =
            values.iter().filter(|(v, _)| v.name == at.name).collect();
        let chosen: Vec<&&(&Value, Duration)> = named
            .iter()
            .filter(|(v, _)| v.labels == at.labels)
            .collect();
        match (chosen.as_slice(), named.len()) {
            ([(value, interval)], _) => Some((
                Found {
                    at,
                    value: (*value).clone(),
                },
                *interval,
            )),
            (_, 0) => {
                let names: Vec<&str> = values.iter().map(|(v, _)| v.name.as_str()).collect();
                let names = if names.is_empty() {
                    "it has no values".to_owned()
                } else {
                    format!("its values are {}", names.join(", "))
                };
                fail(
                    format!("{key}.value"),
                    format!(
                        "`{at}`: slave {} of `{}` has no such value; {names}",
                        at.slave, at.bus
                    ),
                );
                None
            }
            _ => {
                let series: Vec<String> = named
                    .iter()
                    .map(|(v, _)| {
                        ValueRef {
                            labels: v.labels.clone(),
                            ..at.clone()
                        }
                        .to_string()
                    })
                    .collect();
                fail(
                    format!("{key}.value"),
                    format!(
                        "`{at}` is none of its series: name one, {}",
                        series.join(", ")
                    ),
                );
                None
            }
        }
    }
}

/// Why a writable register cannot be written where its value is.
fn writable_problems(
    register: &VirtualRegister,
    source: &Value,
    key: &str,
    fail: &mut impl FnMut(String, String),
) {
    let mut refuse = |why: String| fail(format!("{key}.writable"), why);
    if matches!(register.table, Table::Input | Table::Discrete) {
        refuse(format!(
            "a master cannot write a {} register: a writable register is holding or coil",
            register.table.name()
        ));
    }
    if matches!(source.table, Table::Input | Table::Discrete) {
        refuse(format!(
            "its value `{}` is a {} of its slave, which no master can write",
            source.name,
            source.table.name()
        ));
    }
    if source.bit.is_some() {
        refuse(format!(
            "its value `{}` is one bit of a register: writing it would write the other bits",
            source.name
        ));
    }
}

/// Two slots of one table on one address, unless both are bits of a register and not the same
/// bit.
fn check_overlaps(slots: &[Slot], fail: &mut impl FnMut(String, String)) {
    let mut sorted: Vec<&Slot> = slots.iter().collect();
    sorted.sort_by_key(|s| (s.encoding.table, s.first()));
    // The slot reaching furthest so far in this table.
    let mut furthest: Option<&Slot> = None;
    for slot in sorted {
        if let Some(a) = furthest.filter(|a| a.encoding.table == slot.encoding.table) {
            let bits = match (a.encoding.bit, slot.encoding.bit) {
                (Some(x), Some(y)) => a.first() == slot.first() && x != y,
                _ => false,
            };
            if slot.first() <= a.last() && !bits {
                fail(
                    slot.key.clone(),
                    format!(
                        "{} {} overlaps {} ({} {}-{})",
                        slot.encoding.table.name(),
                        slot.first(),
                        a.key,
                        a.encoding.table.name(),
                        a.first(),
                        a.last()
                    ),
                );
            }
            if slot.last() <= a.last() {
                continue;
            }
        }
        furthest = Some(slot);
    }
}

impl Value {
    /// The problems of how it is held in registers (its type in its table, its registers'
    /// range, scale and offset), each with its key under `at`.
    pub(crate) fn check_encoding(&self, at: &str, errors: &mut Vec<ConfigError>) {
        let mut all = Vec::new();
        self.check(at, &mut all);
        // A virtual register has no name or labels of its own: only how it is held counts.
        errors.extend(
            all.into_iter()
                .filter(|e| !e.key.ends_with(".name") && !e.key.contains(".labels.")),
        );
    }
}

/// Every problem of the `[[virtual]]` units, by key: their ids and names, routes that would
/// take their units, and their layouts.
pub(super) fn check(config: &Config, errors: &mut Vec<ConfigError>) {
    let mut fail = |key: String, reason: String| errors.push(ConfigError { key, reason });
    let mut units: BTreeMap<u8, usize> = BTreeMap::new();
    let mut names: BTreeMap<&str, usize> = BTreeMap::new();
    for (i, unit) in config.virtual_units.iter().enumerate() {
        let key = |field: &str| format!("virtual[{i}].{field}");
        if unit.unit == crate::line::BROADCAST {
            fail(
                key("unit"),
                "0 is the broadcast address of a serial line: a virtual unit is 1-255".to_owned(),
            );
        }
        if let Some(first) = units.insert(unit.unit, i) {
            fail(
                key("unit"),
                format!("unit {} is already virtual[{first}]'s", unit.unit),
            );
        }
        if let Err(why) = unit_name(&unit.name) {
            fail(key("name"), why);
        } else if let Some(first) = names.insert(&unit.name, i) {
            fail(
                key("name"),
                format!("`{}` is already virtual[{first}]'s name", unit.name),
            );
        }
        if let Some(why) = routed_elsewhere(config, unit.unit) {
            fail(key("unit"), why);
        }
    }
    for i in 0..config.virtual_units.len() {
        errors.extend(config.virtual_layout(i).1);
    }
}

/// Why unit `unit` cannot be a virtual unit's: a `[[route]]` sends it to a bus, or the only bus
/// has a slave configured at that address (which the unit would reach without routes).
fn routed_elsewhere(config: &Config, unit: u8) -> Option<String> {
    if let Some(i) = config.route.iter().position(|r| r.units.contains(unit)) {
        return Some(format!(
            "unit {unit} is routed to bus `{}` by route[{i}]: a virtual unit's id must not be \
             routed",
            config.route[i].bus
        ));
    }
    match &config.bus[..] {
        [only] if unit <= only.framing.highest_address() => {
            let configured = only.slave.iter().any(|s| s.address == unit)
                || only.sim_slave.iter().any(|s| s.address.contains(unit));
            configured.then(|| {
                format!(
                    "bus `{}` has a slave at address {unit}, which unit {unit} reaches: \
                     choose a unit no slave answers",
                    only.name
                )
            })
        }
        _ => None,
    }
}

/// Whether `name` may name a virtual unit: as a bus is named, letters, digits, `-`, `_`, `.`.
fn unit_name(name: &str) -> Result<(), String> {
    let fine = |c: char| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.');
    if name.is_empty() || !name.chars().all(fine) {
        return Err(format!(
            "`{name}`: a virtual unit's name is letters, digits, -, _ and ., and not empty"
        ));
    }
    Ok(())
}
