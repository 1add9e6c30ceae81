//! Several requests outstanding at once on a Modbus TCP device's connection (`max_in_flight`
//! above 1): each sent with the gateway's own transaction id, and the replies, in whatever order
//! they come, read off the stream as whole MBAP frames for the caller to match by that id. No
//! gap, no silence rules; a stream that stops being MBAP cannot be followed any more and is an
//! error (the caller makes the connection anew). Knows nothing of queues or what a reply means.

use super::engine::LineCounters;
use super::framing::{Completion, Framing};
use super::Transport;
use crate::mbap;
use std::io;

/// One whole frame from the device.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Frame {
    pub transaction: u16,
    pub unit: u8,
    pub pdu: Vec<u8>,
    /// The frame as it came.
    pub bytes: Vec<u8>,
}

pub(crate) struct Pipeline<T> {
    port: T,
    transaction: u16,
    tx: Vec<u8>,
    rx: Vec<u8>,
    counters: LineCounters,
}

impl<T: Transport> Pipeline<T> {
    pub(crate) fn new(port: T) -> Self {
        Pipeline {
            port,
            transaction: 0,
            tx: Vec::with_capacity(mbap::MAX_FRAME_LEN),
            rx: Vec::with_capacity(2 * mbap::MAX_FRAME_LEN),
            counters: LineCounters::default(),
        }
    }

    /// Send `pdu` to `unit` under the next transaction id; returns the id and the frame sent.
    pub(crate) async fn send(&mut self, unit: u8, pdu: &[u8]) -> io::Result<(u16, &[u8])> {
        self.transaction = self.transaction.wrapping_add(1);
        Framing::Tcp.encode_into(&mut self.tx, self.transaction, unit, pdu);
        self.port.send(&self.tx).await?;
        self.counters.sent_bytes += self.tx.len() as u64;
        Ok((self.transaction, &self.tx))
    }

    /// The next whole frame from the device. Cancel-safe: bytes read stay for the next call.
    pub(crate) async fn next_frame(&mut self) -> io::Result<Frame> {
        loop {
            match Framing::mbap_completion(&self.rx) {
                Completion::Whole(len) => {
                    let bytes: Vec<u8> = self.rx.drain(..len).collect();
                    // Whole: its header and PDU are in.
                    let (header, pdu) = mbap::split(&bytes).unwrap_or_default();
                    let pdu = pdu.to_vec();
                    return Ok(Frame {
                        transaction: header.transaction,
                        unit: header.unit,
                        pdu,
                        bytes,
                    });
                }
                Completion::Invalid => {
                    return Err(io::Error::new(
                        io::ErrorKind::InvalidData,
                        "the device's bytes are no MBAP frame: the stream cannot be followed",
                    ))
                }
                Completion::AtLeast(_) | Completion::Open(_) => {}
            }
            let n = self.port.recv(&mut self.rx).await?;
            if n == 0 {
                return Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    "the device closed the connection",
                ));
            }
            self.counters.received_bytes += n as u64;
        }
    }

    /// A frame that answered no request in flight was dropped.
    pub(crate) fn discarded(&mut self) {
        self.counters.foreign_frames += 1;
    }

    pub(crate) fn counters(&self) -> LineCounters {
        self.counters
    }

    pub(crate) fn port(&self) -> &T {
        &self.port
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;
    use tokio::time::Instant;

    /// A transport over an in-memory pipe to a fake device.
    struct Pipe(tokio::io::DuplexStream);

    impl Transport for Pipe {
        async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
            tokio::io::AsyncWriteExt::write_all(&mut self.0, frame).await
        }

        fn end_of_transmission(&self, returned: Instant, _: Duration) -> Instant {
            returned
        }

        async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
            let mut chunk = [0u8; 64];
            let n = tokio::io::AsyncReadExt::read(&mut self.0, &mut chunk).await?;
            buf.extend_from_slice(&chunk[..n]);
            Ok(n)
        }

        fn clear_input(&mut self, _: &mut Vec<u8>) -> io::Result<()> {
            Ok(())
        }
    }

    #[tokio::test]
    async fn replies_come_out_whole_in_the_order_the_device_sent_them_however_they_are_cut() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let (near, mut far) = tokio::io::duplex(1024);
        let mut pipeline = Pipeline::new(Pipe(near));
        let (first, _) = pipeline.send(1, &[0x03, 0, 0, 0, 1]).await.unwrap();
        let (second, _) = pipeline.send(1, &[0x03, 0, 1, 0, 1]).await.unwrap();
        assert_eq!((first, second), (1, 2));
        let mut sent = [0u8; 24];
        far.read_exact(&mut sent).await.unwrap();
        // The second answered first, and the two split across writes at odd places.
        let mut replies = Vec::new();
        Framing::Tcp.encode_into(&mut replies, 2, 1, &[0x03, 0x02, 0x00, 0x02]);
        let mut one = Vec::new();
        Framing::Tcp.encode_into(&mut one, 1, 1, &[0x03, 0x02, 0x00, 0x01]);
        replies.extend(one);
        for piece in replies.chunks(5) {
            far.write_all(piece).await.unwrap();
        }
        let a = pipeline.next_frame().await.unwrap();
        let b = pipeline.next_frame().await.unwrap();
        assert_eq!((a.transaction, a.pdu), (2, vec![0x03, 0x02, 0x00, 0x02]));
        assert_eq!((b.transaction, b.pdu), (1, vec![0x03, 0x02, 0x00, 0x01]));
        // Bytes that are no MBAP: the stream cannot be followed.
        far.write_all(&[0, 9, 0, 7, 0, 3, 1, 3, 0]).await.unwrap();
        let error = pipeline.next_frame().await.unwrap_err();
        assert_eq!(error.kind(), io::ErrorKind::InvalidData);
    }
}
