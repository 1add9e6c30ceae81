//! What the gateway publishes for one configuration: every polled value's topic (in the
//! store's order, so a sample's place is its value's), deadband and encoding; every slave's
//! availability topic; Home Assistant's discovery configs; the `set` topics of writable values.
//! Made anew at start and at every reload, from the store's values and the configuration.

use super::discovery;
use crate::config::{Config, Mqtt, Value, ValueType};
use crate::values::ValueSpec;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;

/// One published value.
pub(super) struct Publishable {
    pub(super) topic: Arc<str>,
    pub(super) deadband: f64,
    /// Where it is and how it is held, for a `set`: its bus, slave and configured value.
    pub(super) bus: Arc<str>,
    pub(super) slave: u8,
    pub(super) value: Value,
    /// Its place in [`Catalogue::slaves`].
    pub(super) owner: usize,
}

impl Publishable {
    /// A coil, a discrete input, a `bool` or a bit of a register: published as 0 or 1.
    pub(super) fn is_bool(&self) -> bool {
        self.value.table.is_bits()
            || self.value.kind() == ValueType::Bool
            || self.value.bit.is_some()
    }
}

/// One slave with values.
pub(super) struct Owner {
    pub(super) availability: Arc<str>,
}

/// The slaves with values, as a catalogue is made: each one's place, and its configured values
/// (read once a slave, not once a value).
#[derive(Default)]
struct Slaves<'c> {
    list: Vec<Owner>,
    by: HashMap<(Arc<str>, u8), Known<'c>>,
}

/// A slave's place in [`Slaves::list`] and its configured values.
type Known<'c> = (usize, Vec<&'c Value>);

impl<'c> Slaves<'c> {
    /// The place of `spec`'s slave (added if new), and the configured value `spec` is of.
    fn of(&mut self, prefix: &str, config: &'c Config, spec: &ValueSpec) -> (usize, Option<Value>) {
        let list = &mut self.list;
        let (at, values) = self
            .by
            .entry((spec.bus.clone(), spec.slave))
            .or_insert_with(|| {
                let topic = format!("{prefix}/{}/{}/availability", spec.bus, spec.slave);
                list.push(Owner {
                    availability: topic.into(),
                });
                let values = config.values_of(&spec.bus, spec.slave).unwrap_or_default();
                (list.len() - 1, values.into_iter().map(|(v, _)| v).collect())
            });
        let value = values
            .iter()
            .find(|v| v.name == spec.name && v.labels == spec.labels);
        (*at, value.map(|v| (*v).clone()))
    }
}

/// Everything one configuration publishes.
pub(super) struct Catalogue {
    /// The store's configuration these places are of.
    pub(super) generation: u64,
    pub(super) values: Vec<Publishable>,
    pub(super) slaves: Vec<Owner>,
    /// Discovery topic and its retained config, one per value (with `home_assistant`).
    pub(super) discovery: Vec<(Arc<str>, String)>,
    /// The writable values by their `set` topic (with `writes`).
    pub(super) sets: HashMap<String, usize>,
    pub(super) status: Arc<str>,
    /// Whose discovery configs are the gateway's: `DISCOVERY_PREFIX/COMPONENT/NODE_PREFIX...`.
    pub(super) node_prefix: String,
    pub(super) discovery_prefix: String,
    /// `PREFIX/`: where its values' state topics begin.
    pub(super) state_prefix: Arc<str>,
    /// Every retained topic it publishes (values, availabilities, discovery configs), and the
    /// discovery configs' alone.
    pub(super) retained: HashSet<Arc<str>>,
    pub(super) configs: HashSet<Arc<str>>,
}

/// `text` as Home Assistant's ids take it: letters, digits, `_` and `-`.
pub(super) fn id(text: &str) -> String {
    text.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// A value's topic below its slave's: its name, then `key=value` for each label, in order.
pub(super) fn value_level(name: &str, labels: &BTreeMap<String, String>) -> String {
    if labels.is_empty() {
        return name.to_owned();
    }
    let labels: Vec<String> = labels.iter().map(|(k, v)| format!("{k}={v}")).collect();
    format!("{name}/{}", labels.join(","))
}

impl Catalogue {
    /// Nothing to publish (before the first configuration).
    pub(super) fn empty() -> Catalogue {
        Catalogue {
            generation: u64::MAX,
            values: Vec::new(),
            slaves: Vec::new(),
            discovery: Vec::new(),
            sets: HashMap::new(),
            status: Arc::from(""),
            node_prefix: String::new(),
            discovery_prefix: String::new(),
            state_prefix: Arc::from("\0"),
            retained: HashSet::new(),
            configs: HashSet::new(),
        }
    }

    /// What `settings` publishes of `config`'s values, the store holding `specs` in its
    /// configuration `generation`.
    pub(super) fn new(
        settings: &Mqtt,
        config: &Config,
        (generation, specs): (u64, Vec<ValueSpec>),
    ) -> Catalogue {
        let prefix = &settings.topic_prefix;
        let mut values = Vec::with_capacity(specs.len());
        let mut slaves = Slaves::default();
        let mut discovery = Vec::new();
        let mut sets = HashMap::new();
        let node_prefix = format!("{}_", id(prefix));
        for spec in specs {
            let (owner, value) = slaves.of(prefix, config, &spec);
            let Some(value) = value else {
                continue;
            };
            let level = value_level(&spec.name, &spec.labels);
            let topic: Arc<str> = format!("{prefix}/{}/{}/{level}", spec.bus, spec.slave).into();
            let item = Publishable {
                topic,
                deadband: value.deadband,
                bus: spec.bus.clone(),
                slave: spec.slave,
                value,
                owner,
            };
            if settings.writes && item.value.writable {
                sets.insert(format!("{}/set", item.topic), values.len());
            }
            if settings.home_assistant {
                let model = template_of(config, &spec.bus, spec.slave);
                discovery.push(discovery::config(
                    settings,
                    &node_prefix,
                    &item,
                    &spec,
                    model,
                    &slaves.list[owner],
                ));
            }
            values.push(item);
        }
        let slaves = slaves.list;
        let configs: HashSet<Arc<str>> = discovery.iter().map(|(t, _)| t.clone()).collect();
        let retained = values
            .iter()
            .map(|v| v.topic.clone())
            .chain(slaves.iter().map(|s| s.availability.clone()))
            .chain(configs.iter().cloned())
            .collect();
        Catalogue {
            generation,
            values,
            slaves,
            discovery,
            sets,
            status: format!("{prefix}/status").into(),
            node_prefix,
            discovery_prefix: settings.discovery_prefix.clone(),
            state_prefix: format!("{prefix}/").into(),
            retained,
            configs,
        }
    }

    /// Whether `topic`, holding `config`, is a discovery config of this gateway's: under its
    /// node prefix, and of a value under its topic prefix.
    pub(super) fn is_ours(&self, topic: &str, config: &[u8]) -> bool {
        let Some(rest) = topic.strip_prefix(&self.discovery_prefix) else {
            return false;
        };
        let mut levels = rest.trim_start_matches('/').split('/');
        let (_component, node) = (levels.next(), levels.next());
        if !(node.is_some_and(|n| n.starts_with(&self.node_prefix)) && topic.ends_with("/config")) {
            return false;
        }
        #[derive(serde::Deserialize)]
        struct Discovered<'a> {
            #[serde(borrow)]
            state_topic: Option<std::borrow::Cow<'a, str>>,
        }
        let state = serde_json::from_slice::<Discovered<'_>>(config)
            .ok()
            .and_then(|c| c.state_topic);
        state.is_some_and(|t| t.starts_with(&*self.state_prefix))
    }
}

/// The template slave `slave` of `bus` names, if any.
fn template_of<'a>(config: &'a Config, bus: &str, slave: u8) -> Option<&'a str> {
    let bus = config.bus.iter().find(|b| b.name == bus)?;
    bus.slave
        .iter()
        .find(|s| s.address == slave)?
        .template
        .as_deref()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn catalogue(prefix: &str) -> Catalogue {
        let text = format!(
            "[[bus]]\nname = \"line\"\ndevice = \"sim\"\n[[bus.slave]]\naddress = 2\n\
             [[bus.slave.value]]\nname = \"power_watts\"\nregister = 0\nunit = \"W\"\n\
             [mqtt]\nurl = \"mqtt://127.0.0.1\"\ntopic_prefix = \"{prefix}\"\n"
        );
        let config = Config::from_toml_str(&text).unwrap();
        let spec = ValueSpec {
            bus: "line".into(),
            slave: 2,
            name: "power_watts".to_owned(),
            help: String::new(),
            unit: Some("W".to_owned()),
            labels: BTreeMap::new(),
        };
        Catalogue::new(config.mqtt.as_ref().unwrap(), &config, (7, vec![spec]))
    }

    #[test]
    fn a_gateway_claims_the_discovery_configs_of_its_own_prefix_only() {
        let plant = catalogue("plant");
        let north = catalogue("plant_north");
        let (topic, config) = &north.discovery[0];
        assert_eq!(
            &**topic,
            "homeassistant/sensor/plant_north_line_2/power_watts/config"
        );
        assert!(north.is_ours(topic, config.as_bytes()));
        assert!(
            !plant.is_ours(topic, config.as_bytes()),
            "plant_north's is not plant's"
        );
        let (own, own_config) = &plant.discovery[0];
        assert!(plant.is_ours(own, own_config.as_bytes()));
        assert!(
            !plant.is_ours(own, b"not json"),
            "no state topic of its own"
        );
        assert_eq!(&*plant.values[0].topic, "plant/line/2/power_watts");
        assert_eq!(plant.generation, 7);
    }

    #[test]
    fn labels_make_a_level_of_their_own_in_key_order() {
        let labels = BTreeMap::from([
            ("phase".to_owned(), "2".to_owned()),
            ("kind".to_owned(), "l-n".to_owned()),
        ]);
        assert_eq!(value_level("voltage", &labels), "voltage/kind=l-n,phase=2");
        assert_eq!(value_level("voltage", &BTreeMap::new()), "voltage");
        assert_eq!(id("modbus-gateway/a.b"), "modbus-gateway_a_b");
    }
}
