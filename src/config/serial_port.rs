//! The `[[server.serial]]` sections: serial master ports, where a master on a serial line (a
//! UART, a pty the gateway makes for local software, or a line behind a serial device server)
//! talks to the gateway as its slave. Plain values and their checks; knows nothing of ports or
//! tasks.

use super::defaults;
use super::device::{DeviceName, ServerAddr};
use super::serde_adapters::{duration, opt_duration};
use super::{Bus, ConfigError, Rs485, UnitSet};
use crate::line::framing::TransportKind;
use crate::line::{Framing, Parity, MAX_SERIAL_ADDRESS};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Duration;

/// `device` prefix that makes a pty and links the path after it to the pty's far end.
pub const PTY_PREFIX: &str = "pty:";

/// One serial master port.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerSerial {
    /// Unique among the ports; the `port` label, the master's name (`serial:NAME`).
    #[serde(default)]
    pub name: String,
    /// A UART's path, `pty:PATH`, `tcp://HOST:PORT` or `rfc2217://HOST:PORT`. Left out is a
    /// problem the check names, with the others of the same run.
    #[serde(default)]
    pub device: String,
    #[serde(default = "defaults::baud")]
    pub baud: u32,
    #[serde(default)]
    pub framing: Framing,
    /// Left out: 8 for RTU, 7 for ASCII.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data_bits: Option<u8>,
    #[serde(default = "defaults::parity")]
    pub parity: Parity,
    /// Left out: 1 with parity, 2 without.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_bits: Option<u8>,
    /// The unit ids the port answers; a request to any other is not for it: silence.
    #[serde(default = "defaults::port_units")]
    pub units: UnitSet,
    /// A reply not ready this long after the request's end is never sent.
    #[serde(default = "defaults::answer_within", with = "duration")]
    pub answer_within: Duration,
    /// The port's master may only read.
    #[serde(default)]
    pub read_only: bool,
    /// The port's master is served before the others, as `server.priority`'s are.
    #[serde(default)]
    pub priority: bool,
    /// RTU: silence inside a request that breaks it, and that ends one of unknown length, if
    /// longer than t3.5 (USB adapters deliver in bursts). ASCII: the inter-character timeout
    /// (default 1 s).
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub byte_timeout: Option<Duration>,
    /// A USB adapter's latency timer to set at open, as on `[[bus]]`.
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub latency_timer: Option<Duration>,
    /// How long after a failed open (or a lost device) the port is opened again.
    #[serde(default = "defaults::reopen_delay", with = "duration")]
    pub reopen_delay: Duration,
    /// The port's transceiver, as `[bus.rs485]`.
    #[serde(default, skip_serializing_if = "Rs485::is_default")]
    pub rs485: Rs485,
}

/// What a port's `device` names.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PortDevice {
    /// A serial device's path.
    Uart(String),
    /// A pty the gateway makes, its far end linked at this path.
    Pty(String),
    /// A serial device server's port (`tcp://`, raw, or `rfc2217://`).
    Server(ServerAddr),
}

impl PortDevice {
    /// Read `device`; the error says what the key takes.
    pub fn parse(device: &str) -> Result<PortDevice, String> {
        const TAKES: &str = "a serial device path, `pty:PATH`, `tcp://HOST:PORT` or \
                             `rfc2217://HOST:PORT`";
        if let Some(path) = device.strip_prefix(PTY_PREFIX) {
            if !path.starts_with('/') {
                return Err(format!("`{device}`: a pty's link needs an absolute path"));
            }
            return Ok(PortDevice::Pty(path.to_owned()));
        }
        match DeviceName::parse(device) {
            Err(_) if device.is_empty() => Err(format!("missing: {TAKES}")),
            Err(why) => Err(why),
            Ok(DeviceName::Serial(path)) => Ok(PortDevice::Uart(path)),
            Ok(DeviceName::Server(addr)) if addr.mode != super::ServerMode::Tls => {
                Ok(PortDevice::Server(addr))
            }
            Ok(_) => Err(format!("`{device}` is no port a master can be on: {TAKES}")),
        }
    }

    /// What the framing table and the metrics call its transport.
    pub fn kind(&self) -> TransportKind {
        match self {
            PortDevice::Uart(_) | PortDevice::Pty(_) => TransportKind::Serial,
            PortDevice::Server(addr) => DeviceName::Server(addr.clone()).kind(),
        }
    }

    /// What one gateway's ports and buses may open only once: a device's path (a pty's link),
    /// or a device server's host and port.
    fn owned(&self) -> String {
        match self {
            PortDevice::Uart(path) | PortDevice::Pty(path) => path.clone(),
            PortDevice::Server(addr) => {
                format!("{}:{}", addr.host.to_ascii_lowercase(), addr.port)
            }
        }
    }
}

/// Every problem of the `[[server.serial]]` sections, each with its key, into `report`: names,
/// devices, formats, units, and the loop guard (a port on a device a bus or another port opens:
/// its requests would come back to it).
pub(super) fn check(ports: &[ServerSerial], buses: &[Bus], report: &mut Vec<ConfigError>) {
    let mut fail = |key: String, reason: String| report.push(ConfigError { key, reason });
    let mut names: BTreeMap<&str, usize> = BTreeMap::new();
    let mut owners: BTreeMap<String, String> = BTreeMap::new();
    for (i, bus) in buses.iter().enumerate() {
        let owned = match DeviceName::parse(&bus.device) {
            Ok(DeviceName::Serial(path)) => path,
            Ok(DeviceName::Server(addr)) => {
                format!("{}:{}", addr.host.to_ascii_lowercase(), addr.port)
            }
            _ => continue,
        };
        owners
            .entry(owned)
            .or_insert_with(|| format!("bus[{i}].device"));
    }
    for (i, port) in ports.iter().enumerate() {
        let key = |field: &str| format!("server.serial[{i}].{field}");
        let name_ok = !port.name.is_empty()
            && port
                .name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"_-.".contains(&b));
        if !name_ok {
            fail(
                key("name"),
                format!("`{}` must be letters, digits, `_`, `-` or `.`", port.name),
            );
        } else if let Some(first) = names.insert(&port.name, i) {
            fail(
                key("name"),
                format!(
                    "`{}` is already the name of server.serial[{first}]",
                    port.name
                ),
            );
        }
        match PortDevice::parse(&port.device) {
            Err(why) => fail(key("device"), why),
            Ok(device) => {
                if let Some(owner) = owners.get(&device.owned()) {
                    fail(
                        key("device"),
                        format!(
                            "`{}` is already {owner}: a port on it would hear its own requests \
                             (a loop)",
                            port.device
                        ),
                    );
                } else {
                    owners.insert(device.owned(), key("device"));
                }
                check_driver(port, &device, &key, &mut fail);
            }
        }
        check_format(port, &key, &mut fail);
        if let Some(unit) = port.units.iter().find(|&u| u > MAX_SERIAL_ADDRESS) {
            fail(
                key("units"),
                format!(
                    "{unit} is past {MAX_SERIAL_ADDRESS}, the highest address on a serial line"
                ),
            );
        }
        if port.answer_within.is_zero() {
            fail(key("answer_within"), "must be longer than 0".into());
        }
        if port.reopen_delay.is_zero() {
            fail(key("reopen_delay"), "must be longer than 0".into());
        }
    }
}

fn check_format(
    port: &ServerSerial,
    key: &dyn Fn(&str) -> String,
    fail: &mut dyn FnMut(String, String),
) {
    if port.baud == 0 {
        fail(key("baud"), "must be more than 0".into());
    }
    match port.framing {
        Framing::Tcp => fail(
            key("framing"),
            "\"tcp\" is no serial framing: \"rtu\" or \"ascii\"".into(),
        ),
        Framing::Rtu if port.data_bits == Some(7) => fail(
            key("data_bits"),
            "RTU frames carry 8-bit bytes: 7 data bits need framing = \"ascii\"".into(),
        ),
        _ => {}
    }
    if let Some(n) = port.data_bits.filter(|n| !matches!(n, 7 | 8)) {
        fail(key("data_bits"), format!("{n} is not 7 or 8"));
    }
    if let Some(n) = port.stop_bits.filter(|n| !matches!(n, 1 | 2)) {
        fail(key("stop_bits"), format!("{n} is not 1 or 2"));
    }
}

fn check_driver(
    port: &ServerSerial,
    device: &PortDevice,
    key: &dyn Fn(&str) -> String,
    fail: &mut dyn FnMut(String, String),
) {
    if let PortDevice::Pty(_) = device {
        if port.rs485 != Rs485::default() {
            fail(
                key("rs485"),
                "a pty has no transceiver to drive or echo".into(),
            );
        }
        if port.latency_timer.is_some() {
            fail(key("latency_timer"), "a pty has no USB adapter".into());
        }
        return;
    }
    for (field, reason) in port.rs485.problems(device.kind()) {
        fail(key(&format!("rs485.{field}")), reason);
    }
    if port.latency_timer.is_some() && device.kind() != TransportKind::Serial {
        fail(
            key("latency_timer"),
            "a line behind a serial device server has no USB adapter of the gateway's".into(),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    /// The keys `text` fails on, in the order reported.
    fn failing(text: &str) -> Vec<String> {
        match Config::from_toml_str(text) {
            Ok(_) => Vec::new(),
            Err(errors) => errors.0.into_iter().map(|e| e.key).collect(),
        }
    }

    #[test]
    fn every_bad_port_key_is_named_in_one_run() {
        let text = "[[bus]]\nname = \"line\"\ndevice = \"/dev/ttyS3\"\n\
                    [[server.serial]]\nname = \"a\"\nbaud = 0\nframing = \"tcp\"\n\
                    [[server.serial]]\nname = \"a\"\ndevice = \"/dev/ttyS2\"\nunits = \"1-250\"\n\
                    [[server.serial]]\nname = \"b\"\ndevice = \"/dev/ttyS3\"\n\
                    answer_within = \"0s\"\n";
        assert_eq!(
            failing(text),
            [
                "server.serial[0].device",
                "server.serial[0].baud",
                "server.serial[0].framing",
                "server.serial[1].name",
                "server.serial[1].units",
                "server.serial[2].device",
                "server.serial[2].answer_within",
            ]
        );
    }

    #[test]
    fn a_port_on_another_ports_pty_link_or_a_bus_device_server_is_a_loop() {
        let text = "[[bus]]\nname = \"line\"\ndevice = \"tcp://Conv:4001\"\n\
                    [[server.serial]]\nname = \"a\"\ndevice = \"rfc2217://conv:4001\"\n\
                    [[server.serial]]\nname = \"b\"\ndevice = \"pty:/run/x\"\n\
                    [[server.serial]]\nname = \"c\"\ndevice = \"/run/x\"\n";
        assert_eq!(
            failing(text),
            ["server.serial[0].device", "server.serial[2].device"]
        );
    }

    #[test]
    fn a_port_left_to_its_defaults_is_19200_8e1_rtu_for_units_1_to_247_within_800_ms() {
        let text = "[[bus]]\nname = \"line\"\ndevice = \"sim\"\n\
                    [[server.serial]]\nname = \"p\"\ndevice = \"/dev/ttyS1\"\n";
        let config = Config::from_toml_str(text).expect("valid");
        let port = &config.server.serial[0];
        assert_eq!(port.format().to_string(), "19200 baud 8E1");
        assert_eq!(port.framing, Framing::Rtu);
        assert_eq!(port.units.to_string(), "1-247");
        assert_eq!(port.answer_within, Duration::from_millis(800));
        assert!(!port.read_only && !port.priority);
    }

    #[test]
    fn a_port_device_is_a_path_a_pty_or_a_device_server_and_nothing_else() {
        assert_eq!(
            PortDevice::parse("/dev/ttyS1"),
            Ok(PortDevice::Uart("/dev/ttyS1".into()))
        );
        assert_eq!(
            PortDevice::parse("pty:/run/modbus-gateway/scada"),
            Ok(PortDevice::Pty("/run/modbus-gateway/scada".into()))
        );
        assert!(matches!(
            PortDevice::parse("rfc2217://10.0.0.9:4001"),
            Ok(PortDevice::Server(_))
        ));
        for bad in ["", "sim", "tls://10.0.0.9:802", "pty:relative", "udp://x:1"] {
            assert!(PortDevice::parse(bad).is_err(), "{bad}");
        }
    }
}
