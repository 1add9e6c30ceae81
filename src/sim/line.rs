//! A timed, half-duplex RS-485 line with one master port and simulated slaves.
//!
//! The line is lazy: nothing runs between calls. When the master sends a frame, the line works out
//! when it occupies the wire, whether it started a full t3.5 after the previous frame, whether it
//! collided with a slave still talking, which slave reads it and when that slave's reply occupies
//! the wire, byte by byte. The port then hands each byte over once its time has come. That keeps
//! the simulation exact under tokio's paused clock and costs no task. A bus monitor keeps counts
//! and the recent frames with their times, for tests and benchmarks.

use super::slaves::{Heard, Slaves};
use super::{Simulated, Transmission};
use crate::line::framing::{Completion, Silence};
use crate::line::{Framing, LineTiming, Transport};
use crate::timer::sleep_until;
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

/// Who put a frame on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    Master,
    Slave(u8),
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

    /// Open the master port, as opening a serial device would. Any older port goes dead.
    pub fn open(&self) -> io::Result<SimPort> {
        let mut state = self.shared.lock();
        if !state.plugged {
            return Err(io::Error::new(
                io::ErrorKind::NotFound,
                "simulated adapter unplugged",
            ));
        }
        state.generation += 1;
        state.inbound.clear();
        Ok(SimPort {
            shared: self.shared.clone(),
            generation: state.generation,
        })
    }

    /// Pull the simulated USB adapter: the open port reads 0 bytes and fails writes, and opening
    /// fails until [`SimLine::plug`].
    pub fn unplug(&self) {
        {
            let mut state = self.shared.lock();
            state.plugged = false;
            state.generation += 1;
            state.inbound.clear();
        }
        self.shared.changed.notify_waiters();
    }

    pub fn plug(&self) {
        self.shared.lock().plugged = true;
    }

    pub fn stats(&self) -> LineStats {
        self.shared.lock().stats
    }

    /// The most recent frames, oldest first.
    pub fn frames(&self) -> Vec<WireFrame> {
        self.shared.lock().log.iter().cloned().collect()
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
        let mut finished = None;
        self.slave_tx.retain(|&(_, slave_end)| {
            let over = slave_end <= start;
            if over {
                finished = finished.max(Some(slave_end));
            }
            !over
        });
        if let Some(slave_end) = finished {
            self.extend_wire_end(slave_end);
        }
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
                // Bytes arrive in time order, even when a late reply was scheduled before this one.
                let position = self.inbound.partition_point(|&(due, _)| due <= at);
                self.inbound.insert(position, (at, byte));
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

/// The master's end of a [`SimLine`], as a serial port.
pub struct SimPort {
    shared: Arc<Shared>,
    generation: u64,
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
                let n = state.deliver(Instant::now(), buf);
                if n > 0 {
                    return Ok(n);
                }
                state.inbound.front().map(|&(at, _)| at)
            };
            match next_arrival {
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
        while state.inbound.front().is_some_and(|&(at, _)| at <= now) {
            state.inbound.pop_front();
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::{rtu, Parity, SerialFormat};

    fn line_9600_8e1() -> SimLine {
        SimLine::new(LineTiming::new(&SerialFormat {
            baud: 9600,
            data_bits: 8,
            parity: Parity::Even,
            stop_bits: 1,
        }))
    }

    /// Answers every request with the same PDU, after `delay`.
    struct Echo {
        delay: Duration,
    }

    impl Simulated for Echo {
        fn handle(&mut self, address: u8, request: &[u8], _at: Instant) -> Option<Transmission> {
            Some(Transmission {
                bytes: rtu::encode(address, request),
                delay: self.delay,
                pause: None,
            })
        }
    }

    const READ: [u8; 8] = [0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA];
    /// tokio's timer wakes sleepers on whole milliseconds, paused clock included.
    const TIMER_RESOLUTION: Duration = Duration::from_millis(1);

    fn assert_about(elapsed: Duration, expected: Duration) {
        assert!(
            elapsed >= expected && elapsed <= expected + TIMER_RESOLUTION,
            "{elapsed:?} is not within the timer resolution after {expected:?}"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn a_reply_arrives_byte_by_byte_after_the_request_and_t35() {
        let line = line_9600_8e1();
        line.add_slave(
            1,
            Echo {
                delay: Duration::ZERO,
            },
        );
        let timing = line.timing();
        let mut port = line.open().unwrap();
        let t0 = Instant::now();
        port.send(&READ).await.unwrap();
        let mut buf = Vec::new();
        let n = port.recv(&mut buf).await.unwrap();
        assert!(n >= 1);
        // Request on the wire, slave waits t3.5, first reply byte takes one character time.
        assert_about(
            Instant::now() - t0,
            timing.frame_time(8) + timing.t35 + timing.char_time,
        );
        while buf.len() < READ.len() {
            port.recv(&mut buf).await.unwrap();
        }
        assert_eq!(buf, READ);
        // The reply ends 16 characters and one t3.5 after the request started.
        assert_about(Instant::now() - t0, timing.frame_time(16) + timing.t35);
        let frames = line.frames();
        assert_eq!(frames[1].start - frames[0].end, timing.t35);
        assert_eq!(
            frames[1].end - frames[0].start,
            timing.frame_time(16) + timing.t35
        );
        let stats = line.stats();
        assert_eq!((stats.master_frames, stats.slave_frames), (1, 1));
        assert_eq!(stats.busy, timing.frame_time(16));
    }

    /// Answers with the request's own frame, pausing after `after` bytes for `gap`.
    struct Stutter {
        after: usize,
        gap: Duration,
    }

    impl Simulated for Stutter {
        fn handle(&mut self, address: u8, request: &[u8], _at: Instant) -> Option<Transmission> {
            Some(Transmission {
                bytes: rtu::encode(address, request),
                delay: Duration::ZERO,
                pause: Some(super::super::Pause {
                    after: self.after,
                    gap: self.gap,
                }),
            })
        }
    }

    #[tokio::test(start_paused = true)]
    async fn a_paused_reply_arrives_in_two_bursts_with_the_line_silent_between() {
        let line = line_9600_8e1();
        let gap = Duration::from_millis(20);
        line.add_slave(1, Stutter { after: 3, gap });
        let timing = line.timing();
        let mut port = line.open().unwrap();
        let t0 = Instant::now();
        port.send(&READ).await.unwrap();
        let mut buf = Vec::new();
        while buf.len() < 3 {
            port.recv(&mut buf).await.unwrap();
        }
        assert_eq!(
            buf.len(),
            3,
            "nothing of the rest came with the first burst"
        );
        let first_done = Instant::now();
        while buf.len() < READ.len() {
            port.recv(&mut buf).await.unwrap();
        }
        assert_eq!(buf, READ);
        // The fourth byte takes its character time after the gap.
        assert_about(Instant::now() - first_done, gap + timing.frame_time(5));
        assert_about(
            Instant::now() - t0,
            timing.frame_time(16) + timing.t35 + gap,
        );
        let frames = line.frames();
        assert_eq!(frames.len(), 3, "the request and two bursts");
        assert_eq!(frames[2].start - frames[1].end, gap);
        assert_eq!(frames[1].bytes, READ[..3]);
        let stats = line.stats();
        assert_eq!(stats.slave_frames, 1, "one transmission");
        assert_eq!(stats.busy, timing.frame_time(16), "the gap is not busy");
    }

    #[tokio::test(start_paused = true)]
    async fn the_master_may_talk_in_a_slaves_pause_without_a_collision() {
        let line = line_9600_8e1();
        line.add_slave(
            1,
            Stutter {
                after: 3,
                gap: Duration::from_millis(50),
            },
        );
        let timing = line.timing();
        let mut port = line.open().unwrap();
        port.send(&READ).await.unwrap();
        tokio::time::advance(timing.frame_time(11) + 2 * timing.t35).await;
        port.send(&rtu::encode(2, &[0x03, 0x00, 0x00, 0x00, 0x01]))
            .await
            .unwrap();
        assert_eq!(line.stats().collisions, 0);
        assert_eq!(line.stats().unread_frames, 0);
    }

    #[tokio::test(start_paused = true)]
    async fn a_frame_sent_before_t35_of_silence_is_counted_and_not_read() {
        let line = line_9600_8e1();
        line.add_slave(
            1,
            Echo {
                delay: Duration::ZERO,
            },
        );
        let timing = line.timing();
        let mut port = line.open().unwrap();
        port.send(&READ).await.unwrap();
        // The reply ends 16 characters and t3.5 later; resend one character time after that.
        tokio::time::advance(timing.frame_time(16) + timing.t35 + timing.char_time).await;
        port.clear_input(&mut Vec::new()).unwrap();
        port.send(&READ).await.unwrap();
        let stats = line.stats();
        assert_eq!(stats.gap_violations, 1);
        assert_eq!(stats.unread_frames, 1);
        assert_eq!(
            stats.slave_frames, 1,
            "the slave did not answer the merged frame"
        );
        assert_eq!(stats.min_gap, Some(timing.char_time));
    }

    #[tokio::test(start_paused = true)]
    async fn sending_while_a_slave_talks_garbles_both() {
        let line = line_9600_8e1();
        line.add_slave(
            1,
            Echo {
                delay: Duration::ZERO,
            },
        );
        let mut port = line.open().unwrap();
        port.send(&READ).await.unwrap();
        let mut buf = Vec::new();
        port.recv(&mut buf).await.unwrap();
        port.send(&READ).await.unwrap();
        while buf.len() < READ.len() {
            port.recv(&mut buf).await.unwrap();
        }
        assert_eq!(buf[0], READ[0], "the byte before the collision is intact");
        assert!(!rtu::crc_ok(&buf));
        assert_eq!(line.stats().collisions, 1);
    }

    #[tokio::test(start_paused = true)]
    async fn an_unplugged_adapter_reads_zero_and_cannot_be_opened_until_plugged() {
        let line = line_9600_8e1();
        let mut port = line.open().unwrap();
        let waiting = tokio::spawn(async move {
            let mut buf = Vec::new();
            port.recv(&mut buf).await
        });
        tokio::task::yield_now().await;
        line.unplug();
        assert_eq!(waiting.await.unwrap().unwrap(), 0);
        assert!(line.open().is_err());
        line.plug();
        let mut port = line.open().unwrap();
        port.send(&READ).await.unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn broadcasts_reach_every_slave_and_nobody_answers() {
        let line = line_9600_8e1();
        line.add_slave(
            1,
            Echo {
                delay: Duration::ZERO,
            },
        );
        line.add_slave(
            2,
            Echo {
                delay: Duration::ZERO,
            },
        );
        let mut port = line.open().unwrap();
        port.send(&rtu::encode(0, &[0x06, 0, 1, 0, 1]))
            .await
            .unwrap();
        let mut buf = Vec::new();
        let nothing = tokio::time::timeout(Duration::from_secs(1), port.recv(&mut buf)).await;
        assert!(nothing.is_err());
        assert_eq!(line.stats().slave_frames, 0);
    }
}
