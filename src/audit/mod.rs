//! Every write-class request, as it was decided and as it ended: the journal (`[audit]`), the
//! last writes for the status page, and the writes' metrics. A write's entry is handed to the
//! kernel before the dispatcher lets it go to its bus (begun at one site, [`Audit::begin`], with
//! who decided it, [`Decided`]), and with `fsync` the bus's pre-send step waits for it to be on
//! the disk ([`Pending::durable`]), so no write a slave carried out is missing from the journal
//! after the gateway is killed; its outcome is written when its [`Pending`] ends, which the bus's
//! `Waiter` does wherever the request ends. Knows nothing of sessions, queues or lines.

pub(crate) mod entry;
mod journal;

use crate::config::{self, Action};
use crate::error::{Answer, Outcome as Ended, RequestError};
use crate::master::Protocol;
use crate::metrics::Metrics;
use crate::pdu::{self, EXCEPTION_BIT};
use crate::routing::Inbound;
use entry::{Carried, Line, Write, WriteOutcome};
pub(crate) use journal::rotated;
use journal::{Journal, Ticket};
use serde::Serialize;
use std::collections::VecDeque;
use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};

/// Writes the status page lists.
const RECENT: usize = 20;

/// The writes' record: the journal in force (if `[audit]` is set), the last writes, the
/// metrics. One for the gateway; a reload changes its journal, never the record itself.
pub(crate) struct Audit {
    journal: RwLock<Option<Arc<Journal>>>,
    next_id: AtomicU64,
    recent: Mutex<VecDeque<Recent>>,
    metrics: Arc<Metrics>,
}

/// A write as the status page lists it: the entry, and its outcome once it has one.
#[derive(Clone, Debug, Serialize)]
pub(crate) struct Recent {
    pub(crate) write: Write,
    pub(crate) outcome: Option<entry::Ended>,
}

/// Who decided a write, for its entry: the deciding rule's name (or the setting that refused
/// it), `None` when nothing did, and what it decided.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Decided<'a> {
    pub(crate) rule: Option<&'a str>,
    pub(crate) action: Action,
}

/// The entry could not be written and `on_error = "deny_writes"`: the write is refused (0x0A).
#[derive(Debug)]
pub(crate) struct Refused;

impl Audit {
    pub(crate) fn new(metrics: Arc<Metrics>) -> Arc<Audit> {
        Arc::new(Audit {
            journal: RwLock::new(None),
            next_id: AtomicU64::new(1),
            recent: Mutex::new(VecDeque::with_capacity(RECENT)),
            metrics,
        })
    }

    fn journal(&self) -> Option<Arc<Journal>> {
        self.journal
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Open the journal `settings` names (none: no journal). At start, an error is the
    /// gateway's: it does not run without the journal it was told to keep.
    pub(crate) fn open(&self, settings: Option<&config::Audit>) -> io::Result<()> {
        let journal = settings
            .map(|settings| Journal::open(settings, self.metrics.clone()))
            .transpose()?;
        if journal.is_none() {
            self.metrics.audit.journal(None);
        }
        *self.journal.write().unwrap_or_else(PoisonError::into_inner) = journal.map(Arc::new);
        Ok(())
    }

    /// Apply a reload's `[audit]`: the same path takes the new settings from the next entry;
    /// a new path is opened, and if it cannot be, the journal in force stays and the reason
    /// is returned. `Ok(Some(what))` says what changed.
    pub(crate) fn apply(&self, settings: Option<&config::Audit>) -> Result<Option<String>, String> {
        let current = self.journal();
        match (current, settings) {
            (None, None) => Ok(None),
            (Some(journal), Some(settings)) if journal.path() == settings.path => {
                if journal.settings() == *settings {
                    return Ok(None);
                }
                journal.set(settings);
                Ok(Some("audit journal settings".to_owned()))
            }
            (_, Some(settings)) => {
                let journal = Journal::open(settings, self.metrics.clone()).map_err(|e| {
                    format!(
                        "audit.path: cannot open `{}`: {e}; the journal in force is kept",
                        settings.path.display()
                    )
                })?;
                *self.journal.write().unwrap_or_else(PoisonError::into_inner) =
                    Some(Arc::new(journal));
                Ok(Some(format!("audit journal: {}", settings.path.display())))
            }
            (Some(_), None) => {
                *self.journal.write().unwrap_or_else(PoisonError::into_inner) = None;
                self.metrics.audit.journal(None);
                Ok(Some("audit journal: none".to_owned()))
            }
        }
    }

    /// Journal `asked` before anything of it is sent. `Err(Refused)`: its entry could not be
    /// written and `on_error = "deny_writes"`.
    pub(crate) fn begin(
        self: &Arc<Self>,
        asked: &Inbound<'_>,
        by: Decided<'_>,
    ) -> Result<Pending, Refused> {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let (span, values) = pdu::written(asked.pdu);
        let write = Write {
            time: entry::now(),
            id,
            master: asked.peer.to_string(),
            protocol: asked.protocol.label().to_owned(),
            subject: asked.subject.map(str::to_owned),
            role: asked.role.map(str::to_owned),
            unit: asked.unit,
            bus: asked.bus.map(str::to_owned),
            slave: asked.target.map(|t| t.address),
            virtual_unit: asked.virtual_unit.map(str::to_owned),
            function: asked.pdu.first().copied().unwrap_or(0),
            table: span.map(|s| s.table.word().to_owned()),
            start: span.map(|s| s.first),
            count: span.map(|s| s.count()),
            values: entry::hex(values),
            rule: by.rule.map(str::to_owned),
            action: by.action.label().to_owned(),
        };
        let journal = self.journal();
        let mut recorded = None;
        let mut ticket = None;
        if let Some(journal) = &journal {
            match journal.record(&Line::Write(write.clone())) {
                Ok(sync) => {
                    recorded = Some(journal.clone());
                    ticket = sync;
                }
                Err(unwritten) if unwritten.refuse => return Err(Refused),
                Err(_) => {}
            }
        }
        self.remember(write);
        Ok(Pending {
            audit: self.clone(),
            journal: recorded,
            ticket,
            id,
            protocol: asked.protocol,
            action: by.action,
            broadcast: asked.target.is_some_and(|t| t.broadcast),
        })
    }

    /// `asked`, whose entry could not be written, ended unsent in `refusal`: counted, as
    /// every write is, by how it ended.
    pub(crate) fn unjournaled(&self, asked: &Inbound<'_>, by: Decided<'_>, refusal: RequestError) {
        let (outcome, ..) = judge_error(refusal);
        let (protocol, action) = (asked.protocol.label(), by.action.label());
        self.metrics
            .audit
            .write_ended(protocol, action, outcome.label());
    }

    fn remember(&self, write: Write) {
        let mut recent = self.recent.lock().unwrap_or_else(PoisonError::into_inner);
        if recent.len() == RECENT {
            recent.pop_front();
        }
        recent.push_back(Recent {
            write,
            outcome: None,
        });
    }

    /// The last writes, newest last.
    pub(crate) fn recent(&self) -> Vec<Recent> {
        let recent = self.recent.lock().unwrap_or_else(PoisonError::into_inner);
        recent.iter().cloned().collect()
    }

    fn ended(&self, pending: &Pending, ended: entry::Ended) {
        {
            let mut recent = self.recent.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(entry) = recent.iter_mut().rev().find(|r| r.write.id == pending.id) {
                entry.outcome = Some(ended.clone());
            }
        }
        let (protocol, action) = (pending.protocol.label(), pending.action.label());
        self.metrics
            .audit
            .write_ended(protocol, action, ended.outcome.label());
        if let Some(journal) = &pending.journal {
            journal.note(&Line::Outcome(ended));
        }
    }
}

/// A journaled write on its way: its outcome is written when it ends. Ended once, by whoever
/// ends its request; dropped unended (the gateway aborted mid-request), it leaves its entry
/// without an outcome, which reads "may have been carried out".
#[derive(Debug)]
pub(crate) struct Pending {
    audit: Arc<Audit>,
    journal: Option<Arc<Journal>>,
    /// With `fsync`: the entry's place in the line to the disk.
    ticket: Option<Ticket>,
    id: u64,
    protocol: Protocol,
    action: Action,
    broadcast: bool,
}

impl std::fmt::Debug for Audit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Audit")
    }
}

impl std::fmt::Debug for Journal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Journal({})", self.path().display())
    }
}

impl Pending {
    /// Whether the write may go on the wire now: at once, or with `fsync` once its entry is on
    /// the disk. `false`: syncing it failed and `on_error = "deny_writes"` refuses it.
    pub(crate) async fn durable(&self) -> bool {
        let (Some(ticket), Some(journal)) = (&self.ticket, &self.journal) else {
            return true;
        };
        ticket.synced().await || !journal.sync_failed()
    }

    /// The request ended in `outcome`; `None`: its master left before it was sent.
    pub(crate) fn end(self, outcome: Option<&Ended>) {
        let (outcome, carried, exception, detail) = match outcome {
            None => (
                WriteOutcome::Cancelled,
                Carried::No,
                None,
                Some("the master left before it was sent".to_owned()),
            ),
            Some(outcome) => self.judge(outcome),
        };
        self.finish(outcome, carried, exception, detail);
    }

    /// Refused unsent by a rule, `server.read_only` or a role, with `exception`.
    pub(crate) fn denied(self, exception: u8, detail: String) {
        self.finish(
            WriteOutcome::Denied,
            Carried::No,
            Some(exception),
            Some(detail),
        );
    }

    /// Answered with its normal reply by an `acknowledge` rule, unsent.
    pub(crate) fn acknowledged(self) {
        let detail = "answered by the gateway as the slave would have; not sent".to_owned();
        self.finish(WriteOutcome::Acknowledged, Carried::No, None, Some(detail));
    }

    fn finish(
        self,
        outcome: WriteOutcome,
        carried: Carried,
        exception: Option<u8>,
        detail: Option<String>,
    ) {
        let ended = entry::Ended {
            time: entry::now(),
            id: self.id,
            outcome,
            carried_out: carried,
            exception,
            detail,
        };
        self.audit.ended(&self, ended);
    }

    fn judge(&self, outcome: &Ended) -> (WriteOutcome, Carried, Option<u8>, Option<String>) {
        let reply = match outcome {
            Ok(Answer::Reply(pdu) | Answer::Malformed(pdu) | Answer::Acknowledged(pdu)) => {
                Some(pdu.as_slice())
            }
            Ok(Answer::Nothing) => None,
            Err(error) => return judge_error(*error),
        };
        if self.broadcast {
            let detail = "sent to every slave; none answers a broadcast".to_owned();
            return (WriteOutcome::Broadcast, Carried::Maybe, None, Some(detail));
        }
        match reply {
            Some([function, code, ..]) if function & EXCEPTION_BIT != 0 => {
                let name = pdu::exception_name(*code).unwrap_or("the vendor's own code");
                let detail = format!("the slave refused it: {name}");
                (
                    WriteOutcome::SlaveException,
                    Carried::No,
                    Some(*code),
                    Some(detail),
                )
            }
            _ => (WriteOutcome::Answered, Carried::Yes, None, None),
        }
    }
}

fn judge_error(error: RequestError) -> (WriteOutcome, Carried, Option<u8>, Option<String>) {
    let code = error.exception_code() as u8;
    match error {
        RequestError::NoResponse { .. } => (
            WriteOutcome::Timeout,
            Carried::Maybe,
            Some(code),
            Some(format!("{error}; may have been carried out")),
        ),
        RequestError::PortLost => (
            WriteOutcome::GatewayException,
            Carried::Maybe,
            Some(code),
            Some(format!("{error}; may have been carried out")),
        ),
        RequestError::ReadOnly(_)
        | RequestError::Denied { .. }
        | RequestError::NoAccess(_)
        | RequestError::UnitNotPermitted(_)
        | RequestError::Unverifiable(_) => (
            WriteOutcome::Denied,
            Carried::No,
            Some(code),
            Some(error.to_string()),
        ),
        _ => (
            WriteOutcome::GatewayException,
            Carried::No,
            Some(code),
            Some(format!("{error}; not sent")),
        ),
    }
}
