//! The configuration: the TOML file, `MBGW__` environment overrides, every default (defined once,
//! in [`defaults`]), and validation whose errors name the key and the reason. Produces plain
//! values; knows nothing of sockets, ports or tasks.

use crate::line::{LineTiming, MasterTiming, Parity, SerialFormat};
use crate::pdu::EXCEPTION_BIT;
use crate::sim::{self, faults::Faults, Pause};
use ipnet::IpNet;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;
use std::net::{IpAddr, SocketAddr};
use std::path::Path;
use std::time::Duration;

/// Where the daemon looks for its file unless told otherwise.
pub const DEFAULT_PATH: &str = "/etc/modbus-gateway/gateway.toml";
/// Environment variables starting with this override file keys: `MBGW__SERVER__LISTEN`,
/// `MBGW__BUS__0__BAUD` (array entries by index).
pub const ENV_PREFIX: &str = "MBGW__";
const ENV_SEPARATOR: &str = "__";
/// `device` value that selects the built-in simulated line.
pub const SIM_DEVICE: &str = "sim";
/// Highest unicast slave address on a serial line.
pub const MAX_SLAVE_ADDRESS: u8 = 247;
const MAX_RETRIES: u32 = 10;
const MIN_KEEPALIVE: Duration = Duration::from_secs(1);
/// Most garbage a simulated slave may wrap a reply in: a frame's worth.
const MAX_GARBAGE: usize = 256;

/// Every default, once.
pub mod defaults {
    use super::*;

    pub fn listen() -> Vec<SocketAddr> {
        vec![SocketAddr::from(([0, 0, 0, 0], 502))]
    }
    pub const MAX_CONNECTIONS: usize = 1024;
    pub const IDLE_TIMEOUT: Duration = Duration::from_secs(600);
    pub const PIPELINE_DEPTH: usize = 16;
    pub const SHUTDOWN_TIMEOUT: Duration = Duration::from_secs(10);
    pub const FRAME_TIMEOUT: Duration = Duration::from_secs(5);
    pub const KEEPALIVE: Duration = Duration::from_secs(60);
    pub fn metrics_listen() -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], 9502))
    }
    pub const LOG_LEVEL: &str = "info";

    pub fn baud() -> u32 {
        19_200
    }
    pub fn data_bits() -> u8 {
        8
    }
    pub fn parity() -> Parity {
        Parity::Even
    }
    pub fn response_timeout() -> Duration {
        Duration::from_secs(1)
    }
    pub fn turnaround_delay() -> Duration {
        Duration::from_millis(100)
    }
    pub fn broadcast_reply() -> bool {
        true
    }
    pub fn queue_depth() -> usize {
        256
    }
    pub fn queue_timeout() -> Duration {
        Duration::from_secs(1)
    }
    pub fn reopen_delay() -> Duration {
        Duration::from_millis(250)
    }
    pub fn reopen_delay_max() -> Duration {
        Duration::from_secs(5)
    }
    pub fn slave_down_after() -> u32 {
        3
    }
    pub fn slave_probe_interval() -> Duration {
        Duration::from_secs(5)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
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
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Server {
    /// One address, a comma-separated string of them, or a list.
    #[serde(with = "text_list")]
    pub listen: Vec<SocketAddr>,
    /// TCP connections open at once, over all listeners; more are refused.
    pub max_connections: usize,
    /// A connection with no request and nothing pending for this long is closed ("0s": never).
    #[serde(with = "duration")]
    pub idle_timeout: Duration,
    /// Requests one connection may have in flight; the gateway stops reading until one is answered.
    pub pipeline_depth: usize,
    /// On SIGTERM/SIGINT, how long queued requests may still be served; the rest get 0x0A.
    #[serde(with = "duration")]
    pub shutdown_timeout: Duration,
    /// What a new connection does at `max_connections`.
    pub when_full: WhenFull,
    /// A request's bytes must all be in this long after its first byte, or the connection closes.
    #[serde(with = "duration")]
    pub frame_timeout: Duration,
    /// TCP keepalive: silence before the first probe of a connection's peer ("0s": off).
    #[serde(with = "duration")]
    pub keepalive: Duration,
    /// Who may connect: addresses or networks; empty: anyone.
    #[serde(with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub allow: Vec<IpNet>,
    /// Masters connecting from these may only read: anything else gets exception 0x01.
    #[serde(with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub read_only: Vec<IpNet>,
}

/// What a connection beyond `server.max_connections` does.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WhenFull {
    /// Close the connection that has been idle longest (nothing in flight), then accept; refuse
    /// if every connection has a request in flight.
    #[default]
    CloseOldestIdle,
    /// Refuse the new connection.
    Refuse,
}

impl Default for Server {
    fn default() -> Self {
        Server {
            listen: defaults::listen(),
            max_connections: defaults::MAX_CONNECTIONS,
            idle_timeout: defaults::IDLE_TIMEOUT,
            pipeline_depth: defaults::PIPELINE_DEPTH,
            shutdown_timeout: defaults::SHUTDOWN_TIMEOUT,
            when_full: WhenFull::default(),
            frame_timeout: defaults::FRAME_TIMEOUT,
            keepalive: defaults::KEEPALIVE,
            allow: Vec::new(),
            read_only: Vec::new(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Metrics {
    pub listen: SocketAddr,
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics {
            listen: defaults::metrics_listen(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Log {
    /// A tracing filter: `info`, `debug`, `modbus_gateway=trace`; `RUST_LOG` overrides it.
    pub level: String,
    pub format: LogFormat,
}

/// How log lines are written to stderr.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    /// Human text; under systemd, without timestamps and with the journal's priority prefix.
    #[default]
    Text,
    /// One JSON object per line.
    Json,
}

impl<'de> Deserialize<'de> for LogFormat {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        match text.as_str() {
            "text" => Ok(LogFormat::Text),
            "json" => Ok(LogFormat::Json),
            _ => Err(serde::de::Error::custom(format!(
                "`{text}` is not text or json"
            ))),
        }
    }
}

impl Default for Log {
    fn default() -> Self {
        Log {
            level: defaults::LOG_LEVEL.to_owned(),
            format: LogFormat::default(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bus {
    pub name: String,
    /// A serial device path, or "sim".
    pub device: String,
    #[serde(default = "defaults::baud")]
    pub baud: u32,
    #[serde(default = "defaults::data_bits")]
    pub data_bits: u8,
    #[serde(default = "defaults::parity")]
    pub parity: Parity,
    /// 1 or 2; left out: 1 with parity, 2 without (filled in by validation).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_bits: Option<u8>,
    #[serde(default = "defaults::response_timeout", with = "duration")]
    pub response_timeout: Duration,
    /// Extra tries after a timeout or a corrupt reply, for reads (and writes with `retry_writes`).
    #[serde(default)]
    pub retries: u32,
    #[serde(default)]
    pub retry_writes: bool,
    /// Silence before every frame, if longer than t3.5.
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub inter_frame_delay: Option<Duration>,
    /// Silence that ends a reply of unknown length, if longer than t3.5 (USB adapters).
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub byte_timeout: Option<Duration>,
    /// Silence after a broadcast, so slaves can carry it out.
    #[serde(default = "defaults::turnaround_delay", with = "duration")]
    pub turnaround_delay: Duration,
    /// Answer a broadcast write with its normal response once it is sent.
    #[serde(default = "defaults::broadcast_reply")]
    pub broadcast_reply: bool,
    #[serde(default = "defaults::queue_depth")]
    pub queue_depth: usize,
    /// A request not on the wire this long after it arrived gets exception 0x06.
    #[serde(default = "defaults::queue_timeout", with = "duration")]
    pub queue_timeout: Duration,
    #[serde(default = "defaults::reopen_delay", with = "duration")]
    pub reopen_delay: Duration,
    #[serde(default = "defaults::reopen_delay_max", with = "duration")]
    pub reopen_delay_max: Duration,
    /// After this many requests in a row timed out, a slave is down: its requests get 0x0B at
    /// once, without using the line, but for one probe per `slave_probe_interval` (0: never down).
    #[serde(default = "defaults::slave_down_after")]
    pub slave_down_after: u32,
    #[serde(default = "defaults::slave_probe_interval", with = "duration")]
    pub slave_probe_interval: Duration,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub slave: Vec<Slave>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sim_slave: Vec<SimSlave>,
}

/// Per-slave overrides of the bus settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Slave {
    pub address: u8,
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub response_timeout: Option<Duration>,
    /// The slave may answer Read Holding Registers with a two-byte byte count (an inverter's
    /// "non-standard Modbus" mode); the gateway reads both forms and passes on the standard one.
    #[serde(default, skip_serializing_if = "is_false")]
    pub wide_read_count: bool,
}

fn is_false(value: &bool) -> bool {
    !value
}

fn is_zero(value: &Duration) -> bool {
    value.is_zero()
}

fn is_zero_usize(value: &usize) -> bool {
    *value == 0
}

fn is_zero_f64(value: &f64) -> bool {
    *value == 0.0
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SimModel {
    /// Four plain register banks.
    #[default]
    Registers,
    /// INVT Goodrive20.
    Gd20,
    /// INVT Goodrive300.
    Gd300,
    /// INVT Goodrive10.
    Gd10,
    /// The inverter with the Pd communication group (shared/reference/003).
    #[serde(rename = "pd-inverter")]
    PdInverter,
}

impl SimModel {
    pub fn is_drive(self) -> bool {
        self != SimModel::Registers
    }
}

/// Slaves on a simulated line.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimSlave {
    /// One address, a list or ranges: 3, "1-4", "1,5-7".
    pub address: UnitSet,
    #[serde(default)]
    pub model: SimModel,
    /// Time the slave takes after recognising a request before it starts its reply.
    #[serde(default, with = "duration")]
    pub processing_delay: Duration,
    /// Drive models: parameters that differ from the factory defaults, by the manual's name,
    /// in fieldbus units (`"P00.11" = 50` is 5.0 s).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub params: BTreeMap<String, u16>,
    /// Drive models: the fault code the drive has tripped with at power-on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trip: Option<u16>,
    /// Fault knob: never answers, carries nothing out.
    #[serde(default, skip_serializing_if = "is_false")]
    pub offline: bool,
    /// Fault knob: added to every reply's delay.
    #[serde(default, with = "duration", skip_serializing_if = "is_zero")]
    pub extra_delay: Duration,
    /// Fault knob: every reply starts this long after the request, whatever the slave's own delay.
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub late_reply: Option<Duration>,
    /// Fault knob: fraction of replies (0 to 1) sent with a corrupted CRC.
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub crc_error_rate: f64,
    /// Fault knob: random bytes sent straight before every reply.
    #[serde(default, skip_serializing_if = "is_zero_usize")]
    pub garbage_before: usize,
    /// Fault knob: random bytes sent straight after every reply.
    #[serde(default, skip_serializing_if = "is_zero_usize")]
    pub garbage_after: usize,
    /// Fault knob: replies carry this address instead of the slave's own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reply_address: Option<u8>,
    /// Fault knob: replies carry this function code (1-127) instead of the request's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reply_function: Option<u8>,
    /// Fault knob: only the first this many bytes of every reply are sent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truncate_reply: Option<usize>,
    /// Fault knob: every reply falls silent for this long after `reply_gap_after` bytes.
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub reply_gap: Option<Duration>,
    /// Fault knob: bytes of every reply sent before its `reply_gap`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reply_gap_after: Option<usize>,
}

impl SimSlave {
    pub fn faults(&self) -> Faults {
        Faults {
            offline: self.offline,
            extra_delay: self.extra_delay,
            late_reply: self.late_reply,
            crc_error_rate: self.crc_error_rate,
            garbage_before: self.garbage_before,
            garbage_after: self.garbage_after,
            reply_address: self.reply_address,
            reply_function: self.reply_function,
            truncate_reply: self.truncate_reply,
            reply_gap: self
                .reply_gap
                .zip(self.reply_gap_after)
                .map(|(gap, after)| Pause { after, gap }),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Route {
    pub units: UnitSet,
    pub bus: String,
    /// Every unit goes to this slave address.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub address: Option<u8>,
    /// Slave address = unit + offset (neither given: offset 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset: Option<i32>,
}

impl Bus {
    pub fn is_sim(&self) -> bool {
        self.device == SIM_DEVICE
    }

    /// Character time and the spec's gaps at this bus's format.
    pub fn line_timing(&self) -> LineTiming {
        LineTiming::new(&self.format())
    }

    /// The gaps the master keeps: t3.5, raised by `inter_frame_delay` and `byte_timeout`.
    pub fn master_timing(&self) -> MasterTiming {
        MasterTiming::new(
            self.line_timing(),
            self.inter_frame_delay.unwrap_or_default(),
            self.byte_timeout.unwrap_or_default(),
        )
    }

    pub fn format(&self) -> SerialFormat {
        SerialFormat {
            baud: self.baud,
            data_bits: self.data_bits,
            parity: self.parity,
            stop_bits: self
                .stop_bits
                .unwrap_or_else(|| SerialFormat::default_stop_bits(self.parity)),
        }
    }
}

impl Route {
    /// The slave address `unit` goes to, if it is on the serial line's address range.
    pub fn target(&self, unit: u8) -> Option<u8> {
        let address = match (self.address, self.offset) {
            (Some(address), _) => i64::from(address),
            (None, offset) => i64::from(unit) + i64::from(offset.unwrap_or(0)),
        };
        u8::try_from(address)
            .ok()
            .filter(|&a| a <= MAX_SLAVE_ADDRESS)
    }
}

/// A set of unit ids or slave addresses (0-255), written `5`, `"1-10,20"` or `[1, 2, 3]`.
#[derive(Clone, Copy, PartialEq, Eq, Default)]
pub struct UnitSet([u64; 4]);

impl UnitSet {
    pub fn insert(&mut self, unit: u8) {
        self.0[usize::from(unit / 64)] |= 1 << (unit % 64);
    }

    pub fn contains(&self, unit: u8) -> bool {
        self.0[usize::from(unit / 64)] & (1 << (unit % 64)) != 0
    }

    pub fn iter(&self) -> impl Iterator<Item = u8> + '_ {
        (0..=255u8).filter(|&u| self.contains(u))
    }

    pub fn is_empty(&self) -> bool {
        self.0 == [0; 4]
    }
}

impl std::str::FromStr for UnitSet {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let number = |s: &str| -> Result<u8, String> {
            s.trim()
                .parse::<u8>()
                .map_err(|_| format!("`{}` is not a number from 0 to 255", s.trim()))
        };
        let mut set = UnitSet::default();
        for part in text.split(',') {
            match part.split_once('-') {
                Some((low, high)) => {
                    let (low, high) = (number(low)?, number(high)?);
                    if low > high {
                        return Err(format!("range `{}` runs backwards", part.trim()));
                    }
                    (low..=high).for_each(|u| set.insert(u));
                }
                None => set.insert(number(part)?),
            }
        }
        Ok(set)
    }
}

impl fmt::Display for UnitSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut first = true;
        let mut units = self.iter().peekable();
        while let Some(low) = units.next() {
            let mut high = low;
            while units.peek() == Some(&high.wrapping_add(1)) && high != 255 {
                high = units.next().unwrap_or(high);
            }
            let sep = if first { "" } else { "," };
            first = false;
            if low == high {
                write!(f, "{sep}{low}")?;
            } else {
                write!(f, "{sep}{low}-{high}")?;
            }
        }
        Ok(())
    }
}

impl fmt::Debug for UnitSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "UnitSet({self})")
    }
}

impl Serialize for UnitSet {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for UnitSet {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = UnitSet;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a unit id, a list of them, or ranges like \"1-10,20\"")
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<UnitSet, E> {
                let unit = u8::try_from(v)
                    .map_err(|_| E::custom(format!("{v} is not a number from 0 to 255")))?;
                let mut set = UnitSet::default();
                set.insert(unit);
                Ok(set)
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<UnitSet, E> {
                self.visit_i64(i64::try_from(v).unwrap_or(i64::MAX))
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<UnitSet, E> {
                v.parse().map_err(E::custom)
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<UnitSet, A::Error> {
                let mut set = UnitSet::default();
                while let Some(part) = seq.next_element::<UnitSet>()? {
                    part.iter().for_each(|u| set.insert(u));
                }
                Ok(set)
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// Durations as humantime strings: "1s", "250ms", "10m".
mod duration {
    use serde::{Deserialize, Deserializer, Serializer};
    use std::time::Duration;

    pub fn serialize<S: Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(&humantime::format_duration(*d))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Duration, D::Error> {
        let text = String::deserialize(d)?;
        humantime::parse_duration(&text).map_err(|e| {
            serde::de::Error::custom(format!("`{text}` is not a duration like \"500ms\": {e}"))
        })
    }
}

mod opt_duration {
    use serde::{Deserializer, Serializer};
    use std::time::Duration;

    pub fn serialize<S: Serializer>(d: &Option<Duration>, s: S) -> Result<S::Ok, S::Error> {
        match d {
            Some(d) => super::duration::serialize(d, s),
            None => s.serialize_none(),
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Duration>, D::Error> {
        super::duration::deserialize(d).map(Some)
    }
}

/// Lists written as one string, a comma-separated string (handy in the environment), or a list
/// of strings: listen addresses, allowed networks.
mod text_list {
    use serde::{Deserializer, Serializer};
    use std::marker::PhantomData;

    /// An item of such a list.
    pub trait Item: Sized + std::fmt::Display {
        /// What one item looks like, for error messages.
        const EXAMPLE: &'static str;
        fn parse(text: &str) -> Option<Self>;
    }

    pub fn serialize<T: Item, S: Serializer>(items: &[T], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(items.iter().map(ToString::to_string))
    }

    fn parse<T: Item, E: serde::de::Error>(text: &str, out: &mut Vec<T>) -> Result<(), E> {
        for part in text
            .split(',')
            .map(str::trim)
            .filter(|part| !part.is_empty())
        {
            out.push(
                T::parse(part)
                    .ok_or_else(|| E::custom(format!("`{part}` is not {}", T::EXAMPLE)))?,
            );
        }
        Ok(())
    }

    struct Visitor<T>(PhantomData<T>);

    impl<'de, T: Item> serde::de::Visitor<'de> for Visitor<T> {
        type Value = Vec<T>;

        fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "{}, or a list of them", T::EXAMPLE)
        }

        fn visit_str<E: serde::de::Error>(self, text: &str) -> Result<Self::Value, E> {
            let mut out = Vec::new();
            parse(text, &mut out)?;
            Ok(out)
        }

        fn visit_seq<A: serde::de::SeqAccess<'de>>(
            self,
            mut seq: A,
        ) -> Result<Self::Value, A::Error> {
            let mut out = Vec::new();
            while let Some(text) = seq.next_element::<String>()? {
                parse(&text, &mut out)?;
            }
            Ok(out)
        }
    }

    pub fn deserialize<'de, T: Item, D: Deserializer<'de>>(d: D) -> Result<Vec<T>, D::Error> {
        d.deserialize_any(Visitor(PhantomData))
    }
}

impl text_list::Item for SocketAddr {
    const EXAMPLE: &'static str = "a socket address like \"0.0.0.0:502\" or \"[::1]:502\"";
    fn parse(text: &str) -> Option<Self> {
        text.parse().ok()
    }
}

/// A network in `server.allow` or `server.read_only`: CIDR, or a single address.
impl text_list::Item for IpNet {
    const EXAMPLE: &'static str = "an address or a network like \"192.168.10.0/24\"";
    fn parse(text: &str) -> Option<Self> {
        text.parse()
            .ok()
            .or_else(|| text.parse::<IpAddr>().ok().map(IpNet::from))
            .map(|net| net.trunc())
    }
}

/// One thing wrong with the configuration: the key path and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConfigError {
    pub key: String,
    pub reason: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.key, self.reason)
    }
}

/// Everything wrong with a configuration, reported together.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub struct ConfigErrors(pub Vec<ConfigError>);

impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

impl ConfigErrors {
    fn one(key: impl Into<String>, reason: impl fmt::Display) -> Self {
        ConfigErrors(vec![ConfigError {
            key: key.into(),
            reason: reason.to_string(),
        }])
    }
}

/// `SERVER__LISTEN` -> `server.listen`; `BUS__0__SLAVE__1__ADDRESS` -> `bus[0].slave[1].address`.
fn env_key_path(rest: &str) -> String {
    let mut path = String::new();
    for part in rest.split(ENV_SEPARATOR) {
        if !part.is_empty() && part.bytes().all(|b| b.is_ascii_digit()) {
            path.push_str(&format!("[{part}]"));
        } else {
            if !path.is_empty() {
                path.push('.');
            }
            path.push_str(&part.to_ascii_lowercase());
        }
    }
    path
}

impl Config {
    /// Read `path`, apply the `MBGW__` variables among `env`, fill in defaults and validate.
    pub fn load(
        path: &Path,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Config, ConfigErrors> {
        let file = config::File::from(path)
            .format(config::FileFormat::Toml)
            .required(true);
        let mut builder = config::Config::builder().add_source(file);
        for (name, value) in env {
            let Some(rest) = name.strip_prefix(ENV_PREFIX) else {
                continue;
            };
            let key = env_key_path(rest);
            builder = builder
                .set_override(&key, value)
                .map_err(|e| ConfigErrors::one(&name, format!("cannot be used as `{key}`: {e}")))?;
        }
        let raw = builder
            .build()
            .map_err(|e| ConfigErrors::one(path.display().to_string(), e))?;
        Self::finish(raw)
    }

    /// Parse TOML text with no environment, fill in defaults and validate.
    pub fn from_toml_str(text: &str) -> Result<Config, ConfigErrors> {
        let raw = config::Config::builder()
            .add_source(config::File::from_str(text, config::FileFormat::Toml))
            .build()
            .map_err(|e| ConfigErrors::one("(config)", e))?;
        Self::finish(raw)
    }

    fn finish(raw: config::Config) -> Result<Config, ConfigErrors> {
        let mut config: Config = serde_path_to_error::deserialize(raw).map_err(|e| {
            let path = e.path().to_string();
            let path = if path == "." { String::new() } else { path };
            let join = |field: &str| match path.as_str() {
                "" => field.to_owned(),
                p => format!("{p}.{field}"),
            };
            match e.into_inner() {
                // config-rs names a missing field by its whole (unseparated) path: keep the field.
                config::ConfigError::NotFound(missing) => {
                    let field = missing.rsplit([']', '.']).next().unwrap_or(&missing);
                    ConfigErrors::one(join(field), "is required")
                }
                other => {
                    let mut reason = other.to_string();
                    if let Some(at) = reason.find(" for key `") {
                        reason.truncate(at);
                    }
                    let key = if path.is_empty() {
                        "(top level)".to_owned()
                    } else {
                        path
                    };
                    ConfigErrors::one(key, reason)
                }
            }
        })?;
        config.validate()?;
        Ok(config)
    }

    /// The resolved configuration as TOML, defaults included.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# cannot print the configuration: {e}\n"))
    }

    /// Check what serde cannot: ranges, names, references between sections. Fills in the
    /// defaults that depend on other keys (stop bits).
    pub fn validate(&mut self) -> Result<(), ConfigErrors> {
        let mut errors = Vec::new();
        let mut fail = |key: String, reason: String| errors.push(ConfigError { key, reason });

        if self.server.listen.is_empty() {
            fail("server.listen".into(), "needs at least one address".into());
        }
        if self.server.max_connections == 0 {
            fail("server.max_connections".into(), "must be at least 1".into());
        }
        if self.server.pipeline_depth == 0 {
            fail("server.pipeline_depth".into(), "must be at least 1".into());
        }
        if self.server.frame_timeout.is_zero() {
            fail(
                "server.frame_timeout".into(),
                "must be longer than 0".into(),
            );
        }
        if !self.server.keepalive.is_zero() && self.server.keepalive < MIN_KEEPALIVE {
            fail(
                "server.keepalive".into(),
                "must be \"0s\" (off) or at least 1s (TCP counts it in seconds)".into(),
            );
        }
        if let Err(e) = tracing_subscriber::EnvFilter::try_new(&self.log.level) {
            fail(
                "log.level".into(),
                format!("`{}` is not a log filter: {e}", self.log.level),
            );
        }
        if self.bus.is_empty() {
            fail("bus".into(), "at least one [[bus]] is needed".into());
        }

        let mut names = BTreeMap::new();
        for (i, bus) in self.bus.iter_mut().enumerate() {
            let key = |field: &str| format!("bus[{i}].{field}");
            if bus.name.is_empty()
                || !bus
                    .name
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"_-.".contains(&b))
            {
                fail(
                    key("name"),
                    format!("`{}` must be letters, digits, `_`, `-` or `.`", bus.name),
                );
            } else if let Some(first) = names.insert(bus.name.clone(), i) {
                fail(
                    key("name"),
                    format!("`{}` is already the name of bus[{first}]", bus.name),
                );
            }
            if bus.device.is_empty() {
                fail(
                    key("device"),
                    "needs a serial device path or \"sim\"".into(),
                );
            }
            if bus.baud == 0 {
                fail(key("baud"), "must be more than 0".into());
            }
            if !matches!(bus.data_bits, 7 | 8) {
                fail(key("data_bits"), format!("{} is not 7 or 8", bus.data_bits));
            }
            match bus.stop_bits {
                None => bus.stop_bits = Some(SerialFormat::default_stop_bits(bus.parity)),
                Some(1 | 2) => {}
                Some(n) => fail(key("stop_bits"), format!("{n} is not 1 or 2")),
            }
            for (field, value) in [
                ("response_timeout", bus.response_timeout),
                ("queue_timeout", bus.queue_timeout),
                ("reopen_delay", bus.reopen_delay),
                ("slave_probe_interval", bus.slave_probe_interval),
            ] {
                if value.is_zero() {
                    fail(key(field), "must be longer than 0".into());
                }
            }
            if bus.reopen_delay_max < bus.reopen_delay {
                fail(
                    key("reopen_delay_max"),
                    "must not be shorter than reopen_delay".into(),
                );
            }
            if bus.retries > MAX_RETRIES {
                fail(
                    key("retries"),
                    format!("{} is more than {MAX_RETRIES}", bus.retries),
                );
            }
            if bus.queue_depth == 0 {
                fail(key("queue_depth"), "must be at least 1".into());
            }
            let mut seen = UnitSet::default();
            for (j, slave) in bus.slave.iter().enumerate() {
                let key = format!("bus[{i}].slave[{j}]");
                if slave.address == 0 || slave.address > MAX_SLAVE_ADDRESS {
                    fail(
                        format!("{key}.address"),
                        format!("{} is not a slave address 1-247", slave.address),
                    );
                } else if seen.contains(slave.address) {
                    fail(
                        format!("{key}.address"),
                        format!("slave {} is configured twice", slave.address),
                    );
                }
                seen.insert(slave.address);
                if slave.response_timeout.is_some_and(|t| t.is_zero()) {
                    fail(
                        format!("{key}.response_timeout"),
                        "must be longer than 0".into(),
                    );
                }
            }
            if !bus.sim_slave.is_empty() && !bus.is_sim() {
                fail(
                    key("sim_slave"),
                    format!("only a bus with device = \"{SIM_DEVICE}\" has simulated slaves"),
                );
            }
            let mut seen = UnitSet::default();
            let format = bus.format();
            for (j, sim) in bus.sim_slave.iter().enumerate() {
                let key = |field: &str| format!("bus[{i}].sim_slave[{j}].{field}");
                if sim.address.is_empty() {
                    fail(key("address"), "names no address".into());
                }
                for address in sim.address.iter() {
                    if address == 0 || address > MAX_SLAVE_ADDRESS {
                        fail(
                            key("address"),
                            format!("{address} is not a slave address 1-247"),
                        );
                        break;
                    }
                    if seen.contains(address) {
                        fail(
                            key("address"),
                            format!("slave {address} is simulated twice"),
                        );
                        break;
                    }
                    seen.insert(address);
                }
                if !(0.0..=1.0).contains(&sim.crc_error_rate) {
                    fail(key("crc_error_rate"), "must be from 0 to 1".into());
                }
                for (field, bytes) in [
                    ("garbage_before", sim.garbage_before),
                    ("garbage_after", sim.garbage_after),
                ] {
                    if bytes > MAX_GARBAGE {
                        fail(
                            key(field),
                            format!("{bytes} is more than {MAX_GARBAGE} bytes"),
                        );
                    }
                }
                if sim
                    .reply_function
                    .is_some_and(|f| f == 0 || f & EXCEPTION_BIT != 0)
                {
                    fail(
                        key("reply_function"),
                        "must be a function code 1-127".into(),
                    );
                }
                if sim.truncate_reply == Some(0) {
                    fail(
                        key("truncate_reply"),
                        "must be at least 1 byte (a slave that sends nothing is `offline`)".into(),
                    );
                }
                match (sim.reply_gap, sim.reply_gap_after) {
                    (Some(_), None) => {
                        fail(key("reply_gap_after"), "is required with reply_gap".into())
                    }
                    (None, Some(_)) => {
                        fail(key("reply_gap"), "is required with reply_gap_after".into())
                    }
                    (_, Some(0)) => fail(key("reply_gap_after"), "must be at least 1 byte".into()),
                    _ => {}
                }
                if !sim.model.is_drive() {
                    for (field, set) in [
                        ("params", !sim.params.is_empty()),
                        ("trip", sim.trip.is_some()),
                    ] {
                        if set {
                            fail(
                                key(field),
                                "only drive models have parameters and faults".into(),
                            );
                        }
                    }
                } else if let Some(address) = sim.address.iter().next() {
                    // The drive checks its own parameters; one power-on tells for every address.
                    if let Err(e) = sim::build(sim, address, format) {
                        let field = if e.param == "trip" {
                            e.param
                        } else {
                            format!("params.\"{}\"", e.param)
                        };
                        fail(key(&field), e.reason);
                    }
                }
            }
        }

        let mut routed: BTreeMap<u8, usize> = BTreeMap::new();
        for (i, route) in self.route.iter().enumerate() {
            let key = |field: &str| format!("route[{i}].{field}");
            if !names.contains_key(&route.bus) {
                fail(key("bus"), format!("there is no bus named `{}`", route.bus));
            }
            if route.address.is_some() && route.offset.is_some() {
                fail(key("offset"), "give `address` or `offset`, not both".into());
            }
            if route.address.is_some_and(|a| a > MAX_SLAVE_ADDRESS) {
                fail(key("address"), "must be a slave address 0-247".into());
            }
            if route.units.is_empty() {
                fail(key("units"), "names no unit".into());
            }
            for unit in route.units.iter() {
                if let Some(first) = routed.insert(unit, i) {
                    fail(
                        key("units"),
                        format!("unit {unit} is already routed by route[{first}]"),
                    );
                    break;
                }
                if route.target(unit).is_none() {
                    fail(
                        key("offset"),
                        format!("sends unit {unit} outside slave addresses 0-247"),
                    );
                    break;
                }
            }
        }

        if errors.is_empty() {
            Ok(())
        } else {
            Err(ConfigErrors(errors))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
        [[bus]]
        name = "line1"
        device = "/dev/ttyUSB0"
    "#;

    fn errors(text: &str) -> Vec<String> {
        Config::from_toml_str(text)
            .expect_err("config should be refused")
            .0
            .iter()
            .map(ToString::to_string)
            .collect()
    }

    #[test]
    fn a_minimal_file_gets_every_default() {
        let c = Config::from_toml_str(MINIMAL).unwrap();
        assert_eq!(c.server, Server::default());
        assert_eq!(c.metrics.listen, defaults::metrics_listen());
        assert_eq!(
            (c.log.level.as_str(), c.log.format),
            ("info", LogFormat::Text)
        );
        let bus = &c.bus[0];
        assert_eq!(
            (bus.baud, bus.data_bits, bus.parity),
            (19_200, 8, Parity::Even)
        );
        assert_eq!(bus.stop_bits, Some(1), "parity even means one stop bit");
        assert_eq!(bus.response_timeout, Duration::from_secs(1));
        assert_eq!(bus.turnaround_delay, Duration::from_millis(100));
        assert!(bus.broadcast_reply);
        assert!(!bus.retry_writes);
    }

    #[test]
    fn allow_and_read_only_take_networks_single_addresses_and_comma_strings() {
        let c = Config::from_toml_str(&format!(
            "[server]\nallow = [\"10.1.0.0/16\", \"192.168.1.7\", \"fd00::/8\"]\n\
             read_only = \"10.1.2.0/24, ::1\"\n{MINIMAL}"
        ))
        .unwrap();
        let nets: Vec<String> = c.server.allow.iter().map(ToString::to_string).collect();
        assert_eq!(nets, ["10.1.0.0/16", "192.168.1.7/32", "fd00::/8"]);
        let nets: Vec<String> = c.server.read_only.iter().map(ToString::to_string).collect();
        assert_eq!(nets, ["10.1.2.0/24", "::1/128"]);
        // Host bits are dropped: "10.1.2.3/8" is the network 10.0.0.0/8.
        let c =
            Config::from_toml_str(&format!("[server]\nallow = \"10.1.2.3/8\"\n{MINIMAL}")).unwrap();
        assert_eq!(c.server.allow[0].to_string(), "10.0.0.0/8");
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
    }

    #[test]
    fn bad_server_access_and_connection_keys_are_named() {
        for (keys, key, reason) in [
            ("allow = [\"10.0.0.0/33\"]", "server.allow", "10.0.0.0/33"),
            ("read_only = \"plc.local\"", "server.read_only", "plc.local"),
            ("when_full = \"drop\"", "server.when_full", "drop"),
            (
                "frame_timeout = \"0s\"",
                "server.frame_timeout",
                "longer than 0",
            ),
            ("keepalive = \"500ms\"", "server.keepalive", "at least 1s"),
        ] {
            let e = errors(&format!("[server]\n{keys}\n{MINIMAL}"));
            assert_eq!(e.len(), 1, "{e:?}");
            assert!(e[0].starts_with(key), "{keys}: {e:?}");
            assert!(e[0].contains(reason), "{keys}: {e:?}");
        }
        let c = Config::from_toml_str(&format!("[server]\nkeepalive = \"0s\"\n{MINIMAL}"));
        assert!(c.is_ok(), "0s turns keepalive off");
    }

    #[test]
    fn a_zero_slave_probe_interval_is_refused() {
        let e = errors(&format!("{MINIMAL}\nslave_probe_interval = \"0s\""));
        assert!(e[0].starts_with("bus[0].slave_probe_interval"), "{e:?}");
    }

    #[test]
    fn no_parity_defaults_to_two_stop_bits() {
        let c = Config::from_toml_str(&format!("{MINIMAL}\nparity = \"none\"")).unwrap();
        assert_eq!(c.bus[0].stop_bits, Some(2));
        assert_eq!(c.bus[0].format().bits_per_char(), 11);
    }

    #[test]
    fn an_unknown_key_is_named_with_its_path() {
        let e = errors(&format!("{MINIMAL}\nbaud_rate = 9600"));
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("bus[0]"), "{e:?}");
        assert!(e[0].contains("baud_rate"), "{e:?}");
    }

    #[test]
    fn a_wrong_value_is_named_with_its_path_and_reason() {
        let e = errors(&format!("{MINIMAL}\nparity = \"evn\""));
        assert!(e[0].starts_with("bus[0].parity:"), "{e:?}");
        assert!(!e[0].contains("for key"), "{e:?}");
        let e = errors(&format!("{MINIMAL}\nresponse_timeout = \"soon\""));
        assert!(e[0].starts_with("bus[0].response_timeout:"), "{e:?}");
        assert!(e[0].contains("soon"), "{e:?}");
        let e = errors(&format!("[server]\nlisten = \"localhost\"\n{MINIMAL}"));
        assert!(e[0].starts_with("server.listen:"), "{e:?}");
    }

    #[test]
    fn semantic_errors_are_all_reported_with_their_keys() {
        let e = errors(
            r#"
            [[bus]]
            name = "a"
            device = "sim"
            data_bits = 6
            stop_bits = 3
            [[bus.slave]]
            address = 248
            [[bus]]
            name = "a"
            device = ""
            [[route]]
            units = "1-3"
            bus = "nope"
            "#,
        );
        let keys: Vec<&str> = e.iter().map(|s| s.split(':').next().unwrap()).collect();
        assert_eq!(
            keys,
            [
                "bus[0].data_bits",
                "bus[0].stop_bits",
                "bus[0].slave[0].address",
                "bus[1].name",
                "bus[1].device",
                "route[0].bus"
            ],
            "{e:#?}"
        );
    }

    #[test]
    fn a_missing_required_key_is_named() {
        let e = errors("[[bus]]\nname = \"a\"\n");
        assert_eq!(e, ["bus[0].device: is required"]);
    }

    #[test]
    fn a_config_without_buses_is_refused() {
        assert_eq!(errors("")[0], "bus: at least one [[bus]] is needed");
    }

    #[test]
    fn routes_may_not_overlap_or_leave_the_address_range() {
        let e = errors(&format!(
            "{MINIMAL}\n[[route]]\nunits = \"1-10\"\nbus = \"line1\"\noffset = 240\n\
             [[route]]\nunits = [5, 6]\nbus = \"line1\"\naddress = 3\n"
        ));
        assert_eq!(e.len(), 2, "{e:?}");
        assert!(e[0].starts_with("route[0].offset: sends unit 8"), "{e:?}");
        assert!(
            e[1].starts_with("route[1].units: unit 5 is already routed by route[0]"),
            "{e:?}"
        );
    }

    #[test]
    fn sim_slaves_only_live_on_a_sim_bus() {
        let e = errors(&format!(
            "{MINIMAL}\n[[bus.sim_slave]]\naddress = \"1-4\"\n"
        ));
        assert!(e[0].starts_with("bus[0].sim_slave:"), "{e:?}");
    }

    const SIM_BUS: &str =
        "[[bus]]\nname = \"sim\"\ndevice = \"sim\"\n[[bus.sim_slave]]\naddress = 2\n";

    #[test]
    fn the_new_fault_knobs_reach_the_slave_and_read_back_the_same() {
        let text = format!(
            "{SIM_BUS}reply_function = 4\ntruncate_reply = 5\nreply_gap = \"30ms\"\nreply_gap_after = 3\n"
        );
        let c = Config::from_toml_str(&text).unwrap();
        let faults = c.bus[0].sim_slave[0].faults();
        assert_eq!(faults.reply_function, Some(4));
        assert_eq!(faults.truncate_reply, Some(5));
        assert_eq!(
            faults.reply_gap,
            Some(Pause {
                after: 3,
                gap: Duration::from_millis(30)
            })
        );
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
    }

    #[test]
    fn bad_fault_knobs_are_refused_by_key() {
        for (knobs, key, reason) in [
            (
                "reply_function = 0",
                "reply_function",
                "must be a function code 1-127",
            ),
            (
                "reply_function = 131",
                "reply_function",
                "must be a function code 1-127",
            ),
            (
                "truncate_reply = 0",
                "truncate_reply",
                "must be at least 1 byte",
            ),
            (
                "reply_gap = \"30ms\"",
                "reply_gap_after",
                "is required with reply_gap",
            ),
            (
                "reply_gap_after = 3",
                "reply_gap",
                "is required with reply_gap_after",
            ),
            (
                "reply_gap = \"30ms\"\nreply_gap_after = 0",
                "reply_gap_after",
                "must be at least 1 byte",
            ),
        ] {
            let e = errors(&format!("{SIM_BUS}{knobs}\n"));
            let expected = format!("bus[0].sim_slave[0].{key}: {reason}");
            assert!(
                e.len() == 1 && e[0].starts_with(&expected),
                "{knobs}: {e:?}"
            );
        }
    }

    #[test]
    fn unit_sets_parse_ids_lists_and_ranges_and_print_canonically() {
        let set: UnitSet = "1-4, 7,10-11".parse().unwrap();
        assert_eq!(set.iter().collect::<Vec<_>>(), [1, 2, 3, 4, 7, 10, 11]);
        assert_eq!(set.to_string(), "1-4,7,10-11");
        assert_eq!("255".parse::<UnitSet>().unwrap().to_string(), "255");
        assert_eq!("0-255".parse::<UnitSet>().unwrap().iter().count(), 256);
        assert!("4-1".parse::<UnitSet>().is_err());
        assert!("256".parse::<UnitSet>().is_err());
        assert!("".parse::<UnitSet>().is_err());
    }

    #[test]
    fn environment_variables_override_the_file_including_array_entries() {
        let dir = std::env::temp_dir().join(format!("mbgw-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("gateway.toml");
        std::fs::write(&path, MINIMAL).unwrap();
        let env = [
            ("MBGW__SERVER__LISTEN", "127.0.0.1:5020,[::1]:5020"),
            ("MBGW__BUS__0__BAUD", "9600"),
            ("MBGW__BUS__0__RETRY_WRITES", "true"),
            ("MBGW__BUS__0__RESPONSE_TIMEOUT", "250ms"),
            ("PATH", "/usr/bin"),
        ]
        .map(|(k, v)| (k.to_owned(), v.to_owned()));
        let c = Config::load(&path, env).unwrap();
        assert_eq!(c.server.listen.len(), 2);
        assert_eq!(c.server.listen[1], "[::1]:5020".parse().unwrap());
        assert_eq!(c.bus[0].baud, 9600);
        assert!(c.bus[0].retry_writes);
        assert_eq!(c.bus[0].response_timeout, Duration::from_millis(250));

        let typo = [("MBGW__SERVER__LISTN".to_owned(), "x".to_owned())];
        let e = Config::load(&path, typo).unwrap_err().to_string();
        assert!(e.starts_with("server"), "{e}");
        assert!(e.contains("listn"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_missing_file_is_an_error_naming_it() {
        let e = Config::load(Path::new("/nonexistent/gateway.toml"), []).unwrap_err();
        assert!(
            e.to_string().starts_with("/nonexistent/gateway.toml:"),
            "{e}"
        );
    }

    #[test]
    fn the_printed_configuration_reads_back_the_same() {
        let text = format!(
            "{MINIMAL}\ninter_frame_delay = \"5ms\"\n[[bus.slave]]\naddress = 3\nresponse_timeout = \"2s\"\n\
             [[route]]\nunits = \"255\"\nbus = \"line1\"\naddress = 17\n"
        );
        let c = Config::from_toml_str(&text).unwrap();
        let again = Config::from_toml_str(&c.to_toml()).unwrap();
        assert_eq!(c, again, "{}", c.to_toml());
    }

    #[test]
    fn routes_map_units_by_address_or_offset() {
        let fixed = Route {
            units: UnitSet::default(),
            bus: "b".into(),
            address: Some(17),
            offset: None,
        };
        assert_eq!(fixed.target(255), Some(17));
        let shifted = Route {
            units: UnitSet::default(),
            bus: "b".into(),
            address: None,
            offset: Some(-100),
        };
        assert_eq!(shifted.target(101), Some(1));
        assert_eq!(shifted.target(99), None);
        let same = Route {
            units: UnitSet::default(),
            bus: "b".into(),
            address: None,
            offset: None,
        };
        assert_eq!(same.target(248), None);
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;
        use std::net::{Ipv4Addr, Ipv6Addr};

        fn duration() -> impl Strategy<Value = Duration> {
            prop_oneof![
                (1u64..=60_000).prop_map(Duration::from_millis),
                (1u64..=10_000_000).prop_map(Duration::from_micros),
                (1u64..=100_000).prop_map(Duration::from_secs),
            ]
        }

        fn socket_addr() -> impl Strategy<Value = SocketAddr> {
            prop_oneof![
                any::<([u8; 4], u16)>().prop_map(SocketAddr::from),
                any::<([u16; 8], u16)>()
                    .prop_map(|(ip, port)| SocketAddr::from((Ipv6Addr::from(ip), port))),
            ]
        }

        fn server() -> impl Strategy<Value = Server> {
            let limits = (
                prop::collection::vec(socket_addr(), 1..4),
                1usize..=100_000,
                prop_oneof![Just(Duration::ZERO), duration()],
                1usize..=64,
                prop_oneof![Just(Duration::ZERO), duration()],
            );
            let guard = (
                prop::sample::select(vec![WhenFull::CloseOldestIdle, WhenFull::Refuse]),
                duration(),
                prop_oneof![
                    Just(Duration::ZERO),
                    (1u64..=7200).prop_map(Duration::from_secs)
                ],
                prop::collection::vec(net(), 0..4),
                prop::collection::vec(net(), 0..4),
            );
            (limits, guard).prop_map(
                |(
                    (listen, max_connections, idle, depth, shutdown),
                    (when_full, frame_timeout, keepalive, allow, read_only),
                )| Server {
                    listen,
                    max_connections,
                    idle_timeout: idle,
                    pipeline_depth: depth,
                    shutdown_timeout: shutdown,
                    when_full,
                    frame_timeout,
                    keepalive,
                    allow,
                    read_only,
                },
            )
        }

        /// An IPv4 or IPv6 network, host bits cleared as the loader clears them.
        fn net() -> impl Strategy<Value = IpNet> {
            prop_oneof![
                (any::<u32>(), 0u8..=32).prop_map(|(ip, len)| {
                    IpNet::from(ipnet::Ipv4Net::new(Ipv4Addr::from(ip), len).unwrap()).trunc()
                }),
                (any::<u128>(), 0u8..=128).prop_map(|(ip, len)| {
                    IpNet::from(ipnet::Ipv6Net::new(Ipv6Addr::from(ip), len).unwrap()).trunc()
                }),
            ]
        }

        fn log() -> impl Strategy<Value = Log> {
            let levels = [
                "info",
                "debug",
                "warn",
                "error",
                "modbus_gateway=trace",
                "info,tokio=warn",
            ];
            let formats = [LogFormat::Text, LogFormat::Json];
            (
                prop::sample::select(levels.to_vec()),
                prop::sample::select(formats.to_vec()),
            )
                .prop_map(|(level, format)| Log {
                    level: level.into(),
                    format,
                })
        }

        /// Disjoint sets of addresses 1-247.
        fn address_sets(n: usize) -> impl Strategy<Value = Vec<UnitSet>> {
            prop::collection::vec(prop::collection::vec((1u8..=247, 0u8..4), 1..3), 0..=n).prop_map(
                |sets| {
                    let mut taken = UnitSet::default();
                    let mut out = Vec::new();
                    for ranges in sets {
                        let mut set = UnitSet::default();
                        for (low, span) in ranges {
                            for a in low..=low.saturating_add(span).min(MAX_SLAVE_ADDRESS) {
                                if !taken.contains(a) {
                                    taken.insert(a);
                                    set.insert(a);
                                }
                            }
                        }
                        if !set.is_empty() {
                            out.push(set);
                        }
                    }
                    out
                },
            )
        }

        fn slaves() -> impl Strategy<Value = Vec<Slave>> {
            (
                prop::collection::btree_set(1u8..=MAX_SLAVE_ADDRESS, 0..4),
                prop::collection::vec((prop::option::of(duration()), any::<bool>()), 4),
            )
                .prop_map(|(addresses, knobs)| {
                    addresses
                        .into_iter()
                        .zip(knobs)
                        .map(|(address, (response_timeout, wide_read_count))| Slave {
                            address,
                            response_timeout,
                            wide_read_count,
                        })
                        .collect()
                })
        }

        fn sim_slaves() -> impl Strategy<Value = Vec<SimSlave>> {
            let models = [
                SimModel::Registers,
                SimModel::Gd20,
                SimModel::Gd300,
                SimModel::Gd10,
                SimModel::PdInverter,
            ];
            let knobs = (
                prop::sample::select(models.to_vec()),
                prop_oneof![Just(Duration::ZERO), duration()],
                any::<bool>(),
                prop::option::of(duration()),
                prop_oneof![Just(0.0), 0.0..=1.0, Just(1.0)],
                (0..=MAX_GARBAGE, 0..=MAX_GARBAGE),
                prop::option::of(any::<u8>()),
            );
            let bends = (
                prop::option::of(1u8..=127),
                prop::option::of(1usize..=300),
                prop::option::of((duration(), 1usize..=300)),
            );
            let knobs = (knobs, bends);
            (address_sets(3), prop::collection::vec(knobs, 3)).prop_map(|(sets, knobs)| {
                sets.into_iter()
                    .zip(knobs)
                    .map(
                        |(
                            address,
                            (
                                (model, delay, offline, late, rate, garbage, reply),
                                (function, truncate, gap),
                            ),
                        )| SimSlave {
                            address,
                            model,
                            processing_delay: delay,
                            params: BTreeMap::new(),
                            trip: None,
                            offline,
                            extra_delay: delay / 2,
                            late_reply: late,
                            crc_error_rate: rate,
                            garbage_before: garbage.0,
                            garbage_after: garbage.1,
                            reply_address: reply,
                            reply_function: function,
                            truncate_reply: truncate,
                            reply_gap: gap.map(|(gap, _)| gap),
                            reply_gap_after: gap.map(|(_, after)| after),
                        },
                    )
                    .collect()
            })
        }

        fn bus() -> impl Strategy<Value = Bus> {
            let bauds = [1200, 2400, 4800, 9600, 19_200, 38_400, 57_600, 115_200];
            let parities = [Parity::None, Parity::Even, Parity::Odd];
            let line = (
                "[a-zA-Z0-9_.-]{0,8}",
                prop_oneof![Just(SIM_DEVICE.to_owned()), "/dev/tty(USB|S|AMA)[0-9]"],
                prop::sample::select(bauds.to_vec()),
                prop_oneof![Just(7u8), Just(8u8)],
                prop::sample::select(parities.to_vec()),
                prop::option::of(1u8..=2),
            );
            let timing = (
                duration(),
                (0..=MAX_RETRIES, any::<bool>()),
                prop::option::of(duration()),
                prop::option::of(duration()),
                prop_oneof![Just(Duration::ZERO), duration()],
                any::<bool>(),
            );
            let queue = (1usize..=4096, duration(), duration(), duration());
            let down = (0u32..=10, duration());
            (line, timing, queue, down, slaves(), sim_slaves()).prop_map(
                |(line, timing, queue, down, slave, sim_slave)| {
                    let (name, device, baud, data_bits, parity, stop_bits) = line;
                    let (response_timeout, retry, inter_frame, byte, turn, reply) = timing;
                    let (retries, retry_writes) = retry;
                    let (queue_depth, queue_timeout, reopen_delay, reopen_extra) = queue;
                    let sim_slave = if device == SIM_DEVICE {
                        sim_slave
                    } else {
                        Vec::new()
                    };
                    Bus {
                        name,
                        device,
                        baud,
                        data_bits,
                        parity,
                        stop_bits,
                        response_timeout,
                        retries,
                        retry_writes,
                        inter_frame_delay: inter_frame,
                        byte_timeout: byte,
                        turnaround_delay: turn,
                        broadcast_reply: reply,
                        queue_depth,
                        queue_timeout,
                        reopen_delay,
                        reopen_delay_max: reopen_delay + reopen_extra,
                        slave_down_after: down.0,
                        slave_probe_interval: down.1,
                        slave,
                        sim_slave,
                    }
                },
            )
        }

        /// How a route picks its slave: the unit itself, a fixed address, or an offset (a point
        /// in the range of offsets that keep every unit on the line).
        #[derive(Clone, Debug)]
        enum Target {
            Same,
            Address(u8),
            Offset(f64),
        }

        fn routes(buses: usize) -> impl Strategy<Value = Vec<(UnitSet, usize, Target)>> {
            let target = prop_oneof![
                Just(Target::Same),
                (0..=MAX_SLAVE_ADDRESS).prop_map(Target::Address),
                (0.0..=1.0).prop_map(Target::Offset),
            ];
            let units = prop::collection::vec((any::<u8>(), 0u8..16), 1..3).prop_map(|ranges| {
                let mut set = UnitSet::default();
                for (low, span) in ranges {
                    (low..=low.saturating_add(span)).for_each(|u| set.insert(u));
                }
                set
            });
            prop::collection::vec((units, 0..buses, target), 0..4)
        }

        /// A configuration that validates: every section, a few buses (some simulated), slaves,
        /// simulated slaves and routes.
        fn config() -> impl Strategy<Value = Config> {
            let parts = (
                server(),
                socket_addr(),
                log(),
                prop::collection::vec(bus(), 1..4),
            );
            parts
                .prop_flat_map(|(server, metrics, log, buses)| {
                    let n = buses.len();
                    (Just((server, metrics, log, buses)), routes(n))
                })
                .prop_map(|((server, metrics, log, mut bus), wanted)| {
                    // Unique names: the generated prefix plus the position.
                    for (i, b) in bus.iter_mut().enumerate() {
                        b.name = format!("{}{i}", b.name);
                    }
                    let mut routed = UnitSet::default();
                    let mut route = Vec::new();
                    for (units, b, target) in wanted {
                        let mut fresh = UnitSet::default();
                        units
                            .iter()
                            .filter(|&u| !routed.contains(u))
                            .for_each(|u| fresh.insert(u));
                        let (Some(low), Some(high)) = (fresh.iter().next(), fresh.iter().last())
                        else {
                            continue;
                        };
                        let (low, high) = (i32::from(low), i32::from(high));
                        let max = i32::from(MAX_SLAVE_ADDRESS);
                        let (address, offset) = match target {
                            Target::Same if high <= max => (None, None),
                            Target::Offset(at) if high - low <= max => {
                                let span = f64::from(max - high + low);
                                (None, Some(-low + (at * span) as i32))
                            }
                            Target::Address(a) => (Some(a), None),
                            _ => (Some(1), None),
                        };
                        fresh.iter().for_each(|u| routed.insert(u));
                        route.push(Route {
                            units: fresh,
                            bus: bus[b].name.clone(),
                            address,
                            offset,
                        });
                    }
                    Config {
                        server,
                        metrics: Metrics { listen: metrics },
                        log,
                        bus,
                        route,
                    }
                })
        }

        /// Where a key sits in the TOML document: `bus[1].slave[0].address`.
        fn at<'a>(doc: &'a mut toml::Value, path: &str) -> Option<&'a mut toml::Value> {
            let mut here = doc;
            for part in path.split('.') {
                let mut pieces = part.split('[');
                let key = pieces.next()?;
                here = here
                    .as_table_mut()?
                    .entry(key)
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                for index in pieces {
                    let index: usize = index.trim_end_matches(']').parse().ok()?;
                    here = here.as_array_mut()?.get_mut(index)?;
                }
            }
            Some(here)
        }

        /// Keys of `config` set to values the loader must refuse, each with the key the error
        /// must name.
        fn mutations(config: &Config) -> Vec<(String, toml::Value)> {
            use toml::Value::{Float, Integer, String as Text};
            let text = |s: &str| Text(s.to_owned());
            let table = |key: &str, value| {
                toml::Value::Table(toml::Table::from_iter([(key.to_owned(), value)]))
            };
            let mut out = vec![
                ("server.max_connections".to_owned(), Integer(0)),
                ("server.pipeline_depth".to_owned(), Integer(0)),
                ("server.listen".to_owned(), text("localhost")),
                ("server.listen".to_owned(), toml::Value::Array(vec![])),
                ("server.idle_timeout".to_owned(), text("soon")),
                ("server.frame_timeout".to_owned(), text("0s")),
                ("server.keepalive".to_owned(), text("10ms")),
                ("server.when_full".to_owned(), text("oldest")),
                ("server.allow".to_owned(), text("10.0.0.0/40")),
                ("server.read_only".to_owned(), text("plc")),
                ("metrics.listen".to_owned(), text("127.0.0.1")),
                ("log.level".to_owned(), text("[")),
                ("log.format".to_owned(), text("xml")),
            ];
            for (i, bus) in config.bus.iter().enumerate() {
                let mut key = |field: &str, value| out.push((format!("bus[{i}].{field}"), value));
                key("baud", Integer(0));
                key("baud", Integer(-9600));
                key("data_bits", Integer(6));
                key("stop_bits", Integer(3));
                key("parity", text("evn"));
                key("response_timeout", text("0s"));
                key("queue_timeout", text("0s"));
                key("reopen_delay", text("0s"));
                key("reopen_delay_max", text("0s"));
                key("slave_probe_interval", text("0s"));
                key("turnaround_delay", text("later"));
                key("retries", Integer(11));
                key("queue_depth", Integer(0));
                key("name", text("line one"));
                key("device", text(""));
                key("broadcast_reply", text("maybe"));
                if i > 0 {
                    key("name", text(&config.bus[0].name));
                }
                if !bus.is_sim() {
                    key(
                        "sim_slave",
                        toml::Value::Array(vec![table("address", Integer(1))]),
                    );
                }
                for j in 0..bus.slave.len() {
                    let mut key = |field: &str, value| {
                        out.push((format!("bus[{i}].slave[{j}].{field}"), value))
                    };
                    key("address", Integer(0));
                    key("address", Integer(248));
                    key("address", Integer(256));
                    key("response_timeout", text("0s"));
                    if j > 0 {
                        key("address", Integer(i64::from(bus.slave[0].address)));
                    }
                }
                for (j, sim) in bus.sim_slave.iter().enumerate() {
                    let mut key = |field: &str, value| {
                        out.push((format!("bus[{i}].sim_slave[{j}].{field}"), value))
                    };
                    key("address", text("0-3"));
                    key("address", text("240-248"));
                    key("address", text("4-1"));
                    key("model", text("gd2000"));
                    key("crc_error_rate", Float(1.5));
                    key("crc_error_rate", Float(-0.1));
                    key("garbage_before", Integer(MAX_GARBAGE as i64 + 1));
                    key("garbage_after", Integer(MAX_GARBAGE as i64 + 1));
                    if sim.model.is_drive() {
                        key("trip", Integer(0xFFFF));
                    } else {
                        key("trip", Integer(35));
                        key("params", table("P00.01", Integer(2)));
                    }
                    if j > 0 {
                        let first = bus.sim_slave[0].address.iter().next().unwrap_or(1);
                        key("address", Integer(i64::from(first)));
                    }
                }
            }
            for (k, route) in config.route.iter().enumerate() {
                let mut key = |field: &str, value| out.push((format!("route[{k}].{field}"), value));
                key("bus", text("nowhere"));
                key("units", text("9-1"));
                if route.offset.is_none() {
                    key("address", Integer(248));
                }
                if k > 0 {
                    key("units", text(&config.route[0].units.to_string()));
                }
            }
            out
        }

        /// A TOML value of any type, mostly one that some key takes.
        fn toml_value() -> impl Strategy<Value = String> {
            let words = [
                "sim",
                "/dev/ttyUSB0",
                "1s",
                "0s",
                "250ms",
                "2h",
                "1-4",
                "1,5-7",
                "0-255",
                "4-1",
                "127.0.0.1:502",
                "[::1]:502",
                "0.0.0.0:502,[::]:502",
                "even",
                "odd",
                "none",
                "text",
                "json",
                "info",
                "registers",
                "gd20",
                "gd300",
                "gd10",
                "pd-inverter",
                "line1",
                "yes",
                "",
            ];
            let scalar = prop_oneof![
                prop::sample::select(words.to_vec()).prop_map(|w| format!("\"{w}\"")),
                "\"[ -~]{0,12}\"",
                prop_oneof![-2i64..=260, Just(9600), Just(65_536), any::<i64>()]
                    .prop_map(|n| n.to_string()),
                prop_oneof![
                    Just("true"),
                    Just("false"),
                    Just("0.5"),
                    Just("1e9"),
                    Just("-0.0")
                ]
                .prop_map(str::to_owned),
            ];
            scalar.prop_recursive(2, 8, 4, |inner| {
                prop_oneof![
                    prop::collection::vec(inner.clone(), 0..4)
                        .prop_map(|items| format!("[{}]", items.join(", "))),
                    prop::collection::vec(("[A-Za-z0-9.]{1,7}", inner), 0..3).prop_map(|pairs| {
                        let pairs: Vec<String> = pairs
                            .iter()
                            .map(|(k, v)| format!("\"{k}\" = {v}"))
                            .collect();
                        format!("{{ {} }}", pairs.join(", "))
                    }),
                ]
            })
        }

        /// Sections and keys of the real layout, each key with a value it takes or a value of
        /// any type, a rare garbage line, and buses that mostly have a name and a device, so
        /// that some documents load.
        const BUS_KEYS: &[&str] = &[
            "baud",
            "data_bits",
            "parity",
            "stop_bits",
            "response_timeout",
            "retries",
            "retry_writes",
            "inter_frame_delay",
            "byte_timeout",
            "queue_depth",
            "reopen_delay_max",
        ];
        const SIM_SLAVE_KEYS: &[&str] = &[
            "address",
            "model",
            "params",
            "trip",
            "offline",
            "late_reply",
            "crc_error_rate",
            "garbage_before",
            "reply_address",
        ];

        fn toml_document() -> impl Strategy<Value = String> {
            // Headers with the keys they take, [[bus]] and its parts more likely; the last two
            // are the wrong kind of table.
            let sections: &[(&str, &[&str])] = &[
                (
                    "[server]",
                    &[
                        "listen",
                        "max_connections",
                        "idle_timeout",
                        "pipeline_depth",
                    ],
                ),
                ("[metrics]", &["listen"]),
                ("[log]", &["level", "format"]),
                ("[[bus]]", BUS_KEYS),
                ("[[bus]]", BUS_KEYS),
                ("[[bus]]", BUS_KEYS),
                (
                    "[[bus.slave]]",
                    &["address", "response_timeout", "wide_read_count"],
                ),
                ("[[bus.sim_slave]]", SIM_SLAVE_KEYS),
                ("[[route]]", &["units", "bus", "address", "offset"]),
                (
                    "[[bus.slave]]",
                    &["address", "response_timeout", "wide_read_count"],
                ),
                ("[[bus.sim_slave]]", SIM_SLAVE_KEYS),
                ("[[route]]", &["units", "bus", "address", "offset"]),
                ("[bus]", &["baud"]),
                ("[[server]]", &["listen"]),
            ];
            let keys: &[(&str, &[&str])] = &[
                (
                    "listen",
                    &["\"127.0.0.1:5020\"", "[\"[::1]:502\", \"0.0.0.0:502\"]"],
                ),
                ("max_connections", &["1", "64"]),
                ("idle_timeout", &["\"0s\"", "\"10m\""]),
                ("pipeline_depth", &["1", "16"]),
                ("level", &["\"debug\""]),
                ("format", &["\"json\""]),
                ("baud", &["9600", "115200"]),
                ("data_bits", &["7", "8"]),
                ("parity", &["\"none\"", "\"odd\""]),
                ("stop_bits", &["1", "2"]),
                ("response_timeout", &["\"20ms\"", "\"1s 500ms\""]),
                ("retries", &["0", "3"]),
                ("retry_writes", &["true"]),
                ("inter_frame_delay", &["\"5ms\""]),
                ("byte_timeout", &["\"3ms\""]),
                ("queue_depth", &["1", "500"]),
                ("reopen_delay_max", &["\"1m\""]),
                ("address", &["3", "247"]),
                ("wide_read_count", &["true"]),
                ("model", &["\"registers\"", "\"gd20\"", "\"pd-inverter\""]),
                ("params", &["{ \"P00.01\" = 2 }", "{ \"Pd-00\" = 3 }"]),
                ("trip", &["35"]),
                ("offline", &["true"]),
                ("late_reply", &["\"2s\""]),
                ("crc_error_rate", &["0.25", "1.0"]),
                ("garbage_before", &["0", "256"]),
                ("reply_address", &["9"]),
                ("units", &["\"1-10\"", "[20, 21]", "255"]),
                ("bus", &["\"b0\"", "\"b1\""]),
                ("offset", &["-1", "100"]),
            ];
            let section =
                prop::sample::select(sections.to_vec()).prop_flat_map(|(header, names)| {
                    let known: Vec<_> = keys
                        .iter()
                        .filter(|(k, _)| names.contains(k))
                        .copied()
                        .collect();
                    let key_value = prop::sample::select(known).prop_flat_map(|(key, good)| {
                        let good = prop::sample::select(good.to_vec()).prop_map(str::to_owned);
                        (Just(key), prop_oneof![2 => good, 1 => toml_value()])
                    });
                    // A map: a key twice is a TOML error, and those are plenty already.
                    let lines = prop::collection::vec(key_value, 0..5).prop_map(|lines| {
                        let lines: BTreeMap<_, _> = lines.into_iter().collect();
                        lines
                            .into_iter()
                            .map(|(k, v)| format!("{k} = {v}\n"))
                            .collect::<String>()
                    });
                    (
                        Just(header),
                        prop::bool::weighted(0.9),
                        lines,
                        prop::option::weighted(
                            0.05,
                            prop_oneof![Just("bogus = 1".to_owned()), "[ -~]{0,16}"],
                        ),
                    )
                });
            let first_bus = prop::bool::weighted(0.8);
            (first_bus, prop::collection::vec(section, 0..6)).prop_map(|(first_bus, sections)| {
                let mut text = String::new();
                let mut seen = Vec::new();
                let mut buses = 0;
                if first_bus {
                    text.push_str("[[bus]]\nname = \"b0\"\ndevice = \"sim\"\n");
                    buses += 1;
                }
                for (header, named, lines, garbage) in sections {
                    // A table opened twice is a TOML error, and those are plenty already.
                    if !header.starts_with("[[") && seen.contains(&header) {
                        continue;
                    }
                    seen.push(header);
                    text.extend([header, "\n"]);
                    if named && header == "[[bus]]" {
                        text.push_str(&format!("name = \"b{buses}\"\ndevice = \"sim\"\n"));
                        buses += 1;
                    }
                    text.push_str(&lines);
                    text.extend(garbage.map(|g| g + "\n"));
                }
                text
            })
        }

        proptest! {
            #[test]
            fn no_text_whatever_makes_the_loader_panic(text in "\\PC*") {
                let _ = Config::from_toml_str(&text);
            }

            #[test]
            fn any_document_is_refused_with_named_keys_or_loads_and_prints_back_the_same(
                text in toml_document(),
            ) {
                match Config::from_toml_str(&text) {
                    Ok(config) => {
                        let printed = config.to_toml();
                        let again = Config::from_toml_str(&printed);
                        prop_assert_eq!(again, Ok(config), "{}\n---\n{}", text, printed);
                    }
                    Err(errors) => {
                        prop_assert!(!errors.0.is_empty());
                        prop_assert!(errors.0.iter().all(|e| !e.key.is_empty()), "{:?}", errors);
                    }
                }
            }

            #[test]
            fn every_valid_configuration_printed_loads_back_the_same(config in config()) {
                let mut config = config;
                // Fills in the stop bits, as loading does.
                let valid = config.validate();
                prop_assert!(valid.is_ok(), "the generator made an invalid config: {:?}", valid);
                let text = config.to_toml();
                let again = Config::from_toml_str(&text);
                prop_assert_eq!(again, Ok(config), "{}", text);
            }

            #[test]
            fn a_bad_value_is_refused_with_an_error_naming_its_key(
                config in config(),
                // A few of the config's mutations each: loading all of them takes seconds.
                picks in prop::collection::vec(any::<prop::sample::Index>(), 4),
            ) {
                let mut config = config;
                prop_assert!(config.validate().is_ok());
                let printed: toml::Table = config.to_toml().parse().map_err(|e| {
                    TestCaseError::fail(format!("to_toml printed bad TOML: {e}"))
                })?;
                let mutations = mutations(&config);
                for pick in picks {
                    let (key, value) = &mutations[pick.index(mutations.len())];
                    let mut doc = toml::Value::Table(printed.clone());
                    let Some(slot) = at(&mut doc, key) else {
                        return Err(TestCaseError::fail(format!("no {key} in the document")));
                    };
                    *slot = value.clone();
                    let text =
                        toml::to_string(&doc).map_err(|e| TestCaseError::fail(e.to_string()))?;
                    match Config::from_toml_str(&text) {
                        Ok(_) => prop_assert!(false, "{} = {} was accepted", key, value),
                        Err(errors) => prop_assert!(
                            errors.0.iter().any(|e| &e.key == key),
                            "{} = {} gave {:?}",
                            key,
                            value,
                            errors.0
                        ),
                    }
                }
            }
        }
    }
}
