//! The timing rule across a link with a 20 ms round trip: the simulated line behind the
//! simulator's device server, and between it and the master a link that delays every byte by
//! 10 ms each way (in memory, on tokio's paused clock).

use super::tests::Measured;
use super::*;
use crate::line::{Framing, LineMaster, LineTiming, MasterTiming, Parity, Reply, TxError};
use crate::sim::device_server::DeviceServer;
use crate::sim::{Scripted, SimLine, Source, Transmission};
use tokio::io::split;

const ONE_WAY: Duration = Duration::from_millis(10);
const RESPONSE_TIMEOUT: Duration = Duration::from_millis(100);
const INTER_FRAME_DELAY: Duration = Duration::from_millis(5);
/// Read two holding registers from 0004H (Goodrive300 manual 10.4.1), and its answer.
const READ: [u8; 5] = [0x03, 0x00, 0x04, 0x00, 0x02];
const ANSWER: [u8; 6] = [0x03, 0x04, 0x13, 0x88, 0x00, 0x00];

/// Carry what `from` reads to `to`, each chunk `ONE_WAY` after it came, in order.
fn delay<R, W>(mut from: R, mut to: W)
where
    R: AsyncRead + Unpin + Send + 'static,
    W: AsyncWrite + Unpin + Send + 'static,
{
    let (chunks, mut due) = tokio::sync::mpsc::unbounded_channel();
    tokio::spawn(async move {
        let mut chunk = [0u8; 512];
        while let Ok(n @ 1..) = from.read(&mut chunk).await {
            if chunks
                .send((Instant::now() + ONE_WAY, chunk[..n].to_vec()))
                .is_err()
            {
                break;
            }
        }
    });
    tokio::spawn(async move {
        while let Some((at, bytes)) = due.recv().await {
            crate::timer::coarse_sleep_until(at).await;
            if to.write_all(&bytes).await.is_err() {
                break;
            }
        }
    });
}

/// A master whose port reports `round_trip`, a link of twice [`ONE_WAY`], and the simulator's
/// device server in front of a 19200 8E1 line whose slave 1 starts each of `requests` answers
/// `answers_after` the request ended on its wire.
fn over_link(
    round_trip: Duration,
    answers_after: Duration,
    requests: usize,
) -> (SimLine, LineMaster<NetPort<Measured>>) {
    let reply = Transmission::frame(1, &ANSWER, Duration::ZERO);
    over_link_answering(
        round_trip,
        answers_after,
        vec![Some(reply); requests],
        Duration::ZERO,
    )
}

/// [`over_link`] with slave 1's replies as `plan` has them, and a master that tolerates
/// `packing` of the device server's packing timer.
fn over_link_answering(
    round_trip: Duration,
    answers_after: Duration,
    plan: Vec<Option<Transmission>>,
    packing: Duration,
) -> (SimLine, LineMaster<NetPort<Measured>>) {
    let timing = LineTiming::new(&crate::line::SerialFormat {
        baud: 19_200,
        data_bits: 8,
        parity: Parity::Even,
        stop_bits: 1,
    });
    let line = SimLine::new(timing);
    // The line starts a reply no sooner than t3.5 after the request, then waits the delay.
    let plan = plan.into_iter().map(|reply| {
        reply.map(|reply| Transmission {
            delay: answers_after - timing.t35,
            ..reply
        })
    });
    line.add_slave(1, Scripted::new(plan));
    let (master_end, relay_near) = tokio::io::duplex(4096);
    let (relay_far, mut server_end) = tokio::io::duplex(4096);
    let (near_read, near_write) = split(relay_near);
    let (far_read, far_write) = split(relay_far);
    delay(near_read, far_write);
    delay(far_read, near_write);
    let server = DeviceServer::new(line.clone(), Framing::Rtu, timing.t35);
    tokio::spawn(async move { server.serve(&mut server_end).await });
    let link = Measured {
        stream: master_end,
        round_trip: Some(round_trip),
    };
    let port = NetPort::new(link, "192.0.2.7:4001".into());
    let master_timing =
        MasterTiming::new(timing, INTER_FRAME_DELAY, Duration::ZERO).with_packing(packing);
    (line, LineMaster::new(port, Framing::Rtu, master_timing))
}

/// When each request started on the far wire, and how long after the previous reply ended there.
fn gaps_before_requests(line: &SimLine) -> Vec<Duration> {
    let frames = line.frames();
    frames
        .windows(2)
        .filter(|pair| pair[0].from != Source::Master && pair[1].from == Source::Master)
        .map(|pair| pair[1].start - pair[0].end)
        .collect()
}

#[tokio::test(start_paused = true)]
async fn across_a_20ms_link_a_slave_answering_within_its_timeout_is_no_timeout_and_the_gap_holds() {
    let answers_after = RESPONSE_TIMEOUT * 8 / 10;
    let requests = 5;
    // The kernel's measurement of this link: 20 ms at least.
    let (line, mut master) = over_link(2 * ONE_WAY, answers_after, requests);
    for _ in 0..requests {
        let reply = master.transact(1, &READ, RESPONSE_TIMEOUT).await;
        assert_eq!(reply.unwrap(), Reply::Fits(ANSWER.to_vec()));
    }
    // On the far wire: every answer started within the slave's timeout of its request's end...
    let frames = line.frames();
    for pair in frames.windows(2).filter(|p| p[0].from == Source::Master) {
        assert_eq!(pair[1].from, Source::Slave(1));
        assert!(pair[1].start - pair[0].end < RESPONSE_TIMEOUT);
    }
    // ...and every request after the first started at least inter_frame_delay after the
    // previous reply ended there.
    let gaps = gaps_before_requests(&line);
    assert_eq!(gaps.len(), requests - 1);
    for gap in gaps {
        assert!(gap >= INTER_FRAME_DELAY, "{gap:?}");
    }
    assert_eq!(line.stats().gap_violations, 0);
}

#[tokio::test(start_paused = true)]
async fn a_link_budget_below_the_real_round_trip_turns_the_same_answer_into_a_timeout() {
    // The rule's counterpart: had the gateway not budgeted the link (a loopback's few
    // microseconds measured instead of 20 ms), the answer would come after the deadline.
    let answers_after = RESPONSE_TIMEOUT * 8 / 10;
    let tiny = Duration::from_micros(30);
    let (_line, mut master) = over_link(tiny, answers_after, 1);
    let result = master.transact(1, &READ, RESPONSE_TIMEOUT).await;
    assert!(matches!(result, Err(TxError::Timeout)), "{result:?}");
}

#[tokio::test(start_paused = true)]
async fn a_reply_the_packing_timer_holds_up_mid_way_is_accepted_within_packing_delay() {
    // A user-defined function: its reply's length is known only by the silence after it, and
    // the converter's packing timer sends the first four bytes 45 ms before the rest.
    let answer = [0x41, 0x01, 0x02, 0x03];
    let paused = Transmission {
        pause: Some(crate::sim::Pause {
            after: 4,
            gap: Duration::from_millis(45),
        }),
        ..Transmission::frame(1, &answer, Duration::ZERO)
    };
    let link = 2 * ONE_WAY;
    let after = Duration::from_millis(20);
    let plan = vec![Some(paused.clone())];
    let (_line, mut master) = over_link_answering(link, after, plan, Duration::from_millis(50));
    let reply = master.transact(1, &[0x41], RESPONSE_TIMEOUT).await;
    assert_eq!(reply.unwrap(), Reply::Fits(answer.to_vec()));
    // Without packing_delay the silence ends the frame after four bytes: not a frame.
    let (_line, mut master) = over_link_answering(link, after, vec![Some(paused)], Duration::ZERO);
    let result = master.transact(1, &[0x41], RESPONSE_TIMEOUT).await;
    assert!(matches!(result, Err(TxError::Check)), "{result:?}");
}

#[tokio::test(start_paused = true)]
async fn junk_that_answers_each_request_at_once_never_lets_the_next_go_sooner() {
    // A converter on a line full of noise: whatever it is sent, it hands back at once a frame
    // of the reply's length whose CRC fails (01 03 04, four data bytes, a wrong check).
    const JUNK: [u8; 9] = [0x01, 0x03, 0x04, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00];
    const REQUESTS: usize = 5;
    let timing = LineTiming::new(&crate::line::SerialFormat {
        baud: 19_200,
        data_bits: 8,
        parity: Parity::Even,
        stop_bits: 1,
    });
    let (near, mut far) = tokio::io::duplex(4096);
    let converter = tokio::spawn(async move {
        let (mut arrivals, mut request) = (Vec::new(), [0u8; 8]);
        while far.read_exact(&mut request).await.is_ok() {
            arrivals.push(Instant::now());
            if far.write_all(&JUNK).await.is_err() {
                break;
            }
        }
        arrivals
    });
    // Loopback: a few microseconds measured, the least budget.
    let link = Measured {
        stream: near,
        round_trip: Some(Duration::from_micros(30)),
    };
    let port = NetPort::new(link, "192.0.2.7:4001".into());
    let master_timing = MasterTiming::new(timing, Duration::ZERO, Duration::ZERO);
    let mut master = LineMaster::new(port, Framing::Rtu, master_timing);
    for _ in 0..REQUESTS {
        let result = master.transact(1, &READ, RESPONSE_TIMEOUT).await;
        assert!(matches!(result, Err(TxError::Check)), "{result:?}");
    }
    drop(master);
    let arrivals = converter.await.unwrap();
    assert_eq!(arrivals.len(), REQUESTS);
    // 8 bytes at 19200 8E1 are 4.58 ms on the far wire, and t3.5 2.005 ms after them.
    let least = timing.frame_time(8) + timing.t35;
    for pair in arrivals.windows(2) {
        let apart = pair[1] - pair[0];
        assert!(apart >= least, "{apart:?} apart, less than {least:?}");
    }
}

#[tokio::test(start_paused = true)]
async fn a_reply_that_answers_lets_the_next_request_go_without_waiting_the_link_budget() {
    // A slave answering 5 ms after the request ended on its wire: its reply is back before the
    // 40 ms budget is over. The reply shows the request had left the wire, so the next request
    // waits only the gap after it, as on a local line.
    let requests = 3;
    let (line, mut master) = over_link(2 * ONE_WAY, Duration::from_millis(5), requests);
    for _ in 0..requests {
        let reply = master.transact(1, &READ, RESPONSE_TIMEOUT).await;
        assert_eq!(reply.unwrap(), Reply::Fits(ANSWER.to_vec()));
    }
    // On the far wire: the reply's way back, the gap, the request's way there, and tokio's
    // millisecond timer; no more.
    let most = 2 * ONE_WAY + INTER_FRAME_DELAY + 2 * Duration::from_millis(1);
    let gaps = gaps_before_requests(&line);
    assert_eq!(gaps.len(), requests - 1);
    for gap in gaps {
        assert!(gap >= INTER_FRAME_DELAY && gap <= most, "{gap:?}");
    }
}
