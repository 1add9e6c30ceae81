//! modbus-gateway: many Modbus TCP masters share RS-485 lines of Modbus RTU slaves.
//!
//! Modules in the order a request flows through them:
//! - [`config`]: the TOML file and `MBGW__` environment: loaded, checked, resolved; diffed on reload.
//! - [`tcp`]: listeners, MBAP framing, one session task per master.
//! - [`dispatch`]: the gateway's immediate answers, or the bus a request goes to.
//! - [`routing`]: unit id to (bus, slave address), a pure table.
//! - [`bus`]: one task per line, the only owner of its port: fair queue, reopen, retries,
//!   broadcast.
//! - [`line`]: the master side of a serial line: one transaction at a time on a port, its gap,
//!   deadlines and late replies, whatever the framing; the judgement of replies against requests.
//! - [`rtu`]: the RTU framing: CRC-16, frames as bytes, their lengths.
//! - [`sim`]: the simulated RS-485 line and its slaves (`device = "sim"`).
//! - [`metrics`]: what all of the above count, and the HTTP endpoint that serves it with the
//!   health checks.
//!
//! Shared by all: [`pdu`] (function and exception codes) and [`error`] (what fails a request, and
//! the one place that turns it into an exception), [`shutdown`] (the stop signal), [`timer`]
//! (sleeps precise to well under a millisecond for the line's timing). [`gateway`]
//! wires the parts together; [`cli`] is the command's subcommands (run the gateway, check the
//! configuration, `simulate`: serve the simulated slaves on a real serial port instead);
//! [`logging`] sets up the daemon's log output.

// Unit tests may be long and cast freely; the product code may not (Cargo.toml's lint table).
#![cfg_attr(test, allow(clippy::too_many_lines, clippy::cast_possible_truncation))]

pub mod bus;
pub mod cli;
pub mod config;
mod dispatch;
pub mod error;
pub mod gateway;
pub mod line;
mod logging;
pub mod metrics;
pub mod pdu;
mod routing;
pub mod shutdown;
pub mod sim;
mod tcp;
pub mod timer;

pub use config::Config;
pub use gateway::Gateway;

/// What the integration tests drive directly beyond the public modules: the TCP session, the
/// dispatcher and the routing table, which the gateway otherwise wires up itself. Not an API.
#[doc(hidden)]
pub mod testing {
    pub use crate::dispatch::{Client, Dispatcher, Rights};
    pub use crate::routing::Router;
    pub use crate::tcp::server::set_keepalive;
    pub use crate::tcp::session::{self, Activity, SessionError};
    pub use crate::tcp::SessionLimits;
}
