//! A gateway configuration built from typed calls, written out as the TOML the gateway reads:
//!
//! ```
//! use test_support::{Bus, GatewayConfig};
//!
//! let config = GatewayConfig::new()
//!     .read_only(&["127.0.0.0/8"])
//!     .bus(Bus::sim("line1").baud(115_200).sim_slaves("1-4"))
//!     .load();
//! assert_eq!(config.bus[0].name, "line1");
//! ```
//!
//! It writes what it is told and checks nothing: the gateway's own loader is the judge, so a test
//! of a bad value builds it here like any other.

use modbus_gateway::gateway::config_from_toml;
use modbus_gateway::{Config, Gateway};
use std::fmt::Write as _;

/// A TOML value: a string (quoted), a number, a boolean, or an array of strings.
#[derive(Clone)]
pub struct Value(String);

impl From<&str> for Value {
    fn from(text: &str) -> Value {
        Value(quoted(text))
    }
}

impl From<String> for Value {
    fn from(text: String) -> Value {
        Value(quoted(&text))
    }
}

impl From<&[&str]> for Value {
    fn from(items: &[&str]) -> Value {
        let items: Vec<String> = items.iter().map(|item| quoted(item)).collect();
        Value(format!("[{}]", items.join(", ")))
    }
}

impl<const N: usize> From<[&str; N]> for Value {
    fn from(items: [&str; N]) -> Value {
        Value::from(&items[..])
    }
}

impl From<bool> for Value {
    fn from(flag: bool) -> Value {
        Value(flag.to_string())
    }
}

macro_rules! number_values {
    ($($t:ty),*) => {$(
        impl From<$t> for Value {
            fn from(n: $t) -> Value {
                Value(n.to_string())
            }
        }
    )*};
}
number_values!(u8, u16, u32, u64, usize, i32, i64);

impl From<f64> for Value {
    /// With its decimal point (`1.0`), so that it stays a TOML float.
    fn from(x: f64) -> Value {
        Value(format!("{x:?}"))
    }
}

/// `text` as a TOML basic string.
fn quoted(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + 2);
    out.push('"');
    for c in text.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// Key-value lines in the order they were set; setting a key again replaces its value in place.
#[derive(Default, Clone)]
struct Keys(Vec<(String, String)>);

impl Keys {
    /// `first`, then `more`.
    fn with(first: (&str, Value), more: &[(&str, Value)]) -> Keys {
        let mut keys = Keys::default();
        keys.set(first.0, first.1);
        for (key, value) in more {
            keys.set(key, Value(value.0.clone()));
        }
        keys
    }

    fn remove(&mut self, key: &str) {
        self.0.retain(|(k, _)| k != key);
    }

    fn set(&mut self, key: &str, value: Value) {
        match self.0.iter_mut().find(|(k, _)| k == key) {
            Some(entry) => entry.1 = value.0,
            None => self.0.push((key.to_owned(), value.0)),
        }
    }

    fn write(&self, out: &mut String) {
        for (key, value) in &self.0 {
            let _ = writeln!(out, "{key} = {value}");
        }
    }
}

/// A whole gateway configuration: `[server]` (listening on 127.0.0.1:0 unless told otherwise),
/// `[metrics]` if set, the buses, and any tables given as text.
#[derive(Clone)]
pub struct GatewayConfig {
    server: Keys,
    server_tables: String,
    metrics: Keys,
    tables: Vec<(String, Keys)>,
    buses: Vec<Bus>,
    tail: String,
}

impl Default for GatewayConfig {
    fn default() -> Self {
        Self::new()
    }
}

impl GatewayConfig {
    /// A gateway listening for Modbus TCP on a free loopback port, with no bus yet.
    pub fn new() -> GatewayConfig {
        let mut server = Keys::default();
        server.set("listen", "127.0.0.1:0".into());
        GatewayConfig {
            server,
            server_tables: String::new(),
            metrics: Keys::default(),
            tables: Vec::new(),
            buses: Vec::new(),
            tail: String::new(),
        }
    }

    /// `server.listen`: the Modbus TCP listener.
    pub fn listen(self, addr: impl ToString) -> Self {
        self.server("listen", addr.to_string())
    }

    /// `server.listen_rtu_over_tcp`.
    pub fn listen_rtu_over_tcp(self, addr: impl ToString) -> Self {
        self.server("listen_rtu_over_tcp", addr.to_string())
    }

    /// `server.listen_udp`.
    pub fn listen_udp(self, addr: impl ToString) -> Self {
        self.server("listen_udp", addr.to_string())
    }

    /// `server.listen_tls`: the Modbus/TCP Security listener (its `[server.tls]` table from
    /// [`crate::tls::Pki::tls_table`], given to [`GatewayConfig::server_table`]).
    pub fn listen_tls(self, addr: impl ToString) -> Self {
        self.server("listen_tls", addr.to_string())
    }

    /// No `server.listen` key: the gateway's default, as in a file an operator starts from (for a
    /// configuration that is checked or read, never run).
    pub fn default_listen(mut self) -> Self {
        self.server.remove("listen");
        self
    }

    /// `server.read_only`: masters (addresses or networks) that may only read.
    pub fn read_only(self, masters: &[&str]) -> Self {
        self.server("read_only", masters)
    }

    /// `server.max_connections`.
    pub fn max_connections(self, n: usize) -> Self {
        self.server("max_connections", n)
    }

    /// `server.pipeline_depth`: requests read ahead from one connection.
    pub fn pipeline_depth(self, n: usize) -> Self {
        self.server("pipeline_depth", n)
    }

    /// Any other `[server]` key.
    pub fn server(mut self, key: &str, value: impl Into<Value>) -> Self {
        self.server.set(key, value.into());
        self
    }

    /// A sub-table of `[server]` as text (`[server.tls]` from [`crate::tls::Pki::tls_table`]).
    pub fn server_table(mut self, toml: &str) -> Self {
        self.server_tables.push_str(toml);
        if !toml.ends_with('\n') {
            self.server_tables.push('\n');
        }
        self
    }

    /// `metrics.listen`.
    pub fn metrics_listen(mut self, addr: impl ToString) -> Self {
        self.metrics.set("listen", addr.to_string().into());
        self
    }

    /// Another top-level table (`[log]`...), written after `[metrics]`.
    pub fn table(mut self, name: &str, keys: &[(&str, Value)]) -> Self {
        let keys = Keys(
            keys.iter()
                .map(|(key, value)| ((*key).to_owned(), value.0.clone()))
                .collect(),
        );
        self.tables.push((name.to_owned(), keys));
        self
    }

    /// One more `[[bus]]`.
    pub fn bus(mut self, bus: Bus) -> Self {
        self.buses.push(bus);
        self
    }

    /// One more `[[route]]`: `units` (a single id, list or range) to `bus`, to slave `address`
    /// there or (`None`) to the slave of the unit's own id.
    pub fn route(mut self, units: &str, bus: &str, address: impl Into<Option<u8>>) -> Self {
        let _ = write!(
            self.tail,
            "[[route]]\nunits = {}\nbus = {}\n",
            quoted(units),
            quoted(bus)
        );
        if let Some(address) = address.into() {
            let _ = writeln!(self.tail, "address = {address}");
        }
        self
    }

    /// Top-level tables given as text (`[[virtual]]`, `[[rule]]`), after the buses and routes.
    pub fn tables(mut self, toml: &str) -> Self {
        self.tail.push_str(toml);
        if !toml.is_empty() && !toml.ends_with('\n') {
            self.tail.push('\n');
        }
        self
    }

    /// One more `[[route]]`: `units` to `bus`, each to the slave of its id plus `offset`.
    pub fn route_offset(mut self, units: &str, bus: &str, offset: i16) -> Self {
        let _ = write!(
            self.tail,
            "[[route]]\nunits = {}\nbus = {}\noffset = {offset}\n",
            quoted(units),
            quoted(bus)
        );
        self
    }

    /// The configuration as the gateway reads it.
    pub fn to_toml(&self) -> String {
        let mut out = String::new();
        if !self.server.0.is_empty() || !self.server_tables.is_empty() {
            out.push_str("[server]\n");
            self.server.write(&mut out);
            out.push_str(&self.server_tables);
        }
        if !self.metrics.0.is_empty() {
            out.push_str("[metrics]\n");
            self.metrics.write(&mut out);
        }
        for (name, keys) in &self.tables {
            let _ = writeln!(out, "[{name}]");
            keys.write(&mut out);
        }
        for bus in &self.buses {
            bus.write(&mut out);
        }
        out.push_str(&self.tail);
        out
    }

    /// The configuration loaded as the gateway loads it.
    ///
    /// # Panics
    /// If the gateway refuses it.
    pub fn load(&self) -> Config {
        config_from_toml(&self.to_toml()).unwrap_or_else(|e| panic!("test config: {e}"))
    }

    /// A gateway running this configuration, its metrics endpoint on a free loopback port
    /// ([`crate::start`]).
    pub async fn start(&self) -> Gateway {
        crate::gateway::start(&self.to_toml()).await
    }
}

/// One `[[bus]]`: its keys in the order set, tables given as text, and `[[bus.sim_slave]]`s.
#[derive(Clone)]
pub struct Bus {
    keys: Keys,
    tables: String,
    slaves: Vec<Keys>,
    sim_slaves: Vec<Keys>,
}

impl Bus {
    /// A bus named `name` on `device` (a serial device, `sim`, `tcp://...`).
    pub fn on(name: &str, device: &str) -> Bus {
        let mut keys = Keys::default();
        keys.set("name", name.into());
        keys.set("device", device.into());
        Bus {
            keys,
            tables: String::new(),
            slaves: Vec::new(),
            sim_slaves: Vec::new(),
        }
    }

    /// This bus alone as TOML, its `[[bus]]` and its tables, for a test that writes the rest
    /// of the file itself.
    pub fn to_toml(&self) -> String {
        let mut out = String::new();
        self.write(&mut out);
        out
    }

    /// A bus named `name` on the built-in simulated line.
    pub fn sim(name: &str) -> Bus {
        Bus::on(name, "sim")
    }

    /// `baud`.
    pub fn baud(self, baud: u32) -> Self {
        self.key("baud", baud)
    }

    /// `parity`: none, even or odd.
    pub fn parity(self, parity: &str) -> Self {
        self.key("parity", parity)
    }

    /// `framing`: rtu or ascii.
    pub fn framing(self, framing: &str) -> Self {
        self.key("framing", framing)
    }

    /// `response_timeout`, a humantime string.
    pub fn response_timeout(self, timeout: &str) -> Self {
        self.key("response_timeout", timeout)
    }

    /// `retries`: how many times a request that timed out is sent again.
    pub fn retries(self, n: u32) -> Self {
        self.key("retries", n)
    }

    /// `queue_depth`: requests waiting for the line.
    pub fn queue_depth(self, n: usize) -> Self {
        self.key("queue_depth", n)
    }

    /// `queue_timeout`, a humantime string: how long a request may wait for the line.
    pub fn queue_timeout(self, timeout: &str) -> Self {
        self.key("queue_timeout", timeout)
    }

    /// Any other bus key.
    pub fn key(mut self, key: &str, value: impl Into<Value>) -> Self {
        self.keys.set(key, value.into());
        self
    }

    /// Keys or sub-tables of this bus as text (`[bus.rs485]`, `[[bus.slave]]`...), written after
    /// its keys.
    pub fn text(mut self, toml: &str) -> Self {
        self.tables.push_str(toml);
        if !toml.is_empty() && !toml.ends_with('\n') {
            self.tables.push('\n');
        }
        self
    }

    /// The `[bus.rs485]` table: how the transceiver is switched (`mode`, `echo`, delays).
    pub fn rs485(self, keys: &[(&str, Value)]) -> Self {
        let mut toml = String::from("[bus.rs485]\n");
        for (key, value) in keys {
            let _ = writeln!(toml, "{key} = {}", value.0);
        }
        self.text(&toml)
    }

    /// A `[[bus.slave]]`: per-slave settings for slave `address` (`response_timeout`...).
    pub fn slave(mut self, address: u8, keys: &[(&str, Value)]) -> Self {
        self.slaves
            .push(Keys::with(("address", address.into()), keys));
        self
    }

    /// Register-bank simulated slaves at `addresses` (a single address, list or range).
    pub fn sim_slaves(self, addresses: &str) -> Self {
        self.sim_slave(addresses, &[])
    }

    /// Simulated slaves at `addresses` with more keys (`processing_delay`, fault knobs...).
    pub fn sim_slave(mut self, addresses: &str, keys: &[(&str, Value)]) -> Self {
        self.sim_slaves
            .push(Keys::with(("address", addresses.into()), keys));
        self
    }

    fn write(&self, out: &mut String) {
        out.push_str("[[bus]]\n");
        self.keys.write(out);
        out.push_str(&self.tables);
        for slave in &self.slaves {
            out.push_str("[[bus.slave]]\n");
            slave.write(out);
        }
        for slave in &self.sim_slaves {
            out.push_str("[[bus.sim_slave]]\n");
            slave.write(out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_typed_configuration_is_written_as_the_toml_the_gateway_reads() {
        let toml = GatewayConfig::new()
            .read_only(&["127.0.0.0/8"])
            .bus(
                Bus::sim("line1")
                    .baud(115_200)
                    .parity("none")
                    .sim_slaves("1-4"),
            )
            .route("255", "line1", 17)
            .to_toml();
        assert_eq!(
            toml,
            "[server]\nlisten = \"127.0.0.1:0\"\nread_only = [\"127.0.0.0/8\"]\n\
             [[bus]]\nname = \"line1\"\ndevice = \"sim\"\nbaud = 115200\nparity = \"none\"\n\
             [[bus.sim_slave]]\naddress = \"1-4\"\n\
             [[route]]\nunits = \"255\"\nbus = \"line1\"\naddress = 17\n"
        );
    }

    #[test]
    fn without_listen_there_is_no_server_table_and_a_float_keeps_its_point() {
        let toml = GatewayConfig::new()
            .default_listen()
            .bus(
                Bus::on("usb", "/dev/ttyUSB0")
                    .rs485(&[("echo", true.into())])
                    .sim_slave("2", &[("crc_error_rate", 1.0.into())]),
            )
            .to_toml();
        assert_eq!(
            toml,
            "[[bus]]\nname = \"usb\"\ndevice = \"/dev/ttyUSB0\"\n[bus.rs485]\necho = true\n\
             [[bus.sim_slave]]\naddress = \"2\"\ncrc_error_rate = 1.0\n"
        );
    }

    #[test]
    fn a_key_set_twice_keeps_its_place_and_its_last_value() {
        let toml = GatewayConfig::new().listen("127.0.0.1:5020").to_toml();
        assert_eq!(toml, "[server]\nlisten = \"127.0.0.1:5020\"\n");
    }
}
