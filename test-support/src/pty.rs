//! An RTU slave on a pty pair: the real serial path, with no hardware.

use modbus_gateway::testing::line::rtu::{self, FrameLen};
use modbus_gateway::testing::sim::{RegisterBank, Simulated};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::task::JoinHandle;
use tokio_serial::{SerialPort, SerialStream};

/// A pty passes a frame in one write; a user-defined frame is taken as complete after this pause.
const PTY_FRAME_PAUSE: Duration = Duration::from_millis(20);

type Responder = Box<dyn FnMut(&[u8]) -> Option<Vec<u8>> + Send>;

/// An RTU slave on the far end of a pty pair; the gateway opens `path` like a serial device.
pub struct PtySlave {
    pub path: String,
    received: Arc<Mutex<Vec<Vec<u8>>>>,
    task: JoinHandle<()>,
    /// Kept open so the pty stays usable until the gateway opens it.
    _tty: SerialStream,
}

impl PtySlave {
    /// `respond` gets each whole request frame and returns the bytes to answer with, if any.
    pub fn start(respond: impl FnMut(&[u8]) -> Option<Vec<u8>> + Send + 'static) -> Self {
        let (mut master, tty) = SerialStream::pair().expect("pty pair");
        let path = tty.name().expect("pty has a path");
        let received = Arc::new(Mutex::new(Vec::new()));
        let log = received.clone();
        let mut respond: Responder = Box::new(respond);
        let task = tokio::spawn(async move {
            let mut buf = Vec::new();
            let mut chunk = [0u8; 512];
            loop {
                let complete = match rtu::request_len(&buf) {
                    FrameLen::Exact(n) if buf.len() >= n => Some(n),
                    FrameLen::Invalid => Some(buf.len()),
                    _ => None,
                };
                if let Some(n) = complete {
                    let request: Vec<u8> = buf.drain(..n).collect();
                    log.lock().unwrap().push(request.clone());
                    if let Some(reply) = respond(&request) {
                        if master.write_all(&reply).await.is_err() {
                            return;
                        }
                    }
                    continue;
                }
                let by_silence = rtu::request_len(&buf) == FrameLen::BySilence;
                let read = master.read(&mut chunk);
                let n = if by_silence {
                    match tokio::time::timeout(PTY_FRAME_PAUSE, read).await {
                        Ok(result) => result,
                        Err(_) => {
                            let request: Vec<u8> = std::mem::take(&mut buf);
                            log.lock().unwrap().push(request.clone());
                            if let Some(reply) = respond(&request) {
                                if master.write_all(&reply).await.is_err() {
                                    return;
                                }
                            }
                            continue;
                        }
                    }
                } else {
                    read.await
                };
                match n {
                    Ok(n) if n > 0 => buf.extend_from_slice(&chunk[..n]),
                    _ => return,
                }
            }
        });
        PtySlave {
            path,
            received,
            task,
            _tty: tty,
        }
    }

    /// Register-bank slaves at every address, answering like the simulated ones.
    pub fn registers() -> Self {
        let mut bank = RegisterBank::new(Duration::ZERO);
        Self::start(move |request| {
            if !rtu::crc_ok(request) {
                return None;
            }
            let now = tokio::time::Instant::now();
            bank.handle(request[0], rtu::pdu_of(request), now)
                .map(|t| t.bytes)
        })
    }

    /// Every request frame received so far, byte for byte.
    pub fn received(&self) -> Vec<Vec<u8>> {
        self.received.lock().unwrap().clone()
    }

    /// Pull the plug: the pty goes away and the gateway's reads fail.
    pub fn unplug(self) {
        self.task.abort();
    }
}

impl Drop for PtySlave {
    fn drop(&mut self) {
        self.task.abort();
    }
}
