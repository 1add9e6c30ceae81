//! modbus-gateway: many Modbus TCP masters share RS-485 lines of Modbus RTU slaves.
//!
//! Modules in the order a request flows through them:
//! - [`config`]: the TOML file and `MBGW__` environment, validated into settings.
//! - [`tcp`]: listeners, MBAP framing, one session task per master.
//! - [`dispatch`]: a request's route, or the gateway's immediate answer.
//! - [`routing`]: unit id to (bus, slave address), a pure table.
//! - [`bus`]: one task per line owning its port: fair queue, reopen, retries, broadcast.
//! - [`rtu`]: the RTU master: CRC, frames, t3.5 timing, one transaction on a port.
//! - [`sim`]: the simulated RS-485 line and its slaves (`device = "sim"`).
//!
//! Shared by all: [`pdu`] (function and exception codes) and [`error`] (what fails a request, and
//! the one place it becomes an exception). [`gateway`] wires them together.

pub mod config;
pub mod pdu;
pub mod rtu;
pub mod sim;
