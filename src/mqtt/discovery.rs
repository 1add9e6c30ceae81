//! Home Assistant's MQTT discovery: one retained config per value at
//! `DISCOVERY_PREFIX/sensor/NODE/OBJECT/config` (`binary_sensor` for a bit), naming its state
//! topic, the gateway's and the slave's availability, its unit and the device class the unit
//! says, and one device per slave. The ids are made of the topic prefix, the bus, the slave and
//! the value, so they stay the same across restarts.

use super::catalogue::{id, Owner, Publishable};
use crate::config::Mqtt;
use crate::values::ValueSpec;
use serde_json::{json, Value};
use std::sync::Arc;

/// Home Assistant's device class and state class for a value in `unit`, where the unit says
/// one.
fn classes(unit: &str) -> (Option<&'static str>, &'static str) {
    let class = match unit {
        "V" | "mV" | "kV" => "voltage",
        "A" | "mA" => "current",
        "W" | "kW" | "MW" => "power",
        "VA" | "kVA" => "apparent_power",
        "var" | "kvar" => "reactive_power",
        "Hz" => "frequency",
        "Wh" | "kWh" | "MWh" => return (Some("energy"), "total_increasing"),
        "varh" | "kvarh" => return (Some("reactive_energy"), "total_increasing"),
        "°C" | "°F" | "K" => "temperature",
        "Pa" | "hPa" | "kPa" | "bar" | "mbar" | "psi" => "pressure",
        "s" | "ms" | "min" | "h" | "d" => "duration",
        _ => return (None, "measurement"),
    };
    (Some(class), "measurement")
}

/// A value's name as Home Assistant shows an entity's: `drive_output_frequency_hertz` as
/// `Drive output frequency hertz`.
fn words(name: &str) -> String {
    let spaced = name.replace(['_', ':'], " ");
    let mut chars = spaced.trim().chars();
    chars
        .next()
        .map(|first| first.to_uppercase().chain(chars).collect())
        .unwrap_or_default()
}

/// The discovery topic and retained config of `item` (whose store entry is `spec`), its slave
/// `owner` using `model` (its template), for the gateway's `settings`.
pub(super) fn config(
    settings: &Mqtt,
    node_prefix: &str,
    item: &Publishable,
    spec: &ValueSpec,
    model: Option<&str>,
    owner: &Owner,
) -> (Arc<str>, String) {
    let node = format!("{node_prefix}{}_{}", id(&spec.bus), spec.slave);
    let mut object = id(&spec.name);
    for (key, value) in &spec.labels {
        object.push_str(&format!("_{}_{}", id(key), id(value)));
    }
    let component = if item.is_bool() {
        "binary_sensor"
    } else {
        "sensor"
    };
    let mut name = words(&spec.name);
    if !spec.labels.is_empty() {
        let labels: Vec<String> = spec
            .labels
            .iter()
            .map(|(k, v)| format!("{k} {v}"))
            .collect();
        name.push_str(&format!(" ({})", labels.join(", ")));
    }
    let mut config = json!({
        "name": name,
        "unique_id": format!("{node}_{object}"),
        "state_topic": &*item.topic,
        "availability": [
            {"topic": format!("{}/status", settings.topic_prefix)},
            {"topic": &*owner.availability},
        ],
        "availability_mode": "all",
        "device": {
            "identifiers": [node.clone()],
            "name": format!("{} slave {}", spec.bus, spec.slave),
            "model": model.unwrap_or("Modbus slave"),
        },
        "origin": {
            "name": "modbus-gateway",
            "sw_version": env!("CARGO_PKG_VERSION"),
        },
    });
    let fields = config.as_object_mut().expect("a JSON object");
    if item.is_bool() {
        fields.insert("payload_on".into(), Value::from("1"));
        fields.insert("payload_off".into(), Value::from("0"));
    } else {
        let (device_class, state_class) =
            spec.unit.as_deref().map_or((None, "measurement"), classes);
        if let Some(unit) = &spec.unit {
            fields.insert("unit_of_measurement".into(), Value::from(unit.as_str()));
        }
        if let Some(class) = device_class {
            fields.insert("device_class".into(), Value::from(class));
        }
        fields.insert("state_class".into(), Value::from(state_class));
    }
    let topic = format!(
        "{}/{component}/{node}/{object}/config",
        settings.discovery_prefix
    );
    (topic.into(), config.to_string())
}
