//! Serving a listen-only line (`mode = "listen"`): the bus task hears what another master and
//! its slaves say (`line::listen`'s [`Ear`]), keeps what the replies carried in the line's
//! [`Shadow`], counts and traces what it heard, and tells the slaves' health. It never sends:
//! the port is only ever read ([`Hearing`] has no way to write), and every request a master
//! routes here is answered by the [`BusHandle`] from the shadow, in the one place requests are
//! submitted, so nothing is ever queued for this loop to take.

use super::health::Response;
use super::shadow::Shadow;
use super::task::{BusTask, Served};
use super::{Port, HEARTBEAT};
use crate::error::{Answer, NoReply, Outcome, RequestError};
use crate::line::listen::{Ear, EarTiming, Event, HeardFrame};
use crate::line::Transport;
use crate::metrics::Discarded;
use crate::shutdown::Stopping;
use crate::timer::coarse_sleep_until;
use crate::trace::{Direction, TraceEvent};
use std::collections::VecDeque;
use std::io;
use std::sync::Arc;
use std::time::{Duration, SystemTime};
use tokio::time::{sleep, Instant};

/// Distinct reads per slave whose last request time is kept, for the other master's poll
/// interval: the oldest is forgotten past this.
const CADENCE_KEYS: usize = 16;

/// A port that can only be read: what a listen line holds of its device.
struct Hearing(Port);

impl Hearing {
    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        self.0.recv(buf).await
    }
}

/// When each of a slave's reads was last asked for: the time between two asks of one read is
/// the other master's poll interval.
#[derive(Default)]
struct Cadence {
    last: VecDeque<(u8, Vec<u8>, Instant)>,
}

impl Cadence {
    /// A request `pdu` to `slave` at `at`: how long since the same request was last heard.
    fn asked(&mut self, slave: u8, pdu: &[u8], at: Instant) -> Option<Duration> {
        let found = self
            .last
            .iter()
            .position(|(s, p, _)| *s == slave && p == pdu);
        let since = found
            .and_then(|i| self.last.remove(i))
            .map(|(_, _, then)| at.saturating_duration_since(then));
        if self.last.len() >= CADENCE_KEYS * 4 {
            self.last.pop_front();
        }
        let same_slave = self.last.iter().filter(|(s, _, _)| *s == slave).count();
        if same_slave >= CADENCE_KEYS {
            if let Some(i) = self.last.iter().position(|(s, _, _)| *s == slave) {
                self.last.remove(i);
            }
        }
        self.last.push_back((slave, pdu.to_vec(), at));
        since
    }
}

impl BusTask {
    /// How this line hears, from its settings.
    fn ear_timing(&self) -> (EarTiming, [Duration; 256]) {
        let derived = &self.current.derived;
        let timing = EarTiming {
            silence: derived.timing.silence,
            char_time: derived.timing.line.char_time,
        };
        (timing, *derived.timeouts)
    }

    /// Hear `port` until it is lost, a stop or a new device, keeping `shadow`.
    pub(super) async fn serve_listening(
        &mut self,
        port: Port,
        shadow: &Arc<Shadow>,
        stopping: &mut Stopping,
    ) -> Served {
        let mut port = Hearing(port);
        let (timing, timeouts) = self.ear_timing();
        let mut ear = Ear::new(self.current.derived.framing, timing, timeouts);
        let mut cadence = Cadence::default();
        let mut chunk = Vec::with_capacity(512);
        let mut heard = Vec::new();
        let end = loop {
            self.beat();
            let deadline = ear.next_deadline();
            tokio::select! {
                biased;
                _ = stopping.requested() => break Served::Stopped,
                () = self.updates.changed() => {
                    if self.take_update() == Some(true) {
                        break Served::Reopen;
                    }
                    let (timing, timeouts) = self.ear_timing();
                    ear.set_timing(timing, timeouts);
                    shadow.set_max_age(self.current.settings.max_age);
                }
                received = port.recv(&mut chunk) => match received {
                    Ok(0) => {
                        break Served::Lost(io::Error::new(
                            io::ErrorKind::UnexpectedEof,
                            "the port reads 0 bytes (device gone)",
                        ))
                    }
                    Ok(n) => {
                        self.handle.metrics.observed_bytes(n);
                        ear.feed(&chunk, Instant::now(), &mut heard);
                        chunk.clear();
                    }
                    Err(error) => break Served::Lost(error),
                },
                () = coarse_sleep_until(deadline.unwrap_or_else(Instant::now)),
                    if deadline.is_some() => ear.tick(Instant::now(), &mut heard),
                () = sleep(HEARTBEAT) => {}
            }
            for event in heard.drain(..) {
                self.heard(event, shadow, &mut cadence);
            }
        };
        ear.reset(&mut heard);
        for event in heard.drain(..) {
            self.heard(event, shadow, &mut cadence);
        }
        end
    }

    /// One thing the line carried: into the shadow, the metrics, the slaves' health and the
    /// trace.
    fn heard(&mut self, event: Event, shadow: &Shadow, cadence: &mut Cadence) {
        let metrics = self.handle.metrics.clone();
        match event {
            Event::Answered {
                request,
                reply,
                response,
            } => self.answered(&request, &reply, response, shadow, cadence),
            Event::Unanswered(request) => {
                self.asked(&request, cadence);
                metrics.observed_timeout(request.address);
                let outcome = no_reply(NoReply::Timeout);
                self.record_of(
                    request.address,
                    request.function(),
                    Response::TimedOut,
                    &outcome,
                );
                self.trace_heard(&request, Direction::Request, "timeout");
            }
            Event::Broadcast(request) => {
                self.asked(&request, cadence);
                self.trace_heard(&request, Direction::Request, "broadcast");
            }
            Event::Corrupt {
                bytes,
                end,
                request,
            } => {
                metrics.observed_discarded(Discarded::CrcError);
                let (address, function) = self.current.derived.framing.header(&bytes);
                let direction = if let Some(request) = &request {
                    self.asked(request, cadence);
                    let outcome = no_reply(NoReply::Check);
                    self.record_of(
                        request.address,
                        request.function(),
                        Response::Garbled,
                        &outcome,
                    );
                    self.trace_heard(request, Direction::Request, "crc_error");
                    Direction::Reply
                } else {
                    Direction::Rx
                };
                self.trace_bytes(bytes, end, (address, function), direction, "crc_error");
            }
            Event::Unpaired(frame) => {
                metrics.observed_discarded(Discarded::Unpaired);
                self.trace_heard(&frame, Direction::Rx, "unpaired");
            }
            Event::Broken { bytes, end } => {
                metrics.observed_discarded(Discarded::Broken);
                let header = self.current.derived.framing.header(&bytes);
                self.trace_bytes(bytes, end, header, Direction::Rx, "broken");
            }
        }
    }

    /// The other master's `request`, answered by `reply` after `response`.
    fn answered(
        &mut self,
        request: &HeardFrame,
        reply: &HeardFrame,
        response: Duration,
        shadow: &Shadow,
        cadence: &mut Cadence,
    ) {
        let metrics = self.handle.metrics.clone();
        self.asked(request, cadence);
        let wall = wall_time(reply.end);
        if !reply.is_exception() {
            shadow.record(request.address, &request.pdu, &reply.pdu, (reply.end, wall));
        }
        let exception = reply
            .is_exception()
            .then(|| reply.pdu.get(1).copied().unwrap_or(0));
        metrics.observed_reply(request.address, request.function(), exception, response);
        let outcome = Ok(Answer::Reply(reply.pdu.clone()));
        let request_time = self
            .current
            .derived
            .timing
            .line
            .frame_time(request.bytes.len());
        let round_trip = reply.end.saturating_duration_since(request.end) + request_time;
        metrics.transaction(request.address, 1, Some(round_trip), &outcome);
        self.record_of(
            request.address,
            request.function(),
            Response::Answered,
            &outcome,
        );
        let label = if exception.is_some() {
            "exception"
        } else {
            "ok"
        };
        self.trace_heard(request, Direction::Request, label);
        self.trace_heard(reply, Direction::Reply, label);
    }

    /// The other master asked `request`: counted, with how long since it last asked the same.
    fn asked(&self, request: &HeardFrame, cadence: &mut Cadence) {
        let interval = cadence.asked(request.address, &request.pdu, request.end);
        let metrics = &self.handle.metrics;
        metrics.observed_request(request.address, request.function(), interval);
    }

    fn trace_heard(&self, frame: &HeardFrame, direction: Direction, outcome: &'static str) {
        let header = (Some(frame.address), Some(frame.function()));
        self.trace_bytes(frame.bytes.clone(), frame.end, header, direction, outcome);
    }

    fn trace_bytes(
        &self,
        bytes: Vec<u8>,
        end: Instant,
        (address, function): (Option<u8>, Option<u8>),
        direction: Direction,
        outcome: &'static str,
    ) {
        let hub = self.trace.hub();
        if !hub.active() {
            return;
        }
        hub.publish(TraceEvent {
            time: wall_time(end),
            bus: self.trace.bus().clone(),
            direction,
            slave: address.unwrap_or(0),
            function: function.unwrap_or(0),
            bytes,
            framing: self.current.derived.framing.name(),
            outcome,
        });
    }
}

/// The outcome of a transaction that got no valid reply, for the slave's health to log.
fn no_reply(last: NoReply) -> Outcome {
    Err(RequestError::NoResponse { attempts: 1, last })
}

/// `at` on the wall clock.
fn wall_time(at: Instant) -> SystemTime {
    let ago = Instant::now().saturating_duration_since(at);
    SystemTime::now()
        .checked_sub(ago)
        .unwrap_or_else(SystemTime::now)
}

#[cfg(test)]
#[path = "listen_tests.rs"]
mod tests;
