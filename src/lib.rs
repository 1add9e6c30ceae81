//! modbus-gateway: many Modbus masters (TCP, TLS, UDP, RTU over TCP) share lines of Modbus
//! slaves: RS-485 on a UART or behind a serial device server, or a Modbus TCP/TLS device.
//!
//! Modules in the order a request flows through them (docs/architecture.md walks through them):
//! - [`config`]: the TOML file and `MBGW__` environment: loaded, checked per section, resolved
//!   (derived values); diffed on reload. Imports no runtime module.
//! - `net`: the listeners, each a transport (TCP, TLS with Modbus/TCP Security's certificate
//!   roles, UDP) and a framing (MBAP, RTU): binding and admission shared by all, one session
//!   task per connection, Modbus UDP's datagrams.
//! - `dispatch`: the gateway's immediate answers, or the bus a request goes to.
//! - `routing`: unit id to (bus, slave address), a pure table.
//! - `rules`: which `[[rule]]` decides a request (allow, deny, acknowledge), a pure table.
//! - `audit`: every write-class request as it was decided and as it ended: the journal
//!   (`[audit]`), written before a write goes to its bus, the last writes, the writes' metrics.
//! - `bus`: one task per line, the only owner of its port: the fair queue (rings and shares,
//!   coalescing, the cache), reopen, the one pre-send step (`bus::ready`) before either serving
//!   loop (one transaction at a time, or pipelined to a Modbus TCP device) with retries and
//!   broadcast rules, reconfiguration between transactions, the one state machine that says
//!   whether a slave is alive, the `Waiter` through which every request is counted and answered
//!   exactly once, and the seam a line's transport plugs into (`bus::device`: a serial port, a
//!   device server over TCP or RFC 2217, a Modbus TCP/TLS device, the simulated line).
//! - `line`: the master side of a line: the transaction engine (gap, deadlines, validation,
//!   late replies, broadcast turnaround) on a transport, given the line's framing (RTU,
//!   `line::rtu`, ASCII, or MBAP toward a Modbus TCP device), and which framing runs over which
//!   transport; the line's timing.
//! - `sim`: the simulated RS-485 line and its slaves (`device = "sim"`): register banks and the
//!   reference manuals' drives on one drive pipeline.
//! - `values`: the plant's values for Prometheus: each slave's listed values and its device
//!   template's, polled by the gateway itself through the bus's queue below every master, kept
//!   for `/metrics`, `/values` and the status page.
//! - `metrics`: what all of the above count and log, from plain values (it imports no runtime
//!   module).
//! - `web`: the operator's HTTP surface on `metrics.listen`: the status page and `/status`, the
//!   live trace (`/trace`), `/metrics` and the health checks; it reads the gateway through one
//!   narrow trait.
//!
//! Below every other module, shared by all: `master` (who a request comes from: the master's id,
//! its protocol as a transport and framing, its rights), `pdu` (the one table of function codes,
//! and exception codes), `mbap` (Modbus TCP's frame header, for the listeners and the lines to
//! Modbus TCP devices alike) and `error` (what fails a request, and the one place that turns it
//! into an exception), `shutdown` (the stop signal, and how a stopped task's end is logged),
//! `timer` (sleeps precise to well under a millisecond for the line's timing), `socket` (TCP
//! keepalive and the kernel's round trip, for masters' and device servers' sockets), `trace` (the
//! live trace of the frames on the lines). [`gateway`] wires the parts together; [`cli`] is the
//! command's subcommands (run the gateway, check the configuration, `simulate`: serve the simulated
//! slaves on a real serial port instead); `logging` sets up the daemon's log output. The modules
//! form layers: `tests/layers.rs` fails on any cycle among them.
//!
//! `pub` is the daemon's API and nothing more: [`cli`] (what `main` runs), [`config`] and
//! [`gateway`] (a configuration, and the gateway started on it); the workspace lints deny any
//! other `pub` the API cannot reach. What the tests, test-support and the bench drive beyond it
//! (the simulated line, a bus task on its own, the session, the dispatcher, the line's framing)
//! is re-exported in `testing`, under each part's module name, compiled only with the
//! `test-util` feature, which they turn on and the shipped daemon does not.

// Unit tests may be long and cast freely; the product code may not (Cargo.toml's lint table).
#![cfg_attr(test, allow(clippy::too_many_lines, clippy::cast_possible_truncation))]
// What `testing` re-exports is `pub` for the build that has it (feature `test-util`: the tests,
// test-support and the bench; `clippy --workspace --all-targets` checks that build) and
// unreachable in the daemon's, which has no `testing`: the lint is for the build with the hooks.
#![cfg_attr(not(feature = "test-util"), allow(unreachable_pub))]

mod audit;
mod bus;
pub mod cli;
pub mod config;
mod dispatch;
mod error;
pub mod gateway;
mod line;
mod logging;
mod master;
mod mbap;
mod metrics;
mod mqtt;
mod net;
mod pdu;
mod pem;
mod port;
mod routing;
mod rules;
mod shutdown;
mod sim;
mod socket;
#[cfg(feature = "test-util")]
pub mod testing;
mod timer;
mod trace;
mod values;
mod virtuals;
mod web;

pub use config::Config;
pub use gateway::Gateway;
