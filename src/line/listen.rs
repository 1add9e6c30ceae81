//! The ear of a listen-only line: another master's requests and its slaves' replies as they come
//! off the wire, cut by the lengths their function codes give (ASCII: by their characters) and
//! by silence, checked (CRC, LRC), and each request paired with the reply that answers it (the
//! slave asked, the request's function code, the shape the request asks for). Pure: fed the bytes
//! with the time they came, it says what was heard; knows nothing of ports, shadows or metrics.

use super::framing::{Completion, Framing, Silence};
use super::reply::{self, ReplyForm, Verdict};
use super::BROADCAST;
use crate::pdu::EXCEPTION_BIT;
use std::time::Duration;
use tokio::time::Instant;

/// One whole frame heard, checked.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct HeardFrame {
    /// As on the wire.
    pub(crate) bytes: Vec<u8>,
    pub(crate) address: u8,
    pub(crate) pdu: Vec<u8>,
    /// When its last byte came.
    pub(crate) end: Instant,
}

impl HeardFrame {
    pub(crate) fn function(&self) -> u8 {
        self.pdu.first().copied().unwrap_or(0)
    }

    pub(crate) fn is_exception(&self) -> bool {
        self.function() & EXCEPTION_BIT != 0
    }
}

/// What the line carried, in the order it came.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) enum Event {
    /// A request and the reply that answered it (normally or with an exception).
    Answered {
        request: HeardFrame,
        reply: HeardFrame,
        /// From the end of the request to the start of the reply, as far as the bytes' times tell.
        response: Duration,
    },
    /// A request that no reply answered before its response timeout, or before the master's
    /// next request.
    Unanswered(HeardFrame),
    /// A request to the broadcast address: no reply is due.
    Broadcast(HeardFrame),
    /// A frame whose check failed. Where the reply to `request` was due, it ends that
    /// transaction.
    Corrupt {
        bytes: Vec<u8>,
        end: Instant,
        request: Option<HeardFrame>,
    },
    /// A good frame that answers no request: a reply to nobody, another slave's reply, a late one.
    Unpaired(HeardFrame),
    /// Bytes that made no frame: cut short by silence, or more than a frame holds.
    Broken { bytes: Vec<u8>, end: Instant },
}

/// How a listen line hears: its framing, its silences, how long a reply may take.
#[derive(Clone, Copy, Debug)]
pub(crate) struct EarTiming {
    /// Silence that ends a frame (at least t3.5 on RTU; ASCII's inter-character timeout).
    pub(crate) silence: Duration,
    /// One character on the wire.
    pub(crate) char_time: Duration,
}

/// The decoder of one listen line.
pub(crate) struct Ear {
    framing: Framing,
    timing: EarTiming,
    /// Per address: how long after a request its reply may start.
    response_timeout: Box<[Duration; 256]>,
    buf: Vec<u8>,
    /// When the last bytes came.
    last: Option<Instant>,
    /// The request whose reply is due.
    pending: Option<HeardFrame>,
    pdu: Vec<u8>,
}

impl Ear {
    pub(crate) fn new(
        framing: Framing,
        timing: EarTiming,
        response_timeout: [Duration; 256],
    ) -> Ear {
        Ear {
            framing,
            timing,
            response_timeout: Box::new(response_timeout),
            buf: Vec::with_capacity(framing.max_frame_len() * 2),
            last: None,
            pending: None,
            pdu: Vec::new(),
        }
    }

    /// New timeouts, after a reload.
    pub(crate) fn set_timing(&mut self, timing: EarTiming, response_timeout: [Duration; 256]) {
        self.timing = timing;
        *self.response_timeout = response_timeout;
    }

    /// When something is due without more bytes: the silence that ends what is held, or the
    /// response timeout of the request waiting.
    pub(crate) fn next_deadline(&self) -> Option<Instant> {
        let silence = self
            .last
            .filter(|_| !self.buf.is_empty())
            .map(|last| last + self.timing.silence);
        // While bytes that claim to be the reply are coming, silence decides, not the timeout.
        let timeout = self
            .pending
            .as_ref()
            .filter(|_| !self.reply_under_way())
            .map(|request| self.reply_due_by(request));
        silence.into_iter().chain(timeout).min()
    }

    fn reply_due_by(&self, request: &HeardFrame) -> Instant {
        request.end + self.response_timeout[usize::from(request.address)]
    }

    /// `bytes` came at `at`: what they complete goes to `out`.
    pub(crate) fn feed(&mut self, bytes: &[u8], at: Instant, out: &mut Vec<Event>) {
        if let Some(last) = self.last {
            if !self.buf.is_empty() && at.saturating_duration_since(last) >= self.timing.silence {
                self.silent(last, out);
            }
        }
        // The first of these bytes started this long before they were all in.
        let start = at
            .checked_sub(self.timing.char_time * u32::try_from(bytes.len()).unwrap_or(u32::MAX))
            .unwrap_or(at);
        if !self.reply_under_way() {
            let at = if self.buf.is_empty() { start } else { at };
            self.expire(at, out);
        }
        self.buf.extend_from_slice(bytes);
        self.last = Some(at);
        self.cut(at, out);
    }

    /// Time has come to `now` with no more bytes: silence ends what is held, and a request past
    /// its response timeout is unanswered.
    pub(crate) fn tick(&mut self, now: Instant, out: &mut Vec<Event>) {
        if let Some(last) = self.last {
            if !self.buf.is_empty() && now.saturating_duration_since(last) >= self.timing.silence {
                self.silent(last, out);
            }
        }
        if !self.reply_under_way() {
            self.expire(now, out);
        }
    }

    /// Whether bytes held claim to be the reply to the request due: its timeout waits for them.
    fn reply_under_way(&self) -> bool {
        !self.buf.is_empty() && self.claims_due()
    }

    /// The port was lost or reopened: what was held is dropped, and the request waiting is
    /// unanswered as far as this ear can tell.
    pub(crate) fn reset(&mut self, out: &mut Vec<Event>) {
        if let Some(request) = self.pending.take() {
            out.push(Event::Unanswered(request));
        }
        self.buf.clear();
        self.last = None;
    }

    fn expire(&mut self, now: Instant, out: &mut Vec<Event>) {
        let due = self.pending.as_ref().map(|r| self.reply_due_by(r));
        if due.is_some_and(|due| now >= due) {
            out.extend(self.pending.take().map(Event::Unanswered));
        }
    }

    /// Silence after the bytes held, which last came at `last`: a frame that only silence ends
    /// is whole, anything else held is broken.
    fn silent(&mut self, last: Instant, out: &mut Vec<Event>) {
        self.cut(last, out);
        if self.buf.is_empty() {
            return;
        }
        let held = self.buf.len();
        let by_itself = self
            .framing
            .reply_completion(&self.buf, 0, &[], ReplyForm::Standard);
        let (whole, reply) = if by_itself == Completion::Whole(held) && !self.claims_due() {
            // A reply the rules for the frame due could not measure: as long as its own bytes say.
            (true, true)
        } else {
            let whole = self.completion() == Completion::Open(Silence::EndsFrame);
            (whole, self.claims_due())
        };
        let bytes = std::mem::take(&mut self.buf);
        if whole {
            self.frame(bytes, last, reply, out);
        } else {
            out.push(Event::Broken { bytes, end: last });
        }
    }

    /// Whether the bytes held claim to be the reply to the request due.
    fn claims_due(&self) -> bool {
        let (address, function) = self.framing.header(&self.buf);
        self.pending
            .as_ref()
            .is_some_and(|request| claims(request, address, function))
    }

    /// How far the bytes held make the frame that is due: the reply to the request waiting if
    /// they claim to be it (its slave, its function code), a request otherwise.
    fn completion(&self) -> Completion {
        let (address, function) = self.framing.header(&self.buf);
        match &self.pending {
            Some(request) if claims(request, address, function) => self.framing.reply_completion(
                &self.buf,
                request.address,
                &request.pdu,
                ReplyForm::Standard,
            ),
            // A reply from another slave is as long as its own bytes say.
            Some(_) if address.is_some() && function.is_none() => Completion::AtLeast(2),
            _ => self.framing.request_completion(&self.buf),
        }
    }

    /// Cut every whole frame off the bytes held.
    fn cut(&mut self, at: Instant, out: &mut Vec<Event>) {
        loop {
            if self.buf.is_empty() {
                return;
            }
            match self.completion() {
                Completion::Whole(n) => {
                    let (n, reply) = match self.as_reply_to_nobody(n) {
                        Some(m) => (m, true),
                        None => (n, self.claims_due()),
                    };
                    let bytes: Vec<u8> = self.buf.drain(..n).collect();
                    self.frame(bytes, at, reply, out);
                }
                Completion::Invalid => {
                    // Not the start of a frame: one byte is noise, the next may start one.
                    let byte = self.buf.remove(0);
                    push_broken(out, byte, at);
                }
                _ if self.buf.len() > self.framing.max_frame_len() => {
                    let bytes = std::mem::take(&mut self.buf);
                    out.push(Event::Broken { bytes, end: at });
                }
                _ => return,
            }
        }
    }

    /// The length of the frame held if it is not the `n` bytes the rules for the frame due say
    /// (they fail their CRC) but a good reply that answers nothing of the ear's (another slave's,
    /// a reply to nobody): its bytes alone tell its length. RTU only: ASCII frames end at CR LF.
    fn as_reply_to_nobody(&self, n: usize) -> Option<usize> {
        if self.framing != Framing::Rtu || super::rtu::crc_ok(&self.buf[..n]) {
            return None;
        }
        match self
            .framing
            .reply_completion(&self.buf, 0, &[], ReplyForm::Standard)
        {
            Completion::Whole(m) if m != n && super::rtu::crc_ok(&self.buf[..m]) => Some(m),
            _ => None,
        }
    }

    /// A whole frame, `bytes`, ended at `end`, cut as a reply (`reply`) or as a request:
    /// checked, and paired if it is the reply due.
    fn frame(&mut self, bytes: Vec<u8>, end: Instant, reply: bool, out: &mut Vec<Event>) {
        let Some(address) = self.framing.decode_into(&bytes, &mut self.pdu) else {
            let (claimed, function) = self.framing.header(&bytes);
            let request = self
                .pending
                .take_if(|request| claims(request, claimed, function));
            out.push(Event::Corrupt {
                bytes,
                end,
                request,
            });
            return;
        };
        let frame = HeardFrame {
            bytes,
            address,
            pdu: std::mem::take(&mut self.pdu),
            end,
        };
        // ASCII frames say nothing of which way they go: one with the exception bit is a reply.
        if reply || !is_request(&frame) {
            self.reply(frame, out);
            return;
        }
        if let Some(request) = self.pending.take() {
            // The master has moved on: its request went unanswered.
            out.push(Event::Unanswered(request));
        }
        if frame.address == BROADCAST {
            out.push(Event::Broadcast(frame));
        } else {
            self.pending = Some(frame);
        }
    }

    /// A good frame cut as a reply: the answer to the request due, or unpaired.
    fn reply(&mut self, frame: HeardFrame, out: &mut Vec<Event>) {
        let Some(request) = self.pending.take() else {
            out.push(Event::Unpaired(frame));
            return;
        };
        let verdict = reply::judge(
            frame.address,
            &frame.pdu,
            request.address,
            &request.pdu,
            ReplyForm::Standard,
        );
        if verdict == Verdict::Answer {
            let on_wire = self.timing.char_time * u32::try_from(frame.bytes.len()).unwrap_or(0);
            let response = frame
                .end
                .saturating_duration_since(request.end)
                .saturating_sub(on_wire);
            out.push(Event::Answered {
                request,
                reply: frame,
                response,
            });
        } else {
            self.pending = Some(request);
            out.push(Event::Unpaired(frame));
        }
    }
}

/// Whether a frame from `address` with `function` claims to answer `request`.
fn claims(request: &HeardFrame, address: Option<u8>, function: Option<u8>) -> bool {
    address == Some(request.address)
        && function.is_some_and(|f| f & !EXCEPTION_BIT == request.function())
}

/// Whether a good frame can be a request: no exception bit.
fn is_request(frame: &HeardFrame) -> bool {
    frame.function() & EXCEPTION_BIT == 0 && frame.function() != 0
}

/// One byte of noise, joined to the noise just before it.
fn push_broken(out: &mut Vec<Event>, byte: u8, at: Instant) {
    if let Some(Event::Broken { bytes, end }) = out.last_mut() {
        if bytes.len() < 256 {
            bytes.push(byte);
            *end = at;
            return;
        }
    }
    out.push(Event::Broken {
        bytes: vec![byte],
        end: at,
    });
}

#[cfg(test)]
#[path = "listen_tests.rs"]
mod tests;
