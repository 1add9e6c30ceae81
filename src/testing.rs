//! What the tests, test-support and the bench use beyond the daemon's API (`cli`, `config`,
//! `gateway`): the crate's inner parts, each under the name of the module that holds it
//! (`testing::sim::SimLine` is `crate::sim::SimLine`). Compiled only with the `test-util` feature,
//! which the tests, test-support and the bench turn on and the shipped daemon does not: nothing
//! here is an interface an operator or another program may rely on.

/// The bus task and its handle: a line's queue and its one owner of the port.
pub mod bus {
    pub use crate::bus::{BusHandle, BusTask, Device, Port, SerialDriver};
}

/// What fails a request, and how it is answered.
pub mod error {
    pub use crate::error::{Answer, NoReply, Outcome, RequestError};
}

/// The master side of a serial line: framing, format, timing.
pub mod line {
    pub use crate::line::{rtu, Framing, LineTiming, Parity, SerialFormat};
}

/// Who a request comes from.
pub mod master {
    pub use crate::master::{Class, Origin, Protocol};
}

/// What the gateway counts.
pub mod metrics {
    pub use crate::metrics::Metrics;
}

/// The function-code table.
pub mod pdu {
    pub use crate::pdu::{function, PduLen};
}

/// The stop signal.
pub mod shutdown {
    pub use crate::shutdown::Stopping;
}

/// The simulated line and its slaves, and the fault knobs and scripts tests drive them with.
pub mod sim {
    pub use crate::sim::{
        faults, responder, Pause, RegisterBank, Scripted, SimLine, Simulated, Source, Transmission,
    };
}

/// The line's precise sleeps.
pub mod timer {
    pub use crate::timer::{sleep_until, use_precise_timer};
}

/// The live trace of the frames on the lines.
pub mod trace {
    pub use crate::trace::{Traced, MAX_READERS};
}

pub use crate::dispatch::client::Client;
pub use crate::dispatch::Dispatcher;
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
