//! The transaction engine on a line that hands back every byte it sends (`rs485.echo`), and on
//! a port that returns from `send` only once the frame is out (`rs485.mode = "rts"`), on tokio's
//! paused clock over a scripted line.

use super::*;
use crate::line::rtu;
use crate::line::{Parity, SerialFormat};
use std::collections::VecDeque;

const TIMEOUT: Duration = Duration::from_millis(100);
/// tokio's timer wakes sleepers on whole milliseconds, paused clock included.
const TIMER_RESOLUTION: Duration = Duration::from_millis(1);
/// Read two holding registers from 0004H (Goodrive300 manual 10.4.1).
const READ: [u8; 5] = [0x03, 0x00, 0x04, 0x00, 0x02];
/// Its answer: 0004H = 1388H, 0005H = 0.
const READ_ANSWER: [u8; 6] = [0x03, 0x04, 0x13, 0x88, 0x00, 0x00];

/// A line that, for each frame sent, hands back what `echo` makes of the frame, then `reply`;
/// its `send` takes `send_time` and, if `returns_when_sent`, says it returns once the frame is
/// out; `driver_delays` is the time a kernel's RS-485 mode adds around a frame.
struct ScriptedLine {
    pending: VecDeque<u8>,
    echo: fn(&[u8]) -> Vec<u8>,
    reply: Vec<u8>,
    send_time: Duration,
    returns_when_sent: bool,
    driver_delays: Duration,
}

impl Transport for ScriptedLine {
    async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        tokio::time::sleep(self.send_time).await;
        self.pending.extend((self.echo)(frame));
        self.pending.extend(&self.reply);
        Ok(())
    }

    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        if self.pending.is_empty() {
            std::future::pending::<()>().await;
        }
        let n = self.pending.len();
        buf.extend(self.pending.drain(..));
        Ok(n)
    }

    fn clear_input(&mut self, _stale: &mut Vec<u8>) -> io::Result<()> {
        Ok(())
    }

    fn end_of_transmission(&self, returned: Instant, frame_time: Duration) -> Instant {
        if self.returns_when_sent {
            returned
        } else {
            returned + self.driver_delays + frame_time
        }
    }
}

fn master(echo: fn(&[u8]) -> Vec<u8>, reply: Vec<u8>) -> LineMaster<ScriptedLine> {
    let line = LineTiming::new(&SerialFormat {
        baud: 9600,
        data_bits: 8,
        parity: Parity::Even,
        stop_bits: 1,
    });
    let port = ScriptedLine {
        pending: VecDeque::new(),
        echo,
        reply,
        send_time: Duration::ZERO,
        returns_when_sent: false,
        driver_delays: Duration::ZERO,
    };
    let mut master = LineMaster::new(
        port,
        Framing::Rtu,
        MasterTiming::new(line, Duration::ZERO, Duration::ZERO),
    );
    master.set_echo(true);
    master
}

fn as_sent(frame: &[u8]) -> Vec<u8> {
    frame.to_vec()
}

#[tokio::test(start_paused = true)]
async fn the_echo_of_the_request_is_dropped_and_the_reply_after_it_returned() {
    let mut master = master(as_sent, rtu::encode(1, &READ_ANSWER));
    let reply = master.transact(1, &READ, TIMEOUT).await.unwrap();
    assert_eq!(reply, Reply::Fits(READ_ANSWER.to_vec()));
    let counters = master.counters();
    assert_eq!((counters.foreign_frames, counters.stray_bytes), (0, 0));
    // The request's 8 bytes came back, then the reply's 9.
    assert_eq!(counters.received_bytes, 8 + 9);
}

#[tokio::test(start_paused = true)]
async fn an_echo_that_differs_from_the_frame_sent_fails_the_try() {
    fn collided(frame: &[u8]) -> Vec<u8> {
        let mut echo = frame.to_vec();
        echo[3] ^= 0x10;
        echo
    }
    let mut master = master(collided, rtu::encode(1, &READ_ANSWER));
    let result = master.transact(1, &READ, TIMEOUT).await;
    assert!(matches!(result, Err(TxError::Echo)), "{result:?}");
    assert!(
        master.late_reply_window(1).is_some(),
        "the request may have reached the slave"
    );
}

#[tokio::test(start_paused = true)]
async fn a_missing_echo_fails_the_try_within_the_response_timeout() {
    let mut master = master(|_| Vec::new(), Vec::new());
    master.wait_for_gap(TIMEOUT).await.unwrap();
    let started = Instant::now();
    let result = master.transact(1, &READ, TIMEOUT).await;
    assert!(matches!(result, Err(TxError::Echo)), "{result:?}");
    let frame_time = master.timing.line.frame_time(8);
    assert!(started.elapsed() <= frame_time + TIMEOUT + TIMER_RESOLUTION);
}

#[tokio::test(start_paused = true)]
async fn a_port_that_returns_once_the_frame_is_out_starts_the_response_timeout_then() {
    let mut master = master(|_| Vec::new(), Vec::new());
    master.set_echo(false);
    let send_time = Duration::from_millis(30);
    master.port.send_time = send_time;
    master.port.returns_when_sent = true;
    master.wait_for_gap(TIMEOUT).await.unwrap();
    let started = Instant::now();
    let result = master.transact(1, &READ, TIMEOUT).await;
    assert!(matches!(result, Err(TxError::Timeout)), "{result:?}");
    let took = started.elapsed();
    assert!(took >= send_time + TIMEOUT, "{took:?}");
    assert!(took <= send_time + TIMEOUT + TIMER_RESOLUTION, "{took:?}");
    assert_eq!(
        master.sent_at(),
        started + send_time - master.timing.line.frame_time(8)
    );
}

#[tokio::test(start_paused = true)]
async fn the_kernels_rs485_delays_push_the_start_of_the_response_timeout_back() {
    let mut master = master(|_| Vec::new(), Vec::new());
    master.set_echo(false);
    let delays = Duration::from_millis(15);
    master.port.driver_delays = delays;
    master.wait_for_gap(TIMEOUT).await.unwrap();
    let started = Instant::now();
    let result = master.transact(1, &READ, TIMEOUT).await;
    assert!(matches!(result, Err(TxError::Timeout)), "{result:?}");
    let earliest = started + delays + master.timing.line.frame_time(8) + TIMEOUT;
    let ended = Instant::now();
    assert!(ended >= earliest, "{:?} early", earliest - ended);
    assert!(
        ended <= earliest + TIMER_RESOLUTION,
        "{:?} late",
        ended - earliest
    );
}
