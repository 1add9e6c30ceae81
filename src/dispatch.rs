//! Between the sessions and the buses. Each request is described once, as it enters
//! ([`Inbound`]), and then refused at once by the gateway (bad function code, a PDU longer or
//! shorter than its function code says, a write from a read-only master, no route, a read to the
//! broadcast address) or decided by the first matching `[[rule]]`: sent, refused or acknowledged
//! (its [`Ruling`]).
//! A write's journal entry begins at one place, before any of that is carried out. The length
//! check comes first, for every protocol alike: bytes after a request are never sent, since a
//! slave framing by length would take them as a request. Either way the session gets a receiver
//! for its outcome.

use crate::audit::{self, Audit, Decided, Pending};
use crate::bus::{BusHandle, Tally, Waiter};
use crate::config::{Action, Config};
use crate::error::{Answer, Outcome, RequestError};
use crate::master::{Class, MasterId, Origin, Rights};
use crate::metrics::{Metrics, Refusal};
use crate::pdu::{self, RequestLen, EXCEPTION_BIT};
use crate::routing::{Inbound, Router, Target};
use crate::rules::{self, Rules};
use crate::values::Store;
use crate::virtuals::{Declined, SourceWrite, Units, Virtual};
pub(crate) mod client;

pub(crate) use client::{Client, Identity};
use std::sync::{Arc, PoisonError, RwLock};
use tokio::sync::oneshot;
use tokio::time::Instant;

/// The routes, the buses they index, the rules and the virtual units, replaced whole on a
/// reload.
struct Table {
    router: Router,
    buses: Vec<BusHandle>,
    rules: Rules,
    virtuals: Arc<Units>,
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
        let virtuals = Arc::new(Units::none(Arc::default()));
        Self::with_rules(router, buses, (Rules::default(), virtuals), audit, metrics)
    }

    /// What decides `config`'s requests beside `router`: its rules, and its virtual units, their
    /// values found in `store`.
    pub(crate) fn decided(
        config: &Config,
        router: &Router,
        store: &Arc<Store>,
        metrics: &Metrics,
    ) -> (Rules, Arc<Units>) {
        let rules = Rules::new(&config.rule, router);
        (rules, Units::serving(config, store, metrics))
    }

    /// Routing by `router` to `buses`, under `rules`, answering `virtuals` itself.
    pub(crate) fn with_rules(
        router: Router,
        buses: Vec<BusHandle>,
        (rules, virtuals): (Rules, Arc<Units>),
        audit: Arc<Audit>,
        metrics: Arc<Metrics>,
    ) -> Self {
        Dispatcher {
            table: RwLock::new(Arc::new(Table {
                router,
                buses,
                rules,
                virtuals,
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

    /// Route by `router` to `buses` under `rules`, answering `virtuals`, from the next request
    /// on; requests already queued stay where they are.
    pub(crate) fn replace(
        &self,
        router: Router,
        buses: Vec<BusHandle>,
        (rules, virtuals): (Rules, Arc<Units>),
    ) {
        *self.table.write().unwrap_or_else(PoisonError::into_inner) = Arc::new(Table {
            router,
            buses,
            rules,
            virtuals,
        });
    }

    /// The virtual units answered now.
    pub(crate) fn virtual_units(&self) -> Arc<Units> {
        self.table().virtuals.clone()
    }

    pub fn buses(&self) -> Vec<BusHandle> {
        self.table().buses.clone()
    }

    /// Route `pdu` from `client` to `unit`: refused unsent, or decided by the first matching
    /// `[[rule]]` (sent, refused or acknowledged); a write journaled first, whatever becomes of
    /// it (refused 0x0A if it cannot be, with `on_error = "deny_writes"`).
    pub fn submit(
        &self,
        client: &mut Client,
        unit: u8,
        pdu: Vec<u8>,
    ) -> oneshot::Receiver<Outcome> {
        let table = self.table();
        let emulated = table.virtuals.get(unit);
        let target = table.router.resolve(unit);
        let inbound = client.asking(&table, unit, target, emulated.map(|v| &*v.name), &pdu);
        let to = match (emulated, target) {
            (Some(unit), _) => Some(To::Virtual(unit)),
            (None, target) => target.map(To::Bus),
        };
        self.dispatch(client, &table, &inbound, to).1
    }

    /// `pdu` from `client`, a master that names slaves rather than unit ids (MQTT), to slave
    /// `address` of bus `bus`: decided as [`Dispatcher::submit`] decides any request, with the
    /// name of the rule that decides it. `None`: no such bus.
    pub(crate) fn submit_to_slave(
        &self,
        client: &Client,
        (bus, address): (&str, u8),
        pdu: &[u8],
    ) -> Option<(Option<String>, oneshot::Receiver<Outcome>)> {
        let table = self.table();
        let index = table.buses.iter().position(|b| b.name() == bus)?;
        let target = Target {
            bus: index,
            address,
            broadcast: false,
        };
        let inbound = client.asking(&table, address, Some(target), None, pdu);
        let (by, outcome) = self.dispatch(client, &table, &inbound, Some(To::Bus(target)));
        Some((by.map(str::to_owned), outcome))
    }

    /// `inbound` from `client`, going `to` a slave or a virtual unit (`None`: no route):
    /// refused unsent, or decided by the first matching rule; a write journaled first. With
    /// the name of what decided it (a rule, or the setting that limits the master), if anything.
    fn dispatch<'a>(
        &self,
        client: &'a Client,
        table: &'a Table,
        inbound: &Inbound<'_>,
        to: Option<To<'_>>,
    ) -> (Option<&'a str>, oneshot::Receiver<Outcome>) {
        let (by, admitted) = match admit(client, inbound.unit, inbound.pdu, to) {
            Ok(to) => {
                let decision = table.rules.decide(inbound);
                let by = Decided {
                    rule: decision.rule.map(|at| table.rules.name(at)),
                    action: decision.action,
                };
                (by, Ok((to, decision)))
            }
            // Refused before any rule: journaled with the setting that refused it.
            Err(refusal) => (refused_by(client, refusal), Err(refusal)),
        };
        (
            by.rule,
            self.carry_out(client, table, inbound, by, admitted),
        )
    }

    /// `inbound` as `by` decided it (`admitted` where it goes and the rules' decision, or the
    /// refusal before any rule): journaled, then sent, acknowledged or refused.
    fn carry_out(
        &self,
        client: &Client,
        table: &Table,
        inbound: &Inbound<'_>,
        by: Decided<'_>,
        admitted: Result<(To<'_>, rules::Decision), RequestError>,
    ) -> oneshot::Receiver<Outcome> {
        let pdu = inbound.pdu;
        let function = pdu.first().copied().unwrap_or(0);
        // Everything that may change a slave is journaled: its entry begins here, and only here.
        let journaled = pdu::is_valid_request_function(function) && !pdu::is_read_only(pdu);
        let pending = match journaled.then(|| self.audit.begin(inbound, by)) {
            None => None,
            Some(Ok(pending)) => Some(pending),
            Some(Err(audit::Refused)) => {
                let refusal = admitted.err().unwrap_or(RequestError::Unrecorded(function));
                self.audit.unjournaled(inbound, by, refusal);
                return self.refuse(client, table, inbound, refusal, None);
            }
        };
        let (to, decision) = match admitted {
            Ok(admitted) => admitted,
            Err(refusal) => return self.refuse(client, table, inbound, refusal, pending),
        };
        let rule = by.rule.unwrap_or("a rule");
        let target = match to {
            To::Bus(target) => target,
            To::Virtual(unit) => {
                return match ruling(&table.rules, decision, rule, pdu, None, pending) {
                    Ruling::Send(pending) => self.emulate(client, table, inbound, unit, pending),
                    Ruling::Acknowledge(answer) => {
                        self.answer_virtual(client, unit, inbound, Ok(answer))
                    }
                    Ruling::Refuse(refusal) => self.refuse(client, table, inbound, refusal, None),
                };
            }
        };
        let bus = &table.buses[target.bus];
        match ruling(
            &table.rules,
            decision,
            rule,
            pdu,
            Some((target, bus)),
            pending,
        ) {
            Ruling::Send(pending) => {
                bus.submit_journaled(origin_of(client), target.address, pdu.to_vec(), pending)
            }
            Ruling::Acknowledge(answer) => {
                let (waiter, receiver) = Waiter::new(origin_of(client), Instant::now());
                waiter.answer(bus.tally(), target.address, function, Ok(answer));
                receiver
            }
            Ruling::Refuse(refusal) => self.refuse(client, table, inbound, refusal, None),
        }
    }

    /// `inbound` to virtual `unit`, allowed: a read answered from memory at once; a write (its
    /// journal entry `pending`) sent on as one write to each source slave it covers, each
    /// decided and journaled as any write to that slave, and answered when they are all done.
    fn emulate(
        &self,
        client: &Client,
        table: &Table,
        inbound: &Inbound<'_>,
        unit: &Virtual,
        pending: Option<Pending>,
    ) -> oneshot::Receiver<Outcome> {
        let pdu = inbound.pdu;
        let function = pdu.first().copied().unwrap_or(0);
        let exception = |Declined(code)| Err(RequestError::Emulated(code));
        let Some(pending) = pending else {
            let outcome = table
                .virtuals
                .read(unit, pdu, Instant::now())
                .map_or_else(exception, |reply| Ok(Answer::Reply(reply)));
            return self.answer_virtual(client, unit, inbound, outcome);
        };
        let (writes, normal) = match table.virtuals.write(unit, pdu) {
            Ok(translated) => translated,
            Err(refused) => {
                let (waiter, receiver) = Waiter::new(origin_of(client), Instant::now());
                let tally = Tally::Virtual(&self.metrics.virtual_units, &unit.name);
                let waiter = waiter.journaled(Some(pending));
                let outcome = exception(refused);
                unit.trace(pdu, &outcome);
                waiter.answer(tally, unit.id, function, outcome);
                return receiver;
            }
        };
        // Every write it becomes is decided before any is sent: none goes if a rule denies one.
        if let Some((refusal, detail)) = first_denial(
            &table.rules,
            writes.iter().map(|w| through(table, inbound, w)),
        ) {
            pending.denied(refusal.exception_code() as u8, detail);
            return self.refuse(client, table, inbound, refusal, None);
        }
        let (waiter, receiver) = Waiter::new(origin_of(client), Instant::now());
        let waiter = waiter.journaled(Some(pending));
        let sent: Vec<oneshot::Receiver<Outcome>> = writes
            .iter()
            .map(|write| {
                let to = Some(To::Bus(write.target));
                self.dispatch(client, table, &through(table, inbound, write), to)
                    .1
            })
            .collect();
        let (metrics, units) = (self.metrics.clone(), table.virtuals.clone());
        let (id, name, request) = (unit.id, unit.name.clone(), pdu.to_vec());
        tokio::spawn(async move {
            let outcome = written(function, normal, sent).await;
            if let Some(unit) = units.get(id) {
                unit.trace(&request, &outcome);
            }
            let tally = Tally::Virtual(&metrics.virtual_units, &name);
            waiter.answer(tally, id, function, outcome);
        });
        receiver
    }

    /// `inbound` to virtual `unit` ends in `outcome` now.
    fn answer_virtual(
        &self,
        client: &Client,
        unit: &Virtual,
        inbound: &Inbound<'_>,
        outcome: Outcome,
    ) -> oneshot::Receiver<Outcome> {
        let (waiter, receiver) = Waiter::new(origin_of(client), Instant::now());
        let function = inbound.pdu.first().copied().unwrap_or(0);
        unit.trace(inbound.pdu, &outcome);
        let tally = Tally::Virtual(&self.metrics.virtual_units, &unit.name);
        waiter.answer(tally, unit.id, function, outcome);
        receiver
    }

    /// Answer `refusal` to `client`'s request `inbound` at once, unsent; a journaled write's
    /// outcome with it.
    fn refuse(
        &self,
        client: &Client,
        table: &Table,
        inbound: &Inbound<'_>,
        refusal: RequestError,
        pending: Option<Pending>,
    ) -> oneshot::Receiver<Outcome> {
        self.note_refusal(client, refusal);
        let origin = origin_of(client);
        // Counted against the bus and slave the unit routes to, if any; without a route, with
        // no bus and no slave (the unit id is the master's to choose).
        let (tally, slave) = match (inbound.target, inbound.virtual_unit) {
            (Some(target), _) => (table.buses[target.bus].tally(), target.address),
            (None, Some(name)) => (
                Tally::Virtual(&self.metrics.virtual_units, name),
                inbound.unit,
            ),
            (None, None) => (Tally::Unrouted(&self.metrics), inbound.unit),
        };
        let function = inbound.pdu.first().copied().unwrap_or(0);
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

/// What a rule's `decision` makes of a request the master may make.
enum Ruling {
    /// On to the line, with its journal entry if it has one.
    Send(Option<Pending>),
    /// Answered with its normal reply, unsent.
    Acknowledge(Answer),
    Refuse(RequestError),
}

/// What `decision` (by the rule named `rule`) makes of `pdu` to `target` on `bus` (`None`: to a
/// virtual unit), whose journal entry is `pending` if it is a write; that entry is told of a
/// refusal or an acknowledgement.
fn ruling(
    rules: &Rules,
    decision: rules::Decision,
    rule: &str,
    pdu: &[u8],
    on: Option<(Target, &BusHandle)>,
    pending: Option<Pending>,
) -> Ruling {
    let function = pdu.first().copied().unwrap_or(0);
    match (decision.action, pending) {
        (Action::Allow, pending) => Ruling::Send(pending),
        // A read under an `acknowledge` rule goes on: only writes are kept back.
        (Action::Acknowledge, None) => Ruling::Send(None),
        (Action::Acknowledge, Some(pending)) => match acknowledgement(pdu, on) {
            Some(answer) => {
                pending.acknowledged();
                Ruling::Acknowledge(answer)
            }
            None => {
                let refusal = RequestError::Denied {
                    function,
                    registers: false,
                };
                let detail = format!(
                    "{rule}: acknowledge; its normal reply is the slave's to make, so it cannot \
                     be acknowledged unsent"
                );
                pending.denied(refusal.exception_code() as u8, detail);
                Ruling::Refuse(refusal)
            }
        },
        (Action::Deny, pending) => {
            let registers = decision.exception(rules) == pdu::ExceptionCode::IllegalDataAddress;
            let refusal = RequestError::Denied {
                function,
                registers,
            };
            if let Some(pending) = pending {
                pending.denied(refusal.exception_code() as u8, format!("{rule}: deny"));
            }
            Ruling::Refuse(refusal)
        }
    }
}

/// Who a request `client` may not make was refused by, for its journal entry: the setting that
/// limits the master's access, for a refusal of access; nobody for any other.
fn refused_by(client: &Client, refusal: RequestError) -> Decided<'_> {
    let access = matches!(
        refusal,
        RequestError::ReadOnly(_)
            | RequestError::NoAccess(_)
            | RequestError::UnitNotPermitted(_)
            | RequestError::Unverifiable(_)
    );
    match &client.limited_by {
        Some(by) if access => Decided {
            rule: Some(by),
            action: Action::Deny,
        },
        _ => Decided {
            rule: None,
            action: Action::Allow,
        },
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

/// Where a request goes: a slave of a bus, or a virtual unit.
#[derive(Clone, Copy)]
enum To<'a> {
    Bus(Target),
    Virtual(&'a Virtual),
}

/// Where `pdu` from `client` to `unit` (going `to`) goes, or why the gateway refuses it
/// unsent: the first reason in this order.
fn admit<'a>(
    client: &Client,
    unit: u8,
    pdu: &[u8],
    to: Option<To<'a>>,
) -> Result<To<'a>, RequestError> {
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
        match to {
            None => RequestError::NoRoute(unit),
            Some(To::Bus(target)) if target.broadcast && pdu::broadcast_response(pdu).is_none() => {
                RequestError::NotBroadcastable(function)
            }
            Some(to) => return Ok(to),
        }
    };
    Err(refusal)
}

/// The reply an `acknowledge` rule gives a write in place of the slave (`on` a bus, or a
/// virtual unit): the normal reply the slave would give (the one the gateway makes for a
/// broadcast), or for a broadcast unit what a broadcast gets. `None` for a write whose normal
/// reply only the slave can make (it carries data read, or is the vendor's).
fn acknowledgement(pdu: &[u8], on: Option<(Target, &BusHandle)>) -> Option<Answer> {
    let reply = pdu::broadcast_response(pdu)?;
    if on.is_some_and(|(target, bus)| target.broadcast && !bus.broadcast_reply()) {
        return Some(Answer::Nothing);
    }
    Some(Answer::Acknowledged(reply))
}

/// `inbound`, a write to a virtual unit, as the `write` to a source slave it becomes.
fn through<'a>(table: &'a Table, inbound: &Inbound<'a>, write: &'a SourceWrite) -> Inbound<'a> {
    Inbound {
        bus: Some(table.buses[write.target.bus].name()),
        target: Some(write.target),
        pdu: &write.pdu,
        ..*inbound
    }
}

/// The first of a virtual unit's source writes `through` that a rule denies: the refusal, and
/// the journal's detail for the master's write.
fn first_denial<'a>(
    rules: &Rules,
    mut through: impl Iterator<Item = Inbound<'a>>,
) -> Option<(RequestError, String)> {
    through.find_map(|write| {
        let decision = rules.decide(&write);
        (decision.action == Action::Deny).then(|| {
            let rule = decision.rule.map_or("a rule", |at| rules.name(at));
            let function = write.pdu.first().copied().unwrap_or(0);
            let registers = decision.exception(rules) == pdu::ExceptionCode::IllegalDataAddress;
            let detail = format!(
                "{rule}: deny, of the write to slave {} of {} it becomes",
                write.target.map_or(0, |t| t.address),
                write.bus.unwrap_or("its bus")
            );
            (
                RequestError::Denied {
                    function,
                    registers,
                },
                detail,
            )
        })
    })
}

/// What the writes `sent` on for a write with `function` to a virtual unit came to: its
/// `normal` reply when every one was carried out, else the first failure, as the master's
/// exception (the slave's code under the master's function code) or the gateway's.
async fn written(function: u8, normal: Vec<u8>, sent: Vec<oneshot::Receiver<Outcome>>) -> Outcome {
    let mut failed = None;
    for receiver in sent {
        let ended = receiver.await.unwrap_or(Err(RequestError::ShuttingDown));
        let failure = match ended {
            Ok(Answer::Reply(reply)) if reply.first().is_some_and(|f| f & EXCEPTION_BIT != 0) => {
                let code = reply.get(1).copied().unwrap_or(0x04);
                Some(Ok(Answer::Reply(vec![function | EXCEPTION_BIT, code])))
            }
            Ok(Answer::Reply(_) | Answer::Acknowledged(_) | Answer::Nothing) => None,
            Ok(Answer::Malformed(_)) => Some(Ok(Answer::Reply(
                pdu::exception_pdu(function, pdu::ExceptionCode::ServerDeviceFailure).to_vec(),
            ))),
            Err(error) => Some(Err(error)),
        };
        failed = failed.or(failure);
    }
    failed.unwrap_or(Ok(Answer::Reply(normal)))
}
