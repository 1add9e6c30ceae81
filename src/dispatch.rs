//! Between the TCP sessions and the buses: each request is refused at once by the gateway (bad
//! function code, no route, a read to the broadcast address, port down, queue full) or queued on
//! the bus its unit routes to. Either way the session gets a receiver for its outcome.

use crate::bus::{BusHandle, MasterId};
use crate::error::{Outcome, RequestError};
use crate::metrics::Metrics;
use crate::pdu;
use crate::routing::Router;
use crate::rtu::frame::BROADCAST;
use std::sync::{Arc, PoisonError, RwLock};
use tokio::sync::oneshot;

/// The routes and the buses they index, replaced whole on a reload.
struct Table {
    router: Router,
    buses: Vec<BusHandle>,
}

pub struct Dispatcher {
    table: RwLock<Arc<Table>>,
    metrics: Arc<Metrics>,
}

impl Dispatcher {
    pub fn new(router: Router, buses: Vec<BusHandle>, metrics: Arc<Metrics>) -> Self {
        Dispatcher {
            table: RwLock::new(Arc::new(Table { router, buses })),
            metrics,
        }
    }

    fn table(&self) -> Arc<Table> {
        self.table
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Route by `router` to `buses` from the next request on; requests already queued stay where
    /// they are.
    pub fn replace(&self, router: Router, buses: Vec<BusHandle>) {
        *self.table.write().unwrap_or_else(PoisonError::into_inner) =
            Arc::new(Table { router, buses });
    }

    pub fn buses(&self) -> Vec<BusHandle> {
        self.table().buses.clone()
    }

    /// Route `pdu` from `unit`.
    pub fn submit(&self, master: MasterId, unit: u8, pdu: Vec<u8>) -> oneshot::Receiver<Outcome> {
        let function = pdu.first().copied().unwrap_or(0);
        let table = self.table();
        let target = table.router.resolve(unit);
        let refusal = match target {
            _ if !pdu::is_valid_request_function(function) => {
                RequestError::InvalidFunction(function)
            }
            None => RequestError::NoRoute(unit),
            Some(target)
                if target.address == BROADCAST && pdu::broadcast_response(&pdu).is_none() =>
            {
                RequestError::NotBroadcastable(function)
            }
            Some(target) => return table.buses[target.bus].submit(master, target.address, pdu),
        };
        // Counted against the bus and slave the unit routes to, if any, else the unit id.
        let (bus, slave) = match target {
            Some(target) => (table.buses[target.bus].name(), target.address),
            None => ("", unit),
        };
        let outcome = Err(refusal);
        self.metrics.request(bus, slave, function, &outcome);
        let (reply, receiver) = oneshot::channel();
        let _ = reply.send(outcome);
        receiver
    }

    /// A master has gone: drop whatever it still has queued.
    pub fn forget(&self, master: MasterId) {
        for bus in &self.table().buses {
            bus.forget(master);
        }
    }
}
