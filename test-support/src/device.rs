//! A fake Modbus TCP device that pipelines: it answers each request a fixed time after it came,
//! several outstanding at once if they come so, and keeps the most it ever held unanswered. Over
//! any stream, so the same device is behind a loopback socket (tests/tcp_device.rs) and behind
//! tokio's in-memory pipe (the pipelined loop's unit tests in `src/bus/`). It names none of the
//! library's types, so the library's own unit tests may use it.

use crate::frames::mbap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};

/// Read holding register `register`, one of them.
pub fn read(register: u16) -> Vec<u8> {
    let [hi, lo] = register.to_be_bytes();
    vec![0x03, hi, lo, 0x00, 0x01]
}

/// The device's answer to [`read`]: the register's own number as its value.
pub fn answer_to(request: &[u8]) -> Vec<u8> {
    vec![0x03, 0x02, request[1], request[2]]
}

/// Answer every read `stream` brings with [`answer_to`], `delay` after it came, echoing the
/// transaction and unit ids, until the stream closes. Each request waits in a task of its own;
/// `most` is raised to the most requests held unanswered at once.
pub async fn answer_each_after<S>(stream: S, delay: Duration, most: Arc<AtomicUsize>)
where
    S: AsyncRead + AsyncWrite + Send + 'static,
{
    let (mut reader, writer) = tokio::io::split(stream);
    let writer = Arc::new(tokio::sync::Mutex::new(writer));
    let pending = Arc::new(AtomicUsize::new(0));
    loop {
        let mut header = [0u8; 7];
        if reader.read_exact(&mut header).await.is_err() {
            return;
        }
        let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
        let mut pdu = vec![0u8; length - 1];
        if reader.read_exact(&mut pdu).await.is_err() {
            return;
        }
        let now = pending.fetch_add(1, Ordering::SeqCst) + 1;
        most.fetch_max(now, Ordering::SeqCst);
        let (writer, pending) = (writer.clone(), pending.clone());
        tokio::spawn(async move {
            tokio::time::sleep(delay).await;
            let transaction = u16::from_be_bytes([header[0], header[1]]);
            let frame = mbap(transaction, header[6], &answer_to(&pdu));
            pending.fetch_sub(1, Ordering::SeqCst);
            let _ = writer.lock().await.write_all(&frame).await;
        });
    }
}
