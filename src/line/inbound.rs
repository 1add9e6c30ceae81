//! The slave side of a line: request frames as a slave receives them, for the simulated slaves
//! served on a real port (`simulate`) and the gateway's serial master ports alike. A frame is
//! whole by its length (ASCII: its CR LF), or by silence for function codes whose length the
//! bytes cannot tell; silence before a frame the bytes say is longer (a gap mid-frame), bytes
//! that cannot be a request, or more than a frame's worth of them, break it. Checking the frame
//! (CRC, LRC) and what it asks are the caller's. Knows nothing of what is done with a request.

use super::framing::{Completion, Framing, Silence};
use super::Transport;
use std::io;
use std::time::Duration;
use tokio::time::{timeout_at, Instant};

/// What came off the line.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Received {
    /// A whole frame, unchecked; more bytes may already be in (the next frame's).
    Frame(Vec<u8>),
    /// Bytes that made no frame: cut short by silence, no request's, or too long. Dropped.
    Broken,
}

/// One line's request frames, as they arrive.
pub(crate) struct RequestReader {
    framing: Framing,
    /// Silence that ends a frame whose length its bytes cannot tell, and that breaks one whose
    /// bytes are not all in (at least t3.5 on RTU; ASCII's inter-character timeout).
    silence: Duration,
    buf: Vec<u8>,
    /// When the last bytes came in.
    last: Instant,
}

impl RequestReader {
    pub(crate) fn new(framing: Framing, silence: Duration) -> Self {
        RequestReader {
            framing,
            silence,
            buf: Vec::with_capacity(framing.max_frame_len()),
            last: Instant::now(),
        }
    }

    /// The next frame off `port`, or the next run of bytes that made none. Cancel-safe: bytes
    /// received are kept, and silence counts from the last of them. An error is the port's
    /// (`UnexpectedEof`: it reads 0 bytes, the device is gone).
    pub(crate) async fn next<T: Transport>(&mut self, port: &mut T) -> io::Result<Received> {
        loop {
            let completion = self.framing.request_completion(&self.buf);
            match completion {
                Completion::Whole(n) => return Ok(Received::Frame(self.buf.drain(..n).collect())),
                Completion::Invalid => {
                    self.buf.clear();
                    return Ok(Received::Broken);
                }
                _ if self.buf.len() > self.framing.max_frame_len() => {
                    self.buf.clear();
                    return Ok(Received::Broken);
                }
                _ => {}
            }
            let received = if self.buf.is_empty() {
                port.recv(&mut self.buf).await
            } else {
                match timeout_at(self.last + self.silence, port.recv(&mut self.buf)).await {
                    Ok(received) => received,
                    Err(_) => {
                        // Silence ends the frame: whole if only silence could tell its length,
                        // otherwise cut short.
                        let frame = std::mem::take(&mut self.buf);
                        return Ok(if completion == Completion::Open(Silence::EndsFrame) {
                            Received::Frame(frame)
                        } else {
                            Received::Broken
                        });
                    }
                }
            };
            match received {
                Ok(0) => {
                    return Err(io::Error::new(
                        io::ErrorKind::UnexpectedEof,
                        "the port reads 0 bytes (device gone)",
                    ))
                }
                Ok(_) => self.last = Instant::now(),
                Err(e) => return Err(e),
            }
        }
    }
}
