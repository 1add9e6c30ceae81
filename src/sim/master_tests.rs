//! The other master as a listening port hears it: byte-exact frames at their times, timeouts,
//! saturation against the physics, and a port that never sends.

use super::*;
use crate::config::{SimMaster, SimRead, Table};
use crate::line::{rtu, Parity, SerialFormat, Transport};
use crate::sim::line::{LineStats, Source, WireFrame};
use crate::sim::{RegisterBank, SimLine, SimPort};
use std::io;

fn line(baud: u32, parity: Parity) -> SimLine {
    SimLine::new(LineTiming::new(&SerialFormat {
        baud,
        data_bits: 8,
        parity,
        stop_bits: 1,
    }))
}

/// Reads of input registers (each one's value is its address) in turn.
fn master(pause: Duration, reads: &[(u8, u16, u16)]) -> SimMaster {
    SimMaster {
        pause,
        response_timeout: Duration::from_millis(100),
        read: reads
            .iter()
            .map(|&(slave, register, count)| SimRead {
                slave,
                table: Table::Input,
                register,
                count,
            })
            .collect(),
    }
}

/// Read `port` until the simulated clock has passed `until`, with every byte in by then.
async fn hear_until(port: &mut SimPort, until: Instant) -> Vec<u8> {
    let mut heard = Vec::new();
    while Instant::now() < until {
        tokio::select! {
            // The timer wakes on whole milliseconds: bytes due by then are taken first.
            biased;
            got = port.recv(&mut heard) => assert!(got.unwrap() > 0, "the port is live"),
            () = crate::timer::sleep_until(until) => {}
        }
    }
    heard
}

fn others(frames: &[WireFrame]) -> Vec<&WireFrame> {
    frames
        .iter()
        .filter(|f| f.from == Source::OtherMaster)
        .collect()
}

// Read Input Registers of slave 1: address 01, function 04, start 0x0004, count 2.
const REQUEST_PDU: [u8; 5] = [0x04, 0x00, 0x04, 0x00, 0x02];
// Its reply: function 04, 4 bytes, registers 0x0004 and 0x0005 (an input register is its address).
const REPLY_PDU: [u8; 6] = [0x04, 0x04, 0x00, 0x04, 0x00, 0x05];

#[tokio::test(start_paused = true)]
async fn a_listener_hears_the_request_then_the_reply_byte_exact_at_their_times() {
    let line = line(9600, Parity::Even);
    let delay = Duration::from_millis(3);
    line.add_slave(1, RegisterBank::new(delay));
    line.set_master(&master(Duration::ZERO, &[(1, 4, 2)]));
    let timing = line.timing();
    let mut port = line.open_listening().unwrap();
    let t0 = Instant::now();
    let request = rtu::encode(1, &REQUEST_PDU);
    let reply = rtu::encode(1, &REPLY_PDU);
    let mut heard = Vec::new();
    port.recv(&mut heard).await.unwrap();
    // The first byte of the request is in one character after the master starts, at the open.
    assert!(Instant::now() - t0 <= timing.char_time + Duration::from_millis(1));
    let transaction = timing.frame_time(request.len() + reply.len()) + timing.t35 + delay;
    let mut rest = hear_until(&mut port, t0 + transaction + timing.t35).await;
    heard.append(&mut rest);
    assert_eq!(heard, [request.clone(), reply.clone()].concat());

    let frames = line.frames();
    assert!(frames.len() >= 3, "request, reply, and the next request");
    let (ask, answer, next) = (&frames[0], &frames[1], &frames[2]);
    assert_eq!((ask.from, ask.start), (Source::OtherMaster, t0));
    assert_eq!(ask.end - ask.start, timing.frame_time(request.len()));
    assert_eq!(answer.from, Source::Slave(1));
    assert_eq!(answer.bytes, reply);
    assert_eq!(
        answer.start - ask.end,
        timing.t35 + delay,
        "t3.5, then processing"
    );
    assert_eq!(answer.end - answer.start, timing.frame_time(reply.len()));
    assert_eq!(
        next.start - answer.end,
        timing.t35,
        "the next request after t3.5"
    );
    assert_eq!(next.bytes, request);
    let stats = line.stats();
    assert_eq!((stats.other_requests, stats.other_replies), (2, 1));
    // The slave's answer to the next request is scheduled already.
    assert_eq!((stats.master_frames, stats.slave_frames), (0, 2));
}

#[tokio::test(start_paused = true)]
async fn a_read_of_an_absent_slave_times_out_and_the_next_read_follows_it() {
    let line = line(19_200, Parity::Even);
    line.add_slave(1, RegisterBank::new(Duration::ZERO));
    let pause = Duration::from_millis(5);
    let config = master(pause, &[(9, 0, 1), (1, 4, 2)]);
    line.set_master(&config);
    let timing = line.timing();
    let mut port = line.open_listening().unwrap();
    let t0 = Instant::now();
    let absent = rtu::encode(9, &[0x04, 0x00, 0x00, 0x00, 0x01]);
    let until = t0 + timing.frame_time(absent.len()) + config.response_timeout + pause;
    let heard = hear_until(&mut port, until + timing.frame_time(2)).await;
    assert_eq!(heard[..absent.len()], absent);
    assert_eq!(heard[absent.len()], 0x01, "then the read of slave 1 begins");

    let frames = line.frames();
    let asked = others(&frames);
    assert_eq!(asked[1].start, until, "after the timeout and the pause");
    assert_eq!(asked[1].bytes, rtu::encode(1, &REQUEST_PDU));
    let stats = line.stats();
    assert_eq!((stats.other_timeouts, stats.other_replies), (1, 0));
    let answered = frames.iter().filter(|f| f.from != Source::OtherMaster);
    assert!(
        answered.into_iter().all(|f| f.start > until),
        "nobody answered in the timeout"
    );
}

#[tokio::test(start_paused = true)]
async fn back_to_back_reads_at_115200_fill_the_line_as_the_physics_allow() {
    let line = line(115_200, Parity::None);
    for slave in 1..=4 {
        line.add_slave(slave, RegisterBank::new(Duration::ZERO));
    }
    // 10 registers: an 8-byte request, a 25-byte reply.
    let reads: Vec<_> = (1..=4).map(|slave| (slave, 0x0100, 10)).collect();
    line.set_master(&master(Duration::ZERO, &reads));
    let timing = line.timing();
    let mut port = line.open_listening().unwrap();
    let t0 = Instant::now();
    let window = Duration::from_secs(10);
    let heard = hear_until(&mut port, t0 + window).await;

    // Request, the slave's t3.5, reply, the master's t3.5: the slaves answer at once.
    let t_min = timing.transaction_minimum(8, 25, timing.t35);
    let physics = window.as_secs_f64() / t_min.as_secs_f64();
    let stats: LineStats = line.stats();
    let made = stats.other_replies as f64;
    assert!(
        (made - physics).abs() <= 1.0,
        "{made} transactions in {window:?}, the physics allow {physics:.1}"
    );
    assert!(physics > 1500.0, "t_min {t_min:?}");
    assert_eq!(stats.other_timeouts + stats.other_corrupt, 0);
    let whole = usize::try_from(stats.other_replies).unwrap() * 33;
    assert!(
        heard.len() >= whole && heard.len() < whole + 33,
        "every byte heard"
    );
    let busy = stats.busy.as_secs_f64() / window.as_secs_f64();
    assert!(
        busy > 0.44 && busy < 0.46,
        "the wire is busy {busy:.3} of the time"
    );
}

#[tokio::test(start_paused = true)]
async fn a_listening_port_refuses_to_send_and_the_refusal_is_counted() {
    let line = line(9600, Parity::Even);
    line.add_slave(1, RegisterBank::new(Duration::ZERO));
    line.set_master(&master(Duration::ZERO, &[(1, 4, 2)]));
    let mut port = line.open_listening().unwrap();
    let write = rtu::encode(1, &[0x06, 0x00, 0x01, 0x00, 0x02]);
    let refused = port.send(&write).await.unwrap_err();
    assert_eq!(refused.kind(), io::ErrorKind::PermissionDenied);
    port.send(&write).await.unwrap_err();
    hear_until(&mut port, Instant::now() + Duration::from_millis(200)).await;
    let stats = line.stats();
    assert_eq!((stats.listener_frames, stats.master_frames), (2, 0));
    assert!(stats.other_replies > 0, "the other master went on");
    assert!(line.frames().iter().all(|f| f.from != Source::Master));
}

#[tokio::test(start_paused = true)]
async fn the_other_master_waits_while_nobody_listens_and_goes_on_for_a_new_listener() {
    let line = line(9600, Parity::Even);
    line.add_slave(1, RegisterBank::new(Duration::ZERO));
    line.set_master(&master(Duration::ZERO, &[(1, 4, 2)]));
    tokio::time::advance(Duration::from_secs(1)).await;
    assert_eq!(line.stats().other_requests, 0, "nobody listens yet");
    let mut port = line.open_listening().unwrap();
    hear_until(&mut port, Instant::now() + Duration::from_millis(100)).await;
    let before = line.stats().other_requests;
    assert!(before > 0);
    line.unplug();
    tokio::time::advance(Duration::from_secs(1)).await;
    assert!(
        line.stats().other_requests <= before + 1,
        "waits while unplugged"
    );
    line.plug();
    let mut port = line.open_listening().unwrap();
    let heard = hear_until(&mut port, Instant::now() + Duration::from_millis(100)).await;
    assert!(!heard.is_empty());
    assert!(line.stats().other_requests > before + 1);
}

#[test]
fn a_reply_byte_after_a_pause_arrives_the_gap_later() {
    let t0 = Instant::now();
    let char_time = Duration::from_micros(500);
    let reply = Transmission {
        bytes: vec![0; 8],
        delay: Duration::ZERO,
        pause: Some(super::super::Pause {
            after: 3,
            gap: Duration::from_millis(10),
        }),
    };
    assert_eq!(arrival(&reply, t0, char_time, 3), t0 + 3 * char_time);
    assert_eq!(
        arrival(&reply, t0, char_time, 4),
        t0 + 4 * char_time + Duration::from_millis(10)
    );
}
