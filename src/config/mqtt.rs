//! The `[mqtt]` table: the broker the plant values are published to (and, with `writes`, set
//! from), how the gateway logs in, what its topics are called, and how often an unchanged value
//! is published again. Values only: the client is `crate::mqtt`'s. Every key is read as written
//! and checked after (`check`), so one run names every mistake.

use super::defaults;
use super::load::ConfigError;
use super::serde_adapters::duration;
use super::Config;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::time::Duration;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mqtt {
    /// `mqtt://HOST[:PORT]` (1883) or `mqtts://HOST[:PORT]` (8883), as written; [`Mqtt::broker`]
    /// reads it.
    pub url: String,
    /// Left out: `modbus-gateway-` and the host's name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_id: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub username: Option<String>,
    /// Refused: a password is read from `password_file` only, never kept in the configuration.
    #[serde(default, skip_serializing)]
    pub password: Option<toml::Value>,
    /// The password, the file's first line.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub password_file: Option<PathBuf>,
    /// `mqtts`: the CA that signed the broker's certificate (left out: the system's roots are
    /// not read; name one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ca_file: Option<PathBuf>,
    /// `mqtts` with mutual TLS: the gateway's certificate and key.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cert_file: Option<PathBuf>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub key_file: Option<PathBuf>,
    #[serde(default = "defaults::mqtt_topic_prefix")]
    pub topic_prefix: String,
    /// 0 or 1, as written.
    #[serde(default = "defaults::mqtt_qos")]
    pub qos: i64,
    #[serde(default = "defaults::yes")]
    pub retain: bool,
    /// An unchanged value is published again at least this often.
    #[serde(default = "defaults::mqtt_publish_interval", with = "duration")]
    pub publish_interval: Duration,
    /// Home Assistant's MQTT discovery: one retained config per value.
    #[serde(default = "defaults::yes")]
    pub home_assistant: bool,
    #[serde(default = "defaults::mqtt_discovery_prefix")]
    pub discovery_prefix: String,
    /// `PREFIX/BUS/SLAVE/NAME/set` writes a `writable` value, under the rules and the journal.
    #[serde(default)]
    pub writes: bool,
}

/// Where the broker is, read from `url`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Broker {
    pub host: String,
    pub port: u16,
    /// `mqtts`.
    pub tls: bool,
}

/// The lowest `publish_interval`: below it a broker would see every value every moment.
const MIN_PUBLISH_INTERVAL: Duration = Duration::from_secs(1);

impl Mqtt {
    /// The broker `url` names, or why it names none.
    pub fn broker(&self) -> Result<Broker, String> {
        let (tls, rest) = if let Some(rest) = self.url.strip_prefix("mqtt://") {
            (false, rest)
        } else if let Some(rest) = self.url.strip_prefix("mqtts://") {
            (true, rest)
        } else {
            return Err(format!(
                "`{}` is not an MQTT broker's URL: mqtt://HOST[:PORT] or mqtts://HOST[:PORT]",
                self.url
            ));
        };
        let rest = rest.strip_suffix('/').unwrap_or(rest);
        let default_port = if tls { 8883 } else { 1883 };
        // An IPv6 address is in brackets: `[::1]:1883`.
        let (host, port) = match rest.rsplit_once(':') {
            Some((host, port))
                if !host.ends_with(':') && (!host.contains(':') || host.ends_with(']')) =>
            {
                let port = port
                    .parse::<u16>()
                    .ok()
                    .filter(|p| *p != 0)
                    .ok_or_else(|| format!("`{port}` in `{}` is not a port", self.url))?;
                (host, port)
            }
            _ => (rest, default_port),
        };
        let host = host.trim_start_matches('[').trim_end_matches(']');
        if host.is_empty() || host.contains(['/', '@', '?', '#']) {
            return Err(format!("`{}` names no broker host", self.url));
        }
        Ok(Broker {
            host: host.to_owned(),
            port,
            tls,
        })
    }

    /// The client id the gateway connects with.
    pub fn client_id(&self) -> String {
        self.client_id.clone().unwrap_or_else(|| {
            let host = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
            format!("modbus-gateway-{}", host.trim())
        })
    }

    /// The quality of service, 0 or 1 (checked).
    pub fn qos(&self) -> u8 {
        u8::from(self.qos == 1)
    }

    /// The password, the first line of `password_file`.
    pub fn read_password(&self) -> Result<Option<String>, String> {
        let Some(path) = &self.password_file else {
            return Ok(None);
        };
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read `{}`: {e}", path.display()))?;
        let line = text.lines().next().unwrap_or("").trim_end_matches('\r');
        if line.is_empty() {
            return Err(format!(
                "`{}` is empty: its first line is the password",
                path.display()
            ));
        }
        Ok(Some(line.to_owned()))
    }
}

/// Whether `text` may be a level (or levels) of a topic the gateway publishes: not empty, no
/// wildcard (`+`, `#`), no NUL, and no empty level.
fn topic_levels(text: &str) -> Result<(), String> {
    if text.is_empty() || text.split('/').any(str::is_empty) {
        return Err(format!(
            "`{text}` is not a topic: no empty level, no leading or trailing /"
        ));
    }
    if text.contains(['+', '#', '\0']) {
        return Err(format!(
            "`{text}` holds a wildcard (+ or #): a topic published to cannot"
        ));
    }
    Ok(())
}

/// Every problem with `[mqtt]`, each by key (the values' `deadband` and `writable` are
/// `Value::check`'s).
pub(super) fn check(config: &Config, errors: &mut Vec<ConfigError>) {
    let Some(mqtt) = &config.mqtt else {
        return;
    };
    let mut fail = |key: &str, reason: String| {
        errors.push(ConfigError {
            key: format!("mqtt.{key}"),
            reason,
        });
    };
    let broker = mqtt.broker();
    if let Err(why) = &broker {
        fail("url", why.clone());
    }
    if !(0..=1).contains(&mqtt.qos) {
        fail(
            "qos",
            format!(
                "{} is not 0 or 1: the gateway publishes at most once or at least once",
                mqtt.qos
            ),
        );
    }
    if mqtt.password.is_some() {
        fail(
            "password",
            "a password is never written in the configuration: put it in a file only the \
             gateway can read and name it in mqtt.password_file"
                .to_owned(),
        );
    }
    if let Err(why) = mqtt.read_password() {
        fail("password_file", why);
    }
    if mqtt.password_file.is_some() && mqtt.username.is_none() {
        fail("password_file", "a password needs mqtt.username".to_owned());
    }
    if let Some(id) = &mqtt.client_id {
        if id.is_empty() || id.len() > 65_535 {
            fail("client_id", "must be 1 to 65535 bytes long".to_owned());
        }
    }
    check_tls(mqtt, broker.as_ref().ok(), &mut fail);
    if let Err(why) = topic_levels(&mqtt.topic_prefix) {
        fail("topic_prefix", why);
    }
    if mqtt.home_assistant {
        if let Err(why) = topic_levels(&mqtt.discovery_prefix) {
            fail("discovery_prefix", why);
        }
    }
    if mqtt.publish_interval < MIN_PUBLISH_INTERVAL {
        fail(
            "publish_interval",
            format!(
                "{} is below 1s",
                humantime::format_duration(mqtt.publish_interval)
            ),
        );
    }
    check_labels(config, errors);
}

/// The TLS files of an `mqtts` broker (`broker`, if the url names one).
fn check_tls(mqtt: &Mqtt, broker: Option<&Broker>, fail: &mut impl FnMut(&str, String)) {
    let plain = broker.is_some_and(|b| !b.tls);
    for (key, path) in [
        ("ca_file", &mqtt.ca_file),
        ("cert_file", &mqtt.cert_file),
        ("key_file", &mqtt.key_file),
    ] {
        let Some(path) = path else { continue };
        if plain {
            fail(
                key,
                "is for an mqtts:// broker; the url is mqtt://".to_owned(),
            );
        } else {
            // Read as the client will read it, so a file it cannot use is this check's error.
            let read = match key {
                "ca_file" => crate::pem::roots(path).map(|_| ()),
                "cert_file" => crate::pem::certificates(path).map(|_| ()),
                _ => crate::pem::private_key(path).map(|_| ()),
            };
            if let Err(why) = read {
                fail(key, why);
            }
        }
    }
    if broker.is_some_and(|b| b.tls) && mqtt.ca_file.is_none() {
        fail(
            "ca_file",
            "an mqtts:// broker needs the CA that signed its certificate".to_owned(),
        );
    }
    if mqtt.cert_file.is_some() != mqtt.key_file.is_some() {
        let key = if mqtt.cert_file.is_some() {
            "key_file"
        } else {
            "cert_file"
        };
        fail(
            key,
            "mutual TLS needs both cert_file and key_file".to_owned(),
        );
    }
}

/// Every value published: its labels' values are a topic level, its name is not the slave's
/// availability's.
fn check_labels(config: &Config, errors: &mut Vec<ConfigError>) {
    // A label's value is a topic level of its value's: no wildcard, no `/`.
    for (i, bus) in config.bus.iter().enumerate() {
        for (j, slave) in bus.slave.iter().enumerate() {
            let Some(values) = config.values_of(&bus.name, slave.address) else {
                continue;
            };
            for (value, _) in values {
                // `PREFIX/BUS/SLAVE/availability` is the slave's own topic.
                if value.name == "availability" {
                    errors.push(ConfigError {
                        key: format!("bus[{i}].slave[{j}]"),
                        reason: "a value named availability would publish at the slave's \
                                 availability topic, which [mqtt] keeps for the slave: rename it"
                            .to_owned(),
                    });
                }
                if let Some((label, text)) = value
                    .labels
                    .iter()
                    .find(|(_, v)| v.is_empty() || v.contains(['/', '+', '#', '\0', ',', '=']))
                {
                    errors.push(ConfigError {
                        key: format!("bus[{i}].slave[{j}]"),
                        reason: format!(
                            "value {}'s label {label} = `{text}` cannot be a topic level \
                             (no /, +, #, `,` or =, not empty), and [mqtt] publishes it as one",
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
    use super::super::testing::{errors, MINIMAL};
    use super::*;

    fn url(text: &str) -> Result<Broker, String> {
        let text = format!("{MINIMAL}\n[mqtt]\nurl = \"{text}\"\n");
        let config = Config::from_toml_str(&text).map_err(|e| e.to_string());
        config.map(|c| c.mqtt.unwrap().broker().unwrap())
    }

    #[test]
    fn urls_name_a_host_a_port_and_whether_tls() {
        let plain = url("mqtt://127.0.0.1:1884").unwrap();
        assert_eq!(
            (plain.host.as_str(), plain.port, plain.tls),
            ("127.0.0.1", 1884, false)
        );
        let default = url("mqtt://broker.local").unwrap();
        assert_eq!(default.port, 1883);
        let v6 = Mqtt {
            url: "mqtts://[::1]:8884".to_owned(),
            ..minimal()
        };
        let v6 = v6.broker().unwrap();
        assert_eq!((v6.host.as_str(), v6.port, v6.tls), ("::1", 8884, true));
        for bad in [
            "http://x",
            "mqtt://",
            "mqtt://h:0",
            "mqtt://h:99999",
            "mqtt://u@h",
        ] {
            let mqtt = Mqtt {
                url: bad.to_owned(),
                ..minimal()
            };
            assert!(mqtt.broker().is_err(), "{bad}");
        }
    }

    fn minimal() -> Mqtt {
        toml::from_str("url = \"mqtt://127.0.0.1\"").unwrap()
    }

    #[test]
    fn the_defaults_are_the_documented_ones() {
        let mqtt = minimal();
        assert_eq!(mqtt.topic_prefix, "modbus-gateway");
        assert_eq!((mqtt.qos(), mqtt.retain, mqtt.writes), (1, true, false));
        assert_eq!(mqtt.publish_interval, Duration::from_secs(60));
        assert!(mqtt.home_assistant);
        assert_eq!(mqtt.discovery_prefix, "homeassistant");
        assert!(mqtt.client_id().starts_with("modbus-gateway-"));
    }

    #[test]
    fn every_mistake_of_mqtt_is_named_in_one_run() {
        let text = format!(
            "{MINIMAL}
            [[bus.slave]]
            address = 1
            [[bus.slave.value]]
            name = \"a\"
            register = 0
            deadband = -1
            [[bus.slave.value]]
            name = \"b\"
            register = 1
            table = \"input\"
            writable = true
            [mqtt]
            url = \"http://127.0.0.1\"
            qos = 2
            password = \"secret\"
            username = \"gw\"
            password_file = \"/nonexistent/mqtt.password\"
            topic_prefix = \"plant/#\"
            publish_interval = \"100ms\"
            "
        );
        let errors = errors(&text).join("\n");
        for key in [
            "mqtt.url",
            "mqtt.qos",
            "mqtt.password:",
            "mqtt.password_file",
            "mqtt.topic_prefix",
            "mqtt.publish_interval",
            "bus[0].slave[0].value[0].deadband",
            "bus[0].slave[0].value[1].writable",
        ] {
            assert!(errors.contains(key), "{key} not named in:\n{errors}");
        }
    }

    #[test]
    fn tls_files_are_read_as_the_client_reads_them() {
        let dir = std::env::temp_dir().join(format!("mbgw-mqtt-check-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let ca = dir.join("ca.pem");
        std::fs::write(&ca, "not a certificate").unwrap();
        let text = format!(
            "{MINIMAL}\n[mqtt]\nurl = \"mqtts://127.0.0.1\"\nca_file = {:?}\n",
            ca.display().to_string()
        );
        let errors = errors(&text).join("\n");
        assert!(errors.contains("mqtt.ca_file"), "{errors}");
        assert!(errors.contains("no PEM certificate"), "{errors}");
        let plain = format!("{MINIMAL}\n[mqtt]\nurl = \"mqtt://127.0.0.1\"\nca_file = \"x\"\n");
        assert!(errors_of(&plain).contains("is for an mqtts:// broker"));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_value_cannot_take_its_slaves_availability_topic() {
        let text = format!(
            "{MINIMAL}[[bus.slave]]\naddress = 1\n[[bus.slave.value]]\nname = \"availability\"\n\
             register = 0\n[mqtt]\nurl = \"mqtt://127.0.0.1\"\n"
        );
        let errors = errors_of(&text);
        assert!(
            errors.contains("bus[0].slave[0]") && errors.contains("availability topic"),
            "{errors}"
        );
    }

    fn errors_of(text: &str) -> String {
        errors(text).join("\n")
    }
}
