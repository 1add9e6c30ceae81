//! The simulated line's own tests: frame timing, pauses, gaps, collisions, unplugging, broadcasts.

use super::*;
use crate::line::{rtu, Parity, SerialFormat};

fn line_9600_8e1() -> SimLine {
    SimLine::new(LineTiming::new(&SerialFormat {
        baud: 9600,
        data_bits: 8,
        parity: Parity::Even,
        stop_bits: 1,
    }))
}

/// Answers every request with the same PDU, after `delay`.
struct Echo {
    delay: Duration,
}

impl Simulated for Echo {
    fn handle(&mut self, address: u8, request: &[u8], _at: Instant) -> Option<Transmission> {
        Some(Transmission {
            bytes: rtu::encode(address, request),
            delay: self.delay,
            pause: None,
        })
    }
}

const READ: [u8; 8] = [0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA];
/// tokio's timer wakes sleepers on whole milliseconds, paused clock included.
const TIMER_RESOLUTION: Duration = Duration::from_millis(1);

fn assert_about(elapsed: Duration, expected: Duration) {
    assert!(
        elapsed >= expected && elapsed <= expected + TIMER_RESOLUTION,
        "{elapsed:?} is not within the timer resolution after {expected:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_reply_arrives_byte_by_byte_after_the_request_and_t35() {
    let line = line_9600_8e1();
    line.add_slave(
        1,
        Echo {
            delay: Duration::ZERO,
        },
    );
    let timing = line.timing();
    let mut port = line.open().unwrap();
    let t0 = Instant::now();
    port.send(&READ).await.unwrap();
    let mut buf = Vec::new();
    let n = port.recv(&mut buf).await.unwrap();
    assert!(n >= 1);
    // Request on the wire, slave waits t3.5, first reply byte takes one character time.
    assert_about(
        Instant::now() - t0,
        timing.frame_time(8) + timing.t35 + timing.char_time,
    );
    while buf.len() < READ.len() {
        port.recv(&mut buf).await.unwrap();
    }
    assert_eq!(buf, READ);
    // The reply ends 16 characters and one t3.5 after the request started.
    assert_about(Instant::now() - t0, timing.frame_time(16) + timing.t35);
    let frames = line.frames();
    assert_eq!(frames[1].start - frames[0].end, timing.t35);
    assert_eq!(
        frames[1].end - frames[0].start,
        timing.frame_time(16) + timing.t35
    );
    let stats = line.stats();
    assert_eq!((stats.master_frames, stats.slave_frames), (1, 1));
    assert_eq!(stats.busy, timing.frame_time(16));
}

/// Answers with the request's own frame, pausing after `after` bytes for `gap`.
struct Stutter {
    after: usize,
    gap: Duration,
}

impl Simulated for Stutter {
    fn handle(&mut self, address: u8, request: &[u8], _at: Instant) -> Option<Transmission> {
        Some(Transmission {
            bytes: rtu::encode(address, request),
            delay: Duration::ZERO,
            pause: Some(super::super::Pause {
                after: self.after,
                gap: self.gap,
            }),
        })
    }
}

#[tokio::test(start_paused = true)]
async fn a_paused_reply_arrives_in_two_bursts_with_the_line_silent_between() {
    let line = line_9600_8e1();
    let gap = Duration::from_millis(20);
    line.add_slave(1, Stutter { after: 3, gap });
    let timing = line.timing();
    let mut port = line.open().unwrap();
    let t0 = Instant::now();
    port.send(&READ).await.unwrap();
    let mut buf = Vec::new();
    while buf.len() < 3 {
        port.recv(&mut buf).await.unwrap();
    }
    assert_eq!(
        buf.len(),
        3,
        "nothing of the rest came with the first burst"
    );
    let first_done = Instant::now();
    while buf.len() < READ.len() {
        port.recv(&mut buf).await.unwrap();
    }
    assert_eq!(buf, READ);
    // The fourth byte takes its character time after the gap.
    assert_about(Instant::now() - first_done, gap + timing.frame_time(5));
    assert_about(
        Instant::now() - t0,
        timing.frame_time(16) + timing.t35 + gap,
    );
    let frames = line.frames();
    assert_eq!(frames.len(), 3, "the request and two bursts");
    assert_eq!(frames[2].start - frames[1].end, gap);
    assert_eq!(frames[1].bytes, READ[..3]);
    let stats = line.stats();
    assert_eq!(stats.slave_frames, 1, "one transmission");
    assert_eq!(stats.busy, timing.frame_time(16), "the gap is not busy");
}

#[tokio::test(start_paused = true)]
async fn the_master_may_talk_in_a_slaves_pause_without_a_collision() {
    let line = line_9600_8e1();
    line.add_slave(
        1,
        Stutter {
            after: 3,
            gap: Duration::from_millis(50),
        },
    );
    let timing = line.timing();
    let mut port = line.open().unwrap();
    port.send(&READ).await.unwrap();
    tokio::time::advance(timing.frame_time(11) + 2 * timing.t35).await;
    port.send(&rtu::encode(2, &[0x03, 0x00, 0x00, 0x00, 0x01]))
        .await
        .unwrap();
    assert_eq!(line.stats().collisions, 0);
    assert_eq!(line.stats().unread_frames, 0);
}

#[tokio::test(start_paused = true)]
async fn a_frame_sent_before_t35_of_silence_is_counted_and_not_read() {
    let line = line_9600_8e1();
    line.add_slave(
        1,
        Echo {
            delay: Duration::ZERO,
        },
    );
    let timing = line.timing();
    let mut port = line.open().unwrap();
    port.send(&READ).await.unwrap();
    // The reply ends 16 characters and t3.5 later; resend one character time after that.
    tokio::time::advance(timing.frame_time(16) + timing.t35 + timing.char_time).await;
    port.clear_input(&mut Vec::new()).unwrap();
    port.send(&READ).await.unwrap();
    let stats = line.stats();
    assert_eq!(stats.gap_violations, 1);
    assert_eq!(stats.unread_frames, 1);
    assert_eq!(
        stats.slave_frames, 1,
        "the slave did not answer the merged frame"
    );
    assert_eq!(stats.min_gap, Some(timing.char_time));
}

#[tokio::test(start_paused = true)]
async fn sending_while_a_slave_talks_garbles_both() {
    let line = line_9600_8e1();
    line.add_slave(
        1,
        Echo {
            delay: Duration::ZERO,
        },
    );
    let mut port = line.open().unwrap();
    port.send(&READ).await.unwrap();
    let mut buf = Vec::new();
    port.recv(&mut buf).await.unwrap();
    port.send(&READ).await.unwrap();
    while buf.len() < READ.len() {
        port.recv(&mut buf).await.unwrap();
    }
    assert_eq!(buf[0], READ[0], "the byte before the collision is intact");
    assert!(!rtu::crc_ok(&buf));
    assert_eq!(line.stats().collisions, 1);
}

#[tokio::test(start_paused = true)]
async fn an_unplugged_adapter_reads_zero_and_cannot_be_opened_until_plugged() {
    let line = line_9600_8e1();
    let mut port = line.open().unwrap();
    let waiting = tokio::spawn(async move {
        let mut buf = Vec::new();
        port.recv(&mut buf).await
    });
    tokio::task::yield_now().await;
    line.unplug();
    assert_eq!(waiting.await.unwrap().unwrap(), 0);
    assert!(line.open().is_err());
    line.plug();
    let mut port = line.open().unwrap();
    port.send(&READ).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn broadcasts_reach_every_slave_and_nobody_answers() {
    let line = line_9600_8e1();
    line.add_slave(
        1,
        Echo {
            delay: Duration::ZERO,
        },
    );
    line.add_slave(
        2,
        Echo {
            delay: Duration::ZERO,
        },
    );
    let mut port = line.open().unwrap();
    port.send(&rtu::encode(0, &[0x06, 0, 1, 0, 1]))
        .await
        .unwrap();
    let mut buf = Vec::new();
    let nothing = tokio::time::timeout(Duration::from_secs(1), port.recv(&mut buf)).await;
    assert!(nothing.is_err());
    assert_eq!(line.stats().slave_frames, 0);
}
