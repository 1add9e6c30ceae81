//! One transaction at a time on a [`Transport`], timed per Modbus over Serial Line V1.02: a gap
//! of silence before every frame, the response timeout counted from the end of transmission,
//! replies complete when the [`Framing`] says so (by length, or by silence when the length cannot
//! be known), and only a frame that answers the request is ever returned. Retries, queues and
//! broadcast policy belong to the caller; what frames look like on the wire belongs to the
//! framing, and what a reply means to [`reply`].
//!
//! Serial frames carry no transaction id, so a slave's reply that comes after its try gave up
//! could pass for the answer to the next request to it. The master keeps, per slave, until when
//! such a late reply may still come (its late-reply window): after a try that ended in silence
//! (or in other slaves' frames), one more response timeout. A try the slave itself ended with a
//! frame (an answer, a malformed reply, a frame failing its check) opens none. While a window is
//! open, a frame that does not fit the request is taken for that late reply and discarded; once
//! it is closed, such a frame can only be the slave's own answer and is returned as
//! [`Reply::Malformed`].

use super::framing::{Completion, Framing, Silence};
use super::reply::{self, ReplyForm, Verdict};
use super::timing::LineTiming;
use super::{Transport, BROADCAST};
use crate::timer::LineTimer;
use std::io;
use std::time::Duration;
use tokio::time::Instant;

mod record;
pub(crate) use record::LineCounters;
pub(crate) use record::{RecordedFrame, Seen};

/// The times the master keeps on its line.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct MasterTiming {
    pub line: LineTiming,
    /// Silence before every frame: t3.5, or more if configured.
    pub gap: Duration,
    /// Silence that ends a reply whose length the bytes cannot tell: t3.5, or more if configured
    /// (USB adapters deliver bytes in bursts). The allowance for bursts past a known length too.
    pub silence: Duration,
    /// Behind a serial device server: how long its packing timer may hold a reply's bytes back
    /// (`packing_delay`). Added to every reply's deadline; [`MasterTiming::silence`] includes it.
    pub packing: Duration,
}

impl MasterTiming {
    /// The spec's timing for `line`, raised by the configured floors where they are longer.
    pub(crate) fn new(line: LineTiming, gap_floor: Duration, silence_floor: Duration) -> Self {
        MasterTiming {
            line,
            gap: line.t35.max(gap_floor),
            silence: line.t35.max(silence_floor),
            packing: Duration::ZERO,
        }
    }

    /// This timing on a line whose device server may hold a reply's bytes back for `packing`:
    /// a reply may fall silent that much longer mid-way, and may start that much later.
    pub(crate) fn with_packing(self, packing: Duration) -> Self {
        MasterTiming {
            silence: self.silence - self.packing + packing,
            packing,
            ..self
        }
    }
}

/// The slave's answer to a request: its PDU, byte for byte.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Reply {
    /// A normal reply or an exception that fits the request.
    Fits(Vec<u8>),
    /// From the slave, with the request's function code, but not the shape the request asks for
    /// (byte count, echo), at a time no late reply from the slave could be pending.
    Malformed(Vec<u8>),
}

/// Why a try got no valid reply, when it was not the port's loss: what a request's error keeps
/// of a [`TxError`] (a `Copy` value). The one place these messages are written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum NoReply {
    #[error("no reply to this request within the response timeout")]
    Timeout,
    /// The frame's check failed (the name and message predate framings other than RTU).
    #[error("reply failed its check (CRC-16 on RTU, LRC on ASCII)")]
    Check,
    #[error("reply incomplete, or longer than a frame")]
    Frame,
    #[error("line never fell silent for the gap before the frame")]
    LineBusy,
    /// On a line that echoes (`rs485.echo`): the frame did not come back as sent, in time.
    #[error("the line did not echo the frame as sent (a collision, or no echo)")]
    Echo,
    /// The bytes back are a Modbus TCP (MBAP) answer to the frame: a device server running its
    /// own Modbus TCP gateway rather than carrying the line's bytes.
    #[error(
        "the reply is a Modbus TCP (MBAP) frame: the device server is not in raw (transparent) mode"
    )]
    ModbusTcp,
}

/// How one try failed: as [`NoReply`] says, or the port was lost.
#[derive(Debug, thiserror::Error)]
pub enum TxError {
    #[error("{}", NoReply::Timeout)]
    Timeout,
    #[error("{}", NoReply::Check)]
    Check,
    #[error("{}", NoReply::Frame)]
    Frame,
    #[error("{}", NoReply::LineBusy)]
    LineBusy,
    #[error("{}", NoReply::Echo)]
    Echo,
    #[error("{}", NoReply::ModbusTcp)]
    ModbusTcp,
    #[error("serial port lost: {0}")]
    PortLost(io::Error),
}

/// A failed try's [`NoReply`], or the `io::Error` of a lost port.
impl TryFrom<TxError> for NoReply {
    type Error = io::Error;

    fn try_from(error: TxError) -> Result<NoReply, io::Error> {
        match error {
            TxError::Timeout => Ok(NoReply::Timeout),
            TxError::Check => Ok(NoReply::Check),
            TxError::Frame => Ok(NoReply::Frame),
            TxError::LineBusy => Ok(NoReply::LineBusy),
            TxError::Echo => Ok(NoReply::Echo),
            TxError::ModbusTcp => Ok(NoReply::ModbusTcp),
            TxError::PortLost(lost) => Err(lost),
        }
    }
}

/// Frames recorded for the trace at most between two tries, when they are stray bytes: the rest
/// are only counted.
const MAX_STALE_RECORDS: usize = 32;

pub(crate) struct LineMaster<T> {
    port: T,
    framing: Framing,
    timing: MasterTiming,
    /// Earliest moment the next frame may start: the last byte seen on the line plus the gap, or
    /// the end of a broadcast plus its turnaround delay.
    quiet_until: Instant,
    /// When the last frame was handed to the port.
    sent_at: Instant,
    tx: Vec<u8>,
    rx: Vec<u8>,
    /// The PDU of the last frame decoded.
    pdu: Vec<u8>,
    counters: LineCounters,
    /// How each slave address shapes its replies.
    forms: Box<[ReplyForm; 256]>,
    /// Per slave address: until when a reply to one of its earlier tries may still come.
    late_until: Box<[Option<Instant>; 256]>,
    /// The line hands back every byte sent (`rs485.echo`).
    echo: bool,
    /// The transaction id of the last frame sent, in a framing that has them.
    transaction: u16,
    /// Whether a reply must carry the transaction id of its request (`match_transaction_id`);
    /// off, the one request in flight takes whatever answers it, by unit and function.
    match_transaction: bool,
    /// When a try on a framing with transaction ids last timed out: until twice the timeout
    /// after it, a reply with another transaction id may be its late answer.
    timed_out_at: Option<Instant>,
    /// A reply that answered the request in all but its transaction id, at a time no late
    /// answer could come: (the id sent, the id it carried). Taken by the caller.
    mismatch: Option<(u16, u16)>,
    timer: LineTimer,
    /// Whether frames are recorded for the trace: only while someone watches, so that the line
    /// copies nothing otherwise.
    recording: bool,
    recorded: Vec<RecordedFrame>,
}

fn device_gone() -> io::Error {
    io::Error::new(
        io::ErrorKind::UnexpectedEof,
        "the port reads 0 bytes (device gone)",
    )
}

fn port_lost(result: io::Result<usize>) -> Result<usize, TxError> {
    match result {
        Ok(0) => Err(TxError::PortLost(device_gone())),
        Ok(n) => Ok(n),
        Err(e) => Err(TxError::PortLost(e)),
    }
}

impl<T: Transport> LineMaster<T> {
    /// A master on a freshly opened port whose line is framed by `framing`. What the line was
    /// doing before is unknown, so the first frame waits a full gap.
    pub(crate) fn new(port: T, framing: Framing, timing: MasterTiming) -> Self {
        LineMaster {
            port,
            framing,
            timing,
            quiet_until: Instant::now() + timing.gap,
            sent_at: Instant::now(),
            tx: Vec::with_capacity(framing.max_frame_len()),
            rx: Vec::with_capacity(framing.max_frame_len()),
            pdu: Vec::with_capacity(crate::pdu::MAX_PDU_LEN),
            counters: LineCounters::default(),
            forms: Box::new([ReplyForm::Standard; 256]),
            late_until: Box::new([None; 256]),
            echo: false,
            transaction: 0,
            match_transaction: true,
            timed_out_at: None,
            mismatch: None,
            timer: LineTimer::new(),
            recording: false,
            recorded: Vec::new(),
        }
    }

    /// Keep to `timing` from the next frame on (a reconfigured line in the same format).
    pub(crate) fn set_timing(&mut self, timing: MasterTiming) {
        self.timing = timing;
    }

    /// Whether the line echoes every frame sent: then each frame is read back, and must come
    /// back as sent, before its reply.
    pub(crate) fn set_echo(&mut self, echo: bool) {
        self.echo = echo;
    }

    /// Whether a reply must carry its request's transaction id (in a framing that has them).
    pub(crate) fn set_match_transaction(&mut self, on: bool) {
        self.match_transaction = on;
    }

    /// A reply that answered a request in all but its transaction id, since the last call: the
    /// id sent and the id it carried.
    pub(crate) fn take_transaction_mismatch(&mut self) -> Option<(u16, u16)> {
        self.mismatch.take()
    }

    /// Expect replies from `slave` in `form`; its answers are still returned in standard form.
    pub(crate) fn set_reply_form(&mut self, slave: u8, form: ReplyForm) {
        self.forms[usize::from(slave)] = form;
    }

    /// Record the frames on the wire from now on (for the trace), or stop.
    pub(crate) fn record_frames(&mut self, on: bool) {
        self.recording = on;
    }

    /// The frames recorded since the last call, oldest first.
    pub(crate) fn recorded(&mut self) -> std::vec::Drain<'_, RecordedFrame> {
        self.recorded.drain(..)
    }

    pub(crate) fn counters(&self) -> LineCounters {
        self.counters
    }

    /// The transport the master drives.
    pub(crate) fn port(&self) -> &T {
        &self.port
    }

    /// When the last frame was handed to the port: the start of its transaction on the wire.
    /// The earliest the next frame may start, as far as is known now (stray bytes may push it
    /// back).
    pub(crate) fn quiet_until(&self) -> Instant {
        self.quiet_until
    }

    pub(crate) fn sent_at(&self) -> Instant {
        self.sent_at
    }

    /// Keep the line quiet until at least `until` before the next frame, reading (and counting)
    /// whatever arrives meanwhile, as after any stray bytes.
    pub(crate) fn keep_quiet_until(&mut self, until: Instant) {
        self.quiet_until = self.quiet_until.max(until);
    }

    /// A reply from `slave` may still come until `until`.
    pub(crate) fn expect_late_reply(&mut self, slave: u8, until: Instant) {
        let window = &mut self.late_until[usize::from(slave)];
        *window = Some(window.map_or(until, |open| open.max(until)));
    }

    /// Watch the line while no transaction runs: stray bytes push the next frame back by a gap.
    /// Returns how many arrived, or the error when the port is lost. Cancel-safe.
    pub(crate) async fn watch_idle(&mut self) -> io::Result<usize> {
        self.rx.clear();
        match self.port.recv(&mut self.rx).await {
            Ok(0) => Err(device_gone()),
            Ok(n) => {
                self.saw_stray_bytes(n);
                Ok(n)
            }
            Err(e) => Err(e),
        }
    }

    /// The last `n` bytes in `rx` came while no reply was awaited: counted, shown in the trace,
    /// and the gap starts again.
    fn saw_stray_bytes(&mut self, n: usize) {
        self.counters.stray_bytes += n as u64;
        self.counters.received_bytes += n as u64;
        // Never sooner than the line was to be quiet anyway (a broadcast's turnaround, a settle).
        self.quiet_until = self.quiet_until.max(Instant::now() + self.timing.gap);
        // Bounded: a line that babbles while nobody asks anything would grow the record until
        // the next try publishes it.
        if self.recording && self.recorded.len() < MAX_STALE_RECORDS {
            let bytes = &self.rx[self.rx.len() - n..];
            let (address, function) = self.framing.header(bytes);
            let (address, function) = (address.unwrap_or(0), function.unwrap_or(0));
            let frame = RecordedFrame::new(Seen::Stale, address, function, bytes);
            self.recorded.push(frame);
        }
    }

    /// Send `request` (a PDU) to `slave` and return the PDU of the frame that answers it, a normal
    /// reply or the slave's exception, byte for byte. Does not wait for the slave's late-reply
    /// window: a retry of the same request may take the late reply to its first try, which has
    /// the same form and the right data.
    pub(crate) async fn transact(
        &mut self,
        slave: u8,
        request: &[u8],
        response_timeout: Duration,
    ) -> Result<Reply, TxError> {
        let end_of_tx = self.send_frame(slave, request, response_timeout).await?;
        self.rx.clear();
        let result = match self.take_echo(end_of_tx + response_timeout).await {
            Ok(()) => {
                self.read_reply(slave, request, end_of_tx, response_timeout)
                    .await
            }
            Err(error) => Err(error),
        };
        let serial = self.framing.transaction(&self.tx).is_none();
        let result = match result {
            Err(TxError::Check | TxError::Frame)
                if serial && reply::is_mbap_reply(&self.rx, &self.tx) =>
            {
                Err(TxError::ModbusTcp)
            }
            result => result,
        };
        if !serial {
            // Its transaction id tells a late reply from this try's: no window is needed.
            if matches!(result, Err(TxError::Timeout)) {
                self.timed_out_at = Some(Instant::now());
            }
            return result;
        }
        match &result {
            // Silence, or only other frames: the slave may still answer. So may it when the
            // echo failed: the request may have reached it.
            Err(TxError::Timeout | TxError::Echo) => {
                self.expect_late_reply(slave, Instant::now() + response_timeout);
            }
            // Taken while an earlier try's reply could still come: it may have been that reply,
            // so this try's own may follow, as late as an earlier one could.
            Ok(_) if self.late_reply_window(slave).is_some() => {
                self.expect_late_reply(slave, end_of_tx + 2 * response_timeout);
            }
            _ => {}
        }
        result
    }

    /// Send `request` to every slave and return once its last byte has left the wire. Nobody
    /// answers; the line stays silent for `turnaround` after the frame so slaves can carry it out.
    pub(crate) async fn broadcast(
        &mut self,
        request: &[u8],
        turnaround: Duration,
        busy_limit: Duration,
    ) -> Result<(), TxError> {
        let end_of_tx = self.send_frame(BROADCAST, request, busy_limit).await?;
        self.quiet_until = self.quiet_until.max(end_of_tx + turnaround);
        self.rx.clear();
        self.take_echo(end_of_tx + turnaround.max(self.timing.silence))
            .await?;
        self.timer.sleep_until(end_of_tx).await;
        Ok(())
    }

    /// On a line that echoes: read back the frame just sent, by `deadline`. Bytes past it stay
    /// in `rx`, the start of the reply; the echo is neither a reply nor stray.
    async fn take_echo(&mut self, deadline: Instant) -> Result<(), TxError> {
        if !self.echo {
            return Ok(());
        }
        let len = self.tx.len();
        while self.rx.len() < len {
            if self.rx[..] != self.tx[..self.rx.len()] {
                return Err(TxError::Echo);
            }
            tokio::select! {
                biased;
                received = self.port.recv(&mut self.rx) => {
                    self.counters.received_bytes += port_lost(received)? as u64;
                    self.quiet_until = self.quiet_until.max(Instant::now() + self.timing.gap);
                }
                () = self.timer.sleep_until(deadline) => return Err(TxError::Echo),
            }
        }
        if self.rx[..len] != self.tx[..] {
            return Err(TxError::Echo);
        }
        self.rx.drain(..len);
        Ok(())
    }

    /// Wait for the gap, clear the input, send, and return when the last byte will have left the
    /// wire (the kernel returns from write() before that).
    async fn send_frame(
        &mut self,
        address: u8,
        pdu: &[u8],
        busy_limit: Duration,
    ) -> Result<Instant, TxError> {
        self.wait_for_gap(busy_limit).await?;
        self.transaction = self.transaction.wrapping_add(1);
        self.framing
            .encode_into(&mut self.tx, self.transaction, address, pdu);
        self.port.send(&self.tx).await.map_err(TxError::PortLost)?;
        let returned = Instant::now();
        if self.recording {
            let function = pdu.first().copied().unwrap_or(0);
            let frame = RecordedFrame::new(Seen::Sent, address, function, &self.tx);
            self.recorded.push(frame);
        }
        self.counters.sent_bytes += self.tx.len() as u64;
        let frame_time = self.timing.line.frame_time(self.tx.len());
        let end_of_tx = self.port.end_of_transmission(returned, frame_time);
        self.sent_at = end_of_tx.checked_sub(frame_time).unwrap_or(returned);
        self.quiet_until = end_of_tx + self.timing.gap;
        Ok(end_of_tx)
    }

    /// Wait until the line has been silent for the gap, reading (and discarding) whatever
    /// arrives meanwhile, since every byte restarts the gap, then clear the input. Bytes the
    /// clearing finds (a socket can tell) were on the line too: counted, and the gap starts
    /// again. Gives up if stray bytes keep the line busy for `busy_limit` past the moment it
    /// should have been quiet.
    async fn wait_for_gap(&mut self, busy_limit: Duration) -> Result<(), TxError> {
        let give_up_at = self.quiet_until.max(Instant::now()) + busy_limit;
        loop {
            self.rx.clear();
            // Bytes already in were on the line, even when the gap looks over by the clock: a
            // port (or a USB adapter) may hand them over late. They restart the gap.
            let over = Instant::now() >= self.quiet_until;
            let quiet = tokio::select! {
                biased;
                received = self.port.recv(&mut self.rx) => {
                    let n = port_lost(received)?;
                    self.saw_stray_bytes(n);
                    false
                }
                () = self.timer.sleep_until(self.quiet_until), if !over => true,
                () = std::future::ready(()), if over => true,
            };
            if quiet {
                self.port
                    .clear_input(&mut self.rx)
                    .map_err(TxError::PortLost)?;
                if self.rx.is_empty() {
                    return Ok(());
                }
                self.saw_stray_bytes(self.rx.len());
            }
            if self.quiet_until > give_up_at {
                return Err(TxError::LineBusy);
            }
        }
    }

    async fn read_reply(
        &mut self,
        slave: u8,
        request: &[u8],
        end_of_tx: Instant,
        response_timeout: Duration,
    ) -> Result<Reply, TxError> {
        let form = self.forms[usize::from(slave)];
        // The reply must start within the response timeout; once it has, it gets the time its
        // length needs on the wire, plus the silence allowance for bursty adapters.
        let first_byte_by = end_of_tx + response_timeout + self.timing.packing;
        let mut last_byte_at = end_of_tx;
        loop {
            let completion = self
                .framing
                .reply_completion(&self.rx, slave, request, form);
            let wait_until = match completion {
                Completion::Whole(n) => {
                    match self.judge(n, slave, request, (form, response_timeout)) {
                        Some(reply) => return self.ended(reply, last_byte_at),
                        None => {
                            self.rx.drain(..n);
                            continue;
                        }
                    }
                }
                _ if self.rx.is_empty() => first_byte_by,
                Completion::Invalid => return self.frame_error(),
                Completion::AtLeast(n) => {
                    first_byte_by + self.timing.line.frame_time(n) + self.timing.silence
                }
                Completion::Open(_) => last_byte_at + self.timing.silence,
            };
            if self.rx.len() > self.framing.max_frame_len() {
                return self.frame_error();
            }
            // Bytes first: a reply whose last byte is in when the deadline comes is still in time.
            tokio::select! {
                biased;
                received = self.port.recv(&mut self.rx) => {
                    self.counters.received_bytes += port_lost(received)? as u64;
                    last_byte_at = Instant::now();
                    // Never sooner than the request's own end on the wire and its gap: bytes that
                    // come before it (noise, a converter's junk) say nothing of the request.
                    self.quiet_until = self.quiet_until.max(last_byte_at + self.timing.gap);
                }
                () = self.timer.sleep_until(wait_until) => {
                    if self.rx.is_empty() {
                        return Err(TxError::Timeout);
                    }
                    if completion != Completion::Open(Silence::EndsFrame) {
                        return self.frame_error();
                    }
                    match self.judge(self.rx.len(), slave, request, (form, response_timeout)) {
                        Some(reply) => return self.ended(reply, last_byte_at),
                        None => self.rx.clear(),
                    }
                }
            }
        }
    }

    /// The try ends as `judged`. A reply that answers the request shows that the slave had the
    /// whole request, which has then left the wire: the next frame waits for the gap after the
    /// reply's last byte (`last_byte_at`) alone. Anything else shows nothing, and the next frame
    /// waits for the request's end on the wire too.
    fn ended(
        &mut self,
        judged: Result<Reply, TxError>,
        last_byte_at: Instant,
    ) -> Result<Reply, TxError> {
        if judged.is_ok() {
            self.quiet_until = last_byte_at + self.timing.gap;
        }
        judged
    }
}

impl<T> LineMaster<T> {
    /// Every slave's late-reply window still open, to carry over to the master of a reopened port
    /// (a reply to a request of before may still come through it).
    pub(crate) fn late_reply_windows(&self) -> Vec<(u8, Instant)> {
        let now = Instant::now();
        (0..=u8::MAX)
            .filter_map(|slave| {
                let until = self.late_until[usize::from(slave)]?;
                (until > now).then_some((slave, until))
            })
            .collect()
    }

    /// Until when a reply to an earlier try to `slave` may still come, if that is later than now.
    /// A new request to `slave` should not go out before then: the late reply could pass for its
    /// answer.
    pub(crate) fn late_reply_window(&self, slave: u8) -> Option<Instant> {
        self.late_until[usize::from(slave)].filter(|&until| until > Instant::now())
    }

    /// What the complete frame in the first `len` bytes received means for the request waiting
    /// on `slave`: its reply or the error that ends the try, or `None` when the frame answers
    /// nothing here (counted, and to be dropped) and the wait goes on.
    fn judge(
        &mut self,
        len: usize,
        slave: u8,
        request: &[u8],
        (form, response_timeout): (ReplyForm, Duration),
    ) -> Option<Result<Reply, TxError>> {
        let late_reply_possible = self.late_reply_window(slave).is_some();
        let Some(address) = self.framing.decode_into(&self.rx[..len], &mut self.pdu) else {
            self.record_undecoded(len);
            return Some(Err(TxError::Check));
        };
        let pdu = &self.pdu;
        // A reply to another transaction (a try that timed out) answers nothing here.
        let sent = self.framing.transaction(&self.tx);
        let got = self.framing.transaction(&self.rx[..len]);
        let verdict = reply::judge(address, pdu, slave, request, form);
        let verdict = match (sent, got) {
            (Some(sent), Some(got)) if self.match_transaction && sent != got => {
                let late_answer_possible = self
                    .timed_out_at
                    .is_some_and(|at| at.elapsed() < 2 * response_timeout);
                if verdict == Verdict::Answer && !late_answer_possible {
                    self.mismatch = Some((sent, got));
                }
                Verdict::Foreign
            }
            _ => verdict,
        };
        let judged = match verdict {
            Verdict::Answer => Some(Ok(Reply::Fits(reply::answer_pdu(pdu, form)))),
            Verdict::Malformed if !late_reply_possible => {
                Some(Ok(Reply::Malformed(reply::answer_pdu(pdu, form))))
            }
            Verdict::Malformed | Verdict::Foreign => {
                self.counters.foreign_frames += 1;
                None
            }
            #[cfg(test)]
            Verdict::Corrupt => Some(Err(TxError::Check)),
        };
        if self.recording {
            let seen = if judged.is_some() {
                Seen::Reply
            } else {
                Seen::Foreign
            };
            let function = self.pdu.first().copied().unwrap_or(0);
            let frame = RecordedFrame::new(seen, address, function, &self.rx[..len]);
            self.recorded.push(frame);
        }
        judged
    }

    /// The try ends with bytes that make no frame: recorded as they came.
    fn frame_error(&mut self) -> Result<Reply, TxError> {
        self.record_undecoded(self.rx.len());
        Err(TxError::Frame)
    }

    /// Record the first `len` bytes received, which end the try but are no valid frame.
    fn record_undecoded(&mut self, len: usize) {
        if self.recording {
            let bytes = &self.rx[..len];
            let (address, function) = self.framing.header(bytes);
            let (address, function) = (address.unwrap_or(0), function.unwrap_or(0));
            let frame = RecordedFrame::new(Seen::Reply, address, function, bytes);
            self.recorded.push(frame);
        }
    }
}

#[cfg(test)]
mod ascii_tests;

#[cfg(test)]
mod echo_tests;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::rtu;
    use crate::line::{Parity, SerialFormat};
    use crate::sim::{Scripted, SimLine, SimPort, Transmission};

    /// tokio's timer wakes sleepers on whole milliseconds, paused clock included.
    const TIMER_RESOLUTION: Duration = Duration::from_millis(1);
    const TIMEOUT: Duration = Duration::from_millis(100);
    const FOREVER: Duration = Duration::from_secs(3600);
    /// Read two holding registers from 0004H (Goodrive300 manual 10.4.1).
    const READ: [u8; 5] = [0x03, 0x00, 0x04, 0x00, 0x02];
    /// Its answer: 0004H = 1388H, 0005H = 0.
    const READ_ANSWER: [u8; 6] = [0x03, 0x04, 0x13, 0x88, 0x00, 0x00];

    fn reply(address: u8, pdu: &[u8], delay: Duration) -> Option<Transmission> {
        Some(Transmission::frame(address, pdu, delay))
    }

    fn line(slaves: Vec<(u8, Vec<Option<Transmission>>)>) -> (SimLine, LineMaster<SimPort>) {
        let line = SimLine::new(LineTiming::new(&SerialFormat {
            baud: 9600,
            data_bits: 8,
            parity: Parity::Even,
            stop_bits: 1,
        }));
        for (address, plan) in slaves {
            line.add_slave(address, Scripted::new(plan));
        }
        let timing = MasterTiming::new(line.timing(), Duration::ZERO, Duration::ZERO);
        let master = LineMaster::new(line.open().unwrap(), Framing::Rtu, timing);
        (line, master)
    }

    /// Sends one request and returns the outcome with the time from the end of transmission.
    async fn timed(
        master: &mut LineMaster<SimPort>,
        slave: u8,
        request: &[u8],
        timeout: Duration,
    ) -> (Result<Reply, TxError>, Duration) {
        master.wait_for_gap(FOREVER).await.unwrap();
        let sent_at = Instant::now();
        let result = master.transact(slave, request, timeout).await;
        let end_of_tx = sent_at + master.timing.line.frame_time(request.len() + 3);
        (result, Instant::now() - end_of_tx)
    }

    #[tokio::test(start_paused = true)]
    async fn a_silent_slave_times_out_after_its_timeout_counted_from_the_end_of_transmission() {
        let (_line, mut master) = line(vec![(1, vec![None])]);
        let (result, after) = timed(&mut master, 1, &READ, TIMEOUT).await;
        assert!(matches!(result, Err(TxError::Timeout)), "{result:?}");
        assert!(
            after >= TIMEOUT,
            "gave up {after:?} after the frame, before the timeout"
        );
        assert!(
            after <= TIMEOUT + TIMER_RESOLUTION,
            "gave up late: {after:?}"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn an_exception_is_returned_as_soon_as_its_five_bytes_are_in() {
        let (line, mut master) = line(vec![(1, vec![reply(1, &[0x83, 0x02], Duration::ZERO)])]);
        let (result, after) = timed(&mut master, 1, &READ, FOREVER).await;
        assert_eq!(result.unwrap(), Reply::Fits(vec![0x83, 0x02]));
        let timing = line.timing();
        assert!(
            after <= timing.t35 + timing.frame_time(5) + TIMER_RESOLUTION,
            "{after:?}"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn vendor_exception_codes_pass_unchanged() {
        let (_line, mut master) = line(vec![(1, vec![reply(1, &[0x86, 0x07], Duration::ZERO)])]);
        let result = master
            .transact(1, &[0x06, 0x20, 0x00, 0x00, 0x01], FOREVER)
            .await;
        assert_eq!(result.unwrap(), Reply::Fits(vec![0x86, 0x07]));
    }

    #[tokio::test(start_paused = true)]
    async fn a_reply_from_another_address_is_discarded() {
        let (_line, mut master) = line(vec![(1, vec![reply(9, &READ_ANSWER, Duration::ZERO)])]);
        let result = master.transact(1, &READ, TIMEOUT).await;
        assert!(matches!(result, Err(TxError::Timeout)), "{result:?}");
        assert_eq!(master.counters().foreign_frames, 1);
    }

    #[tokio::test(start_paused = true)]
    async fn a_foreign_frame_before_the_answer_does_not_hide_it() {
        let mut both = rtu::encode(9, &READ_ANSWER);
        both.extend(rtu::encode(1, &READ_ANSWER));
        let plan = vec![Some(Transmission {
            bytes: both,
            delay: Duration::ZERO,
            pause: None,
        })];
        let (_line, mut master) = line(vec![(1, plan)]);
        assert_eq!(
            master.transact(1, &READ, TIMEOUT).await.unwrap(),
            Reply::Fits(READ_ANSWER.to_vec())
        );
        assert_eq!(master.counters().foreign_frames, 1);
    }

    #[tokio::test(start_paused = true)]
    async fn frames_are_recorded_only_while_asked_for_each_as_it_was_on_the_wire() {
        let mut both = rtu::encode(9, &READ_ANSWER);
        both.extend(rtu::encode(1, &READ_ANSWER));
        let plan = vec![
            reply(1, &READ_ANSWER, Duration::ZERO),
            Some(Transmission {
                bytes: both,
                delay: Duration::ZERO,
                pause: None,
            }),
        ];
        let (_line, mut master) = line(vec![(1, plan)]);
        master.transact(1, &READ, TIMEOUT).await.unwrap();
        assert_eq!(master.recorded().count(), 0, "nothing while not asked");
        master.record_frames(true);
        master.transact(1, &READ, TIMEOUT).await.unwrap();
        let recorded: Vec<_> = master
            .recorded()
            .map(|f| (f.seen, f.address, f.function, f.bytes))
            .collect();
        assert_eq!(
            recorded,
            [
                (Seen::Sent, 1, 0x03, rtu::encode(1, &READ)),
                (Seen::Foreign, 9, 0x03, rtu::encode(9, &READ_ANSWER)),
                (Seen::Reply, 1, 0x03, rtu::encode(1, &READ_ANSWER)),
            ]
        );
        assert_eq!(master.recorded().count(), 0, "each frame is taken once");
    }

    #[tokio::test(start_paused = true)]
    async fn a_reply_with_a_bad_crc_is_not_returned() {
        let mut bytes = rtu::encode(1, &READ_ANSWER);
        *bytes.last_mut().unwrap() ^= 0x01;
        let plan = vec![Some(Transmission {
            bytes,
            delay: Duration::ZERO,
            pause: None,
        })];
        let (_line, mut master) = line(vec![(1, plan)]);
        let result = master.transact(1, &READ, FOREVER).await;
        assert!(matches!(result, Err(TxError::Check)), "{result:?}");
    }

    #[tokio::test(start_paused = true)]
    async fn a_late_reply_never_answers_the_next_request() {
        let late = TIMEOUT * 3 / 2;
        let (line, mut master) = line(vec![
            (1, vec![reply(1, &READ_ANSWER, late)]),
            // Slave 2 answers the same request with other data, after the late reply has come.
            (2, vec![reply(2, &[0x03, 0x04, 0, 2, 0, 2], TIMEOUT)]),
        ]);
        let first = master.transact(1, &READ, TIMEOUT).await;
        assert!(matches!(first, Err(TxError::Timeout)), "{first:?}");
        let second = master.transact(2, &READ, TIMEOUT * 2).await.unwrap();
        assert_eq!(second, Reply::Fits(vec![0x03, 0x04, 0, 2, 0, 2]));
        assert_eq!(
            master.counters().foreign_frames,
            1,
            "the late reply was seen and dropped"
        );
        assert_eq!(line.stats().collisions, 0);
    }

    #[tokio::test(start_paused = true)]
    async fn a_late_reply_from_the_same_slave_does_not_answer_a_different_read() {
        let late = TIMEOUT * 3 / 2;
        let other_read = [0x03, 0x00, 0x10, 0x00, 0x01];
        let (_line, mut master) = line(vec![(
            1,
            vec![
                reply(1, &READ_ANSWER, late),
                reply(1, &[0x03, 0x02, 0xAB, 0xCD], TIMEOUT),
            ],
        )]);
        assert!(master.transact(1, &READ, TIMEOUT).await.is_err());
        let second = master.transact(1, &other_read, TIMEOUT * 2).await.unwrap();
        assert_eq!(second, Reply::Fits(vec![0x03, 0x02, 0xAB, 0xCD]));
        assert_eq!(master.counters().foreign_frames, 1);
    }

    /// A slave's replies that pass CRC, address and function code but not the request's shape:
    /// a short read (one register of two), a multiple write's echo of another quantity, a single
    /// write's echo of another value.
    fn malformed_exchanges() -> [(Vec<u8>, Vec<u8>); 3] {
        [
            (READ.to_vec(), vec![0x03, 0x02, 0x13, 0x88]),
            (
                vec![0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32],
                vec![0x10, 0x00, 0x04, 0x00, 0x03],
            ),
            (
                vec![0x06, 0x00, 0x04, 0x13, 0x88],
                vec![0x06, 0x00, 0x04, 0x00, 0x01],
            ),
        ]
    }

    #[tokio::test(start_paused = true)]
    async fn a_malformed_reply_with_no_late_reply_pending_is_the_slaves_answer_at_once() {
        for (request, answer) in malformed_exchanges() {
            let (line, mut master) = line(vec![(1, vec![reply(1, &answer, Duration::ZERO)])]);
            let (result, after) = timed(&mut master, 1, &request, FOREVER).await;
            assert_eq!(result.unwrap(), Reply::Malformed(answer.clone()));
            let timing = line.timing();
            let reply_done = timing.t35 + timing.frame_time(answer.len() + 3);
            assert!(after <= reply_done + TIMER_RESOLUTION, "{after:?}");
            assert_eq!(master.late_reply_window(1), None, "no window after it");
        }
    }

    #[tokio::test(start_paused = true)]
    async fn a_malformed_reply_while_a_late_reply_may_come_is_discarded() {
        for (request, answer) in malformed_exchanges() {
            // The first try gets nothing; the retry gets the malformed frame at once, while the
            // first try's reply may still come.
            let plan = vec![None, reply(1, &answer, Duration::ZERO)];
            let (_line, mut master) = line(vec![(1, plan)]);
            let first = master.transact(1, &request, TIMEOUT).await;
            assert!(matches!(first, Err(TxError::Timeout)), "{first:?}");
            assert!(master.late_reply_window(1).is_some());
            let (retry, after) = timed(&mut master, 1, &request, TIMEOUT).await;
            assert!(matches!(retry, Err(TxError::Timeout)), "{retry:?}");
            assert!(after >= TIMEOUT, "{after:?}");
            assert_eq!(master.counters().foreign_frames, 1);
        }
    }

    #[tokio::test(start_paused = true)]
    async fn a_try_ended_by_the_slaves_own_frame_opens_no_late_reply_window() {
        let mut bad_crc = rtu::encode(1, &READ_ANSWER);
        *bad_crc.last_mut().unwrap() ^= 0x01;
        let plan = vec![
            Some(Transmission {
                bytes: bad_crc,
                delay: Duration::ZERO,
                pause: None,
            }),
            reply(1, &READ_ANSWER, Duration::ZERO),
            None,
        ];
        let (_line, mut master) = line(vec![(1, plan)]);
        assert!(matches!(
            master.transact(1, &READ, TIMEOUT).await,
            Err(TxError::Check)
        ));
        assert_eq!(master.late_reply_window(1), None);
        master.transact(1, &READ, TIMEOUT).await.unwrap();
        assert_eq!(master.late_reply_window(1), None);
        // Silence does open one: one more response timeout from when the try gave up.
        assert!(master.transact(1, &READ, TIMEOUT).await.is_err());
        assert_eq!(master.late_reply_window(1), Some(Instant::now() + TIMEOUT));
        assert_eq!(master.late_reply_window(2), None, "only for that slave");
    }

    #[tokio::test(start_paused = true)]
    async fn a_retry_answered_by_the_first_tries_late_reply_keeps_the_window_open_for_its_own() {
        // The slave always answers 1.5 timeouts after a request: the retry takes the first try's
        // reply, and its own reply comes later still.
        let late = TIMEOUT * 3 / 2;
        let (line, mut master) = line(vec![(
            1,
            vec![reply(1, &READ_ANSWER, late), reply(1, &READ_ANSWER, late)],
        )]);
        assert!(master.transact(1, &READ, TIMEOUT).await.is_err());
        let retry = master.transact(1, &READ, TIMEOUT).await.unwrap();
        assert_eq!(retry, Reply::Fits(READ_ANSWER.to_vec()));
        let until = master
            .late_reply_window(1)
            .expect("the retry's own reply may come");
        crate::timer::coarse_sleep_until(until).await;
        let frames = line.frames();
        let own = frames.last().unwrap();
        assert_eq!(own.from, crate::sim::Source::Slave(1));
        assert!(own.end <= until, "the retry's reply came after the window");
    }

    #[tokio::test(start_paused = true)]
    async fn user_defined_replies_end_after_t35_of_silence() {
        let pdu = [0x41, 0xDE, 0xAD, 0xBE, 0xEF];
        let (line, mut master) = line(vec![(1, vec![reply(1, &pdu, Duration::ZERO)])]);
        let (result, after) = timed(&mut master, 1, &[0x41, 0x01], FOREVER).await;
        assert_eq!(result.unwrap(), Reply::Fits(pdu.to_vec()));
        let timing = line.timing();
        let reply_done = timing.t35 + timing.frame_time(pdu.len() + 3);
        assert!(after >= reply_done + timing.t35, "{after:?}");
        assert!(
            after <= reply_done + timing.t35 + 2 * TIMER_RESOLUTION,
            "{after:?}"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn every_frame_waits_t35_after_the_last_byte_on_the_line() {
        let plan = (0..20)
            .map(|_| reply(1, &READ_ANSWER, Duration::ZERO))
            .collect();
        let (line, mut master) = line(vec![(1, plan)]);
        for _ in 0..20 {
            master.transact(1, &READ, TIMEOUT).await.unwrap();
        }
        let stats = line.stats();
        assert_eq!(stats.gap_violations, 0);
        assert!(stats.min_gap.unwrap() >= line.timing().t35);
        // No fixed pauses: the sim hands over the last byte on the next timer tick, and the gap
        // sleep ends on a tick, so at most two ticks are added.
        assert!(
            stats.min_gap.unwrap() <= line.timing().t35 + 2 * TIMER_RESOLUTION,
            "{:?}",
            stats.min_gap
        );
    }

    #[tokio::test(start_paused = true)]
    async fn a_broadcast_keeps_the_line_silent_for_the_turnaround_delay() {
        let (line, mut master) = line(vec![(1, vec![reply(1, &READ_ANSWER, Duration::ZERO)])]);
        let turnaround = Duration::from_millis(100);
        master
            .broadcast(&[0x06, 0x00, 0x01, 0x00, 0x01], turnaround, FOREVER)
            .await
            .unwrap();
        master.transact(1, &READ, TIMEOUT).await.unwrap();
        let frames = line.frames();
        assert_eq!(frames[0].bytes[0], 0, "the broadcast went to address 0");
        let silence = frames[1].start - frames[0].end;
        assert!(
            silence >= turnaround && silence <= turnaround + TIMER_RESOLUTION,
            "{silence:?}"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn stray_bytes_push_the_next_frame_back() {
        let (line, mut master) = line(vec![
            (1, vec![reply(1, &READ_ANSWER, TIMEOUT * 3 / 2)]),
            (2, vec![reply(2, &READ_ANSWER, Duration::ZERO)]),
        ]);
        assert!(master.transact(1, &READ, TIMEOUT).await.is_err());
        // Slave 1's late reply goes on the wire while the master is idle.
        let watching = tokio::time::timeout(TIMEOUT, async {
            loop {
                if let Err(lost) = master.watch_idle().await {
                    return lost;
                }
            }
        })
        .await;
        assert!(watching.is_err(), "the port is still there");
        let counters = master.counters();
        assert_eq!(counters.stray_bytes, 3 + READ_ANSWER.len() as u64);
        assert_eq!(counters.received_bytes, counters.stray_bytes);
        master.transact(2, &READ, TIMEOUT).await.unwrap();
        assert_eq!(line.stats().gap_violations, 0);
        assert_eq!(line.stats().collisions, 0);
    }

    #[tokio::test(start_paused = true)]
    async fn the_counters_tally_every_byte_each_way() {
        let (_line, mut master) = line(vec![(
            1,
            vec![
                reply(1, &READ_ANSWER, Duration::ZERO),
                reply(1, &[0x83, 0x02], Duration::ZERO),
            ],
        )]);
        master.transact(1, &READ, TIMEOUT).await.unwrap();
        let first = master.counters();
        master.transact(1, &READ, TIMEOUT).await.unwrap();
        // Request: address + 5-byte PDU + CRC; replies: address + PDU + CRC.
        assert_eq!((first.sent_bytes, first.received_bytes), (8, 9));
        let second = master.counters().since(&first);
        assert_eq!((second.sent_bytes, second.received_bytes), (8, 5));
        assert_eq!((second.foreign_frames, second.stray_bytes), (0, 0));
    }

    #[tokio::test(start_paused = true)]
    async fn an_unplugged_port_is_reported_lost() {
        let (line, mut master) = line(vec![(1, vec![None])]);
        line.unplug();
        let result = master.transact(1, &READ, TIMEOUT).await;
        assert!(matches!(result, Err(TxError::PortLost(_))), "{result:?}");
    }
}
