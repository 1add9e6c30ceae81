//! One request on the line: a broadcast, or a request to one slave with its timeout and the tries
//! the pre-send step (`ready`) gave it. Its end is counted, and told to the slave's health, whose
//! changes the metrics and logs render.

use super::health::{Change, Response};
use super::ready::Cleared;
use super::task::BusTask;
use super::{Job, Port};
use crate::error::{Answer, NoReply, Outcome, RequestError};
use crate::line::{LineMaster, Seen};
use crate::metrics::Fate;
use crate::pdu;
use crate::trace::{Direction, TraceEvent, FOREIGN, STALE};
use std::io;
use tokio::time::Instant;
use tracing::{debug, error, warn};

/// How one request on the line ended.
pub(super) enum Ran {
    /// The request's outcome, to answer it with.
    Done(Outcome),
    /// The port is gone: this request and the port's other users get 0x0A.
    PortLost(io::Error),
    /// The request's outcome, and the connection must be made anew: a device matched by order
    /// (`match_transaction_id = false`) timed out, and its late answer could not be told from
    /// the next request's.
    Reset(Outcome),
}

impl Response {
    /// What a request's outcome says of its slave.
    fn of(outcome: &Outcome) -> Response {
        match outcome {
            Ok(_) => Response::Answered,
            Err(RequestError::NoResponse {
                last: NoReply::Timeout,
                ..
            }) => Response::TimedOut,
            Err(RequestError::NoResponse {
                last: NoReply::LineBusy,
                ..
            }) => Response::Unsent,
            Err(_) => Response::Garbled,
        }
    }
}

impl BusTask {
    /// Run one request the pre-send step cleared on the line, with the tries it was given; no
    /// retry starts after `stop_at`.
    pub(super) async fn execute(
        &mut self,
        master: &mut LineMaster<Port>,
        cleared: &Cleared,
        stop_at: Option<Instant>,
    ) -> Ran {
        let (job, retries) = (&cleared.job, cleared.retries);
        // The one cost of the trace with nobody watching: this load.
        let tracing = self.trace.hub().active();
        master.record_frames(tracing);
        if cleared.broadcast {
            return self.broadcast(master, job, tracing).await;
        }
        let timeout = self.current.derived.timeouts[usize::from(job.slave)];
        let mut attempts = 0;
        let mut first_sent_at = None;
        let outcome = loop {
            attempts += 1;
            self.handle.beat();
            let previous = master.sent_at();
            let result = master.transact(job.slave, &job.pdu, timeout).await;
            if tracing {
                self.trace_try(master, Fate::of_try(&result));
            }
            if master.sent_at() != previous {
                first_sent_at.get_or_insert(master.sent_at());
            }
            let failed = match result {
                Ok(reply) => break Ok(Answer::from(reply)),
                Err(error) => NoReply::try_from(error),
            };
            match failed {
                Err(lost) => return Ran::PortLost(lost),
                Ok(NoReply::ModbusTcp) => {
                    self.wrong_mode();
                    break Err(RequestError::NoResponse {
                        attempts,
                        last: NoReply::ModbusTcp,
                    });
                }
                Ok(last)
                    if attempts > retries
                        || job.abandoned()
                        || stop_at.is_some_and(|at| Instant::now() >= at) =>
                {
                    break Err(RequestError::NoResponse { attempts, last });
                }
                Ok(error) => {
                    debug!(bus = &*self.handle.name, slave = job.slave, attempts, %error, "retrying");
                }
            }
        };
        // A request the line was always too busy to send has no round trip.
        let round_trip = first_sent_at.map(|sent| sent.elapsed());
        self.handle.took_line(job, round_trip.unwrap_or_default());
        self.handle
            .metrics
            .transaction(job.slave, attempts, round_trip, &outcome);
        self.record(job, &outcome);
        if let Some((sent, got)) = master.take_transaction_mismatch() {
            self.transaction_mismatch(sent, got);
        }
        let timed_out = matches!(
            outcome,
            Err(RequestError::NoResponse {
                last: NoReply::Timeout,
                ..
            })
        );
        if timed_out && !self.current.settings.match_transaction_id {
            return Ran::Reset(outcome);
        }
        Ran::Done(outcome)
    }

    /// A Modbus TCP device answered with another transaction id than its request's, where no
    /// late answer could have come: said once per connection, with the key that helps.
    fn transaction_mismatch(&mut self, sent: u16, got: u16) {
        if std::mem::replace(&mut self.told_mismatch, true) {
            return;
        }
        warn!(
            bus = &*self.handle.name,
            device = self.current.settings.device,
            sent,
            got,
            "the device answered a request with another transaction id than the request's, so \
             its answers are discarded (0x0B after the timeout); if it always does, set \
             match_transaction_id = false on this bus to match its answers by order"
        );
    }

    /// The device answered in Modbus TCP: said once per connection, at error level, with the fix
    /// (retrying cannot cure it, so the request is not retried).
    fn wrong_mode(&mut self) {
        if std::mem::replace(&mut self.told_wrong_mode, true) {
            return;
        }
        error!(
            bus = &*self.handle.name,
            device = self.current.settings.device,
            "the device answers in Modbus TCP (MBAP), not with the line's frames: set the device \
             server to raw (transparent) TCP mode, its Modbus TCP gateway mode off; a Modbus TCP \
             device is not a serial line's device. Its requests get exception 0x0B"
        );
    }

    /// Send a broadcast; its answer, if the configuration wants one, is the gateway's own.
    async fn broadcast(&mut self, master: &mut LineMaster<Port>, job: &Job, tracing: bool) -> Ran {
        let settings = &self.current.settings;
        let sent = master
            .broadcast(
                &job.pdu,
                settings.turnaround_delay,
                settings.response_timeout,
            )
            .await;
        if tracing {
            let fate = sent
                .as_ref()
                .map_or_else(Fate::of_failed_try, |()| Fate::Ok);
            self.trace_try(master, fate);
        }
        Ran::Done(match sent.map_err(NoReply::try_from) {
            Ok(()) => Ok(settings
                .broadcast_reply
                .then(|| pdu::broadcast_response(&job.pdu))
                .flatten()
                .map_or(Answer::Nothing, Answer::Reply)),
            Err(Err(lost)) => return Ran::PortLost(lost),
            Err(Ok(last)) => Err(RequestError::NoResponse { attempts: 1, last }),
        })
    }

    /// Publish the frames of the try that just ended, which ended as `fate`, to the trace.
    fn trace_try(&self, master: &mut LineMaster<Port>, fate: Fate) {
        let hub = self.trace.hub();
        for frame in master.recorded() {
            hub.publish(TraceEvent {
                time: frame.at,
                bus: self.trace.bus().clone(),
                direction: match frame.seen {
                    Seen::Sent => Direction::Tx,
                    Seen::Reply | Seen::Foreign | Seen::Stale => Direction::Rx,
                },
                slave: frame.address,
                function: frame.function,
                bytes: frame.bytes,
                framing: self.current.derived.framing.name(),
                outcome: match frame.seen {
                    Seen::Foreign => FOREIGN,
                    Seen::Stale => STALE,
                    Seen::Sent | Seen::Reply => fate.label(),
                },
            });
        }
    }

    /// Tell the slave's health how the request ended, and the metrics what changed; an answer
    /// shows the port serves.
    pub(super) fn record(&mut self, job: &Job, outcome: &Outcome) {
        self.record_of(job.slave, job.function(), Response::of(outcome), outcome);
    }

    /// [`BusTask::record`] for a request to `slave` of `function` that got `response`, as
    /// `outcome` says it.
    pub(super) fn record_of(
        &mut self,
        slave: u8,
        function: u8,
        response: Response,
        outcome: &Outcome,
    ) {
        let down = self.current.derived.down;
        if response == Response::Answered {
            self.served();
        }
        let change = self
            .health
            .record(slave, function, response, Instant::now(), down);
        let metrics = &self.handle.metrics;
        match change {
            Change::None => {}
            Change::Answering => metrics.slave_answering(slave, false),
            Change::Up => metrics.slave_answering(slave, true),
            Change::Failing => metrics.slave_failing(slave, outcome),
            Change::Down { timeouts } => {
                metrics.slave_down(slave, timeouts, down.probe_interval);
            }
        }
    }
}
