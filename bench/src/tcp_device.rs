//! The far end of the tcp-device line: a Modbus TCP device in the bench's process that answers
//! every read of holding registers and every write of one register at once, or a fixed time after
//! each request came (several outstanding at once if they come so, each answered on time by the
//! precise timer), on a loopback port, each connection in a task of its own, stopped when dropped.
//! Knows nothing of the gateway or of whoever else connects to it.

use std::net::SocketAddr;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// The MBAP header: transaction id, protocol id, length, unit id.
const HEADER_LEN: usize = 7;
/// Read holding registers.
const READ_HOLDING: u8 = 0x03;
/// Write single register: address and value, echoed in the reply.
const WRITE_SINGLE: u8 = 0x06;
/// The most registers one read may ask for.
const MAX_READ: u16 = 125;
/// The exception codes it answers with: a function it does not serve, a count out of range.
const ILLEGAL_FUNCTION: u8 = 0x01;
const ILLEGAL_VALUE: u8 = 0x03;

/// The device while it lives.
pub(crate) struct TcpDevice {
    pub(crate) addr: SocketAddr,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for TcpDevice {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl TcpDevice {
    /// A device listening on 127.0.0.1, on a port of the system's choosing, answering each
    /// request `delay` after it came.
    pub(crate) async fn start(delay: Duration) -> Result<TcpDevice, String> {
        let listener = TcpListener::bind("127.0.0.1:0")
            .await
            .map_err(|e| format!("the Modbus TCP device: {e}"))?;
        let addr = listener.local_addr().map_err(|e| e.to_string())?;
        let task = tokio::spawn(async move {
            let mut connections = tokio::task::JoinSet::new();
            while let Ok((stream, _)) = listener.accept().await {
                if delay.is_zero() {
                    connections.spawn(serve(stream));
                } else {
                    connections.spawn(serve_after(stream, delay));
                }
            }
        });
        Ok(TcpDevice { addr, task })
    }

    /// What to give the gateway's bus as its `device`.
    pub(crate) fn device(&self) -> String {
        format!("tcp://{}", self.addr)
    }
}

/// Answer every whole request `stream` brings, as it comes, until it closes.
async fn serve(mut stream: TcpStream) {
    if stream.set_nodelay(true).is_err() {
        return;
    }
    let mut received = Vec::with_capacity(512);
    let mut replies = Vec::with_capacity(512);
    let mut chunk = [0u8; 512];
    loop {
        let mut start = 0;
        while let Answer::Answered(used) = answer(&received[start..], &mut replies) {
            start += used;
        }
        received.drain(..start);
        if !replies.is_empty() {
            if stream.write_all(&replies).await.is_err() {
                return;
            }
            replies.clear();
        }
        match stream.read(&mut chunk).await {
            Ok(n) if n > 0 => received.extend_from_slice(&chunk[..n]),
            _ => return,
        }
    }
}

/// Answer every whole request `stream` brings `delay` after it came, until it closes: each
/// request waits in a task of its own, and the replies go out in the order they fall due.
async fn serve_after(stream: TcpStream, delay: Duration) {
    if stream.set_nodelay(true).is_err() {
        return;
    }
    let (mut reader, mut writer) = stream.into_split();
    let (due, mut replies) = tokio::sync::mpsc::unbounded_channel::<Vec<u8>>();
    let writing = tokio::spawn(async move {
        while let Some(reply) = replies.recv().await {
            if writer.write_all(&reply).await.is_err() {
                return;
            }
        }
    });
    let mut received = Vec::with_capacity(512);
    let mut chunk = [0u8; 512];
    loop {
        match reader.read(&mut chunk).await {
            Ok(n) if n > 0 => received.extend_from_slice(&chunk[..n]),
            _ => break,
        }
        let came = tokio::time::Instant::now();
        let mut start = 0;
        loop {
            let mut reply = Vec::new();
            let Answer::Answered(used) = answer(&received[start..], &mut reply) else {
                break;
            };
            start += used;
            let due = due.clone();
            tokio::spawn(async move {
                modbus_gateway::testing::timer::sleep_until(came + delay).await;
                let _ = due.send(reply);
            });
        }
        received.drain(..start);
    }
    writing.abort();
}

/// What [`answer`] made of the bytes received so far.
#[derive(Debug, PartialEq)]
enum Answer {
    /// A whole request of this many bytes, whose reply is written.
    Answered(usize),
    /// Not yet a whole request.
    NeedMore,
}

/// The reply to the request at the start of `received`, appended to `out`: for a read of
/// holding registers, register n holds n (wrapping); a write of one register is acknowledged
/// with its echo, as a device does, and changes nothing; anything else an exception. The
/// transaction and unit ids are echoed.
fn answer(received: &[u8], out: &mut Vec<u8>) -> Answer {
    let Some(header) = received.get(..HEADER_LEN) else {
        return Answer::NeedMore;
    };
    // The length counts the unit id and the PDU; a length of 0 is taken as a unit id alone.
    let length = usize::from(u16::from_be_bytes([header[4], header[5]])).max(1);
    let Some(pdu) = received.get(HEADER_LEN..HEADER_LEN - 1 + length) else {
        return Answer::NeedMore;
    };
    let function = pdu.first().copied().unwrap_or(0);
    let word = |at: usize| Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]));
    let mut reply_pdu = Vec::with_capacity(2 + 2 * usize::from(MAX_READ));
    match (function, word(1), word(3)) {
        (READ_HOLDING, Some(first), Some(count)) if (1..=MAX_READ).contains(&count) => {
            reply_pdu.push(READ_HOLDING);
            // At most 250 bytes, by MAX_READ.
            reply_pdu.push(u8::try_from(2 * count).unwrap_or(u8::MAX));
            for register in 0..count {
                reply_pdu.extend_from_slice(&first.wrapping_add(register).to_be_bytes());
            }
        }
        (READ_HOLDING, ..) => reply_pdu.extend_from_slice(&[READ_HOLDING | 0x80, ILLEGAL_VALUE]),
        (WRITE_SINGLE, Some(_), Some(_)) if pdu.len() == 5 => reply_pdu.extend_from_slice(pdu),
        _ => reply_pdu.extend_from_slice(&[function | 0x80, ILLEGAL_FUNCTION]),
    }
    out.extend_from_slice(&header[..4]);
    // At most 252 bytes, by MAX_READ.
    let reply_length = u16::try_from(reply_pdu.len() + 1).unwrap_or(u16::MAX);
    out.extend_from_slice(&reply_length.to_be_bytes());
    out.push(header[6]);
    out.extend_from_slice(&reply_pdu);
    Answer::Answered(HEADER_LEN - 1 + length)
}

#[cfg(test)]
mod tests {
    use super::{answer, Answer};

    /// Transaction 0x1234, unit 7: read 2 holding registers from 0x0010.
    const READ: [u8; 12] = [
        0x12, 0x34, // transaction id
        0x00, 0x00, // protocol id
        0x00, 0x06, // length: unit id and 5 bytes of PDU
        0x07, // unit id
        0x03, // read holding registers
        0x00, 0x10, // first register
        0x00, 0x02, // count
    ];
    /// Its reply: registers 0x0010 and 0x0011 hold their own numbers.
    const REPLY: [u8; 13] = [
        0x12, 0x34, // the same transaction id
        0x00, 0x00, // protocol id
        0x00, 0x07, // length: unit id and 6 bytes of PDU
        0x07, // the same unit id
        0x03, // read holding registers
        0x04, // 4 bytes of values
        0x00, 0x10, // register 0x0010
        0x00, 0x11, // register 0x0011
    ];

    #[test]
    fn a_whole_read_is_answered_with_the_registers_own_numbers_and_the_ids_echoed() {
        let mut out = Vec::new();
        assert_eq!(answer(&READ, &mut out), Answer::Answered(READ.len()));
        assert_eq!(out, REPLY);
    }

    #[test]
    fn a_read_arriving_byte_by_byte_is_answered_once_it_is_whole() {
        let mut out = Vec::new();
        for end in 0..READ.len() {
            assert_eq!(answer(&READ[..end], &mut out), Answer::NeedMore, "{end}");
        }
        assert!(out.is_empty());
        assert_eq!(answer(&READ, &mut out), Answer::Answered(READ.len()));
        assert_eq!(out, REPLY);
    }

    #[test]
    fn two_reads_in_one_buffer_are_answered_in_turn() {
        let two = [READ, READ].concat();
        let mut out = Vec::new();
        assert_eq!(answer(&two, &mut out), Answer::Answered(READ.len()));
        assert_eq!(
            answer(&two[READ.len()..], &mut out),
            Answer::Answered(READ.len())
        );
        assert_eq!(out, [REPLY, REPLY].concat());
    }

    #[test]
    fn a_write_of_one_register_is_answered_with_its_echo() {
        let mut write = READ;
        write[7] = 0x06; // write single register
        write[10..12].copy_from_slice(&0x1234u16.to_be_bytes()); // its value
        let mut out = Vec::new();
        assert_eq!(answer(&write, &mut out), Answer::Answered(write.len()));
        assert_eq!(out, write);
    }

    #[test]
    fn other_functions_and_counts_out_of_range_get_an_exception() {
        let mut coil = READ;
        coil[7] = 0x05; // write single coil
        let mut out = Vec::new();
        assert_eq!(answer(&coil, &mut out), Answer::Answered(READ.len()));
        assert_eq!(out, [0x12, 0x34, 0, 0, 0, 3, 0x07, 0x85, 0x01]);
        let mut too_many = READ;
        too_many[10..12].copy_from_slice(&126u16.to_be_bytes());
        out.clear();
        assert_eq!(answer(&too_many, &mut out), Answer::Answered(READ.len()));
        assert_eq!(out, [0x12, 0x34, 0, 0, 0, 3, 0x07, 0x83, 0x03]);
    }
}
