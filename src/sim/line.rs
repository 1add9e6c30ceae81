//! A timed, half-duplex RS-485 line with one adapter port and simulated slaves.
//!
//! The line is lazy: nothing runs between calls. When the master sends a frame, the line works out
//! when it occupies the wire, whether it started a full t3.5 after the previous frame, whether it
//! collided with a slave still talking, which slave reads it and when that slave's reply occupies
//! the wire, byte by byte. The port then hands each byte over once its time has come. That keeps
//! the simulation exact under tokio's paused clock and costs no task. A bus monitor keeps counts
//! and the recent frames with their times, for tests and benchmarks.
//!
//! The adapter may instead be opened to listen ([`SimLine::open_listening`]): that port hears
//! every byte on the wire and cannot send. The line's other master ([`SimLine::set_master`],
//! `[bus.sim_master]`) runs only while such a port is open, advanced as the port is polled, as
//! the slaves' replies are scheduled: exact under the paused clock, and idle when nobody listens.

use super::master::{Ending, OtherMaster, Step};
use super::slaves::{Heard, Slaves};
use super::{Simulated, Transmission};
use crate::config;
use crate::line::framing::{Completion, Silence};
use crate::line::{Framing, LineTiming, Transport};
use crate::timer::{sleep_until, LineTimer};
use std::collections::VecDeque;
use std::io;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;
use tokio::sync::Notify;
use tokio::time::Instant;

/// Frames the monitor remembers.
const LOG_CAPACITY: usize = 4096;
/// What two transmitters talking at once do to the bytes.
const COLLISION_NOISE: u8 = 0xA5;
/// Bytes the adapter holds for a port that does not read them, as a tty's buffer does: the
/// rest are lost (a listener polled too seldom overruns).
const INBOUND_CAPACITY: usize = 4096;

/// Who put a frame on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    Master,
    Slave(u8),
    /// The line's other master (`[bus.sim_master]`).
    OtherMaster,
}

/// One frame as the wire carried it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WireFrame {
    pub start: Instant,
    pub end: Instant,
    pub from: Source,
    pub bytes: Vec<u8>,
}

/// What the bus monitor counted since the line was made.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LineStats {
    pub master_frames: u64,
    /// Slave transmissions: a paused one counts once, though the log holds its two bursts.
    pub slave_frames: u64,
    /// Master frames that started less than t3.5 after the previous frame ended.
    pub gap_violations: u64,
    /// Master frames sent while a slave was still transmitting.
    pub collisions: u64,
    /// Master frames no slave could read: merged with the previous frame, collided, or bad CRC.
    pub(crate) unread_frames: u64,
    /// Shortest silence seen before a master frame.
    pub min_gap: Option<Duration>,
    /// Total time frames occupied the wire.
    pub busy: Duration,
    /// Frames handed to a listening port's `send`: refused, never on the wire. Zero is the proof
    /// that a listen line's gateway transmitted nothing.
    pub listener_frames: u64,
    /// The other master's requests put on the wire.
    pub other_requests: u64,
    /// Its transactions that ended with a good reply from the slave asked.
    pub other_replies: u64,
    /// Its transactions that ended with a whole frame failing its check or from another address.
    pub other_corrupt: u64,
    /// Its transactions that ended at its response timeout.
    pub other_timeouts: u64,
}

/// Handle on a simulated line; clones share it.
#[derive(Clone)]
pub struct SimLine {
    shared: Arc<Shared>,
}

struct Shared {
    state: Mutex<LineState>,
    /// Wakes a waiting port when the adapter is unplugged.
    changed: Notify,
}

struct LineState {
    timing: LineTiming,
    slaves: Slaves,
    plugged: bool,
    /// Bumped by every open and unplug: a port of an older generation is dead.
    generation: u64,
    /// The generation opened to listen, if the latest open was a listener's.
    listening: Option<u64>,
    other: Option<OtherMaster>,
    master_busy_until: Option<Instant>,
    /// End of the latest transmission known to be over.
    last_wire_end: Option<Instant>,
    /// Slave transmissions scheduled and not yet over: (start, end).
    slave_tx: VecDeque<(Instant, Instant)>,
    /// Bytes on their way to the master port, with the moment each has fully arrived.
    inbound: VecDeque<(Instant, u8)>,
    stats: LineStats,
    log: VecDeque<WireFrame>,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, LineState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl SimLine {
    /// An RTU line at `timing`.
    pub fn new(timing: LineTiming) -> Self {
        Self::with_framing(timing, Framing::Rtu)
    }

    /// A line at `timing` whose slaves hear and answer frames of `framing`.
    pub(crate) fn with_framing(timing: LineTiming, framing: Framing) -> Self {
        SimLine {
            shared: Arc::new(Shared {
                state: Mutex::new(LineState {
                    timing,
                    slaves: Slaves::new(framing),
                    plugged: true,
                    generation: 0,
                    listening: None,
                    other: None,
                    master_busy_until: None,
                    last_wire_end: None,
                    slave_tx: VecDeque::new(),
                    inbound: VecDeque::new(),
                    stats: LineStats::default(),
                    log: VecDeque::new(),
                }),
                changed: Notify::new(),
            }),
        }
    }

    /// Whether `other` is a handle on this same line.
    pub fn same_line(&self, other: &SimLine) -> bool {
        Arc::ptr_eq(&self.shared, &other.shared)
    }

    pub fn timing(&self) -> LineTiming {
        self.shared.lock().timing
    }

    /// Put a slave on the line at `address`, replacing any slave there.
    pub fn add_slave(&self, address: u8, slave: impl Simulated + 'static) {
        self.shared.lock().slaves.insert(address, Box::new(slave));
    }

    /// Put the other master `master` describes on the line, replacing any; it starts once a
    /// listening port is open.
    pub fn set_master(&self, master: &config::SimMaster) {
        let mut state = self.shared.lock();
        let framing = state.slaves.framing();
        let mut other = OtherMaster::new(master, framing);
        if state.listener_live() {
            other.resume(Instant::now());
        }
        state.other = Some(other);
    }

    /// Open the master port, as opening a serial device would. Any older port goes dead.
    pub fn open(&self) -> io::Result<SimPort> {
        self.open_as(false)
    }

    /// Open the adapter to listen: the port hears every frame on the wire, the masters' and the
    /// slaves', each byte once its time has come, and refuses to send (counted in
    /// [`LineStats::listener_frames`]). Any older port goes dead; the other master, if any, runs.
    pub fn open_listening(&self) -> io::Result<SimPort> {
        self.open_as(true)
    }

    fn open_as(&self, listening: bool) -> io::Result<SimPort> {
        let mut state = self.shared.lock();
        if !state.plugged {
            return Err(io::Error::new(
                io::ErrorKind::NotFound,
                "simulated adapter unplugged",
            ));
        }
        let now = Instant::now();
        // An older listener's master catches up to the moment it goes dead.
        state.advance_other(now);
        state.generation += 1;
        if listening {
            // What is still on its way is on the wire, and the new port hears it.
            while state.inbound.front().is_some_and(|&(at, _)| at <= now) {
                state.inbound.pop_front();
            }
            state.listening = Some(state.generation);
            if let Some(other) = state.other.as_mut() {
                other.resume(now);
            }
        } else {
            state.listening = None;
            state.inbound.clear();
        }
        Ok(SimPort {
            shared: self.shared.clone(),
            generation: state.generation,
            listening,
            timer: LineTimer::new(),
        })
    }

    /// Pull the simulated USB adapter: the open port reads 0 bytes and fails writes, and opening
    /// fails until [`SimLine::plug`].
    pub fn unplug(&self) {
        {
            let mut state = self.shared.lock();
            state.advance_other(Instant::now());
            state.plugged = false;
            state.generation += 1;
            state.inbound.clear();
        }
        self.shared.changed.notify_waiters();
    }

    pub fn plug(&self) {
        self.shared.lock().plugged = true;
    }

    /// The counts as of now (the other master advanced to now first).
    pub fn stats(&self) -> LineStats {
        let mut state = self.shared.lock();
        state.advance_other(Instant::now());
        state.stats
    }

    /// The most recent frames, oldest first, as of now.
    pub fn frames(&self) -> Vec<WireFrame> {
        let mut state = self.shared.lock();
        state.advance_other(Instant::now());
        state.log.iter().cloned().collect()
    }

    /// When the wire falls silent after every frame sent or scheduled so far (`None` before the
    /// first): a master that keeps the gap starts t3.5 after it.
    pub(crate) fn quiet_at(&self) -> Option<Instant> {
        let state = self.shared.lock();
        let slave_end = state.slave_tx.iter().map(|&(_, end)| end).max();
        [state.last_wire_end, state.master_busy_until, slave_end]
            .into_iter()
            .flatten()
            .max()
    }
}

impl LineState {
    fn is_live(&self, generation: u64) -> bool {
        self.plugged && self.generation == generation
    }

    fn record(&mut self, frame: WireFrame) {
        self.stats.busy += frame.end - frame.start;
        if self.log.len() == LOG_CAPACITY {
            self.log.pop_front();
        }
        self.log.push_back(frame);
    }

    fn extend_wire_end(&mut self, end: Instant) {
        self.last_wire_end = Some(self.last_wire_end.map_or(end, |e| e.max(end)));
    }

    /// The master's UART starts sending `bytes` at `now` (after anything it is still sending).
    fn transmit_from_master(&mut self, bytes: &[u8], now: Instant) {
        let timing = self.timing;
        let start = self.master_busy_until.map_or(now, |busy| busy.max(now));
        let end = start + timing.frame_time(bytes.len());
        self.master_busy_until = Some(end);
        self.stats.master_frames += 1;
        let collided = self.collides(start, end);
        let gap = self
            .last_wire_end
            .filter(|_| !collided)
            .map(|previous_end| start.saturating_duration_since(previous_end));
        if let Some(gap) = gap {
            self.stats.min_gap = Some(self.stats.min_gap.map_or(gap, |m| m.min(gap)));
        }
        // An RTU frame that starts too soon runs into the previous one: slaves see one garbled
        // frame. ASCII frames are delimited by their characters, not by silence.
        let merged =
            self.slaves.framing() == Framing::Rtu && gap.is_some_and(|gap| gap < timing.t35);
        if merged {
            self.stats.gap_violations += 1;
        }
        self.record(WireFrame {
            start,
            end,
            from: Source::Master,
            bytes: bytes.to_vec(),
        });
        self.extend_wire_end(end);

        if collided || merged {
            self.stats.unread_frames += 1;
            return;
        }
        self.slaves_hear(bytes, end);
    }

    /// Whether the master's frame on the wire from `start` to `end` runs into a slave's reply
    /// still being sent; the slaves' bytes it overlaps are garbled. Replies that are over end
    /// the wire's last frame.
    fn collides(&mut self, start: Instant, end: Instant) -> bool {
        let timing = self.timing;
        self.settle(start);
        let collided = self
            .slave_tx
            .iter()
            .any(|&(slave_start, _)| slave_start < end);
        if collided {
            self.stats.collisions += 1;
            let char_time = timing.char_time;
            for (at, byte) in self.inbound.iter_mut() {
                if *at > start && *at - char_time < end {
                    *byte ^= COLLISION_NOISE;
                }
            }
        }
        collided
    }

    /// Forget the slaves' transmissions over by `at`: they end the wire's last frame.
    fn settle(&mut self, at: Instant) {
        let mut finished = None;
        self.slave_tx.retain(|&(_, slave_end)| {
            let over = slave_end <= at;
            if over {
                finished = finished.max(Some(slave_end));
            }
            !over
        });
        if let Some(slave_end) = finished {
            self.extend_wire_end(slave_end);
        }
    }

    /// Whether the latest open was a listener's and its port is still live.
    fn listener_live(&self) -> bool {
        self.listening.is_some_and(|g| self.is_live(g))
    }

    /// Run the other master up to `now`, while a listener is live: each request it makes goes on
    /// the wire, the slave asked answers as it would any master, and each ending is counted.
    fn advance_other(&mut self, now: Instant) {
        if !self.listener_live() {
            return;
        }
        let Some(mut other) = self.other.take() else {
            return;
        };
        while let Some(step) = other.step(now) {
            match step {
                Step::Ended(outcome) => match outcome {
                    Ending::Reply => self.stats.other_replies += 1,
                    Ending::Corrupt => self.stats.other_corrupt += 1,
                    Ending::Timeout => self.stats.other_timeouts += 1,
                },
                Step::Request { start, index } => {
                    self.transmit_from_other(&mut other, index, start);
                }
            }
        }
        self.settle(now);
        self.other = Some(other);
    }

    /// The other master sends read `index` from `start`; the slave's answer is scheduled and
    /// the master told what came of it.
    fn transmit_from_other(&mut self, other: &mut OtherMaster, index: usize, start: Instant) {
        let timing = self.timing;
        let frame = other.read(index).frame.clone();
        let end = start + timing.frame_time(frame.len());
        self.stats.other_requests += 1;
        for n in 1..=frame.len() {
            self.receive(start + timing.frame_time(n), frame[n - 1]);
        }
        self.record(WireFrame {
            start,
            end,
            from: Source::OtherMaster,
            bytes: frame.clone(),
        });
        self.extend_wire_end(end);
        let ready_at = match self.slaves.framing() {
            Framing::Rtu => end + timing.t35,
            Framing::Ascii | Framing::Tcp => end,
        };
        match self.slaves.hear(&frame, end) {
            Heard::Answered { address, reply, .. } => {
                other.under_way(index, end, Some((&reply, ready_at + reply.delay)), &timing);
                self.transmit_from_slave(address, reply, ready_at);
            }
            Heard::Corrupt | Heard::Broadcast | Heard::NotHere | Heard::Unanswered { .. } => {
                other.under_way(index, end, None, &timing);
            }
        }
    }

    /// A byte on its way to the port, fully arrived at `at`; kept in time order, even when a
    /// late reply was scheduled before this one, and lost past the adapter's buffer.
    fn receive(&mut self, at: Instant, byte: u8) {
        if self.inbound.len() >= INBOUND_CAPACITY {
            return;
        }
        let position = self.inbound.partition_point(|&(due, _)| due <= at);
        self.inbound.insert(position, (at, byte));
    }

    /// The slaves hear the master's `bytes`, which left the wire at `end`, and answer.
    fn slaves_hear(&mut self, bytes: &[u8], end: Instant) {
        let timing = self.timing;
        // A slave finds a request's end by its function's length, as libmodbus does, or by
        // silence where the bytes cannot tell: bytes after that length are a request of their
        // own, heard after the first is answered.
        let framing = self.slaves.framing();
        // A slave knows the request has ended after t3.5 of silence (RTU) or at its own end
        // (ASCII's LF, MBAP's length), then processes it.
        let mut ready_at = match framing {
            Framing::Rtu => end + timing.t35,
            Framing::Ascii | Framing::Tcp => end,
        };
        let mut rest = bytes;
        while !rest.is_empty() {
            let len = match framing.request_completion(rest) {
                Completion::Whole(n) => n,
                Completion::Open(Silence::EndsFrame) => rest.len(),
                // Cut short by the silence after it, or no frame at all: dropped.
                Completion::AtLeast(_)
                | Completion::Open(Silence::FailsFrame)
                | Completion::Invalid => {
                    self.stats.unread_frames += 1;
                    break;
                }
            };
            let (frame, tail) = rest.split_at(len);
            rest = tail;
            match self.slaves.hear(frame, end) {
                Heard::Corrupt => self.stats.unread_frames += 1,
                Heard::Answered { address, reply, .. } => {
                    ready_at = self.transmit_from_slave(address, reply, ready_at);
                }
                Heard::Broadcast | Heard::NotHere | Heard::Unanswered { .. } => {}
            }
        }
    }

    /// A paused transmission goes on the wire as two bursts: the monitor logs each, and the
    /// master may talk in between without colliding. Returns when its last character is in.
    fn transmit_from_slave(
        &mut self,
        address: u8,
        reply: Transmission,
        ready_at: Instant,
    ) -> Instant {
        let char_time = self.timing.char_time;
        let mut bursts = vec![(ready_at + reply.delay, &reply.bytes[..])];
        if let Some(pause) = reply
            .pause
            .filter(|p| p.after > 0 && p.after < reply.bytes.len())
        {
            let (first, rest) = reply.bytes.split_at(pause.after);
            // A frame is a few hundred bytes at most; saturating keeps a pathological one from panicking.
            let chars = u32::try_from(first.len()).unwrap_or(u32::MAX);
            let first_end = bursts[0].0 + char_time.saturating_mul(chars);
            bursts = vec![(bursts[0].0, first), (first_end + pause.gap, rest)];
        }
        let mut last = ready_at;
        for (start, bytes) in bursts {
            let mut at = start;
            for &byte in bytes {
                at += char_time;
                self.receive(at, byte);
            }
            self.record(WireFrame {
                start,
                end: at,
                from: Source::Slave(address),
                bytes: bytes.to_vec(),
            });
            self.slave_tx.push_back((start, at));
            last = at;
        }
        self.stats.slave_frames += 1;
        last
    }

    /// Hand over every byte that has fully arrived by `now`.
    fn deliver(&mut self, now: Instant, buf: &mut Vec<u8>) -> usize {
        let before = buf.len();
        while let Some(&(at, byte)) = self.inbound.front() {
            if at > now {
                break;
            }
            buf.push(byte);
            self.inbound.pop_front();
        }
        buf.len() - before
    }
}

/// The adapter's end of a [`SimLine`], as a serial port: the master's, or a listener's.
pub struct SimPort {
    shared: Arc<Shared>,
    generation: u64,
    /// Opened to listen: hears every frame, never sends.
    listening: bool,
    /// A listener wakes for every byte (the master port sleeps through a reply it can
    /// measure): on a timer of its own, which costs it a syscall where the shared timer thread
    /// costs two thread switches.
    timer: LineTimer,
}

impl SimPort {
    /// When the next byte on its way to this port will have arrived, if any is.
    pub(crate) fn next_arrival(&self) -> Option<Instant> {
        let state = self.shared.lock();
        state
            .inbound
            .front()
            .filter(|_| state.is_live(self.generation))
            .map(|&(at, _)| at)
    }
}

impl Transport for SimPort {
    async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        let mut state = self.shared.lock();
        if self.listening {
            state.stats.listener_frames += 1;
            return Err(io::Error::new(
                io::ErrorKind::PermissionDenied,
                "a listening port never transmits",
            ));
        }
        if !state.is_live(self.generation) {
            return Err(io::Error::new(
                io::ErrorKind::BrokenPipe,
                "simulated adapter unplugged",
            ));
        }
        state.transmit_from_master(frame, Instant::now());
        Ok(())
    }

    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        loop {
            let changed = self.shared.changed.notified();
            tokio::pin!(changed);
            changed.as_mut().enable();
            let next_arrival = {
                let mut state = self.shared.lock();
                if !state.is_live(self.generation) {
                    return Ok(0);
                }
                let now = Instant::now();
                state.advance_other(now);
                let n = state.deliver(now, buf);
                if n > 0 {
                    return Ok(n);
                }
                let other = state.other.as_ref().and_then(OtherMaster::next_event);
                let due = state.inbound.front().map(|&(at, _)| at);
                due.into_iter()
                    .chain(other.filter(|_| self.listening))
                    .min()
            };
            match next_arrival {
                Some(at) if self.listening => tokio::select! {
                    () = self.timer.sleep_until(at) => {}
                    () = &mut changed => {}
                },
                Some(at) => tokio::select! {
                    () = sleep_until(at) => {}
                    () = &mut changed => {}
                },
                None => changed.await,
            }
        }
    }

    fn clear_input(&mut self, _stale: &mut Vec<u8>) -> io::Result<()> {
        let mut state = self.shared.lock();
        let now = Instant::now();
        state.advance_other(now);
        while state.inbound.front().is_some_and(|&(at, _)| at <= now) {
            state.inbound.pop_front();
        }
        Ok(())
    }
}

#[cfg(test)]
#[path = "line_tests.rs"]
mod tests;
