//! Between the TCP sessions and the buses: each request is refused at once by the gateway (bad
//! function code, a PDU longer or shorter than its function code says, a write from a read-only
//! master, no route, a read to the broadcast address, port down, queue full) or queued on the
//! bus its unit routes to. The length check comes first, for every protocol alike: bytes after
//! a request are never sent, since a slave framing by length would take them as a request. Either way the session gets a
//! receiver for its outcome.

use crate::bus::{BusHandle, Tally, Waiter};
use crate::config::UnitSet;
use crate::error::{Outcome, RequestError};
use crate::master::{Class, MasterId, Origin, Protocol, Rights};
use crate::metrics::{Metrics, Refusal};
use crate::pdu::{self, RequestLen};
use crate::routing::{Router, Target};
use std::net::SocketAddr;
use std::sync::{Arc, PoisonError, RwLock};
use tokio::sync::oneshot;
use tokio::time::Instant;

/// The master requests come from: one per connection.
#[derive(Debug)]
pub struct Client {
    pub master: MasterId,
    pub peer: SocketAddr,
    pub rights: Rights,
    /// The unit ids it may address (its TLS role's `units`); `None`: any.
    pub units: Option<UnitSet>,
    /// Served before the others (`server.priority`).
    pub priority: bool,
    /// How it talks to the gateway: Modbus TCP unless [`Client::speaking`] says otherwise.
    pub protocol: Protocol,
    /// Whose share of a full bus queue its requests count against and whose turn on the line
    /// they take: its own, or one its listener gives all the masters of one source address
    /// (Modbus UDP).
    pub admission: MasterId,
}

impl Client {
    pub fn new(master: MasterId, peer: SocketAddr, rights: Rights) -> Self {
        Client {
            master,
            peer,
            rights,
            units: None,
            priority: false,
            protocol: Protocol::Tcp,
            admission: master,
        }
    }

    /// The same master, speaking `protocol`.
    pub fn speaking(self, protocol: Protocol) -> Self {
        Client { protocol, ..self }
    }

    /// The same master, served before the others if `priority`.
    pub(crate) fn prioritised(self, priority: bool) -> Self {
        Client { priority, ..self }
    }

    /// The same master, allowed to address `units` only (`None`: any).
    pub(crate) fn addressing(self, units: Option<UnitSet>) -> Self {
        Client { units, ..self }
    }
}

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

    /// Route `pdu` from `client` to `unit`.
    pub fn submit(
        &self,
        client: &mut Client,
        unit: u8,
        pdu: Vec<u8>,
    ) -> oneshot::Receiver<Outcome> {
        let table = self.table();
        let target = table.router.resolve(unit);
        let origin = Origin {
            master: client.master,
            admission: client.admission,
            protocol: client.protocol,
            class: Class::of_master(client.priority),
        };
        let refusal = match admit(client, unit, &pdu, target) {
            Ok(target) => return table.buses[target.bus].submit_from(origin, target.address, pdu),
            Err(refusal) => refusal,
        };
        self.note_refusal(client, refusal);
        let function = pdu.first().copied().unwrap_or(0);
        // Counted against the bus and slave the unit routes to, if any; without a route, with
        // no bus and no slave (the unit id is the master's to choose).
        let (tally, slave) = match target {
            Some(target) => (table.buses[target.bus].tally(), target.address),
            None => (Tally::Unrouted(&self.metrics), unit),
        };
        let (waiter, receiver) = Waiter::new(origin, Instant::now());
        waiter.answer(tally, slave, function, Err(refusal));
        receiver
    }

    /// The connection's own account of a refusal, for the refusals its metrics and logs
    /// track.
    fn note_refusal(&self, client: &Client, refusal: RequestError) {
        let tcp = &self.metrics.tcp;
        let (master, peer) = (client.master, &client.peer);
        match refusal {
            RequestError::BadLength { function, len } => {
                tcp.bad_length(master, peer, function, len);
            }
            RequestError::Unverifiable(function) => {
                tcp.request_refused(master, peer, function, Refusal::Unverifiable);
            }
            RequestError::UnitNotPermitted(unit) => tcp.unit_refused(master, peer, unit),
            RequestError::NoAccess(function) => {
                tcp.request_refused(master, peer, function, Refusal::NoAccess);
            }
            RequestError::ReadOnly(function) => {
                tcp.request_refused(master, peer, function, Refusal::ReadOnly);
            }
            _ => {}
        }
    }

    /// `client` sent an RTU over TCP request whose CRC failed: counted, never answered.
    pub(crate) fn bad_frame(&self, client: &Client) {
        self.metrics.tcp.bad_crc(client.master, &client.peer);
    }

    /// A master has gone: drop whatever it still has queued.
    pub(crate) fn forget(&self, master: MasterId) {
        for bus in &self.table().buses {
            bus.forget(master);
        }
    }
}

/// Where `pdu` from `client` to `unit` (routed to `target`) goes, or why the gateway refuses it
/// unsent: the first reason in this order.
fn admit(
    client: &Client,
    unit: u8,
    pdu: &[u8],
    target: Option<Target>,
) -> Result<Target, RequestError> {
    let function = pdu.first().copied().unwrap_or(0);
    let length = pdu::request_len(pdu);
    let refusal = if !pdu::is_valid_request_function(function) {
        RequestError::InvalidFunction(function)
    } else if matches!(length, RequestLen::Wrong { .. }) {
        RequestError::BadLength {
            function,
            len: pdu.len(),
        }
    } else if client.units.is_some() && length == RequestLen::Unchecked {
        // Any bytes the gateway cannot measure could hold a frame to another unit.
        RequestError::Unverifiable(function)
    } else if client.units.is_some_and(|units| !units.contains(unit)) {
        RequestError::UnitNotPermitted(unit)
    } else if client.rights == Rights::NoAccess {
        RequestError::NoAccess(function)
    } else if client.rights == Rights::ReadOnly && !pdu::is_read_only(pdu) {
        RequestError::ReadOnly(function)
    } else {
        match target {
            None => RequestError::NoRoute(unit),
            Some(target) if target.broadcast && pdu::broadcast_response(pdu).is_none() => {
                RequestError::NotBroadcastable(function)
            }
            Some(target) => return Ok(target),
        }
    };
    Err(refusal)
}
