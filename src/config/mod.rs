//! The configuration: the TOML file and the `MBGW__` environment ([`Config::load`]), every
//! default defined once (`defaults`), a check whose errors name the key and the reason
//! ([`Config::check`]), the values derived after it (`Config::resolve`), and what changed
//! between two of them (`ConfigDiff`). Produces plain values; knows nothing of sockets, ports,
//! tasks or the simulator (a simulated drive's parameters are checked through the
//! [`DriveCheck`] the caller passes).

mod audit;
mod bus;
mod check;
pub(crate) mod defaults;
mod device;
pub(crate) mod diff;
mod listen;
mod load;
mod log;
mod metrics;
mod mqtt;
mod resolve;
mod route;
mod rs485;
mod rules;
mod serde_adapters;
mod serial_port;
mod server;
mod tls;
mod unit_set;
mod values;
mod virtual_unit;

pub use audit::{Audit, ByteSize, OnError};
pub use bus::{Bus, Slave};
pub use device::{DeviceName, ServerAddr, ServerMode};

pub(crate) use bus::SIM_DEVICE;

pub use bus::SimSlave;

pub use bus::SimModel;
pub use check::DriveCheck;
pub use check::DriveRefusal;
pub(crate) use check::TlsFilesCheck;
pub(crate) use diff::{BusChange, ConfigDiff};
pub use listen::{BusMode, SimMaster, SimRead};
pub use load::ConfigError;
pub use load::ConfigErrors;
pub use load::DEFAULT_PATH;
pub(crate) use load::ENV_PREFIX;
pub use log::Log;
pub use log::LogFormat;
pub use metrics::Metrics;
pub use mqtt::{Broker, Mqtt};
pub use route::Route;
pub use rs485::{Rs485, Rs485Mode};
pub use rules::{Action, Functions, Registers, Rule};
pub use serial_port::{PortDevice, ServerSerial, PTY_PREFIX};
pub use server::Server;
pub(crate) use server::WhenFull;
pub use tls::RoleAccess;
pub(crate) use tls::OTHER_ROLE;
pub use tls::{DeviceTls, Role, Tls};
pub use unit_set::UnitSet;
pub use values::{Order, Table, Template, Templates, Value, ValueType};
pub(crate) use values::{MAX_READ_BITS, MAX_READ_REGISTERS};
pub(crate) use virtual_unit::Slot;
pub use virtual_unit::{VirtualRegister, VirtualSource, VirtualUnit};

use serde::{Deserialize, Serialize};

/// Highest unicast slave address on a serial line.
pub(crate) const MAX_SLAVE_ADDRESS: u8 = crate::line::MAX_SERIAL_ADDRESS;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// A folder of the user's own device templates (`NAME.toml`); relative to the
    /// configuration file's folder.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub template_dir: Option<std::path::PathBuf>,
    #[serde(default)]
    pub server: Server,
    #[serde(default)]
    pub metrics: Metrics,
    #[serde(default)]
    pub log: Log,
    #[serde(default)]
    pub bus: Vec<Bus>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub route: Vec<Route>,
    /// What requests may do, first match wins; no rule matching: allowed.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rule: Vec<Rule>,
    /// The journal of writes; none without it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub audit: Option<Audit>,
    /// Units the gateway answers itself, from the values it polls.
    #[serde(default, rename = "virtual", skip_serializing_if = "Vec::is_empty")]
    pub virtual_units: Vec<VirtualUnit>,
    /// The plant values published to an MQTT broker; none without it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mqtt: Option<Mqtt>,
    /// The templates slaves may name: the shipped ones and `template_dir`'s, read at load.
    #[serde(skip)]
    pub templates: Templates,
}

#[cfg(test)]
mod properties;

/// What the tests of several files load and expect.
#[cfg(test)]
mod testing {
    use super::Config;

    pub(super) const MINIMAL: &str = r#"
        [[bus]]
        name = "line1"
        device = "/dev/ttyUSB0"
    "#;

    /// Every error `text` gets, as printed.
    pub(super) fn errors(text: &str) -> Vec<String> {
        Config::from_toml_str(text)
            .expect_err("config should be refused")
            .0
            .iter()
            .map(ToString::to_string)
            .collect()
    }
}
