//! What the integration tests and the bench of modbus-gateway share, one of each:
//! - `config`: a gateway configuration from typed calls, written as TOML; `configs`: the ones many
//!   tests start from.
//! - `gateway`: a gateway started in the test's process; `sim`: a bus on the simulated line
//!   started by hand, with no gateway around it.
//! - `frames`: a Modbus TCP ADU (MBAP) and an RTU frame; `master`: a raw Modbus TCP master.
//! - `device`: a fake Modbus TCP device that answers pipelined reads after a delay; `cases`: the
//!   transactions with tests/peers/pymodbus_slave.py's slave that several tests make.
//! - `pty`: an RTU slave on a pty pair (the real serial path).
//! - `ser2net`: ser2net as a serial device server in front of a pty (a `tcp://` or `rfc2217://`
//!   bus's far side).
//! - `mosquitto`: mosquitto as an MQTT broker (anonymous, with a password file, on TLS), and
//!   mosquitto_sub / mosquitto_pub as the subscriber and the publisher on its far side.
//! - `tap`: a shared RS-485 line of ptys: a master and a slave relayed both ways, every byte
//!   copied to the gateway's port, and whatever the gateway writes logged.
//! - `tls`: a test PKI (CA, server and master certificates with the Modbus/TCP Security RoleOID)
//!   and TLS masters.
//! - `http`: the metrics endpoint: GETs, `/metrics` parsed, `/trace` readers.
//! - `process`: the gateway as a process: tools, free ports, logs, signals.
//! - `load`: many masters: rotation and fairness, floods.
//! - `wait`: every wait bounded; panics counted.
//!
//! Everything but `tls`, `device`, `cases` and `mosquitto` (whose `Broker` would meet the
//! library's `config::Broker`) is also at the crate's root. It uses the library's
//! `testing`-grade items (`bus::BusTask`, `gateway::power_on_line`, `sim::*`...), so it is a
//! dev-dependency: unit tests inside `src/` may use only what names none of the
//! library's types (`device`), or they would see two copies of them.

pub mod cases;
pub mod config;
pub mod configs;
pub mod device;
pub mod frames;
pub mod gateway;
pub mod http;
pub mod load;
pub mod master;
pub mod mosquitto;
pub mod process;
pub mod pty;
pub mod ser2net;
pub mod sim;
pub mod tap;
pub mod tls;
pub mod wait;

pub use config::{Bus, GatewayConfig, Value};
pub use configs::*;
pub use frames::{mbap, rtu};
pub use gateway::*;
pub use http::*;
pub use load::*;
pub use master::*;
pub use process::*;
pub use pty::*;
pub use ser2net::{Accepter, Ser2net};
pub use sim::*;
pub use wait::*;
