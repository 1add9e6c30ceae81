//! The serial line discipline as a master notices it: a silent slave gets 0x0B after its own
//! timeout, a late reply never answers a later request, frames keep t3.5 apart, retries, a lost
//! port answers 0x0A at once, a dead slave does not take the line. Driven at the bus (no TCP) on
//! tokio's paused clock, against the simulated line's own record of the wire and when.

use modbus_gateway::testing::bus::BusHandle;
use modbus_gateway::testing::error::{Answer, NoReply, Outcome, RequestError};
use modbus_gateway::testing::metrics::Metrics;
use modbus_gateway::testing::sim::{
    RegisterBank, Scripted, SimLine, Simulated, Source, Transmission,
};

use crate::support::{bus_call as call, settle, sim_bus_filled, sim_bus_settings};
use std::time::Duration;
use tokio::time::Instant;

/// tokio's timer wakes sleepers on whole milliseconds, paused clock included.
const TICK: Duration = Duration::from_millis(1);
const READ_10: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x0A];

/// A sim bus from its keys as TOML text, its line populated by `fill`, its task running.
fn sim_bus(keys: &str, fill: impl FnOnce(&SimLine)) -> (SimLine, BusHandle) {
    sim_bus_filled(sim_bus_settings(keys), &Metrics::new(), fill)
}

fn exception(outcome: &Outcome) -> Option<u8> {
    match outcome {
        Err(e) => Some(e.exception_code() as u8),
        Ok(_) => None,
    }
}

fn answer(address: u8, pdu: &[u8], delay: Duration) -> Option<Transmission> {
    Some(Transmission::frame(address, pdu, delay))
}

#[tokio::test(start_paused = true)]
async fn a_silent_slave_gets_0x0b_after_its_timeout_and_not_before() {
    let (line, bus) = sim_bus("baud = 9600\nresponse_timeout = \"300ms\"", |_| {});
    settle(&bus).await;
    let (outcome, elapsed) = call(&bus, 9, &READ_10).await;
    assert_eq!(exception(&outcome), Some(0x0B));
    let on_wire = line.timing().frame_time(8);
    let timeout = Duration::from_millis(300);
    assert!(
        elapsed >= on_wire + timeout,
        "0x0B after {elapsed:?}, before the timeout"
    );
    assert!(
        elapsed <= on_wire + timeout + 3 * line.timing().char_time,
        "0x0B {elapsed:?} after the request: more than three characters late"
    );
}

#[tokio::test(start_paused = true)]
async fn a_per_slave_timeout_overrides_the_bus_timeout() {
    let keys = "baud = 9600\nresponse_timeout = \"300ms\"\n[[bus.slave]]\naddress = 7\nresponse_timeout = \"2s\"";
    let (line, bus) = sim_bus(keys, |_| {});
    settle(&bus).await;
    let on_wire = line.timing().frame_time(8);
    let (_, other) = call(&bus, 9, &READ_10).await;
    let (outcome, overridden) = call(&bus, 7, &READ_10).await;
    assert_eq!(exception(&outcome), Some(0x0B));
    assert!(
        other < on_wire + Duration::from_millis(300) + 3 * TICK,
        "{other:?}"
    );
    assert!(
        overridden >= on_wire + Duration::from_secs(2),
        "{overridden:?}"
    );
    assert!(
        overridden <= on_wire + Duration::from_secs(2) + 3 * TICK,
        "{overridden:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn an_exception_reply_is_forwarded_as_soon_as_its_five_bytes_are_in() {
    let (line, bus) = sim_bus("baud = 9600\nresponse_timeout = \"1h\"", |line| {
        line.add_slave(1, RegisterBank::new(Duration::ZERO));
    });
    settle(&bus).await;
    // 200 registers is more than a read may ask for: the slave answers 0x03.
    let (outcome, elapsed) = call(&bus, 1, &[0x03, 0x00, 0x00, 0x00, 0xC8]).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(vec![0x83, 0x03]));
    let t = line.timing();
    assert!(
        elapsed <= t.frame_time(8 + 5) + t.t35 + 2 * TICK,
        "{elapsed:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_late_reply_never_answers_a_later_request() {
    let timeout = Duration::from_millis(200);
    let (line, bus) = sim_bus("baud = 9600\nresponse_timeout = \"200ms\"", |line| {
        line.add_slave(
            1,
            Scripted::new([answer(1, &[0x03, 0x02, 0xDE, 0xAD], timeout * 3 / 2)]),
        );
        line.add_slave(
            2,
            Scripted::new([answer(2, &[0x03, 0x02, 0x00, 0x02], timeout / 2)]),
        );
    });
    settle(&bus).await;
    let read_one = [0x03, 0x00, 0x00, 0x00, 0x01];
    let (first, _) = call(&bus, 1, &read_one).await;
    assert!(matches!(
        first,
        Err(RequestError::NoResponse {
            last: NoReply::Timeout,
            ..
        })
    ));
    let (second, _) = call(&bus, 2, &read_one).await;
    assert_eq!(second.unwrap(), Answer::Reply(vec![0x03, 0x02, 0x00, 0x02]));
    let late = line
        .frames()
        .iter()
        .filter(|f| f.from == Source::Slave(1))
        .count();
    assert_eq!(late, 1, "the late reply did go on the wire");
}

#[tokio::test(start_paused = true)]
async fn no_frame_starts_less_than_t35_after_the_previous_one() {
    // Slave 9 is absent and asked five times: it stays on the wire (never marked down).
    let keys = "baud = 9600\nresponse_timeout = \"100ms\"\nturnaround_delay = \"50ms\"\nqueue_timeout = \"1h\"\nslave_down_after = 0";
    let (line, bus) = sim_bus(keys, |line| {
        for address in 1..=4 {
            line.add_slave(address, RegisterBank::new(Duration::ZERO));
        }
    });
    settle(&bus).await;
    let requests: [(u8, &[u8]); 7] = [
        (1, &READ_10),
        (2, &[0x06, 0x00, 0x01, 0x12, 0x34]),
        (0, &[0x06, 0x00, 0x02, 0x00, 0x01]),
        (9, &READ_10),
        (3, &[0x41, 0x00]),
        (4, &[0x08, 0x00, 0x00, 0xAB, 0xCD]),
        (1, &[0x03, 0x00, 0x00, 0x00, 0xC8]),
    ];
    let pending: Vec<_> = (0..5)
        .flat_map(|_| requests.iter())
        .map(|&(slave, pdu)| bus.submit(1, slave, pdu.to_vec()))
        .collect();
    for outcome in pending {
        outcome.await.unwrap().ok();
    }
    let stats = line.stats();
    assert_eq!(stats.master_frames, 35);
    assert_eq!(stats.gap_violations, 0);
    assert_eq!(stats.collisions, 0);
    assert!(stats.min_gap.unwrap() >= line.timing().t35);
    let frames = line.frames();
    for pair in frames.windows(2) {
        let silence = pair[1].start - pair[0].end;
        if pair[0].bytes[0] == 0 && pair[0].from == Source::Master {
            assert!(
                silence >= Duration::from_millis(50),
                "turnaround after broadcast: {silence:?}"
            );
        }
    }
}

#[tokio::test(start_paused = true)]
async fn one_master_polling_back_to_back_uses_at_least_90_percent_of_the_line() {
    let (line, bus) = sim_bus("baud = 9600\nparity = \"even\"", |line| {
        line.add_slave(1, RegisterBank::new(Duration::ZERO));
    });
    settle(&bus).await;
    let t = line.timing();
    let transactions = 200;
    let started = Instant::now();
    for _ in 0..transactions {
        let (outcome, _) = call(&bus, 1, &READ_10).await;
        assert_eq!(outcome.unwrap().into_pdu().unwrap().len(), 22);
    }
    let wall = started.elapsed();
    // The simulated slave turns round in t3.5 (it sees the request end), with no processing time.
    let minimum = t.transaction_minimum(8, 25, t.t35) * transactions;
    let efficiency = minimum.as_secs_f64() / wall.as_secs_f64();
    assert!(efficiency >= 0.90, "bus efficiency {efficiency:.3}");
    assert!(efficiency <= 1.0, "faster than physics: {efficiency:.3}");
}

#[tokio::test(start_paused = true)]
async fn reads_are_retried_and_writes_only_with_retry_writes() {
    for (retry_writes, write_frames) in [(false, 1), (true, 3)] {
        let keys = format!(
            "baud = 19200\nresponse_timeout = \"50ms\"\nretries = 2\nretry_writes = {retry_writes}"
        );
        let (line, bus) = sim_bus(&keys, |_| {});
        settle(&bus).await;
        let (read, _) = call(&bus, 5, &READ_10).await;
        assert!(
            matches!(read, Err(RequestError::NoResponse { attempts: 3, .. })),
            "{read:?}"
        );
        let (write, _) = call(&bus, 5, &[0x06, 0x00, 0x01, 0x00, 0x01]).await;
        assert_eq!(exception(&write), Some(0x0B));
        let writes = line
            .frames()
            .iter()
            .filter(|f| f.from == Source::Master && f.bytes[1] == 0x06)
            .count();
        assert_eq!(writes, write_frames, "retry_writes = {retry_writes}");
        assert_eq!(line.stats().master_frames, 3 + write_frames as u64);
    }
}

#[tokio::test(start_paused = true)]
async fn a_request_that_waits_past_queue_timeout_gets_0x06_and_is_never_sent() {
    let keys = "baud = 9600\nresponse_timeout = \"500ms\"\nqueue_timeout = \"200ms\"";
    let (line, bus) = sim_bus(keys, |_| {});
    settle(&bus).await;
    let first = bus.submit(1, 9, READ_10.to_vec());
    let second = bus.submit(2, 9, vec![0x06, 0x00, 0x01, 0x00, 0x01]);
    assert_eq!(exception(&first.await.unwrap()), Some(0x0B));
    assert_eq!(exception(&second.await.unwrap()), Some(0x06));
    assert_eq!(
        line.stats().master_frames,
        1,
        "the expired write never went out"
    );
}

#[tokio::test(start_paused = true)]
async fn requests_of_a_master_that_left_are_never_sent() {
    let (line, bus) = sim_bus("baud = 9600\nresponse_timeout = \"100ms\"", |line| {
        line.add_slave(1, RegisterBank::new(Duration::ZERO));
    });
    settle(&bus).await;
    let first = bus.submit(1, 1, READ_10.to_vec());
    let gone: Vec<_> = (0..5).map(|_| bus.submit(2, 1, READ_10.to_vec())).collect();
    drop(gone);
    assert!(first.await.unwrap().is_ok());
    let after = bus.submit(3, 1, READ_10.to_vec());
    assert!(after.await.unwrap().is_ok());
    assert_eq!(line.stats().master_frames, 2);
}

#[tokio::test(start_paused = true)]
async fn a_lost_port_answers_0x0a_at_once_and_serves_again_when_back() {
    let keys = "baud = 9600\nresponse_timeout = \"1h\"\nreopen_delay = \"100ms\"\nreopen_delay_max = \"400ms\"";
    let (line, bus) = sim_bus(keys, |line| {
        line.add_slave(1, RegisterBank::new(Duration::ZERO));
    });
    settle(&bus).await;
    assert!(call(&bus, 1, &READ_10).await.0.is_ok());
    line.unplug();
    // The bus notices while idle, without a request having to fail first.
    tokio::time::sleep(Duration::from_millis(1)).await;
    assert!(!bus.is_up());
    let (outcome, elapsed) = call(&bus, 1, &READ_10).await;
    assert_eq!(exception(&outcome), Some(0x0A));
    assert_eq!(elapsed, Duration::ZERO, "0x0A at once, not after a timeout");
    // Still down after several reopen attempts.
    tokio::time::sleep(Duration::from_secs(2)).await;
    assert_eq!(exception(&call(&bus, 1, &READ_10).await.0), Some(0x0A));
    line.plug();
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(bus.is_up(), "reopened within the longest backoff");
    let (outcome, _) = call(&bus, 1, &READ_10).await;
    assert_eq!(outcome.unwrap().into_pdu().unwrap().len(), 22);
}

#[tokio::test(start_paused = true)]
async fn a_port_lost_mid_transaction_answers_that_request_0x0a() {
    let (line, bus) = sim_bus("baud = 9600\nresponse_timeout = \"1h\"", |_| {});
    settle(&bus).await;
    let waiting = bus.submit(1, 9, READ_10.to_vec());
    tokio::time::sleep(Duration::from_millis(100)).await;
    line.unplug();
    assert_eq!(exception(&waiting.await.unwrap()), Some(0x0A));
}

#[tokio::test(start_paused = true)]
async fn a_broadcast_is_answered_once_sent_and_the_line_stays_quiet_for_the_turnaround() {
    let keys = "baud = 9600\nturnaround_delay = \"150ms\"";
    let (line, bus) = sim_bus(keys, |line| {
        line.add_slave(1, RegisterBank::new(Duration::ZERO));
        line.add_slave(2, RegisterBank::new(Duration::ZERO));
    });
    settle(&bus).await;
    let write = [0x10, 0x00, 0x05, 0x00, 0x01, 0x02, 0xAB, 0xCD];
    let (outcome, elapsed) = call(&bus, 0, &write).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(write[..5].to_vec()));
    let on_wire = line.timing().frame_time(write.len() + 3);
    assert!(
        elapsed >= on_wire && elapsed <= on_wire + TICK,
        "{elapsed:?}"
    );
    for slave in [1, 2] {
        let (read, _) = call(&bus, slave, &[0x03, 0x00, 0x05, 0x00, 0x01]).await;
        assert_eq!(
            read.unwrap(),
            Answer::Reply(vec![0x03, 0x02, 0xAB, 0xCD]),
            "slave {slave}"
        );
    }
    let frames = line.frames();
    assert!(frames[1].start - frames[0].end >= Duration::from_millis(150));
    assert_eq!(
        line.stats().slave_frames,
        2,
        "nobody answered the broadcast"
    );
}

/// For `run_for` on the paused clock, master 1 polls slave 1 (absent: nobody answers) every
/// 50 ms while master 2 reads slave 2 back to back. Returns master 2's answers, the frames that
/// went to slave 1, and the exception codes master 1 got.
async fn a_dead_slave_beside_a_healthy_one(
    keys: &str,
    with_dead: bool,
    run_for: Duration,
) -> (usize, usize, Vec<u8>) {
    let keys = format!("baud = 19200\nresponse_timeout = \"100ms\"\n{keys}");
    let (line, bus) = sim_bus(&keys, |line| {
        line.add_slave(2, RegisterBank::new(Duration::ZERO));
    });
    settle(&bus).await;
    let end = Instant::now() + run_for;
    let healthy = tokio::spawn({
        let bus = bus.clone();
        async move {
            let mut answers = 0;
            while Instant::now() < end {
                let outcome = bus.submit(2, 2, READ_10.to_vec()).await.unwrap();
                assert!(outcome.is_ok(), "the healthy slave answers: {outcome:?}");
                answers += 1;
            }
            answers
        }
    });
    let mut codes = Vec::new();
    while with_dead && Instant::now() < end {
        let outcome = bus.submit(1, 1, READ_10.to_vec()).await.unwrap();
        codes.push(exception(&outcome).expect("the dead slave is answered by the gateway"));
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let answers = healthy.await.unwrap();
    let to_dead = line
        .frames()
        .iter()
        .filter(|f| f.from == Source::Master && f.bytes[0] == 1)
        .count();
    (answers, to_dead, codes)
}

#[tokio::test(start_paused = true)]
async fn a_slave_that_keeps_timing_out_is_only_probed_and_the_healthy_one_keeps_the_line() {
    let run_for = Duration::from_secs(30);
    let (alone, _, _) = a_dead_slave_beside_a_healthy_one("", false, run_for).await;
    // The defaults: down after 3 timeouts in a row, probed every 5 s.
    let (answers, to_dead, codes) = a_dead_slave_beside_a_healthy_one("", true, run_for).await;
    assert!(codes.iter().all(|&code| code == 0x0B), "{codes:?}");
    assert!(codes.len() > 400, "polled {} times", codes.len());
    // 3 timeouts, then one probe per 5 s of the remaining 29.7 s.
    assert!(
        (8..=10).contains(&to_dead),
        "{to_dead} frames to the dead slave"
    );
    assert!(
        answers as f64 >= 0.95 * alone as f64,
        "the healthy slave answered {answers} times beside the dead one, {alone} alone"
    );
}

#[tokio::test(start_paused = true)]
async fn without_the_down_policy_a_dead_slave_takes_most_of_the_line() {
    let run_for = Duration::from_secs(10);
    let (alone, _, _) = a_dead_slave_beside_a_healthy_one("", false, run_for).await;
    let (answers, to_dead, codes) =
        a_dead_slave_beside_a_healthy_one("slave_down_after = 0", true, run_for).await;
    assert_eq!(to_dead, codes.len(), "every poll went on the wire");
    assert!(
        (answers as f64) < 0.5 * alone as f64,
        "the healthy slave answered {answers} times beside the dead one, {alone} alone"
    );
}

#[tokio::test(start_paused = true)]
async fn a_down_slave_that_answers_its_probe_is_served_normally_again() {
    let keys = "baud = 19200\nresponse_timeout = \"100ms\"\nslave_probe_interval = \"2s\"";
    let (line, bus) = sim_bus(keys, |_| {});
    settle(&bus).await;
    for _ in 0..3 {
        let (outcome, elapsed) = call(&bus, 1, &READ_10).await;
        assert_eq!(exception(&outcome), Some(0x0B));
        assert!(elapsed >= Duration::from_millis(100), "{elapsed:?}");
    }
    let (outcome, elapsed) = call(&bus, 1, &READ_10).await;
    assert!(
        matches!(outcome, Err(RequestError::SlaveDown { timeouts: 3 })),
        "{outcome:?}"
    );
    assert_eq!(elapsed, Duration::ZERO, "answered without the line");
    assert_eq!(line.stats().master_frames, 3);
    // The drive is powered again; its requests get 0x0B until its probe is due.
    line.add_slave(1, RegisterBank::new(Duration::ZERO));
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let (outcome, _) = call(&bus, 1, &READ_10).await;
    assert_eq!(exception(&outcome), Some(0x0B));
    assert_eq!(line.stats().master_frames, 3);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let (outcome, _) = call(&bus, 1, &READ_10).await;
    assert!(outcome.is_ok(), "the probe is answered: {outcome:?}");
    for _ in 0..5 {
        assert!(call(&bus, 1, &READ_10).await.0.is_ok());
    }
    assert_eq!(line.stats().master_frames, 3 + 6);
}

#[tokio::test(start_paused = true)]
async fn a_late_reply_never_answers_the_next_masters_request_of_the_same_form() {
    use modbus_gateway::testing::sim::faults::{Faults, Faulty};
    // Slave 1 always answers 80 ms after a request: 30 ms after its 50 ms timeout.
    let late = Faults {
        late_reply: Some(Duration::from_millis(80)),
        ..Faults::default()
    };
    // Without coalescing, or the two identical reads would be one transaction.
    let keys = "baud = 19200\nresponse_timeout = \"50ms\"\ncoalesce_reads = false";
    let (line, bus) = sim_bus(keys, |line| {
        let slave = Faulty::new(RegisterBank::new(Duration::ZERO), late, 1);
        line.add_slave(1, slave);
    });
    settle(&bus).await;
    let first = bus.submit(1, 1, READ_10.to_vec());
    let second = bus.submit(2, 1, READ_10.to_vec());
    assert_eq!(exception(&first.await.unwrap()), Some(0x0B));
    // Without the late-reply window, master 2's request would go out at master 1's timeout, and
    // the late reply to master 1 would come back as its answer.
    assert_eq!(
        exception(&second.await.unwrap()),
        Some(0x0B),
        "master 2 must not get the reply to master 1's request"
    );
    let frames = line.frames();
    let requests: Vec<_> = frames.iter().filter(|f| f.from == Source::Master).collect();
    let late_reply = frames
        .iter()
        .find(|f| f.from != Source::Master)
        .expect("the late reply went on the wire");
    assert!(requests[1].start > late_reply.end);
}

/// A register slave that, like many real devices (pymodbus' serial server among them), stays
/// silent for a function code it does not implement instead of answering exception 01.
struct SilentFor {
    function: u8,
    inner: RegisterBank,
}

impl Simulated for SilentFor {
    fn handle(&mut self, address: u8, request: &[u8], at: Instant) -> Option<Transmission> {
        if request.first() == Some(&self.function) {
            return None;
        }
        self.inner.handle(address, request, at)
    }
}

/// User-defined function code 0x41, which the slave above ignores.
const IGNORED: [u8; 2] = [0x41, 0x00];

#[tokio::test(start_paused = true)]
async fn requests_a_slave_ignores_do_not_change_what_another_master_gets_from_it() {
    let keys = "baud = 19200\nresponse_timeout = \"100ms\"";
    let (line, bus) = sim_bus(keys, |line| {
        let slave = SilentFor {
            function: IGNORED[0],
            inner: RegisterBank::new(Duration::ZERO),
        };
        line.add_slave(1, slave);
    });
    settle(&bus).await;
    // Master 2 has been reading the slave; master 1 then sends ten requests it ignores.
    assert!(bus.submit(2, 1, READ_10.to_vec()).await.unwrap().is_ok());
    for _ in 0..10 {
        let outcome = bus.submit(1, 1, IGNORED.to_vec()).await.unwrap();
        assert!(
            matches!(
                outcome,
                Err(RequestError::NoResponse {
                    last: NoReply::Timeout,
                    ..
                })
            ),
            "each ignored request waits out its timeout: {outcome:?}"
        );
    }
    let sent_before = line.stats().master_frames;
    let (outcome, _) = call(&bus, 1, &READ_10).await;
    assert_eq!(
        outcome.unwrap().into_pdu().unwrap().len(),
        22,
        "master 2's read is sent and answered"
    );
    assert_eq!(line.stats().master_frames, sent_before + 1);
}

/// A slave that answered and then answers nothing.
#[tokio::test(start_paused = true)]
async fn a_slave_that_falls_silent_is_down_after_slave_down_after_timeouts() {
    let keys = "baud = 19200\nresponse_timeout = \"100ms\"";
    let (line, bus) = sim_bus(keys, |line| {
        line.add_slave(1, RegisterBank::new(Duration::ZERO));
    });
    settle(&bus).await;
    assert!(call(&bus, 1, &READ_10).await.0.is_ok());
    // The drive loses power: nothing answers at address 1 any more.
    line.add_slave(1, Scripted::new([]));
    for round in 0..3 {
        // Another master's ignored request between the reads neither counts nor clears.
        let (ignored, _) = call(&bus, 1, &IGNORED).await;
        assert_eq!(exception(&ignored), Some(0x0B), "round {round}");
        let (read, elapsed) = call(&bus, 1, &READ_10).await;
        assert_eq!(exception(&read), Some(0x0B), "round {round}");
        assert!(
            elapsed >= Duration::from_millis(100),
            "round {round}: {elapsed:?}"
        );
    }
    let sent = line.stats().master_frames;
    let (outcome, elapsed) = call(&bus, 1, &READ_10).await;
    assert!(
        matches!(outcome, Err(RequestError::SlaveDown { timeouts: 3 })),
        "{outcome:?}"
    );
    assert_eq!(elapsed, Duration::ZERO, "answered without the line");
    assert_eq!(line.stats().master_frames, sent);
}

/// After a bad CRC or a malformed reply the next request goes out after t3.5; after silence, only
/// after the window.
#[tokio::test(start_paused = true)]
async fn after_a_bad_crc_or_malformed_reply_the_next_request_waits_t35_or_the_window() {
    let timeout = Duration::from_millis(200);
    let read_one = [0x03, 0x00, 0x00, 0x00, 0x01];
    let mut bad_crc = modbus_gateway::testing::line::rtu::encode(1, &[0x03, 0x02, 0x00, 0x07]);
    *bad_crc.last_mut().unwrap() ^= 0x01;
    let first_replies = [
        (
            "a bad CRC",
            Some(Transmission {
                bytes: bad_crc,
                delay: Duration::ZERO,
                pause: None,
            }),
        ),
        // Two registers for a read of one.
        (
            "a malformed reply",
            answer(1, &[0x03, 0x04, 0, 7, 0, 8], Duration::ZERO),
        ),
        ("silence", None),
    ];
    for (what, first) in first_replies {
        let plan = [first, answer(1, &[0x03, 0x02, 0x00, 0x07], Duration::ZERO)];
        let (line, bus) = sim_bus("baud = 9600\nresponse_timeout = \"200ms\"", |line| {
            line.add_slave(1, Scripted::new(plan));
        });
        settle(&bus).await;
        let _ = call(&bus, 1, &read_one).await;
        let (outcome, _) = call(&bus, 1, &read_one).await;
        assert_eq!(
            outcome.unwrap(),
            Answer::Reply(vec![0x03, 0x02, 0x00, 0x07]),
            "{what}"
        );
        let frames = line.frames();
        let requests: Vec<_> = frames.iter().filter(|f| f.from == Source::Master).collect();
        // The line's last activity before the second request: the first reply, or the request.
        let quiet_from = frames
            .iter()
            .filter(|f| f.end <= requests[1].start)
            .map(|f| f.end)
            .max()
            .unwrap();
        let silence = requests[1].start - quiet_from;
        let t35 = line.timing().t35;
        if what == "silence" {
            // The try gave up at the timeout; one more timeout for its late reply.
            let since_request = requests[1].start - requests[0].end;
            assert!(since_request >= 2 * timeout, "{what}: {since_request:?}");
        } else {
            assert!(
                silence >= t35 && silence <= t35 + 2 * TICK,
                "{what}: the next request went out {silence:?} after the line fell silent"
            );
        }
    }
}
