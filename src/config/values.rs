//! Plant values: the `[[bus.slave.value]]` tables, the device templates that list a device's
//! values once (the shipped ones built in, the user's read from `template_dir`), and their
//! checks: names by Prometheus's rules, register ranges, types and the keys that go with them.
//! Plain values and the reading of template files; knows nothing of polling or exporting.

use super::load::{ConfigError, ConfigErrors};
use super::serde_adapters::{is_false, is_zero_f64, opt_duration, words, Choice};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The most registers one read may ask for (Modbus Application Protocol V1.1b3, 6.3).
pub(crate) const MAX_READ_REGISTERS: u16 = 125;
/// The most coils or discrete inputs one read may ask for (6.1, 6.2).
pub(crate) const MAX_READ_BITS: u16 = 2000;
/// The prefix of the gateway's own metrics, which no value may take.
const OWN_PREFIX: &str = "modbus_gateway_";
/// Suffixes promtool's lint reserves for counters, histograms and info metrics.
const RESERVED_SUFFIXES: [&str; 6] = ["_total", "_count", "_sum", "_bucket", "_created", "_info"];
/// The labels every value's series has.
const OWN_LABELS: [&str; 2] = ["bus", "slave"];

/// Where a value's registers are, and which function reads them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Table {
    /// Holding registers, read with 03.
    #[default]
    Holding,
    /// Input registers, read with 04.
    Input,
    /// Coils, read with 01.
    Coil,
    /// Discrete inputs, read with 02.
    Discrete,
}

impl Table {
    const ALL: [Table; 4] = [Table::Holding, Table::Input, Table::Coil, Table::Discrete];

    /// The function code that reads it.
    pub fn function(self) -> u8 {
        match self {
            Table::Coil => 0x01,
            Table::Discrete => 0x02,
            Table::Holding => 0x03,
            Table::Input => 0x04,
        }
    }

    /// Coils and discrete inputs: one bit each, not a register.
    pub fn is_bits(self) -> bool {
        matches!(self, Table::Coil | Table::Discrete)
    }

    /// Input registers and discrete inputs: no function code writes them.
    pub fn is_read_only(self) -> bool {
        matches!(self, Table::Input | Table::Discrete)
    }

    /// As the configuration spells it.
    pub fn name(self) -> &'static str {
        match self {
            Table::Holding => "holding",
            Table::Input => "input",
            Table::Coil => "coil",
            Table::Discrete => "discrete",
        }
    }
}

/// How a value's registers are read as a number.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ValueType {
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F32,
    F64,
    Bool,
}

impl ValueType {
    const ALL: [ValueType; 9] = [
        ValueType::U16,
        ValueType::I16,
        ValueType::U32,
        ValueType::I32,
        ValueType::U64,
        ValueType::I64,
        ValueType::F32,
        ValueType::F64,
        ValueType::Bool,
    ];

    /// How many registers it takes (one coil or input for `bool` on a bit table).
    pub fn registers(self) -> u16 {
        match self {
            ValueType::U16 | ValueType::I16 | ValueType::Bool => 1,
            ValueType::U32 | ValueType::I32 | ValueType::F32 => 2,
            ValueType::U64 | ValueType::I64 | ValueType::F64 => 4,
        }
    }

    /// As the configuration spells it.
    pub fn name(self) -> &'static str {
        match self {
            ValueType::U16 => "u16",
            ValueType::I16 => "i16",
            ValueType::U32 => "u32",
            ValueType::I32 => "i32",
            ValueType::U64 => "u64",
            ValueType::I64 => "i64",
            ValueType::F32 => "f32",
            ValueType::F64 => "f64",
            ValueType::Bool => "bool",
        }
    }
}

/// Big: the most significant first; little: the least.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Order {
    #[default]
    Big,
    Little,
}

impl Order {
    const ALL: [Order; 2] = [Order::Big, Order::Little];

    fn is_big(&self) -> bool {
        *self == Order::Big
    }

    fn name(self) -> &'static str {
        match self {
            Order::Big => "big",
            Order::Little => "little",
        }
    }
}

impl Choice for Table {
    const ALL: &'static [Self] = &Table::ALL;
    fn word(self) -> &'static str {
        self.name()
    }
}

impl Choice for ValueType {
    const ALL: &'static [Self] = &ValueType::ALL;
    fn word(self) -> &'static str {
        self.name()
    }
}

impl Choice for Order {
    const ALL: &'static [Self] = &Order::ALL;
    fn word(self) -> &'static str {
        self.name()
    }
}

words!(Table, ValueType, Order);

/// One value of a slave: where it is, how to read it, what to call it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Value {
    /// The metric's name.
    pub name: String,
    /// The first register (coil, input), 0-based as the manuals number them.
    pub register: u32,
    #[serde(default)]
    pub table: Table,
    /// Left out: `u16` on a register table, `bool` on a bit table ([`Value::kind`]).
    #[serde(default, rename = "type", skip_serializing_if = "Option::is_none")]
    pub kind: Option<ValueType>,
    /// One bit of a 16-bit register (0 the least significant): the value is 0 or 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bit: Option<u8>,
    #[serde(default, skip_serializing_if = "Order::is_big")]
    pub word_order: Order,
    #[serde(default, skip_serializing_if = "Order::is_big")]
    pub byte_order: Order,
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub scale: f64,
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub offset: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unit: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub help: Option<String>,
    /// Constant labels of its series, besides `bus` and `slave`.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub labels: BTreeMap<String, String>,
    /// Its own interval; left out, its slave's.
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub poll_interval: Option<Duration>,
    /// MQTT: a change of at most this much (in its units) is not published (0: every change).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub deadband: f64,
    /// MQTT: `PREFIX/BUS/SLAVE/NAME/set` may write it (with `mqtt.writes`).
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

impl Value {
    /// How many registers (coils, inputs) it takes from `register` on.
    pub fn width(&self) -> u16 {
        self.kind().registers()
    }

    /// `deadband` and `writable`, the keys MQTT reads.
    fn check_mqtt_keys(&self, fail: &mut impl FnMut(&str, String)) {
        if !(self.deadband.is_finite() && self.deadband >= 0.0) {
            fail(
                "deadband",
                format!(
                    "{} is not a change of zero or more, in the value's units",
                    self.deadband
                ),
            );
        }
        if self.writable && self.table.is_read_only() {
            let what = match self.table {
                Table::Input => "input registers",
                _ => "discrete inputs",
            };
            fail(
                "writable",
                format!(
                    "{what} cannot be written (table = \"{}\")",
                    self.table.name()
                ),
            );
        } else if self.writable && self.bit.is_some() {
            fail(
                "writable",
                "one bit of a register cannot be written without writing its other bits: \
                 make a coil or a whole register writable"
                    .to_owned(),
            );
        }
    }

    /// Every problem with it, each with its key under `at` (`bus[0].slave[1].value[2]`).
    pub(super) fn check(&self, at: &str, errors: &mut Vec<ConfigError>) {
        let mut fail = |key: &str, reason: String| {
            errors.push(ConfigError {
                key: format!("{at}.{key}"),
                reason,
            });
        };
        if let Err(why) = metric_name(&self.name) {
            fail("name", why);
        }
        self.check_mqtt_keys(&mut fail);
        let kind = self.kind();
        if self.table.is_bits() && kind != ValueType::Bool {
            fail(
                "type",
                format!(
                    "a {} holds one bit: its type is \"bool\", not \"{}\"",
                    self.table.name(),
                    kind.name()
                ),
            );
        }
        let end = u64::from(self.register) + u64::from(self.width()) - 1;
        if end > u64::from(u16::MAX) {
            fail(
                "register",
                format!(
                    "{} with {} register(s) of {} ends at {end}, past 65535",
                    self.register,
                    self.width(),
                    kind.name()
                ),
            );
        }
        if let Some(bit) = self.bit {
            if self.table.is_bits() {
                fail(
                    "bit",
                    format!("a {} has no bits to pick", self.table.name()),
                );
            } else if kind.registers() != 1 {
                fail(
                    "bit",
                    format!(
                        "picks one bit of a 16-bit register; \"{}\" takes {} registers",
                        kind.name(),
                        kind.registers()
                    ),
                );
            } else if bit > 15 {
                fail("bit", format!("{bit} is not a bit of a register (0-15)"));
            }
        }
        if !self.scale.is_finite() || self.scale == 0.0 {
            fail(
                "scale",
                format!("{} must be a number other than 0", self.scale),
            );
        }
        if !self.offset.is_finite() {
            fail("offset", format!("{} must be a number", self.offset));
        }
        for label in self.labels.keys() {
            if let Err(why) = label_name(label) {
                fail(&format!("labels.{label}"), why);
            }
        }
        if self.poll_interval.is_some_and(|d| d.is_zero()) {
            fail("poll_interval", "must be longer than 0".to_owned());
        }
    }
}

/// Whether `name` is a name by Prometheus's rules for `what` (metrics and labels share them
/// here, since values' names need no colon), and not one of Prometheus's own (`__`).
fn prometheus_name(name: &str, what: &str) -> Result<(), String> {
    let mut chars = name.chars();
    let first_ok = chars
        .next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_');
    if !first_ok || !chars.all(|c| c.is_ascii_alphanumeric() || c == '_') {
        return Err(format!(
            "`{name}` is no Prometheus {what} name: letters, digits and _, not first a digit"
        ));
    }
    if name.starts_with("__") {
        return Err(format!(
            "`{name}`: {what} names starting with __ are Prometheus's own"
        ));
    }
    Ok(())
}

/// Whether `name` may be a value's metric: Prometheus's rules, and none of the names the gateway
/// or promtool's lint keep for themselves.
pub(crate) fn metric_name(name: &str) -> Result<(), String> {
    prometheus_name(name, "metric")?;
    if name.starts_with(OWN_PREFIX) {
        return Err(format!(
            "`{name}`: names starting with {OWN_PREFIX} are the gateway's own metrics"
        ));
    }
    if let Some(suffix) = RESERVED_SUFFIXES.iter().find(|s| name.ends_with(*s)) {
        return Err(format!(
            "`{name}`: a value is a gauge, and {suffix} is for other kinds of metric"
        ));
    }
    Ok(())
}

/// Whether `name` may be a constant label of a value.
fn label_name(name: &str) -> Result<(), String> {
    prometheus_name(name, "label")?;
    if OWN_LABELS.contains(&name) {
        return Err(format!("`{name}` is a label every value has already"));
    }
    Ok(())
}

/// A device's values, once, for every slave of that device.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Template {
    /// What device, from which manual.
    #[serde(default)]
    pub description: String,
    /// The device's own limit on registers per read.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_read_registers: Option<u16>,
    #[serde(default)]
    pub value: Vec<Value>,
}

/// `(NAME, text of config/templates/NAME.toml)` for each name: the file is named once, by the
/// template's name.
macro_rules! shipped {
    ($($name:literal),* $(,)?) => {
        &[$(($name, include_str!(concat!("../../config/templates/", $name, ".toml")))),*]
    };
}

/// The shipped templates (config/templates/), built in: name and text. A test checks that the
/// list is the folder's.
const SHIPPED: &[(&str, &str)] = shipped![
    "goodrive20",
    "goodrive300",
    "goodrive10",
    "pd-inverter",
    "eastron-sdm120",
    "eastron-sdm630",
];

/// The templates a configuration may name: the shipped ones, and those of `template_dir`, which
/// replace shipped ones of the same name. Each with where it came from, for the errors.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Templates {
    by_name: BTreeMap<String, (Template, String)>,
}

impl Templates {
    /// The shipped templates, and those in `dir` (every `NAME.toml` in it) if given. Every
    /// problem is reported under `key` (the `template_dir` key), naming the file and the key in
    /// it.
    pub(crate) fn load(dir: Option<&Path>, key: &str) -> Result<Templates, ConfigErrors> {
        let mut templates = Templates::default();
        let mut errors = Vec::new();
        for (name, text) in SHIPPED {
            let source = format!("the shipped template {name}");
            match parse(text, &source, key) {
                Ok(template) => {
                    templates
                        .by_name
                        .insert((*name).to_owned(), (template, source));
                }
                Err(more) => errors.extend(more),
            }
        }
        if let Some(dir) = dir {
            if let Err(more) = templates.read_dir(dir, key) {
                errors.extend(more);
            }
        }
        if errors.is_empty() {
            Ok(templates)
        } else {
            Err(ConfigErrors(errors))
        }
    }

    fn read_dir(&mut self, dir: &Path, key: &str) -> Result<(), Vec<ConfigError>> {
        let fail = |reason: String| ConfigError {
            key: key.to_owned(),
            reason,
        };
        let entries = std::fs::read_dir(dir)
            .map_err(|e| vec![fail(format!("cannot read {}: {e}", dir.display()))])?;
        let mut files: Vec<PathBuf> = entries
            .filter_map(|entry| Some(entry.ok()?.path()))
            .filter(|path| path.extension().is_some_and(|ext| ext == "toml"))
            .collect();
        files.sort();
        let mut errors = Vec::new();
        for path in files {
            let Some(name) = path.file_stem().and_then(|s| s.to_str()) else {
                continue;
            };
            let source = path.display().to_string();
            let text = match std::fs::read_to_string(&path) {
                Ok(text) => text,
                Err(e) => {
                    errors.push(fail(format!("cannot read {source}: {e}")));
                    continue;
                }
            };
            match parse(&text, &source, key) {
                Ok(template) => {
                    self.by_name.insert(name.to_owned(), (template, source));
                }
                Err(more) => errors.extend(more),
            }
        }
        if errors.is_empty() {
            Ok(())
        } else {
            Err(errors)
        }
    }

    /// The template called `name`, and where it came from.
    pub fn get(&self, name: &str) -> Option<&Template> {
        self.by_name.get(name).map(|(template, _)| template)
    }

    /// Every name, in order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.by_name.keys().map(String::as_str)
    }
}

/// `text` as a template, checked; its problems reported under `key`, naming `source` and the key
/// within it.
fn parse(text: &str, source: &str, key: &str) -> Result<Template, Vec<ConfigError>> {
    let fail = |reason: String| ConfigError {
        key: key.to_owned(),
        reason,
    };
    let deserializer = toml::Deserializer::parse(text)
        .map_err(|e| vec![fail(format!("{source}: {}", e.message()))])?;
    let template: Template = serde_path_to_error::deserialize(deserializer).map_err(|e| {
        let path = e.path().to_string();
        vec![fail(format!("{source}: {path}: {}", e.inner().message()))]
    })?;
    let mut errors = Vec::new();
    for (i, value) in template.value.iter().enumerate() {
        let mut inner = Vec::new();
        value.check(&format!("value[{i}]"), &mut inner);
        if value.poll_interval.is_some() {
            inner.push(ConfigError {
                key: format!("value[{i}].poll_interval"),
                reason: "a template's values take their slave's poll_interval".to_owned(),
            });
        }
        errors.extend(
            inner
                .into_iter()
                .map(|e| fail(format!("{source}: {}: {}", e.key, e.reason))),
        );
    }
    if let Some(max) = template.max_read_registers {
        if !(1..=MAX_READ_REGISTERS).contains(&max) {
            errors.push(fail(format!(
                "{source}: max_read_registers: {max} must be 1 to {MAX_READ_REGISTERS}"
            )));
        }
    }
    if errors.is_empty() {
        Ok(template)
    } else {
        Err(errors)
    }
}

/// Check the values of the slave at `at` (`bus[0].slave[1]`): its own, each under
/// `at.value[N]`, and with its template's (named by `template`, reported under `at.template`),
/// that no two share a name and labels, and that `max_read_registers` is a read's.
pub(crate) fn check_slave(
    at: &str,
    slave: &super::Slave,
    templates: &Templates,
    errors: &mut Vec<ConfigError>,
) {
    let template = slave_template(at, slave, templates, errors);
    for (i, value) in slave.value.iter().enumerate() {
        value.check(&format!("{at}.value[{i}]"), errors);
    }
    check_series_once(at, slave, template, errors);
    check_read_limit(at, slave, template, errors);
    if slave.poll_interval.is_some_and(|d| d.is_zero()) {
        errors.push(ConfigError {
            key: format!("{at}.poll_interval"),
            reason: "must be longer than 0".to_owned(),
        });
    }
}

/// The template the slave at `at` names, if it names one that exists; one it does not find is
/// an error listing those there are.
fn slave_template<'t>(
    at: &str,
    slave: &super::Slave,
    templates: &'t Templates,
    errors: &mut Vec<ConfigError>,
) -> Option<&'t Template> {
    let name = slave.template.as_ref()?;
    let found = templates.get(name);
    if found.is_none() {
        let known: Vec<&str> = templates.names().collect();
        let known = if known.is_empty() {
            "there are none".to_owned()
        } else {
            format!("there are {}", known.join(", "))
        };
        errors.push(ConfigError {
            key: format!("{at}.template"),
            reason: format!("no template `{name}`: {known} (shipped, and in template_dir)"),
        });
    }
    found
}

/// One series per name and label set: a template's values and the slave's own together.
fn check_series_once(
    at: &str,
    slave: &super::Slave,
    template: Option<&Template>,
    errors: &mut Vec<ConfigError>,
) {
    let mut seen: BTreeMap<(&str, &BTreeMap<String, String>), String> = BTreeMap::new();
    let from_template = template
        .into_iter()
        .flat_map(|t| t.value.iter().enumerate())
        .map(|(i, v)| (v, format!("{at}.template (its value[{i}])")));
    let own = slave
        .value
        .iter()
        .enumerate()
        .map(|(i, v)| (v, format!("{at}.value[{i}]")));
    for (value, key) in from_template.chain(own) {
        if let Some(first) = seen.insert((value.name.as_str(), &value.labels), key.clone()) {
            errors.push(ConfigError {
                key: format!("{key}.name"),
                reason: format!(
                    "`{}` is already a value of this slave ({first}): a series once",
                    value.name
                ),
            });
        }
    }
}

/// `max_read_registers` is a read's, and no fewer registers than the widest value takes.
fn check_read_limit(
    at: &str,
    slave: &super::Slave,
    template: Option<&Template>,
    errors: &mut Vec<ConfigError>,
) {
    let key = format!("{at}.max_read_registers");
    if let Some(max) = slave.max_read_registers {
        if !(1..=MAX_READ_REGISTERS).contains(&max) {
            let reason = format!("{max} must be 1 to {MAX_READ_REGISTERS}");
            errors.push(ConfigError {
                key: key.clone(),
                reason,
            });
        }
    }
    let most = slave.read_limit(template);
    let widest = template
        .into_iter()
        .flat_map(|t| &t.value)
        .chain(&slave.value)
        .filter(|v| !v.table.is_bits())
        .map(Value::width)
        .max()
        .unwrap_or(0);
    if widest > most {
        let reason =
            format!("{most} is fewer registers than a value of this slave takes ({widest})");
        errors.push(ConfigError { key, reason });
    }
}

/// Across every slave of every bus: a name is one metric, whose HELP and label names must
/// agree wherever it is used. `values` are (key, value) in the file's order.
pub(crate) fn check_families<'a>(
    values: impl Iterator<Item = (String, &'a Value)>,
    errors: &mut Vec<ConfigError>,
) {
    let mut families: BTreeMap<&str, (String, &str, Vec<&str>)> = BTreeMap::new();
    for (key, value) in values {
        let labels: Vec<&str> = value.labels.keys().map(String::as_str).collect();
        match families.get(value.name.as_str()) {
            None => {
                families.insert(&value.name, (key, value.help_text(), labels));
            }
            Some((first, help, first_labels)) => {
                if *help != value.help_text() {
                    errors.push(ConfigError {
                        key: format!("{key}.help"),
                        reason: format!(
                            "`{}` has another help at {first}: one metric, one help",
                            value.name
                        ),
                    });
                } else if *first_labels != labels {
                    errors.push(ConfigError {
                        key: format!("{key}.labels"),
                        reason: format!(
                            "`{}` has other label names at {first}: one metric, one set of \
                             label names",
                            value.name
                        ),
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(text: &str) -> Value {
        toml::from_str(text).expect("a value")
    }

    fn problems(v: &Value) -> Vec<String> {
        let mut errors = Vec::new();
        v.check("v", &mut errors);
        errors.iter().map(ToString::to_string).collect()
    }

    #[test]
    fn the_shipped_templates_are_the_files_of_config_templates() {
        let folder = concat!(env!("CARGO_MANIFEST_DIR"), "/config/templates");
        let mut files: Vec<String> = std::fs::read_dir(folder)
            .expect("config/templates")
            .filter_map(|entry| {
                let name = entry.ok()?.file_name().into_string().ok()?;
                name.strip_suffix(".toml").map(str::to_owned)
            })
            .collect();
        files.sort();
        let mut shipped: Vec<String> = SHIPPED.iter().map(|(n, _)| (*n).to_owned()).collect();
        shipped.sort();
        assert_eq!(shipped, files, "SHIPPED and config/templates/ differ");
    }

    #[test]
    fn a_value_takes_its_tables_type_and_the_defaults_of_a_plain_register() {
        let v = value("name = \"a\"\nregister = 0x3000\n");
        assert_eq!(
            (v.table, v.kind(), v.width()),
            (Table::Holding, ValueType::U16, 1)
        );
        assert_eq!((v.scale, v.offset), (1.0, 0.0));
        let coil = value("name = \"b\"\nregister = 7\ntable = \"coil\"\n");
        assert_eq!(
            (coil.kind(), coil.table.function()),
            (ValueType::Bool, 0x01)
        );
        assert!(problems(&v).is_empty() && problems(&coil).is_empty());
    }

    #[test]
    fn names_prometheus_refuses_or_the_gateway_keeps_are_refused() {
        for (name, why) in [
            ("2fast", "no Prometheus metric name"),
            ("drive-speed", "no Prometheus metric name"),
            ("__hidden", "Prometheus's own"),
            ("modbus_gateway_requests", "the gateway's own"),
            ("energy_total", "_total is for other kinds"),
        ] {
            let v = value(&format!("name = \"{name}\"\nregister = 0\n"));
            let found = problems(&v);
            assert!(
                found.len() == 1 && found[0].starts_with("v.name:") && found[0].contains(why),
                "{name}: {found:?}"
            );
        }
    }

    /// A range past 65535, a bit of a 32-bit type and a type a coil cannot have are each refused.
    #[test]
    fn out_of_range_addresses_bits_of_wide_types_and_coil_types_are_refused() {
        // An f32 in the last two registers ends at 65535: it fits.
        let last = value("name = \"a\"\nregister = 65534\ntype = \"f32\"\n");
        assert!(problems(&last).is_empty());
        let far = value("name = \"a\"\nregister = 65534\ntype = \"u64\"\n");
        assert_eq!(
            problems(&far),
            ["v.register: 65534 with 4 register(s) of u64 ends at 65537, past 65535"]
        );
        let bit = value("name = \"a\"\nregister = 0\ntype = \"u32\"\nbit = 3\n");
        assert_eq!(
            problems(&bit),
            ["v.bit: picks one bit of a 16-bit register; \"u32\" takes 2 registers"]
        );
        let coil = value("name = \"a\"\nregister = 0\ntable = \"coil\"\ntype = \"u16\"\n");
        assert_eq!(
            problems(&coil),
            ["v.type: a coil holds one bit: its type is \"bool\", not \"u16\""]
        );
        let label = value("name = \"a\"\nregister = 0\nlabels = { slave = \"x\" }\n");
        assert_eq!(
            problems(&label),
            ["v.labels.slave: `slave` is a label every value has already"]
        );
    }

    #[test]
    fn the_shipped_templates_load_each_with_its_devices_limit_and_no_value_past_it() {
        let templates = Templates::load(None, "template_dir").expect("the shipped templates");
        let names: Vec<&str> = templates.names().collect();
        assert_eq!(
            names,
            [
                "eastron-sdm120",
                "eastron-sdm630",
                "goodrive10",
                "goodrive20",
                "goodrive300",
                "pd-inverter"
            ]
        );
        for name in names {
            let template = templates.get(name).unwrap();
            assert!(!template.value.is_empty(), "{name}");
            let most = template.max_read_registers.unwrap_or(MAX_READ_REGISTERS);
            assert!(template.value.iter().all(|v| v.width() <= most), "{name}");
        }
        assert_eq!(
            templates.get("goodrive300").unwrap().max_read_registers,
            Some(16)
        );
    }

    #[test]
    fn a_template_file_with_problems_names_its_file_and_the_key_in_it() {
        let text = "description = \"x\"\n[[value]]\nname = \"a\"\nregister = 1\ntype = \"u17\"\n";
        let errors = parse(text, "t.toml", "template_dir").unwrap_err();
        assert_eq!(errors.len(), 1);
        assert_eq!(errors[0].key, "template_dir");
        assert!(
            errors[0]
                .reason
                .starts_with("t.toml: value[0].type: `u17` is not u16, i16, u32"),
            "{}",
            errors[0].reason
        );
        let text = "[[value]]\nname = \"energy_total\"\nregister = 1\npoll_interval = \"1s\"\n";
        let errors = parse(text, "t.toml", "template_dir").unwrap_err();
        let reasons: Vec<&str> = errors.iter().map(|e| e.reason.as_str()).collect();
        assert_eq!(reasons.len(), 2, "{reasons:?}");
        assert!(reasons[0].starts_with("t.toml: value[0].name: `energy_total`"));
        assert!(reasons[1].starts_with("t.toml: value[0].poll_interval:"));
    }
}

#[cfg(test)]
mod printed {
    use crate::config::Config;

    #[test]
    fn a_configuration_with_values_prints_as_it_reads_back() {
        let text = r#"
[[bus]]
name = "line"
device = "sim"
poll_share = 0.3

[[bus.slave]]
address = 3
poll_interval = "2s"
max_read_registers = 16

[[bus.slave.value]]
name = "pressure_pascals"
register = 0x10
table = "input"
type = "f32"
word_order = "little"
byte_order = "little"
scale = 100000.0
offset = -1.5
unit = "Pa"
help = "Pressure"
labels = { site = "north" }
poll_interval = "500ms"

[[bus.slave.value]]
name = "running"
register = 0x2100
bit = 0
"#;
        let config = Config::from_toml_str(text).expect("a configuration");
        let printed = config.to_toml();
        assert_eq!(Config::from_toml_str(&printed).expect("printed"), config);
        assert!(printed.contains("table = \"input\""), "{printed}");
    }
}
