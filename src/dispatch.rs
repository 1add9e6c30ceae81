//! Between the TCP sessions and the buses: each request is refused at once by the gateway (bad
//! function code, a PDU longer or shorter than its function code says, a write from a read-only
//! master, no route, a read to the broadcast address, port down, queue full) or queued on the
//! bus its unit routes to. The length check comes first, for every protocol alike: bytes after
//! a request are never sent, since a slave framing by length would take them as a request. Either way the session gets a
//! receiver for its outcome.

use crate::audit::{self, Audit, Pending};
use crate::bus::{BusHandle, Tally, Waiter};
use crate::config::{Action, UnitSet};
use crate::error::{Answer, Outcome, RequestError};
use crate::master::{Class, MasterId, Origin, Protocol, Rights};
use crate::metrics::{Metrics, Refusal};
use crate::pdu::{self, RequestLen};
use crate::routing::{Router, Target};
use crate::rules::{self, Rules};
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
    /// Who a TLS master's certificate says it is.
    pub identity: Option<Arc<Identity>>,
    /// The setting that limits its rights, as the journal names it (`server.read_only`,
    /// `server.tls.roles.NAME`); `None` while it may read and write.
    pub limited_by: Option<Arc<str>>,
}

/// A TLS master's certificate: its subject and the role it carries, as written.
#[derive(Debug)]
pub struct Identity {
    pub subject: String,
    pub role: Option<String>,
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
            identity: None,
            limited_by: (rights < Rights::ReadWrite).then(|| Arc::from("server.read_only")),
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

    /// The same master, with its certificate's `identity`, its rights narrowed to `role_rights`
    /// by the role `role_key` names (`server.tls.roles.NAME` or
    /// `server.tls.default_role_access`).
    pub(crate) fn identified(
        self,
        identity: Identity,
        role_rights: Rights,
        role_key: String,
        role_units: bool,
    ) -> Self {
        let limited_by = match self.limited_by {
            Some(by) if self.rights <= role_rights => Some(by),
            _ if role_rights < Rights::ReadWrite || role_units => Some(Arc::from(role_key)),
            by => by,
        };
        Client {
            rights: self.rights.min(role_rights),
            identity: Some(Arc::new(identity)),
            limited_by,
            ..self
        }
    }

    fn role(&self) -> Option<&str> {
        self.identity.as_ref().and_then(|i| i.role.as_deref())
    }
}

/// The routes, the buses they index and the rules, replaced whole on a reload.
struct Table {
    router: Router,
    buses: Vec<BusHandle>,
    rules: Rules,
}

pub struct Dispatcher {
    table: RwLock<Arc<Table>>,
    metrics: Arc<Metrics>,
    audit: Arc<Audit>,
}

impl Dispatcher {
    /// With no rules and no journal: for the tests that drive the dispatcher on its own.
    #[cfg(any(test, feature = "test-util"))]
    pub fn new(router: Router, buses: Vec<BusHandle>, metrics: Arc<Metrics>) -> Self {
        let audit = Audit::new(metrics.clone());
        Self::with_rules(router, buses, Rules::default(), audit, metrics)
    }

    pub(crate) fn with_rules(
        router: Router,
        buses: Vec<BusHandle>,
        rules: Rules,
        audit: Arc<Audit>,
        metrics: Arc<Metrics>,
    ) -> Self {
        Dispatcher {
            table: RwLock::new(Arc::new(Table {
                router,
                buses,
                rules,
            })),
            metrics,
            audit,
        }
    }

    /// The writes' record.
    pub(crate) fn audit(&self) -> &Arc<Audit> {
        &self.audit
    }

    fn table(&self) -> Arc<Table> {
        self.table
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Route by `router` to `buses` under `rules` from the next request on; requests already
    /// queued stay where they are.
    pub(crate) fn replace(&self, router: Router, buses: Vec<BusHandle>, rules: Rules) {
        *self.table.write().unwrap_or_else(PoisonError::into_inner) = Arc::new(Table {
            router,
            buses,
            rules,
        });
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
        let function = pdu.first().copied().unwrap_or(0);
        // Everything that may change a slave is journaled, whatever becomes of it.
        let journaled = pdu::is_valid_request_function(function) && !pdu::is_read_only(&pdu);
        match admit(client, unit, &pdu, target) {
            Ok(target) => self.ruled(client, &table, target, unit, pdu, journaled),
            Err(refusal) => {
                // Refused before any rule: journaled with the setting that refused it.
                let access = matches!(
                    refusal,
                    RequestError::ReadOnly(_)
                        | RequestError::NoAccess(_)
                        | RequestError::UnitNotPermitted(_)
                        | RequestError::Unverifiable(_)
                );
                let (rule, action) = match &client.limited_by {
                    Some(by) if access => (Some(&**by), Action::Deny),
                    _ => (None, Action::Allow),
                };
                let pending = journaled
                    .then(|| {
                        let asked = self.asked(client, &table, unit, target, &pdu);
                        let asked = audit::Asked {
                            rule,
                            action,
                            ..asked
                        };
                        let begun = self.audit.begin(&asked);
                        if begun.is_err() {
                            self.audit.unjournaled(&asked, refusal);
                        }
                        begun.ok()
                    })
                    .flatten();
                self.refuse(client, &table, target, unit, function, refusal, pending)
            }
        }
    }

    /// A request the master may make, as the first matching `[[rule]]` decides: sent, refused
    /// or acknowledged; a write journaled first (refused 0x0A if it cannot be, with
    /// `on_error = "deny_writes"`).
    fn ruled(
        &self,
        client: &Client,
        table: &Table,
        target: Target,
        unit: u8,
        pdu: Vec<u8>,
        journaled: bool,
    ) -> oneshot::Receiver<Outcome> {
        let function = pdu.first().copied().unwrap_or(0);
        let bus = &table.buses[target.bus];
        let decision = table.rules.decide(&rules::Asked {
            peer: client.peer.ip(),
            role: client.role(),
            protocol: client.protocol,
            bus: Some(bus.name()),
            target: Some(target),
            pdu: &pdu,
        });
        let rule = decision.rule.map(|at| table.rules.name(at));
        let mut pending = None;
        if journaled {
            let asked = audit::Asked {
                rule,
                action: decision.action,
                ..self.asked(client, table, unit, Some(target), &pdu)
            };
            match self.audit.begin(&asked) {
                Ok(entry) => pending = Some(entry),
                Err(audit::Refused) => {
                    let refusal = RequestError::Unrecorded(function);
                    self.audit.unjournaled(&asked, refusal);
                    let target = Some(target);
                    return self.refuse(client, table, target, unit, function, refusal, None);
                }
            }
        }
        let rule = rule.unwrap_or("a rule");
        let refusal = match (decision.action, pending) {
            (Action::Allow, pending) => return self.send(client, bus, target, pdu, pending),
            // A read under an `acknowledge` rule goes on: only writes are kept back.
            (Action::Acknowledge, None) => return self.send(client, bus, target, pdu, None),
            (Action::Acknowledge, Some(pending)) => match acknowledgement(&pdu, target, bus) {
                Some(answer) => {
                    pending.acknowledged();
                    let (waiter, receiver) = Waiter::new(origin_of(client), Instant::now());
                    waiter.answer(bus.tally(), target.address, function, Ok(answer));
                    return receiver;
                }
                None => {
                    let refusal = RequestError::Denied {
                        function,
                        registers: false,
                    };
                    let detail = format!(
                        "{rule}: acknowledge; its normal reply is the slave's to make, so \
                             it cannot be acknowledged unsent"
                    );
                    pending.denied(refusal.exception_code() as u8, detail);
                    refusal
                }
            },
            (Action::Deny, pending) => {
                let registers =
                    decision.exception(&table.rules) == pdu::ExceptionCode::IllegalDataAddress;
                let refusal = RequestError::Denied {
                    function,
                    registers,
                };
                if let Some(pending) = pending {
                    pending.denied(refusal.exception_code() as u8, format!("{rule}: deny"));
                }
                refusal
            }
        };
        self.refuse(client, table, Some(target), unit, function, refusal, None)
    }

    /// `pdu` on its way to `target` on `bus`, with its journal entry if it has one.
    fn send(
        &self,
        client: &Client,
        bus: &BusHandle,
        target: Target,
        pdu: Vec<u8>,
        pending: Option<Pending>,
    ) -> oneshot::Receiver<Outcome> {
        bus.submit_journaled(origin_of(client), target.address, pdu, pending)
    }

    /// What the journal needs of a request from `client`, before the rules decide.
    fn asked<'a>(
        &self,
        client: &'a Client,
        table: &'a Table,
        unit: u8,
        target: Option<Target>,
        pdu: &'a [u8],
    ) -> audit::Asked<'a> {
        let bus = target.map(|t| table.buses[t.bus].name());
        audit::Asked {
            master: client.peer,
            protocol: client.protocol,
            subject: client.identity.as_ref().map(|i| i.subject.as_str()),
            role: client.role(),
            unit,
            bus,
            slave: target.map(|t| t.address),
            broadcast: target.is_some_and(|t| t.broadcast),
            pdu,
            rule: None,
            action: Action::Allow,
        }
    }

    /// Answer `refusal` to `client` at once, unsent; a journaled write's outcome with it.
    #[allow(clippy::too_many_arguments)]
    fn refuse(
        &self,
        client: &Client,
        table: &Table,
        target: Option<Target>,
        unit: u8,
        function: u8,
        refusal: RequestError,
        pending: Option<Pending>,
    ) -> oneshot::Receiver<Outcome> {
        self.note_refusal(client, refusal);
        let origin = origin_of(client);
        // Counted against the bus and slave the unit routes to, if any; without a route, with
        // no bus and no slave (the unit id is the master's to choose).
        let (tally, slave) = match target {
            Some(target) => (table.buses[target.bus].tally(), target.address),
            None => (Tally::Unrouted(&self.metrics), unit),
        };
        let (waiter, receiver) = Waiter::new(origin, Instant::now());
        let waiter = waiter.journaled(pending);
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

/// Who a request from `client` comes from, as the bus queues it.
fn origin_of(client: &Client) -> Origin {
    Origin {
        master: client.master,
        admission: client.admission,
        protocol: client.protocol,
        class: Class::of_master(client.priority),
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

/// The reply an `acknowledge` rule gives a write in place of the slave: the normal reply the
/// slave would give (the one the gateway makes for a broadcast), or for a broadcast unit what a
/// broadcast gets. `None` for a write whose normal reply only the slave can make (it carries
/// data read, or is the vendor's).
fn acknowledgement(pdu: &[u8], target: Target, bus: &BusHandle) -> Option<Answer> {
    let reply = pdu::broadcast_response(pdu)?;
    if target.broadcast && !bus.broadcast_reply() {
        return Some(Answer::Nothing);
    }
    Some(Answer::Acknowledged(reply))
}
