//! Serving a Modbus TCP device with several requests outstanding (`max_in_flight` above 1): the
//! fair queue's requests go out as soon as there is room, each under the gateway's own
//! transaction id, and each reply, in whatever order the device sends them, answers the request
//! of its id, unit and function code, and only that one. A request without its reply by its
//! deadline is retried (a read under `retries`) or answered 0x0B; a reply that answers none in
//! flight is discarded and counted. What clears a request for the wire is the pre-send step both
//! loops take (`ready`); slave health, the cache, coalescing, the metrics and the trace are those
//! of the one-at-a-time loop.

use super::device::Linked;
use super::ready::Cleared;
use super::task::{BusTask, Served};
use super::{Job, HEARTBEAT};
use crate::error::{Answer, NoReply, Outcome, RequestError};
use crate::line::pipeline::{Frame, Pipeline};
use crate::line::reply::{self, ReplyForm, Verdict};
use crate::line::{LineCounters, Reply};
use crate::metrics::Fate;
use crate::shutdown::Stopping;
use crate::trace::{Direction, TraceEvent};
use std::io;
use std::time::SystemTime;
use tokio::time::{sleep, Instant};

/// A request on the wire.
struct Flight {
    transaction: u16,
    job: Job,
    deadline: Instant,
    attempts: u32,
    retries: u32,
    first_sent: Instant,
    /// The request as sent, for the trace.
    sent: Vec<u8>,
    sent_at: SystemTime,
}

/// What the loop does next.
enum Step {
    Send(Job),
    Frame(io::Result<Frame>),
    Deadline,
    Again,
    Stop(Instant),
}

impl BusTask {
    /// Serve `port` with up to `max_in_flight` requests outstanding, until it is lost, a new
    /// configuration names another device, or a stop (with no request left in flight).
    pub(super) async fn serve_pipelined<T: Linked>(
        &mut self,
        port: T,
        stopping: &mut Stopping,
    ) -> Served {
        let mut pipeline = Pipeline::new(port);
        let mut flights: Vec<Flight> = Vec::new();
        let mut counted = LineCounters::default();
        let mut draining: Option<Instant> = None;
        let mut quiet_until = Instant::now() + self.current.settings.connect_delay;
        loop {
            self.beat();
            if self.take_update() == Some(true) {
                return self.lose_flights(flights, Served::Reopen);
            }
            if let Some(deadline) = draining {
                let over = Instant::now() >= deadline;
                if (flights.is_empty() && self.handle.queue.is_empty()) || over {
                    return self.lose_flights(flights, Served::Stopped);
                }
            }
            let room = flights.len() < self.current.settings.max_in_flight;
            let next_deadline = flights.iter().map(|f| f.deadline).min();
            let step = tokio::select! {
                biased;
                at = stopping.requested(), if draining.is_none() => Step::Stop(at),
                () = self.updates.changed() => Step::Again,
                frame = pipeline.next_frame() => Step::Frame(frame),
                () = crate::timer::sleep_until(next_deadline.unwrap_or(quiet_until)),
                    if next_deadline.is_some() => Step::Deadline,
                () = crate::timer::sleep_until(quiet_until), if Instant::now() < quiet_until => {
                    Step::Again
                }
                job = self.handle.queue.pop(), if room && Instant::now() >= quiet_until => {
                    Step::Send(job)
                }
                () = sleep(HEARTBEAT) => Step::Again,
            };
            let lost = match step {
                Step::Stop(at) => {
                    draining = Some(at);
                    None
                }
                Step::Again => None,
                Step::Send(job) => self.take_off(&mut pipeline, &mut flights, job).await.err(),
                Step::Frame(Ok(frame)) => {
                    self.land(&mut pipeline, &mut flights, frame);
                    quiet_until = Instant::now() + self.current.derived.timing.gap;
                    None
                }
                Step::Frame(Err(error)) => Some(error),
                Step::Deadline => self.expire(&mut pipeline, &mut flights).await.err(),
            };
            self.count_traffic(pipeline.counters(), &mut counted, pipeline.port().link());
            if let Some(error) = lost {
                return self.lose_flights(flights, Served::Lost(error));
            }
        }
    }

    /// Every request in flight gets 0x0A: the connection they were on is gone.
    fn lose_flights(&mut self, flights: Vec<Flight>, end: Served) -> Served {
        for flight in flights {
            self.handle.answer(flight.job, Err(RequestError::PortLost));
        }
        end
    }

    /// Send `job`, if anyone still waits for it and its slave is not down.
    async fn take_off<T: Linked>(
        &mut self,
        pipeline: &mut Pipeline<T>,
        flights: &mut Vec<Flight>,
        job: Job,
    ) -> io::Result<()> {
        let Some(Cleared { job, retries, .. }) = self.ready(job).await else {
            return Ok(());
        };
        let now = Instant::now();
        let (transaction, sent) = match pipeline.send(job.slave, &job.pdu).await {
            Ok((transaction, sent)) => (transaction, sent.to_vec()),
            Err(error) => {
                self.handle.answer(job, Err(RequestError::PortLost));
                return Err(error);
            }
        };
        flights.push(Flight {
            transaction,
            deadline: self.flight_deadline(pipeline, job.slave),
            job,
            attempts: 1,
            retries,
            first_sent: now,
            sent,
            sent_at: SystemTime::now(),
        });
        Ok(())
    }

    /// When a request sent now to `slave` must have its reply: its response timeout from when it
    /// can have reached the device.
    fn flight_deadline<T: Linked>(&self, pipeline: &Pipeline<T>, slave: u8) -> Instant {
        let timeout = self.current.derived.timeouts[usize::from(slave)];
        let budget = pipeline.port().link().map(|(_, budget, _)| budget);
        Instant::now() + budget.unwrap_or_default() + timeout
    }

    /// `frame` came: the request in flight it answers ends, or it is discarded.
    fn land<T: Linked>(
        &mut self,
        pipeline: &mut Pipeline<T>,
        flights: &mut Vec<Flight>,
        frame: Frame,
    ) {
        // The flight of the frame's transaction, if the frame answers its request: judged once.
        let found = flights.iter().enumerate().find_map(|(at, f)| {
            if f.transaction != frame.transaction || f.job.slave != frame.unit {
                return None;
            }
            let form = ReplyForm::Standard;
            match reply::judge(frame.unit, &frame.pdu, f.job.slave, &f.job.pdu, form) {
                verdict @ (Verdict::Answer | Verdict::Malformed) => Some((at, verdict)),
                Verdict::Foreign => None,
                #[cfg(test)]
                Verdict::Corrupt => None,
            }
        });
        let Some((at, verdict)) = found else {
            pipeline.discarded();
            self.trace_frame(
                Direction::Rx,
                &frame.bytes,
                SystemTime::now(),
                crate::trace::FOREIGN,
            );
            return;
        };
        let flight = flights.swap_remove(at);
        let reply = match verdict {
            Verdict::Answer => Reply::Fits(frame.pdu),
            _ => Reply::Malformed(frame.pdu),
        };
        let outcome: Outcome = Ok(Answer::from(reply));
        let (fate, _) = Fate::of(&outcome);
        self.trace_flight(&flight, fate);
        self.trace_frame(Direction::Rx, &frame.bytes, SystemTime::now(), fate.label());
        self.land_outcome(flight, outcome);
    }

    /// Requests past their deadline: sent again (a read with retries left) or answered 0x0B.
    async fn expire<T: Linked>(
        &mut self,
        pipeline: &mut Pipeline<T>,
        flights: &mut Vec<Flight>,
    ) -> io::Result<()> {
        let now = Instant::now();
        let mut index = 0;
        while index < flights.len() {
            if flights[index].deadline > now {
                index += 1;
                continue;
            }
            let mut flight = flights.swap_remove(index);
            self.trace_flight(&flight, Fate::Timeout);
            if flight.attempts > flight.retries || flight.job.abandoned() {
                let outcome = Err(RequestError::NoResponse {
                    attempts: flight.attempts,
                    last: NoReply::Timeout,
                });
                self.land_outcome(flight, outcome);
                continue;
            }
            let (transaction, sent) = match pipeline.send(flight.job.slave, &flight.job.pdu).await {
                Ok((transaction, sent)) => (transaction, sent.to_vec()),
                Err(error) => {
                    self.handle.answer(flight.job, Err(RequestError::PortLost));
                    return Err(error);
                }
            };
            flight.transaction = transaction;
            flight.sent = sent;
            flight.sent_at = SystemTime::now();
            flight.attempts += 1;
            flight.deadline = self.flight_deadline(pipeline, flight.job.slave);
            flights.push(flight);
        }
        Ok(())
    }

    /// The request of `flight` ends in `outcome`: counted, told to the slave's health, kept for
    /// the cache, answered.
    fn land_outcome(&mut self, flight: Flight, outcome: Outcome) {
        let round_trip = flight.first_sent.elapsed();
        self.handle.took_line(&flight.job, round_trip);
        self.handle.metrics.transaction(
            flight.job.slave,
            flight.attempts,
            Some(round_trip),
            &outcome,
        );
        self.record(&flight.job, &outcome);
        self.remember(&flight.job, &outcome);
        self.handle.answer(flight.job, outcome);
    }

    /// The request of `flight`, to the trace, with the fate of its try.
    fn trace_flight(&self, flight: &Flight, fate: Fate) {
        self.trace_frame(Direction::Tx, &flight.sent, flight.sent_at, fate.label());
    }

    fn trace_frame(
        &self,
        direction: Direction,
        bytes: &[u8],
        time: SystemTime,
        outcome: &'static str,
    ) {
        let hub = self.trace.hub();
        if !hub.active() {
            return;
        }
        let (slave, function) = crate::line::Framing::Tcp.header(bytes);
        hub.publish(TraceEvent {
            time,
            bus: self.trace.bus().clone(),
            direction,
            slave: slave.unwrap_or(0),
            function: function.unwrap_or(0),
            bytes: bytes.to_vec(),
            framing: crate::line::Framing::Tcp.name(),
            outcome,
        });
    }
}
