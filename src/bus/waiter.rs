//! The end of a request: who waits for it, and the one place it is counted and answered. Every
//! way a request ends (the line's answer, a read that followed another, the cache, expiry, a
//! refusal by the bus or the dispatcher, a master gone, shutdown) is a [`Waiter`] ended here,
//! so each request gets exactly one answer and one count. Knows nothing of queues or lines.

use crate::audit::Pending;
use crate::error::Outcome;
use crate::master::{Class, Origin};
use crate::metrics::{BusMetrics, Metrics, VirtualMetrics};
use tokio::sync::oneshot;
use tokio::time::Instant;

/// Where a request's end is counted: the bus and slave its unit routes to, or, for a unit with
/// no route, no bus and no slave (the unit id is the master's to choose).
#[derive(Clone, Copy)]
pub(crate) enum Tally<'a> {
    Bus(&'a BusMetrics),
    Unrouted(&'a Metrics),
    /// A virtual unit, by its name (its `slave` the unit id).
    Virtual(&'a VirtualMetrics, &'a str),
}

impl Tally<'_> {
    fn count(self, slave: u8, function: u8, origin: &Origin, outcome: Option<&Outcome>) {
        // The gateway's own polls are no master's requests: the poller counts them.
        if origin.class == Class::Poll {
            return;
        }
        match self {
            Tally::Bus(metrics) => metrics.request(slave, function, origin.protocol, outcome),
            Tally::Unrouted(metrics) => metrics.unrouted(function, origin.protocol, outcome),
            Tally::Virtual(metrics, name) => {
                if let Some(outcome) = outcome {
                    metrics.request(slave, name, function, outcome);
                }
            }
        }
    }
}

/// One master waiting for one request's outcome. Moved, never copied: ending it consumes it.
#[derive(Debug)]
pub(crate) struct Waiter {
    pub origin: Origin,
    /// When the request arrived.
    pub(crate) queued_at: Instant,
    /// If the line has not started it by then, it is answered 0x06 instead.
    pub deadline: Instant,
    reply: oneshot::Sender<Outcome>,
    /// A write's journal entry, whose outcome is written when it ends.
    journal: Option<Box<Pending>>,
}

impl Waiter {
    /// A master of `origin` waiting from now until `deadline`, and where its outcome comes.
    pub(crate) fn new(origin: Origin, deadline: Instant) -> (Waiter, oneshot::Receiver<Outcome>) {
        let (reply, outcome) = oneshot::channel();
        let waiter = Waiter {
            origin,
            queued_at: Instant::now(),
            deadline,
            reply,
            journal: None,
        };
        (waiter, outcome)
    }

    /// The same waiter, writing `pending`'s outcome when it ends.
    pub(crate) fn journaled(self, pending: Option<Pending>) -> Waiter {
        Waiter {
            journal: pending.map(Box::new),
            ..self
        }
    }

    /// Whether its request may go on the wire now: a write waits here for its journal entry to
    /// reach the disk (`audit.fsync`); `false` if it cannot, and the journal refuses the write.
    pub(crate) async fn durable(&self) -> bool {
        match &self.journal {
            Some(pending) => pending.durable().await,
            None => true,
        }
    }

    /// Its master has stopped waiting (the connection closed).
    pub(crate) fn is_gone(&self) -> bool {
        self.reply.is_closed()
    }

    /// The request (`function` to `slave`) ended in `outcome`: counted in `tally`, and sent to
    /// the master.
    pub(crate) fn answer(self, tally: Tally<'_>, slave: u8, function: u8, outcome: Outcome) {
        self.end(tally, slave, function, Some(outcome));
    }

    /// The request ended unsent because its master left: counted as such, answered to nobody.
    pub(crate) fn left(self, tally: Tally<'_>, slave: u8, function: u8) {
        self.end(tally, slave, function, None);
    }

    /// Sent, uncounted: for tests of the queue alone, which has no metrics.
    #[cfg(test)]
    pub(super) fn reply(self, outcome: Outcome) {
        if let Some(pending) = self.journal {
            pending.end(Some(&outcome));
        }
        let _ = self.reply.send(outcome);
    }

    /// Every end goes through here: counted once, then sent once.
    fn end(self, tally: Tally<'_>, slave: u8, function: u8, outcome: Option<Outcome>) {
        tally.count(slave, function, &self.origin, outcome.as_ref());
        if let Some(pending) = self.journal {
            pending.end(outcome.as_ref());
        }
        if let Some(outcome) = outcome {
            let _ = self.reply.send(outcome);
        }
    }
}
