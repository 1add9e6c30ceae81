//! Simulated slaves served as RTU or ASCII slaves on a real serial port (the `simulate`
//! subcommand), so a SCADA set-up or another gateway can be tried against them. A request frame is
//! complete by its length (ASCII: its CR LF), or by silence for function codes whose length the
//! bytes cannot tell; a frame with a bad CRC (LRC) is ignored, as a slave must. The slave at the
//! frame's address acts on it and its reply goes out the slave's own delay after the request is
//! over (on RTU, t3.5 after its last byte; on ASCII, at its LF). Broadcasts are carried out by
//! every slave and answered by none. Knows nothing of TCP or the gateway's bus.

use super::slaves::{Heard, Slaves};
use super::Simulated;
use crate::line::inbound::{Received, RequestReader};
use crate::line::{Framing, LineTiming, Transport};
use crate::timer::sleep_until;
use std::io;
use std::time::Duration;
use tokio::time::Instant;
use tracing::debug;

/// What the responder has seen, for its log line.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ResponderStats {
    /// Intact frames addressed to a simulated slave or broadcast.
    pub requests: u64,
    pub replies: u64,
    /// Frames with a bad CRC, cut short, or too long, dropped unanswered.
    pub(crate) bad_frames: u64,
    /// Intact frames for addresses nobody simulates here.
    pub others: u64,
}

pub struct Responder {
    slaves: Slaves,
    timing: LineTiming,
    /// Silence that ends a frame whose length its bytes cannot tell.
    silence: Duration,
    stats: ResponderStats,
}

impl Responder {
    /// Slaves on an RTU line at `timing`; a request whose length its bytes cannot tell ends
    /// after `silence` (at least t3.5).
    pub fn new(timing: LineTiming, silence: Duration) -> Self {
        Self::framed(timing, Framing::Rtu, silence.max(timing.t35))
    }

    /// Slaves on a line of `framing` at `timing`. RTU: a request whose length its bytes cannot
    /// tell ends after `silence`. ASCII: `silence` between characters (the inter-character
    /// timeout) drops a request cut short.
    pub(crate) fn framed(timing: LineTiming, framing: Framing, silence: Duration) -> Self {
        Responder {
            slaves: Slaves::new(framing),
            timing,
            silence,
            stats: ResponderStats::default(),
        }
    }

    pub fn add_slave(&mut self, address: u8, slave: Box<dyn Simulated>) {
        self.slaves.insert(address, slave);
    }

    pub fn stats(&self) -> ResponderStats {
        self.stats
    }

    /// Answer requests on `port` until it fails; returns why.
    pub async fn serve<T: Transport>(&mut self, port: &mut T) -> io::Error {
        let mut reader = RequestReader::new(self.slaves.framing(), self.silence);
        loop {
            match reader.next(port).await {
                Ok(Received::Frame(request)) => {
                    if let Err(e) = self.answer(port, &request).await {
                        return e;
                    }
                }
                Ok(Received::Broken) => self.stats.bad_frames += 1,
                Err(e) => return e,
            }
        }
    }

    async fn answer<T: Transport>(&mut self, port: &mut T, request: &[u8]) -> io::Result<()> {
        let at = Instant::now();
        let (address, function, reply) = match self.slaves.hear(request, at) {
            Heard::Corrupt => {
                self.stats.bad_frames += 1;
                return Ok(());
            }
            Heard::NotHere => {
                self.stats.others += 1;
                return Ok(());
            }
            Heard::Broadcast => {
                self.stats.requests += 1;
                return Ok(());
            }
            Heard::Unanswered { address, function } => {
                self.stats.requests += 1;
                debug!(address, function, "no reply");
                return Ok(());
            }
            Heard::Answered {
                address,
                function,
                reply,
            } => (address, function, reply),
        };
        self.stats.requests += 1;
        // The slave knows the request is over after t3.5 of silence (RTU) or at its own end
        // (ASCII's LF, MBAP's length), then takes its own time.
        let heard_at = match self.slaves.framing() {
            Framing::Rtu => at + self.timing.t35,
            Framing::Ascii | Framing::Tcp => at,
        };
        let start = heard_at + reply.delay;
        sleep_until(start).await;
        match reply
            .pause
            .filter(|p| p.after > 0 && p.after < reply.bytes.len())
        {
            Some(pause) => {
                let (first, rest) = reply.bytes.split_at(pause.after);
                port.send(first).await?;
                // write() returns before the bytes are on the wire: the silence starts after them.
                sleep_until(start + self.timing.frame_time(first.len()) + pause.gap).await;
                port.send(rest).await?;
            }
            None => port.send(&reply.bytes).await?,
        }
        self.stats.replies += 1;
        debug!(address, function, bytes = reply.bytes.len(), "replied");
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::{rtu, Parity, SerialFormat};
    use crate::sim::RegisterBank;
    use std::collections::VecDeque;
    use std::sync::{Arc, Mutex};

    type Sent = Arc<Mutex<Vec<(Instant, Vec<u8>)>>>;

    /// A port fed from a script of byte bursts, each due at a time after `start`; what is sent is
    /// kept with its time. Cancel-safe like a real port: a burst is taken only once it is due.
    struct ScriptedPort {
        start: Instant,
        incoming: VecDeque<(Duration, Vec<u8>)>,
        sent: Sent,
    }

    impl Transport for ScriptedPort {
        async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
            self.sent
                .lock()
                .unwrap()
                .push((Instant::now(), frame.to_vec()));
            Ok(())
        }

        async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
            // After the script, long enough for every pending reply, then the port goes away.
            let due = self
                .incoming
                .front()
                .map_or(Duration::from_secs(10), |(due, _)| *due);
            sleep_until(self.start + due).await;
            match self.incoming.pop_front() {
                Some((_, bytes)) => {
                    buf.extend_from_slice(&bytes);
                    Ok(bytes.len())
                }
                None => Ok(0),
            }
        }

        fn clear_input(&mut self, _stale: &mut Vec<u8>) -> io::Result<()> {
            Ok(())
        }
    }

    fn timing() -> LineTiming {
        LineTiming::new(&SerialFormat {
            baud: 9600,
            data_bits: 8,
            parity: Parity::Even,
            stop_bits: 1,
        })
    }

    async fn run(incoming: Vec<(Duration, Vec<u8>)>) -> (Vec<(Instant, Vec<u8>)>, ResponderStats) {
        let mut responder = Responder::new(timing(), Duration::ZERO);
        for address in [1, 2] {
            responder.add_slave(
                address,
                Box::new(RegisterBank::new(Duration::from_millis(2))),
            );
        }
        let sent = Arc::new(Mutex::new(Vec::new()));
        let mut port = ScriptedPort {
            start: Instant::now(),
            incoming: incoming.into(),
            sent: sent.clone(),
        };
        responder.serve(&mut port).await;
        let sent = sent.lock().unwrap().clone();
        (sent, responder.stats())
    }

    /// Goodrive300 manual 10.4.1: read 2 words from 0004H of slave 01H.
    const READ: [u8; 8] = [0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA];

    #[tokio::test(start_paused = true)]
    async fn a_request_split_across_reads_is_answered_after_t35_and_the_slaves_delay() {
        let start = Instant::now();
        let (sent, stats) = run(vec![
            (Duration::ZERO, READ[..3].to_vec()),
            (Duration::from_millis(1), READ[3..].to_vec()),
        ])
        .await;
        assert_eq!(sent.len(), 1);
        let (at, bytes) = &sent[0];
        assert_eq!(bytes, &rtu::encode(1, &[0x03, 0x04, 0, 0, 0, 0]));
        let expected = start + Duration::from_millis(1) + timing().t35 + Duration::from_millis(2);
        assert!(
            *at >= expected && *at <= expected + Duration::from_millis(1),
            "{:?}",
            *at - start
        );
        assert_eq!(stats.replies, 1);
    }

    #[tokio::test(start_paused = true)]
    async fn a_paused_reply_goes_out_in_two_writes_the_gap_apart_on_the_wire() {
        let gap = Duration::from_millis(30);
        let mut responder = Responder::new(timing(), Duration::ZERO);
        let faults = crate::sim::faults::Faults {
            reply_gap: Some(crate::sim::Pause { after: 3, gap }),
            ..Default::default()
        };
        responder.add_slave(
            1,
            Box::new(crate::sim::faults::Faulty::new(
                RegisterBank::new(Duration::ZERO),
                faults,
                1,
            )),
        );
        let sent = Arc::new(Mutex::new(Vec::new()));
        let mut port = ScriptedPort {
            start: Instant::now(),
            incoming: vec![(Duration::ZERO, READ.to_vec())].into(),
            sent: sent.clone(),
        };
        responder.serve(&mut port).await;
        let sent = sent.lock().unwrap().clone();
        let whole = rtu::encode(1, &[0x03, 0x04, 0, 0, 0, 0]);
        assert_eq!(sent.len(), 2);
        assert_eq!((&sent[0].1[..], &sent[1].1[..]), whole.split_at(3));
        // The first write leaves the wire three characters later; then the gap. tokio's timer
        // wakes both writes on whole milliseconds.
        let apart = sent[1].0 - sent[0].0;
        let expected = timing().frame_time(3) + gap;
        let tick = Duration::from_millis(1);
        assert!(
            apart + tick >= expected && apart <= expected + tick,
            "{apart:?}"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn bad_crcs_other_addresses_and_broadcasts_get_no_reply() {
        let mut corrupt = READ;
        corrupt[7] ^= 0xFF;
        let mut other = READ.to_vec();
        other[0] = 9;
        let other = rtu::encode(9, rtu::pdu_of(&other));
        let broadcast = rtu::encode(0, &[0x06, 0x00, 0x01, 0x00, 0x07]);
        let read_back = rtu::encode(2, &[0x03, 0x00, 0x01, 0x00, 0x01]);
        let (sent, stats) = run(vec![
            (Duration::ZERO, corrupt.to_vec()),
            (Duration::from_millis(10), other),
            (Duration::from_millis(20), broadcast),
            (Duration::from_millis(30), read_back),
        ])
        .await;
        // Only the read after the broadcast is answered, and it shows the broadcast was obeyed.
        let replies: Vec<_> = sent.into_iter().map(|(_, bytes)| bytes).collect();
        assert_eq!(replies, [rtu::encode(2, &[0x03, 0x02, 0x00, 0x07])]);
        assert_eq!(stats.bad_frames, 1);
        assert_eq!(stats.others, 1);
    }

    #[tokio::test(start_paused = true)]
    async fn a_frame_cut_short_by_silence_is_dropped_and_the_next_one_answered() {
        let (sent, stats) = run(vec![
            (Duration::ZERO, READ[..5].to_vec()),
            (Duration::from_millis(50), READ.to_vec()),
        ])
        .await;
        assert_eq!(sent.len(), 1);
        assert_eq!(stats.bad_frames, 1);
    }
}
