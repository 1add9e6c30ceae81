//! modbus-gateway: many Modbus TCP masters share RS-485 lines of Modbus RTU slaves.
//!
//! Modules in the order a request flows through them:
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
//! - [`bus`]: one task per line, the only owner of its port: the fair queue (rings and shares,
//!   coalescing, the cache), reopen, one transaction at a time with retries and broadcast rules,
//!   reconfiguration between transactions, the one state machine that says whether a slave is
//!   alive, the [`Waiter`](bus::Waiter) through which every request is counted and answered
//!   exactly once, and the seam a line's transport plugs into (`bus::device`: a serial port or
//!   the simulated line today).
//! - [`line`](mod@line): the master side of a serial line: the transaction engine (gap, deadlines,
//!   validation, late replies, broadcast turnaround) on a transport, given the line's framing
//!   (RTU, [`line::rtu`], or ASCII), and which framing runs over which transport; the line's
//!   timing.
//! - [`sim`]: the simulated RS-485 line and its slaves (`device = "sim"`): register banks and the
//!   reference manuals' drives on one drive pipeline.
//! - `values`: the plant's values for Prometheus: each slave's listed values and its device
//!   template's, polled by the gateway itself through the bus's queue below every master, kept
//!   for `/metrics`, `/values` and the status page.
//! - [`metrics`]: what all of the above count and log, from plain values (it imports no runtime
//!   module).
//! - `web`: the operator's HTTP surface on `metrics.listen`: the status page and `/status`, the
//!   live trace (`/trace`), `/metrics` and the health checks; it reads the gateway through one
//!   narrow trait.
//!
//! Below every other module, shared by all: [`master`] (who a request comes from: the master's
//! id, its protocol as a transport and framing, its rights), [`pdu`] (the one table of function
//! codes, and exception codes) and [`error`] (what fails a request, and the one place that turns
//! it into an exception), [`shutdown`] (the stop signal, and how a stopped task's end is logged),
//! [`timer`] (sleeps precise to well under a millisecond for the line's timing), `socket` (TCP
//! keepalive and the kernel's round trip, for masters' and device servers' sockets), [`trace`] (the
//! live trace of the frames on the lines). [`gateway`] wires the parts together; [`cli`] is the
//! command's subcommands (run the gateway, check the configuration, `simulate`: serve the
//! simulated slaves on a real serial port instead); `logging` sets up the daemon's log output.
//! The modules form layers: `tests/layers.rs` fails on any cycle among them.
//!
//! `pub` is what the daemon's `main`, the bench and the tests use, nothing more (the workspace
//! lints deny unreachable `pub`). What the integration tests drive beyond it (the session, the
//! dispatcher, the routing table, the operator's endpoint on its own) is in `testing`, compiled
//! only with the `test-util` feature, which the tests turn on and the shipped daemon does not.

// Unit tests may be long and cast freely; the product code may not (Cargo.toml's lint table).
#![cfg_attr(test, allow(clippy::too_many_lines, clippy::cast_possible_truncation))]

mod audit;
pub mod bus;
pub mod cli;
pub mod config;
// What `testing` re-exports is `pub` for the tests' build (feature `test-util`) and unreachable
// in the daemon's: the lint is for the build that has the hooks (clippy --all-targets).
#[cfg_attr(not(feature = "test-util"), allow(unreachable_pub))]
mod dispatch;
pub mod error;
pub mod gateway;
pub mod line;
mod logging;
pub mod master;
pub mod metrics;
// What `testing` re-exports is `pub` for the tests' build (feature `test-util`) and unreachable
// in the daemon's: the lint is for the build that has the hooks (clippy --all-targets).
#[cfg_attr(not(feature = "test-util"), allow(unreachable_pub))]
mod net;
pub mod pdu;
mod pem;
// What `testing` re-exports is `pub` for the tests' build (feature `test-util`) and unreachable
// in the daemon's: the lint is for the build that has the hooks (clippy --all-targets).
#[cfg_attr(not(feature = "test-util"), allow(unreachable_pub))]
mod routing;
mod rules;
pub mod shutdown;
pub mod sim;
// What `testing` re-exports is `pub` for the tests' build (feature `test-util`) and unreachable
// in the daemon's: the lint is for the build that has the hooks (clippy --all-targets).
#[cfg_attr(not(feature = "test-util"), allow(unreachable_pub))]
mod socket;
pub mod timer;
pub mod trace;
mod values;
mod web;

pub use config::Config;
pub use gateway::Gateway;

/// What the integration tests drive directly beyond the public modules: the TCP session, the
/// dispatcher and the routing table, which the gateway otherwise wires up itself. Only with the
/// `test-util` feature, which the tests turn on and the shipped daemon does not.
#[cfg(feature = "test-util")]
pub mod testing {
    pub use crate::dispatch::{Client, Dispatcher};
    pub use crate::master::UpstreamFraming;
    pub use crate::master::{Protocol, Rights};
    pub use crate::net::server::RECENTLY_ANSWERED;
    pub use crate::net::session::SessionLimits;
    pub use crate::net::session::{self, Activity, SessionError};
    pub use crate::routing::Router;
    pub use crate::socket::set_keepalive;

    use crate::metrics::Metrics;
    use std::sync::Arc;

    /// The operator's HTTP endpoint on `listener`, for a gateway with no bus and no master.
    pub async fn serve_web(listener: tokio::net::TcpListener, metrics: Arc<Metrics>) {
        crate::web::serve(listener, metrics, Arc::new(Empty::default())).await;
    }

    #[derive(Default)]
    struct Empty(crate::values::Store);

    impl crate::web::Inspect for Empty {
        fn buses(&self) -> Vec<crate::bus::BusHandle> {
            Vec::new()
        }

        fn settings(&self, _: &str) -> Option<crate::config::Bus> {
            None
        }

        fn masters(&self) -> Vec<crate::net::server::Connected> {
            Vec::new()
        }

        fn values(&self) -> &crate::values::Store {
            &self.0
        }

        fn writes(&self) -> Vec<crate::audit::Recent> {
            Vec::new()
        }
    }
}
