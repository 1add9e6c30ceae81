//! The transaction engine on a Modbus ASCII line, on tokio's paused clock over the simulated
//! line at 9600 7E1 (10-bit characters): the same transaction rules as RTU, with frames that end
//! at CR LF and an inter-character timeout instead of t3.5.

use super::*;
use crate::line::ascii;
use crate::line::{Parity, SerialFormat};
use crate::sim::{Pause, Scripted, SimLine, SimPort, Transmission};

/// tokio's timer wakes sleepers on whole milliseconds, paused clock included.
const TIMER_RESOLUTION: Duration = Duration::from_millis(1);
const TIMEOUT: Duration = Duration::from_millis(100);
const BYTE_TIMEOUT: Duration = Duration::from_secs(1);
const FOREVER: Duration = Duration::from_secs(3600);
/// Read two holding registers from 0004H (the Goodrive manuals' ASCII example).
const READ: [u8; 5] = [0x03, 0x00, 0x04, 0x00, 0x02];
/// Its answer: 0004H = 1388H, 0005H = 0.
const READ_ANSWER: [u8; 6] = [0x03, 0x04, 0x13, 0x88, 0x00, 0x00];

/// What a slave on the line sends: `bytes` as they are, after `delay`.
fn sends(bytes: &[u8], delay: Duration) -> Option<Transmission> {
    Some(Transmission {
        bytes: bytes.to_vec(),
        delay,
        pause: None,
    })
}

fn answer(address: u8, pdu: &[u8], delay: Duration) -> Option<Transmission> {
    sends(&ascii::encode(address, pdu), delay)
}

fn line(slaves: Vec<(u8, Vec<Option<Transmission>>)>) -> (SimLine, LineMaster<SimPort>) {
    let format = SerialFormat {
        baud: 9600,
        data_bits: 7,
        parity: Parity::Even,
        stop_bits: 1,
    };
    let line = SimLine::with_framing(LineTiming::new(&format), Framing::Ascii);
    for (address, plan) in slaves {
        line.add_slave(address, Scripted::new(plan));
    }
    let timing = MasterTiming {
        line: line.timing(),
        gap: Duration::ZERO,
        silence: BYTE_TIMEOUT,
        packing: Duration::ZERO,
    };
    let master = LineMaster::new(line.open().unwrap(), Framing::Ascii, timing);
    (line, master)
}

/// Sends one request and returns the outcome with the time from the end of its transmission.
async fn timed(
    master: &mut LineMaster<SimPort>,
    slave: u8,
    request: &[u8],
    timeout: Duration,
) -> (Result<Reply, TxError>, Duration) {
    master.wait_for_gap(FOREVER).await.unwrap();
    let sent_at = Instant::now();
    let result = master.transact(slave, request, timeout).await;
    let characters = ascii::encode(slave, request).len();
    let end_of_tx = sent_at + master.timing.line.frame_time(characters);
    (result, Instant::now() - end_of_tx)
}

#[test]
fn a_7e1_character_is_ten_bits() {
    let (line, _) = line(vec![]);
    // Start, seven data bits, parity, stop: 10 bits at 9600 baud.
    assert_eq!(
        line.timing().char_time,
        Duration::from_nanos(10 * 1_000_000_000 / 9600)
    );
}

#[tokio::test(start_paused = true)]
async fn the_response_timeout_counts_from_the_end_of_the_requests_7e1_characters() {
    let (line, mut master) = line(vec![(1, vec![None])]);
    let (result, after) = timed(&mut master, 1, &READ, TIMEOUT).await;
    assert!(matches!(result, Err(TxError::Timeout)), "{result:?}");
    assert!(after >= TIMEOUT, "gave up {after:?} after the frame");
    assert!(
        after <= TIMEOUT + TIMER_RESOLUTION,
        "gave up late: {after:?}"
    );
    // The request went out as the manual writes it.
    assert_eq!(line.frames()[0].bytes, b":010300040002F6\r\n");
}

#[tokio::test(start_paused = true)]
async fn an_ascii_reply_is_the_answer_at_its_cr_lf_with_no_silence_after_it() {
    let (line, mut master) = line(vec![(1, vec![answer(1, &READ_ANSWER, Duration::ZERO)])]);
    let (result, after) = timed(&mut master, 1, &READ, FOREVER).await;
    assert_eq!(result.unwrap(), Reply::Fits(READ_ANSWER.to_vec()));
    // The reply's 19 characters, and nothing waited for after them.
    let on_wire = line.timing().frame_time(19);
    assert!(after <= on_wire + TIMER_RESOLUTION, "{after:?}");
    assert_eq!(line.frames()[1].bytes, b":010304138800005D\r\n");
}

#[tokio::test(start_paused = true)]
async fn a_user_defined_function_needs_no_silence_to_end_its_reply() {
    let pdu = [0x41, 0x09, 0x01];
    let (line, mut master) = line(vec![(1, vec![answer(1, &pdu, Duration::ZERO)])]);
    let (result, after) = timed(&mut master, 1, &[0x41, 0x00], FOREVER).await;
    assert_eq!(result.unwrap(), Reply::Fits(pdu.to_vec()));
    let on_wire = line.timing().frame_time(ascii::encode(1, &pdu).len());
    assert!(after <= on_wire + TIMER_RESOLUTION, "{after:?}");
}

#[tokio::test(start_paused = true)]
async fn lower_case_hex_from_the_slave_is_its_answer() {
    let lower = b":010304138800005d\r\n";
    let (_line, mut master) = line(vec![(1, vec![sends(lower, Duration::ZERO)])]);
    let result = master.transact(1, &READ, FOREVER).await;
    assert_eq!(result.unwrap(), Reply::Fits(READ_ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn a_bad_lrc_ends_the_try_as_a_check_error() {
    let (_line, mut master) = line(vec![(
        1,
        vec![sends(b":010304138800005C\r\n", Duration::ZERO)],
    )]);
    let result = master.transact(1, &READ, FOREVER).await;
    assert!(matches!(result, Err(TxError::Check)), "{result:?}");
}

#[tokio::test(start_paused = true)]
async fn a_stray_colon_restarts_the_frame_and_the_frame_after_it_answers() {
    let restarted = [&b":0103"[..], &ascii::encode(1, &READ_ANSWER)].concat();
    let (_line, mut master) = line(vec![(1, vec![sends(&restarted, Duration::ZERO)])]);
    let result = master.transact(1, &READ, FOREVER).await;
    assert_eq!(result.unwrap(), Reply::Fits(READ_ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn a_reply_without_its_cr_lf_fails_at_the_byte_timeout() {
    let frame = ascii::encode(1, &READ_ANSWER);
    let cut = &frame[..frame.len() - 2];
    let (line, mut master) = line(vec![(1, vec![sends(cut, Duration::ZERO)])]);
    let (result, after) = timed(&mut master, 1, &READ, FOREVER).await;
    assert!(matches!(result, Err(TxError::Frame)), "{result:?}");
    let last_char = line.timing().frame_time(cut.len());
    assert!(after >= last_char + BYTE_TIMEOUT, "{after:?}");
    assert!(
        after <= last_char + BYTE_TIMEOUT + TIMER_RESOLUTION,
        "{after:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_reply_that_stops_mid_way_fails_at_the_byte_timeout_even_if_the_rest_comes() {
    let mut paused = answer(1, &READ_ANSWER, Duration::ZERO).unwrap();
    paused.pause = Some(Pause {
        after: 7,
        gap: BYTE_TIMEOUT * 2,
    });
    let (line, mut master) = line(vec![(1, vec![Some(paused)])]);
    let (result, after) = timed(&mut master, 1, &READ, FOREVER).await;
    assert!(matches!(result, Err(TxError::Frame)), "{result:?}");
    let first_part = line.timing().frame_time(7);
    assert!(after >= first_part + BYTE_TIMEOUT, "{after:?}");
    assert!(
        after <= first_part + BYTE_TIMEOUT + TIMER_RESOLUTION,
        "{after:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_pause_shorter_than_the_byte_timeout_is_still_one_frame() {
    let mut paused = answer(1, &READ_ANSWER, Duration::ZERO).unwrap();
    paused.pause = Some(Pause {
        after: 7,
        gap: BYTE_TIMEOUT / 2,
    });
    let (_line, mut master) = line(vec![(1, vec![Some(paused)])]);
    let result = master.transact(1, &READ, FOREVER).await;
    assert_eq!(result.unwrap(), Reply::Fits(READ_ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn a_reply_from_another_address_is_discarded_and_the_try_times_out() {
    let (_line, mut master) = line(vec![(1, vec![answer(9, &READ_ANSWER, Duration::ZERO)])]);
    let result = master.transact(1, &READ, TIMEOUT).await;
    assert!(matches!(result, Err(TxError::Timeout)), "{result:?}");
    assert_eq!(master.counters().foreign_frames, 1);
}

#[tokio::test(start_paused = true)]
async fn a_late_ascii_reply_never_answers_the_next_request() {
    let late = TIMEOUT * 3 / 2;
    let (_line, mut master) = line(vec![
        (1, vec![answer(1, &READ_ANSWER, late)]),
        (2, vec![answer(2, &[0x03, 0x04, 0, 2, 0, 2], TIMEOUT)]),
    ]);
    let first = master.transact(1, &READ, TIMEOUT).await;
    assert!(matches!(first, Err(TxError::Timeout)), "{first:?}");
    let second = master.transact(2, &READ, TIMEOUT * 2).await.unwrap();
    assert_eq!(second, Reply::Fits(vec![0x03, 0x04, 0, 2, 0, 2]));
    assert_eq!(
        master.counters().foreign_frames,
        1,
        "the late reply dropped"
    );
}

#[tokio::test(start_paused = true)]
async fn a_broadcast_goes_out_in_ascii_and_keeps_the_line_quiet_for_the_turnaround() {
    let (line, mut master) = line(vec![]);
    let write = [0x06, 0x00, 0x04, 0x13, 0x88];
    let turnaround = Duration::from_millis(100);
    master.broadcast(&write, turnaround, FOREVER).await.unwrap();
    let broadcast_end = Instant::now();
    master.transact(1, &READ, TIMEOUT).await.unwrap_err();
    let frames = line.frames();
    assert_eq!(frames[0].bytes, ascii::encode(0, &write));
    assert!(frames[1].start >= broadcast_end + turnaround - TIMER_RESOLUTION);
}
