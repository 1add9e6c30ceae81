//! The `[[bus]]` sections: one serial line each, its format and timing, its per-slave overrides
//! and, on a simulated line, the slaves to simulate (`[[bus.sim_slave]]`). Plain values; knows
//! nothing of ports, tasks or how a simulated slave is built.

use super::defaults;
use super::device::DeviceName;
use super::listen::{BusMode, SimMaster};
use super::serde_adapters::{
    duration, is_false, is_true, is_zero, is_zero_f64, is_zero_usize, opt_duration,
};
use super::serde_adapters::{words, Choice};
use super::{DeviceTls, Rs485, UnitSet, Value};
use crate::line::framing::TransportKind;
use crate::line::{Framing, LineTiming, Parity};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Duration;

/// `device` value that selects the built-in simulated line.
pub(crate) const SIM_DEVICE: &str = "sim";

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bus {
    pub name: String,
    /// A serial device path, "sim", or a serial device server: `tcp://HOST:PORT` (raw) or
    /// `rfc2217://HOST:PORT` ([`DeviceName`]).
    pub device: String,
    #[serde(default = "defaults::baud")]
    pub baud: u32,
    /// `rtu` or `ascii`: how frames look on this line.
    #[serde(default)]
    pub framing: Framing,
    /// `master`: the gateway drives the line; `listen`: another master does, and the gateway
    /// never transmits on it.
    #[serde(default, skip_serializing_if = "BusMode::is_master")]
    pub mode: BusMode,
    /// A listen line: how old what it saw may be when a master reads it.
    #[serde(default = "defaults::listen_max_age", with = "duration")]
    pub max_age: Duration,
    /// 7 or 8; left out: 8 for RTU, 7 for ASCII (filled in by `resolve`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data_bits: Option<u8>,
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
    pub(crate) inter_frame_delay: Option<Duration>,
    /// RTU: silence that ends a reply of unknown length, if longer than t3.5 (USB adapters).
    /// ASCII: the inter-character timeout that fails a frame stopping mid-way (default 1 s).
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub byte_timeout: Option<Duration>,
    /// A `tls://` device: the gateway's client certificate and the CA of the device's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tls: Option<DeviceTls>,
    /// A Modbus TCP device: requests outstanding on its connection at once (1: one at a time;
    /// more: pipelined, replies matched by transaction id).
    #[serde(default = "defaults::max_in_flight", skip_serializing_if = "is_one")]
    pub max_in_flight: usize,
    /// A Modbus TCP device: a reply must carry its request's transaction id. Off, for firmware
    /// that echoes a wrong one: the request in flight takes the reply by unit and function, and
    /// a timeout resets the connection (a late reply could not be told apart).
    #[serde(
        default = "defaults::match_transaction_id",
        skip_serializing_if = "is_true"
    )]
    pub match_transaction_id: bool,
    /// A line on the network: silence after a connection is made before the first request (a
    /// device that needs time after a connect, as some inverters' dongles do).
    #[serde(default, with = "duration", skip_serializing_if = "is_zero")]
    pub connect_delay: Duration,
    /// A line behind a serial device server: the silence inside a reply its packing timer may
    /// add, tolerated and added to every reply's deadline.
    #[serde(default, with = "duration", skip_serializing_if = "is_zero")]
    pub packing_delay: Duration,
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
    pub(crate) reopen_delay_max: Duration,
    /// After this many requests in a row timed out, a slave is down: its requests get 0x0B at
    /// once, without using the line, but for one probe per `slave_probe_interval` (0: never down).
    #[serde(default = "defaults::slave_down_after")]
    pub slave_down_after: u32,
    #[serde(default = "defaults::slave_probe_interval", with = "duration")]
    pub(crate) slave_probe_interval: Duration,
    /// Identical reads from several masters waiting together are answered by one transaction.
    #[serde(default = "defaults::coalesce_reads")]
    pub coalesce_reads: bool,
    /// Who switches the RS-485 transceiver's direction, and whether the line echoes.
    #[serde(default, skip_serializing_if = "Rs485::is_default")]
    pub rs485: Rs485,
    /// USB serial adapters: set the driver's latency timer to this at open (1-255 ms); left out,
    /// it stays as it is.
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub latency_timer: Option<Duration>,
    /// The most of the line's time the polls of plant values may take.
    #[serde(default = "defaults::poll_share")]
    pub poll_share: f64,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub slave: Vec<Slave>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sim_slave: Vec<SimSlave>,
    /// A simulated listen line: the other master, whose traffic the gateway hears.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim_master: Option<SimMaster>,
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
    /// Overrides the bus's `coalesce_reads` for this slave (off for read-to-clear registers).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coalesce_reads: Option<bool>,
    /// Answer an identical read from the last answer while it is younger than this ("0s": never).
    #[serde(default, with = "duration", skip_serializing_if = "is_zero")]
    pub cache: Duration,
    /// A device template whose values this slave exports.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub template: Option<String>,
    /// How often its values are read, unless a value says otherwise (default 10 s).
    #[serde(
        default,
        with = "opt_duration",
        skip_serializing_if = "Option::is_none"
    )]
    pub poll_interval: Option<Duration>,
    /// The most registers one poll reads from it; left out, its template's or 125.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_read_registers: Option<u16>,
    /// Its own values.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub value: Vec<Value>,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
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
    PdInverter,
    /// Eastron SDM120-Modbus single-phase energy meter.
    Sdm120,
}

impl Choice for SimModel {
    const ALL: &'static [Self] = &[
        SimModel::Registers,
        SimModel::Gd20,
        SimModel::Gd300,
        SimModel::Gd10,
        SimModel::PdInverter,
        SimModel::Sdm120,
    ];
    fn word(self) -> &'static str {
        self.name()
    }
}

words!(SimModel);

impl Choice for Framing {
    const ALL: &'static [Self] = &[Framing::Rtu, Framing::Ascii, Framing::Tcp];
    fn word(self) -> &'static str {
        self.name()
    }
}

words!(Framing);

impl SimModel {
    /// A drive of shared/reference: it takes `params` and `trip`, which it checks itself.
    pub(crate) fn is_drive(self) -> bool {
        matches!(
            self,
            SimModel::Gd20 | SimModel::Gd300 | SimModel::Gd10 | SimModel::PdInverter
        )
    }

    /// As the configuration spells it.
    pub fn name(self) -> &'static str {
        match self {
            SimModel::Registers => "registers",
            SimModel::Gd20 => "gd20",
            SimModel::Gd300 => "gd300",
            SimModel::Gd10 => "gd10",
            SimModel::PdInverter => "pd-inverter",
            SimModel::Sdm120 => "sdm120",
        }
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
    pub(crate) reply_gap_after: Option<usize>,
}

/// For serde: `max_in_flight` at its default is left out.
#[allow(clippy::trivially_copy_pass_by_ref)] // serde's signature
fn is_one(value: &usize) -> bool {
    *value == 1
}

impl Bus {
    pub(crate) fn is_sim(&self) -> bool {
        self.device == SIM_DEVICE
    }

    /// What `device` names; an unreadable one is a serial path here (the check refuses it).
    pub fn device_name(&self) -> DeviceName {
        DeviceName::parse(&self.device).unwrap_or_else(|_| DeviceName::Serial(self.device.clone()))
    }

    /// The kind of transport `device` names.
    pub fn transport(&self) -> TransportKind {
        self.device_name().kind()
    }

    /// Character time and the spec's gaps at this bus's format; none on a Modbus TCP device,
    /// which has no wire of the gateway's.
    pub fn line_timing(&self) -> LineTiming {
        match self.framing {
            Framing::Tcp => LineTiming::NONE,
            Framing::Rtu | Framing::Ascii => LineTiming::new(&self.format()),
        }
    }

    /// The serial format as the metrics and the status page show it: `none` on a Modbus TCP
    /// device, which has no serial line of the gateway's.
    pub fn format_label(&self) -> String {
        match self.framing {
            Framing::Tcp => "none".to_owned(),
            Framing::Rtu | Framing::Ascii => self.format().to_string(),
        }
    }
}
