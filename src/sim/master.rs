//! The other master of a simulated listen line (`[bus.sim_master]`): it reads its list in turn
//! for ever, each request once the line has been quiet t3.5 (+ its pause), and waits for the
//! reply by its length or its response timeout. Pure schedule: says when the next request goes
//! out and, given the slave's transmission, when the master is done with it and how it ended;
//! the line ([`super::line`]) puts the bytes on the wire and asks it when a listener polls.

use super::Transmission;
use crate::config;
use crate::line::framing::{Completion, Silence};
use crate::line::{Framing, LineTiming, ReplyForm};
use std::time::Duration;
use tokio::time::Instant;

/// One read of the list, framed once.
pub(crate) struct OtherRead {
    pub(crate) address: u8,
    /// The request PDU: function, first register, count.
    pub(crate) pdu: Vec<u8>,
    /// The request as it goes on the wire, in the line's framing.
    pub(crate) frame: Vec<u8>,
}

/// How the master's wait for a reply ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Ending {
    /// A whole frame by its length from the slave asked, its check good, within the timeout.
    Reply,
    /// A whole frame within the timeout whose check or address is wrong.
    Corrupt,
    /// Nothing whole before the response timeout.
    Timeout,
}

/// The transaction under way: when the master is done with it, how, and when the next may start.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct UnderWay {
    pub(crate) done: Instant,
    pub(crate) outcome: Ending,
    pub(crate) next_start: Instant,
}

/// What the master does next, by the time asked about.
pub(crate) enum Step {
    /// The transaction under way has ended.
    Ended(Ending),
    /// The next request starts at `start`: read `index` of the list.
    Request { start: Instant, index: usize },
}

/// The simulated other master.
pub(crate) struct OtherMaster {
    reads: Vec<OtherRead>,
    pause: Duration,
    response_timeout: Duration,
    framing: Framing,
    /// The next read of the list.
    turn: usize,
    /// When the next request may start; `None` until a listener first opens.
    next_start: Option<Instant>,
    pending: Option<UnderWay>,
}

impl OtherMaster {
    /// The master `config` describes, on a line of `framing`.
    pub(crate) fn new(config: &config::SimMaster, framing: Framing) -> Self {
        let reads = config
            .read
            .iter()
            .map(|read| {
                let [hi, lo] = read.register.to_be_bytes();
                let [count_hi, count_lo] = read.count.to_be_bytes();
                let pdu = vec![read.table.function(), hi, lo, count_hi, count_lo];
                let mut frame = Vec::new();
                framing.encode_into(&mut frame, 0, read.slave, &pdu);
                OtherRead {
                    address: read.slave,
                    pdu,
                    frame,
                }
            })
            .collect();
        OtherMaster {
            reads,
            pause: config.pause,
            response_timeout: config.response_timeout,
            framing,
            turn: 0,
            next_start: None,
            pending: None,
        }
    }

    pub(crate) fn read(&self, index: usize) -> &OtherRead {
        &self.reads[index]
    }

    /// A listener has opened at `now`: the master, which waits while nobody listens, goes on
    /// from where it was, and not before `now`.
    pub(crate) fn resume(&mut self, now: Instant) {
        self.next_start = Some(self.next_start.map_or(now, |at| at.max(now)));
    }

    /// What happens next, if it happens by `now`.
    pub(crate) fn step(&mut self, now: Instant) -> Option<Step> {
        if let Some(pending) = self.pending {
            if pending.done > now {
                return None;
            }
            self.pending = None;
            self.next_start = Some(pending.next_start);
            return Some(Step::Ended(pending.outcome));
        }
        let start = self.next_start.filter(|&at| at <= now)?;
        let index = self.turn;
        self.reads.get(index)?;
        self.turn = (self.turn + 1) % self.reads.len();
        Some(Step::Request { start, index })
    }

    /// When the master next does something, if it is running.
    pub(crate) fn next_event(&self) -> Option<Instant> {
        if self.reads.is_empty() {
            return None;
        }
        self.pending.map(|p| p.done).or(self.next_start)
    }

    /// Read `index`'s request went out from `start` to `end` and `reply` (the slave's
    /// transmission, its first character starting at `reply.0`) came of it, or nothing did.
    pub(crate) fn under_way(
        &mut self,
        index: usize,
        end: Instant,
        reply: Option<(&Transmission, Instant)>,
        timing: &LineTiming,
    ) -> UnderWay {
        let timeout_at = end + self.response_timeout;
        let mut quiet = end;
        let mut ended = None;
        if let Some((transmission, start)) = reply {
            let read = &self.reads[index];
            let bytes = &transmission.bytes;
            let last = arrival(transmission, start, timing.char_time, bytes.len());
            quiet = quiet.max(last);
            let completion =
                self.framing
                    .reply_completion(bytes, read.address, &read.pdu, ReplyForm::Standard);
            ended = match completion {
                Completion::Whole(n) => {
                    let mut pdu = Vec::new();
                    let from = self.framing.decode_into(&bytes[..n], &mut pdu);
                    let outcome = if from == Some(read.address) {
                        Ending::Reply
                    } else {
                        Ending::Corrupt
                    };
                    Some((arrival(transmission, start, timing.char_time, n), outcome))
                }
                // The bytes cannot tell its end: the silence after it does.
                Completion::Open(Silence::EndsFrame) => Some((last + timing.t35, Ending::Reply)),
                Completion::AtLeast(_) | Completion::Open(Silence::FailsFrame) => None,
                Completion::Invalid => None,
            }
            .filter(|&(at, _)| at <= timeout_at);
        }
        let (done, outcome) = ended.unwrap_or((timeout_at, Ending::Timeout));
        let pending = UnderWay {
            done,
            outcome,
            next_start: done.max(quiet + timing.t35) + self.pause,
        };
        self.pending = Some(pending);
        pending
    }
}

/// When the `n`th character of `reply` (from 1), whose first starts at `start`, has fully
/// arrived: after its pause, if it comes after one.
pub(crate) fn arrival(
    reply: &Transmission,
    start: Instant,
    char_time: Duration,
    n: usize,
) -> Instant {
    let chars = u32::try_from(n).unwrap_or(u32::MAX);
    let at = start + char_time.saturating_mul(chars);
    match reply.pause {
        Some(pause) if pause.after > 0 && pause.after < reply.bytes.len() && n > pause.after => {
            at + pause.gap
        }
        _ => at,
    }
}

#[cfg(test)]
#[path = "master_tests.rs"]
mod tests;
