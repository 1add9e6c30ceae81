//! One serial master port's master, served as a slave serves it: a request frame at a time
//! ([`RequestReader`]: by length, by silence, a gap mid-frame breaking it), checked (CRC, LRC),
//! for a unit the port answers (`units`; any other: silence), handed to the dispatcher, and its
//! reply sent no sooner than t3.5 after the request (RTU) and never later than `answer_within`
//! after it: a late reply would collide with the master's next request, so it is dropped, as is
//! one the master stopped waiting for by sending its next request. Broadcasts are forwarded and
//! never answered. Every frame is counted by how it ended, and shown on the trace (`rx`: the
//! master's, `tx`: the gateway's).

use super::PortView;
use crate::config::UnitSet;
use crate::dispatch::{Client, Dispatcher};
use crate::error::{Outcome, RequestError};
use crate::line::inbound::{Received, RequestReader};
use crate::line::{Framing, LineTiming, Transport, BROADCAST};
use crate::metrics::PortOutcome;
use crate::net::session::reply_pdu;
use crate::pdu::EXCEPTION_BIT;
use crate::timer::sleep_until;
use crate::trace::{BusTap, Direction, TraceEvent};
use std::io;
use std::time::{Duration, SystemTime};
use tokio::sync::oneshot;
use tokio::time::Instant;

/// Broadcasts kept waiting for their bus at once; an older one still queued beyond them is
/// dropped (a master that floods broadcasts gets the line's pace, not the queue's).
const BROADCASTS_HELD: usize = 16;
/// How long the echo of a reply may take to come back beyond its time on the wire.
const ECHO_MARGIN: Duration = Duration::from_millis(50);

/// How a port serves its master.
pub(crate) struct Settings {
    pub(crate) framing: Framing,
    pub(crate) timing: LineTiming,
    /// Silence that breaks a request mid-frame, or ends one of unknown length.
    pub(crate) silence: Duration,
    pub(crate) units: UnitSet,
    pub(crate) answer_within: Duration,
    /// The line hands back every byte sent: dropped before the next request is read.
    pub(crate) echo: bool,
    pub(crate) client: Client,
}

/// The request being worked on.
struct Pending {
    outcome: oneshot::Receiver<Outcome>,
    unit: u8,
    function: u8,
    /// When the request was whole.
    at: Instant,
    /// The request as it came, for the trace once it has ended.
    frame: Vec<u8>,
}

impl Pending {
    fn due(&self, settings: &Settings) -> Instant {
        self.at + settings.answer_within
    }
}

async fn outcome_of(pending: &mut Option<Pending>) -> Outcome {
    match pending {
        Some(p) => (&mut p.outcome)
            .await
            .unwrap_or(Err(RequestError::PortDown)),
        None => std::future::pending().await,
    }
}

/// What the loop shares with its steps.
struct Port<'a, T> {
    port: &'a mut T,
    settings: &'a mut Settings,
    dispatcher: &'a Dispatcher,
    view: &'a PortView,
    trace: &'a BusTap,
    broadcasts: Vec<oneshot::Receiver<Outcome>>,
    pdu: Vec<u8>,
    out: Vec<u8>,
}

/// Serve the master on `port` until the port fails; returns why.
pub(super) async fn serve<T: Transport>(
    port: &mut T,
    settings: &mut Settings,
    dispatcher: &Dispatcher,
    view: &PortView,
    trace: &BusTap,
) -> io::Error {
    let mut reader = RequestReader::new(settings.framing, settings.silence);
    let mut stale = Vec::new();
    if let Err(e) = port.clear_input(&mut stale) {
        return e;
    }
    let mut port = Port {
        port,
        settings,
        dispatcher,
        view,
        trace,
        broadcasts: Vec::new(),
        pdu: Vec::new(),
        out: Vec::new(),
    };
    let mut pending: Option<Pending> = None;
    loop {
        let due = pending.as_ref().map(|p| p.due(port.settings));
        tokio::select! {
            received = reader.next(port.port) => {
                let received = match received {
                    Ok(received) => received,
                    Err(e) => return e,
                };
                // The master has sent its next frame: it no longer waits for this reply.
                if let Some(abandoned) = pending.take() {
                    port.too_late(&abandoned);
                }
                pending = port.heard(received);
            }
            outcome = outcome_of(&mut pending) => {
                let Some(done) = pending.take() else { continue };
                if let Err(e) = port.answer(done, outcome).await {
                    return e;
                }
                if port.settings.echo {
                    if let Err(e) = port.drop_echo().await {
                        return e;
                    }
                }
            }
            () = sleep_until(due.unwrap_or_else(Instant::now)), if due.is_some() => {
                if let Some(late) = pending.take() {
                    port.too_late(&late);
                }
            }
        }
    }
}

impl<T: Transport> Port<'_, T> {
    /// `pending`'s reply is not sent: counted, and traced.
    fn too_late(&self, pending: &Pending) {
        self.count(PortOutcome::TooLate, pending.unit, pending.function);
        self.trace(Direction::Rx, &pending.frame, PortOutcome::TooLate);
    }

    fn count(&self, outcome: PortOutcome, unit: u8, function: u8) {
        self.view.metrics.count(outcome, Some(unit), Some(function));
    }

    /// Show `bytes` on the trace, as the port saw them go `direction`, ended as `outcome`.
    fn trace(&self, direction: Direction, bytes: &[u8], outcome: PortOutcome) {
        let hub = self.trace.hub();
        if !hub.active() {
            return;
        }
        let (slave, function) = self.settings.framing.header(bytes);
        hub.publish(TraceEvent {
            time: SystemTime::now(),
            bus: self.trace.bus().clone(),
            direction,
            slave: slave.unwrap_or(0),
            function: function.unwrap_or(0),
            bytes: bytes.to_vec(),
            framing: self.settings.framing.name(),
            outcome: outcome.label(),
        });
    }

    /// A frame came in: dropped, forwarded unanswered (a broadcast), or submitted and now
    /// pending.
    fn heard(&mut self, received: Received) -> Option<Pending> {
        let at = Instant::now();
        let frame = match received {
            Received::Frame(frame) => frame,
            Received::Broken => {
                self.view.metrics.count(PortOutcome::BadFrame, None, None);
                return None;
            }
        };
        let framing = self.settings.framing;
        let Some(unit) = framing.decode_into(&frame, &mut self.pdu) else {
            let (unit, function) = framing.header(&frame);
            self.view
                .metrics
                .count(PortOutcome::BadFrame, unit, function);
            self.trace(Direction::Rx, &frame, PortOutcome::BadFrame);
            return None;
        };
        let Some(&function) = self.pdu.first() else {
            self.view
                .metrics
                .count(PortOutcome::BadFrame, Some(unit), None);
            self.trace(Direction::Rx, &frame, PortOutcome::BadFrame);
            return None;
        };
        if unit != BROADCAST && !self.settings.units.contains(unit) {
            self.count(PortOutcome::NotAddressed, unit, function);
            self.trace(Direction::Rx, &frame, PortOutcome::NotAddressed);
            return None;
        }
        self.view.requested();
        let outcome = self
            .dispatcher
            .submit(&mut self.settings.client, unit, self.pdu.clone());
        if unit == BROADCAST {
            self.count(PortOutcome::Broadcast, unit, function);
            self.trace(Direction::Rx, &frame, PortOutcome::Broadcast);
            self.hold_broadcast(outcome);
            return None;
        }
        Some(Pending {
            outcome,
            unit,
            function,
            at,
            frame,
        })
    }

    /// Keep a broadcast's receiver while its bus has it queued: a request nobody waits for is
    /// never sent.
    fn hold_broadcast(&mut self, outcome: oneshot::Receiver<Outcome>) {
        self.broadcasts
            .retain_mut(|held| matches!(held.try_recv(), Err(oneshot::error::TryRecvError::Empty)));
        if self.broadcasts.len() >= BROADCASTS_HELD {
            self.broadcasts.remove(0);
        }
        self.broadcasts.push(outcome);
    }

    /// Send the reply `outcome` makes for `done`, no sooner than t3.5 after the request
    /// (RTU), if it is still within `answer_within`.
    async fn answer(&mut self, done: Pending, outcome: Outcome) -> io::Result<()> {
        let Some(reply) = reply_pdu(done.function, outcome) else {
            // No reply to give (a broadcast unit's routed request): silence, as for a
            // broadcast.
            self.count(PortOutcome::Broadcast, done.unit, done.function);
            self.trace(Direction::Rx, &done.frame, PortOutcome::Broadcast);
            return Ok(());
        };
        let earliest = match self.settings.framing {
            Framing::Rtu => done.at + self.settings.timing.t35,
            Framing::Ascii | Framing::Tcp => done.at,
        };
        if Instant::now() < earliest {
            sleep_until(earliest).await;
        }
        if Instant::now() > done.due(self.settings) {
            self.too_late(&done);
            return Ok(());
        }
        self.settings
            .framing
            .encode_into(&mut self.out, 0, done.unit, &reply);
        self.port.send(&self.out).await?;
        let outcome = if reply.first().is_some_and(|f| f & EXCEPTION_BIT != 0) {
            PortOutcome::Exception
        } else {
            PortOutcome::Answered
        };
        self.count(outcome, done.unit, done.function);
        self.trace(Direction::Rx, &done.frame, outcome);
        self.trace(Direction::Tx, &self.out, outcome);
        Ok(())
    }

    /// On a line that echoes: read back the reply just sent and drop it, so that it is not
    /// taken for a request.
    async fn drop_echo(&mut self) -> io::Result<()> {
        let mut echo = Vec::with_capacity(self.out.len());
        let until = Instant::now() + self.settings.timing.frame_time(self.out.len()) + ECHO_MARGIN;
        while echo.len() < self.out.len() {
            match tokio::time::timeout_at(until, self.port.recv(&mut echo)).await {
                Ok(Ok(0)) => {
                    return Err(io::Error::new(
                        io::ErrorKind::UnexpectedEof,
                        "the port reads 0 bytes (device gone)",
                    ))
                }
                Ok(Ok(_)) => {}
                Ok(Err(e)) => return Err(e),
                Err(_) => break,
            }
        }
        Ok(())
    }
}
