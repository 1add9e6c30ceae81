//! Between the TCP sessions and the buses: each request is refused at once by the gateway (bad
//! function code, no route, a read to the broadcast address, port down, queue full) or queued on
//! the bus its unit routes to. Either way the session gets a receiver for its outcome.

use crate::bus::{BusHandle, MasterId};
use crate::error::{Outcome, RequestError};
use crate::pdu;
use crate::routing::Router;
use crate::rtu::frame::BROADCAST;
use tokio::sync::oneshot;

pub struct Dispatcher {
    router: Router,
    buses: Vec<BusHandle>,
}

fn answered(outcome: Outcome) -> oneshot::Receiver<Outcome> {
    let (reply, receiver) = oneshot::channel();
    let _ = reply.send(outcome);
    receiver
}

impl Dispatcher {
    pub fn new(router: Router, buses: Vec<BusHandle>) -> Self {
        Dispatcher { router, buses }
    }

    pub fn buses(&self) -> &[BusHandle] {
        &self.buses
    }

    /// Route `pdu` from `unit`.
    pub fn submit(&self, master: MasterId, unit: u8, pdu: Vec<u8>) -> oneshot::Receiver<Outcome> {
        let function = pdu.first().copied().unwrap_or(0);
        if !pdu::is_valid_request_function(function) {
            return answered(Err(RequestError::InvalidFunction(function)));
        }
        let Some(target) = self.router.resolve(unit) else {
            return answered(Err(RequestError::NoRoute(unit)));
        };
        if target.address == BROADCAST && pdu::broadcast_response(&pdu).is_none() {
            return answered(Err(RequestError::NotBroadcastable(function)));
        }
        self.buses[target.bus].submit(master, target.address, pdu)
    }

    /// A master has gone: drop whatever it still has queued.
    pub fn forget(&self, master: MasterId) {
        for bus in &self.buses {
            bus.forget(master);
        }
    }
}
