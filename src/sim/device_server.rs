//! The simulated line behind a serial device server in transparent (raw TCP) mode, as
//! `simulate --listen` serves it: the client's bytes go on the [`SimLine`] as its master's, and
//! the slaves' answers come back as bytes on the stream, with no MBAP and no framing added.
//!
//! How bytes become frames: a request's end is found by its length, as the line's slaves hear
//! requests (RTU: the function's length rule; ASCII: the LF), so a frame split across TCP
//! segments is still one frame on the wire. A request whose length its bytes cannot tell ends
//! after the line's `silence`; one still short of its length [`SPLIT_TOLERANCE`] after its last
//! byte goes on the wire as it is (the line drops it, as a cut-short frame); bytes that cannot
//! start a frame go on the wire at once as garbage. The line then judges them as it judges any
//! master's: wrong CRC, other address, broadcast.
//!
//! How timing is kept: the line does it. A request goes on the wire when its last byte has come
//! in, at the line's baud; its slave answers after t3.5 and its own delay, byte by byte at the
//! character time. A reply is written to the stream once its last byte is off the wire (a burst
//! is the bytes that follow each other without a pause; a paused reply goes out as two writes),
//! so no byte reaches the socket sooner than the wire could carry it. Like the UART of a device
//! server that queues what it is given, a request starts no sooner than t3.5 (RTU) after the
//! wire last fell silent: a master that knows nothing of the line's gaps is still heard.
//!
//! Knows nothing of listening sockets or of who the client is: that is `cli::simulate`'s.

use super::line::{SimLine, SimPort};
use crate::line::framing::{Completion, Silence};
use crate::line::{Framing, Transport};
use crate::timer::sleep_until;
use std::io;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;

/// How long the rest of a request whose length is known may take to come in after its last
/// byte: TCP may split a frame, and a link may delay a segment, by far more than t3.5.
pub(crate) const SPLIT_TOLERANCE: Duration = Duration::from_millis(500);

/// What one client did, for its log line.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct ClientStats {
    /// Frames (or garbage) put on the wire.
    pub(crate) requests: u64,
    /// Replies (bursts) written back.
    pub(crate) replies: u64,
}

/// The master's end of a simulated line, served to one stream at a time.
pub(crate) struct DeviceServer {
    line: SimLine,
    framing: Framing,
    /// Silence that ends a request whose length its bytes cannot tell.
    silence: Duration,
}

/// Where a client's request stands.
enum Pending {
    /// Nothing to send: wait for bytes.
    Nothing,
    /// Put these many bytes on the wire now.
    Send(usize),
    /// Wait for more bytes until then; then send what there is.
    Until(Instant),
}

impl DeviceServer {
    /// Serve `line`, whose slaves hear `framing`; `silence` ends a request of unknown length.
    pub(crate) fn new(line: SimLine, framing: Framing, silence: Duration) -> Self {
        DeviceServer {
            line,
            framing,
            silence,
        }
    }

    /// Carry bytes between `stream` and the line until the client closes it (or it fails).
    /// The slaves keep their state from one client to the next; bytes of an earlier client's
    /// replies still on the wire are not handed to this one.
    pub(crate) async fn serve<S>(&self, stream: &mut S) -> (ClientStats, io::Result<()>)
    where
        S: AsyncRead + AsyncWrite + Unpin,
    {
        let mut stats = ClientStats::default();
        let result = match self.line.open() {
            Ok(mut port) => self.carry(stream, &mut port, &mut stats).await,
            Err(e) => Err(e),
        };
        (stats, result)
    }

    async fn carry<S>(
        &self,
        stream: &mut S,
        port: &mut SimPort,
        stats: &mut ClientStats,
    ) -> io::Result<()>
    where
        S: AsyncRead + AsyncWrite + Unpin,
    {
        let mut request = Vec::with_capacity(self.framing.max_frame_len());
        let mut last_in = Instant::now();
        let mut reply = Vec::new();
        let mut chunk = [0u8; 512];
        loop {
            let wait_until = match self.pending(&request, last_in) {
                Pending::Send(n) => {
                    let frame: Vec<u8> = request.drain(..n).collect();
                    self.transmit(port, &frame).await?;
                    stats.requests += 1;
                    continue;
                }
                Pending::Until(at) => Some(at),
                Pending::Nothing => None,
            };
            tokio::select! {
                biased;
                read = stream.read(&mut chunk) => match read? {
                    0 => return Ok(()),
                    n => {
                        request.extend_from_slice(&chunk[..n]);
                        last_in = Instant::now();
                    }
                },
                received = port.recv(&mut reply) => {
                    if received? == 0 {
                        return Err(io::Error::other("the simulated line went away"));
                    }
                    if self.burst_over(port) {
                        stream.write_all(&reply).await?;
                        reply.clear();
                        stats.replies += 1;
                    }
                }
                () = sleep_until(wait_until.unwrap_or(last_in)), if wait_until.is_some() => {
                    let frame = std::mem::take(&mut request);
                    self.transmit(port, &frame).await?;
                    stats.requests += 1;
                }
            }
        }
    }

    /// What to do with the bytes received so far, the last of them at `last_in`.
    fn pending(&self, request: &[u8], last_in: Instant) -> Pending {
        if request.is_empty() {
            return Pending::Nothing;
        }
        if request.len() > self.framing.max_frame_len() {
            return Pending::Send(request.len());
        }
        match self.framing.request_completion(request) {
            Completion::Whole(n) => Pending::Send(n),
            Completion::Invalid => Pending::Send(request.len()),
            Completion::Open(Silence::EndsFrame) => Pending::Until(last_in + self.silence),
            Completion::AtLeast(_) | Completion::Open(Silence::FailsFrame) => {
                Pending::Until(last_in + SPLIT_TOLERANCE)
            }
        }
    }

    /// Put `frame` on the wire once the line has been quiet for the gap.
    async fn transmit(&self, port: &mut SimPort, frame: &[u8]) -> io::Result<()> {
        if self.framing == Framing::Rtu {
            if let Some(quiet) = self.line.quiet_at() {
                sleep_until(quiet + self.line.timing().t35).await;
            }
        }
        port.send(frame).await
    }

    /// Whether the bytes received so far end a burst: no byte follows within a character time.
    fn burst_over(&self, port: &SimPort) -> bool {
        let char_time = self.line.timing().char_time;
        port.next_arrival()
            .is_none_or(|next| next > Instant::now() + char_time)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::{rtu, LineTiming, Parity, SerialFormat};
    use crate::sim::{RegisterBank, Source};
    use tokio::io::DuplexStream;

    const DELAY: Duration = Duration::from_millis(2);

    fn server() -> (SimLine, DeviceServer) {
        let timing = LineTiming::new(&SerialFormat {
            baud: 9600,
            data_bits: 8,
            parity: Parity::Even,
            stop_bits: 1,
        });
        let line = SimLine::new(timing);
        line.add_slave(1, RegisterBank::new(DELAY));
        (
            line.clone(),
            DeviceServer::new(line, Framing::Rtu, timing.t35),
        )
    }

    /// A client on one end of an in-memory stream, the server on the other until it closes.
    fn connect(server: DeviceServer) -> (DuplexStream, tokio::task::JoinHandle<ClientStats>) {
        let (client, mut far) = tokio::io::duplex(1024);
        let served = tokio::spawn(async move {
            let (stats, result) = server.serve(&mut far).await;
            result.unwrap();
            stats
        });
        (client, served)
    }

    /// Goodrive300 manual 10.4.1: read 2 words from 0004H of slave 01H.
    const READ: [u8; 8] = [0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA];

    #[tokio::test(start_paused = true)]
    async fn a_reply_reaches_the_stream_only_once_its_last_byte_is_off_the_wire() {
        let (line, server) = server();
        let timing = line.timing();
        let (mut client, served) = connect(server);
        let t0 = Instant::now();
        client.write_all(&READ).await.unwrap();
        let mut reply = [0u8; 9];
        client.read_exact(&mut reply).await.unwrap();
        let arrived = Instant::now();
        assert_eq!(reply[..], rtu::encode(1, &[0x03, 0x04, 0, 0, 0, 0])[..]);
        let frames = line.frames();
        assert_eq!(frames.len(), 2);
        assert_eq!(
            (frames[0].from, &frames[0].bytes[..]),
            (Source::Master, &READ[..])
        );
        assert_eq!(frames[1].from, Source::Slave(1));
        // Request on the wire, t3.5, the slave's delay, nine characters of reply.
        let on_the_wire = timing.frame_time(8) + timing.t35 + DELAY + timing.frame_time(9);
        assert_eq!(frames[1].end - t0, on_the_wire);
        assert!(arrived >= frames[1].end, "{:?}", arrived - t0);
        drop(client);
        assert_eq!(
            served.await.unwrap(),
            ClientStats {
                requests: 1,
                replies: 1
            }
        );
    }

    #[tokio::test(start_paused = true)]
    async fn a_request_split_across_writes_is_one_frame_on_the_wire() {
        let (line, server) = server();
        let (mut client, _served) = connect(server);
        client.write_all(&READ[..3]).await.unwrap();
        tokio::time::sleep(SPLIT_TOLERANCE / 2).await;
        client.write_all(&READ[3..]).await.unwrap();
        let mut reply = [0u8; 9];
        client.read_exact(&mut reply).await.unwrap();
        assert!(rtu::crc_ok(&reply));
        assert_eq!(line.frames()[0].bytes, READ);
        assert_eq!(line.stats().unread_frames, 0);
    }

    #[tokio::test(start_paused = true)]
    async fn garbage_and_a_request_cut_short_go_unanswered_and_the_next_request_is_answered() {
        let (line, server) = server();
        let (mut client, _served) = connect(server);
        // Not a frame (address 250 is out of range), then half a read left to time out.
        client.write_all(&[0xFA, 0xFA]).await.unwrap();
        tokio::time::sleep(Duration::from_millis(10)).await;
        client.write_all(&READ[..4]).await.unwrap();
        tokio::time::sleep(SPLIT_TOLERANCE * 2).await;
        // A broadcast write is obeyed and unanswered; the read shows it.
        client
            .write_all(&rtu::encode(0, &[0x06, 0x00, 0x04, 0x00, 0x07]))
            .await
            .unwrap();
        client.write_all(&READ).await.unwrap();
        let mut reply = [0u8; 9];
        client.read_exact(&mut reply).await.unwrap();
        assert_eq!(reply[..], rtu::encode(1, &[0x03, 0x04, 0, 7, 0, 0])[..]);
        let stats = line.stats();
        assert_eq!((stats.master_frames, stats.slave_frames), (4, 1));
        assert_eq!(stats.unread_frames, 2, "the garbage and the cut-short read");
        assert_eq!(stats.gap_violations, 0, "the server kept the gap");
    }

    #[tokio::test(start_paused = true)]
    async fn a_reply_with_a_pause_in_it_reaches_the_stream_as_two_writes_the_pause_apart() {
        let (line, server) = server();
        let gap = Duration::from_millis(30);
        let faults = crate::sim::faults::Faults {
            reply_gap: Some(crate::sim::Pause { after: 3, gap }),
            ..Default::default()
        };
        line.add_slave(
            2,
            crate::sim::faults::Faulty::new(RegisterBank::new(Duration::ZERO), faults, 2),
        );
        let (mut client, _served) = connect(server);
        client
            .write_all(&rtu::encode(2, &[0x03, 0x00, 0x00, 0x00, 0x01]))
            .await
            .unwrap();
        let mut first = [0u8; 3];
        client.read_exact(&mut first).await.unwrap();
        let first_at = Instant::now();
        let mut rest = [0u8; 4];
        client.read_exact(&mut rest).await.unwrap();
        // The rest leaves the wire after the pause and its four characters, and not before.
        let timing = line.timing();
        assert!(Instant::now() - first_at >= gap + timing.frame_time(4));
        assert_eq!(
            [&first[..], &rest[..]].concat(),
            rtu::encode(2, &[0x03, 0x02, 0x00, 0x00])
        );
    }

    #[tokio::test(start_paused = true)]
    async fn the_slaves_keep_their_registers_from_one_client_to_the_next() {
        let (line, server) = server();
        let server = std::sync::Arc::new(server);
        for (pdu, expected) in [
            (
                &[0x06, 0x00, 0x04, 0x00, 0x2A][..],
                &[0x06, 0x00, 0x04, 0x00, 0x2A][..],
            ),
            (
                &[0x03, 0x00, 0x04, 0x00, 0x01][..],
                &[0x03, 0x02, 0x00, 0x2A][..],
            ),
        ] {
            let (mut client, mut far) = tokio::io::duplex(1024);
            let server = server.clone();
            let served = tokio::spawn(async move { server.serve(&mut far).await.1 });
            client.write_all(&rtu::encode(1, pdu)).await.unwrap();
            let mut reply = vec![0u8; expected.len() + 3];
            client.read_exact(&mut reply).await.unwrap();
            assert_eq!(reply, rtu::encode(1, expected));
            drop(client);
            served.await.unwrap().unwrap();
        }
        assert_eq!(line.stats().slave_frames, 2);
    }
}
