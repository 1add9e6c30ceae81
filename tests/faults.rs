//! Each fault knob of a simulated slave (offline, late, corrupted, truncated, garbage, wrong
//! address or function) and what a master gets for it: a slower answer, 0x0B or the slave's own
//! bytes, never another request's answer or part of one, each counted under its outcome. At the
//! bus on tokio's paused clock, against the line's record of the wire, and over real TCP.

use crate::support::{
    addr, bus_call, frames_from, settle, sim_bus_counted, Bus, GatewayConfig, RawMaster, Scrape,
    Value,
};
use modbus_gateway::testing::bus::BusHandle;
use modbus_gateway::testing::error::{Answer, Outcome};
use modbus_gateway::testing::line::rtu::encode;
use modbus_gateway::testing::metrics::Metrics;
use modbus_gateway::testing::sim::faults::{Faults, Faulty};
use modbus_gateway::testing::sim::{Pause, Scripted, SimLine, Source, Transmission};
use std::time::Duration;

const TIMEOUT: Duration = Duration::from_millis(200);
/// Read one holding register from 0000H.
const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];
const ANSWER: [u8; 4] = [0x03, 0x02, 0x00, 0x00];
/// Read two holding registers from 0000H, and the answer of a register slave nobody wrote to.
const READ_2: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x02];
const ANSWER_2: [u8; 6] = [0x03, 0x04, 0x00, 0x00, 0x00, 0x00];

/// The sim bus named "line" at 9600 baud with a 200 ms response timeout, with no slaves yet.
fn line_9600() -> Bus {
    Bus::sim("line").baud(9600).response_timeout("200ms")
}

/// A 9600 8E1 sim line with a healthy register slave at 1 and one with `knobs` at 2.
fn line_with_faulty_slave_2(line: Bus, knobs: &[(&str, Value)]) -> (SimLine, BusHandle) {
    let (line, bus, _) = counted_line_with_faulty_slave_2(line, knobs);
    (line, bus)
}

/// [`line_with_faulty_slave_2`], with the metrics its bus counts into.
fn counted_line_with_faulty_slave_2(
    line: Bus,
    knobs: &[(&str, Value)],
) -> (SimLine, BusHandle, Metrics) {
    let line = line.sim_slaves("1").sim_slave("2", knobs).slave(3, &[]);
    let config = GatewayConfig::new().bus(line).load();
    let metrics = Metrics::new();
    let (line, bus) = sim_bus_counted(config.bus.into_iter().next().expect("one bus"), &metrics);
    (line, bus, metrics)
}

fn scrape(metrics: &Metrics) -> Scrape {
    Scrape::parse(metrics.render().expect("metrics render"))
}

/// Requests to `slave` with `function` that the bus counted under `outcome` (function codes
/// the gateway does not know are all counted as `other`).
fn counted(metrics: &Metrics, slave: u8, function: u8, outcome: &str) -> f64 {
    let function = modbus_gateway::testing::pdu::function(function)
        .map_or_else(|| "other".to_owned(), |row| format!("0x{:02X}", row.code));
    scrape(metrics)
        .get(&format!(
            "modbus_gateway_requests_total{{bus=\"line\",function=\"{function}\",\
             outcome=\"{outcome}\",protocol=\"tcp\",slave=\"{slave}\"}}"
        ))
        .unwrap_or(0.0)
}

/// A per-bus counter of the line, such as `modbus_gateway_discarded_frames_total`.
fn line_count(metrics: &Metrics, name: &str) -> f64 {
    scrape(metrics)
        .get(&format!("{name}{{bus=\"line\"}}"))
        .unwrap_or(0.0)
}

fn is_0x0b(outcome: &Outcome) -> bool {
    matches!(outcome, Err(e) if e.exception_code() as u8 == 0x0B)
}

#[tokio::test(start_paused = true)]
async fn an_offline_slave_gets_0x0b_after_the_timeout_and_nothing_on_the_wire() {
    let (line, bus) = line_with_faulty_slave_2(line_9600(), &[("offline", true.into())]);
    settle(&bus).await;
    let (outcome, elapsed) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert!(elapsed >= TIMEOUT, "{elapsed:?}");
    assert!(frames_from(&line, Source::Slave(2)).is_empty());
}

#[tokio::test(start_paused = true)]
async fn an_extra_delay_within_the_timeout_only_slows_the_answer() {
    let (_line, bus) = line_with_faulty_slave_2(line_9600(), &[("extra_delay", "80ms".into())]);
    settle(&bus).await;
    // Each timed call follows another, so each waits the same gap first.
    assert!(bus_call(&bus, 1, &READ).await.0.is_ok());
    let (healthy, normal) = bus_call(&bus, 1, &READ).await;
    let (slow, slowed) = bus_call(&bus, 2, &READ).await;
    assert_eq!(healthy.unwrap(), Answer::Reply(ANSWER.to_vec()));
    assert_eq!(slow.unwrap(), Answer::Reply(ANSWER.to_vec()));
    let extra = slowed - normal;
    assert!(
        extra >= Duration::from_millis(80) && extra <= Duration::from_millis(82),
        "{extra:?}"
    );
}

/// Read slave 1 `times` times with `pdu`, expecting `answer`. A stray reply on the wire may
/// collide with an exchange, which then gets 0x0B; returns how many did. Any other answer fails.
async fn reads_spoiled(bus: &BusHandle, pdu: &[u8], answer: &[u8], times: usize) -> usize {
    let mut spoiled = 0;
    for _ in 0..times {
        match bus_call(bus, 1, pdu).await.0 {
            Ok(got) => assert_eq!(got, Answer::Reply(answer.to_vec())),
            Err(e) if e.exception_code() as u8 == 0x0B => spoiled += 1,
            Err(e) => panic!("{e:?}"),
        }
    }
    spoiled
}

#[tokio::test(start_paused = true)]
async fn a_late_reply_gets_0x0b_and_never_answers_a_later_request() {
    let (line, bus) = line_with_faulty_slave_2(line_9600(), &[("late_reply", "300ms".into())]);
    settle(&bus).await;
    // Slave 2 is asked for two registers, slave 1 for one: a crossed reply would show.
    let (outcome, _) = bus_call(&bus, 2, &[0x03, 0x00, 0x00, 0x00, 0x02]).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    let timed_out_at = tokio::time::Instant::now();
    // The late reply may collide with one exchange on the wire: that one times out.
    let spoiled = reads_spoiled(&bus, &READ, &ANSWER, 20).await;
    assert!(spoiled <= 1, "{spoiled} reads spoiled by one late reply");
    let late = line
        .frames()
        .iter()
        .any(|f| f.from == Source::Slave(2) && f.start > timed_out_at);
    assert!(late, "the late reply never went out after the 0x0B");
}

#[tokio::test(start_paused = true)]
async fn corrupted_crcs_get_0x0b_after_every_retry_failed() {
    let (line, bus) =
        line_with_faulty_slave_2(line_9600().retries(2), &[("crc_error_rate", 1.0.into())]);
    settle(&bus).await;
    let (outcome, _) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert_eq!(
        frames_from(&line, Source::Master).len(),
        3,
        "one try and two retries"
    );
    assert_eq!(frames_from(&line, Source::Slave(2)).len(), 3);
    let (outcome, _) = bus_call(&bus, 1, &READ).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn garbage_after_a_reply_is_ignored_and_the_next_frame_waits_for_silence() {
    let (line, bus) = line_with_faulty_slave_2(line_9600(), &[("garbage_after", 6.into())]);
    settle(&bus).await;
    for _ in 0..5 {
        let (outcome, _) = bus_call(&bus, 2, &READ).await;
        assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
        let (outcome, _) = bus_call(&bus, 1, &READ).await;
        assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
    }
    assert_eq!(line.stats().gap_violations, 0);
    assert_eq!(line.stats().collisions, 0);
}

#[tokio::test(start_paused = true)]
async fn garbage_before_a_reply_makes_it_unreadable_so_0x0b() {
    let (_line, bus) = line_with_faulty_slave_2(line_9600(), &[("garbage_before", 4.into())]);
    settle(&bus).await;
    let (outcome, _) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    let (outcome, _) = bus_call(&bus, 1, &READ).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn a_reply_from_the_wrong_address_is_dropped_so_0x0b() {
    let (line, bus) = line_with_faulty_slave_2(line_9600(), &[("reply_address", 9.into())]);
    settle(&bus).await;
    let (outcome, elapsed) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert!(
        elapsed >= TIMEOUT,
        "the gateway kept waiting for slave 2: {elapsed:?}"
    );
    let sent = frames_from(&line, Source::Slave(2));
    assert_eq!(sent.len(), 1);
    assert_eq!(sent[0][0], 9, "the frame on the wire carried address 9");
}

#[tokio::test(start_paused = true)]
async fn a_reply_that_pauses_but_ends_before_the_deadline_is_still_the_answer() {
    // A reply whose length its bytes tell (here 7 bytes) is judged by length, not by silence:
    // it may pause anywhere, since USB adapters deliver in bursts, as long as its last byte is
    // in by the response timeout plus its own time on the wire plus t3.5 (`byte_timeout`).
    let (line, bus, metrics) = counted_line_with_faulty_slave_2(
        line_9600(),
        &[("reply_gap", "150ms".into()), ("reply_gap_after", 3.into())],
    );
    settle(&bus).await;
    let (outcome, elapsed) = bus_call(&bus, 2, &READ).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
    assert!(elapsed >= Duration::from_millis(150), "{elapsed:?}");
    let bursts = frames_from(&line, Source::Slave(2));
    assert_eq!(bursts.len(), 2, "the reply went out in two bursts");
    assert_eq!(bursts[0].len(), 3);
    assert_eq!(counted(&metrics, 2, 0x03, "ok"), 1.0);
}

#[tokio::test(start_paused = true)]
async fn a_reply_that_pauses_past_the_deadline_gets_0x0b_and_its_rest_answers_nothing() {
    let (line, bus, metrics) = counted_line_with_faulty_slave_2(
        line_9600(),
        &[("reply_gap", "250ms".into()), ("reply_gap_after", 3.into())],
    );
    settle(&bus).await;
    let (outcome, elapsed) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    // The deadline: the timeout, the reply's 7 bytes on the wire, t3.5; nowhere near the rest.
    let deadline = TIMEOUT + line.timing().frame_time(8 + 7) + line.timing().t35;
    assert!(elapsed >= deadline, "gave up early: {elapsed:?}");
    assert!(elapsed < deadline + Duration::from_millis(5), "{elapsed:?}");
    assert_eq!(counted(&metrics, 2, 0x03, "frame_error"), 1.0);
    // The rest of the reply comes 50 ms after the 0x0B, while slave 1 is being polled: it may
    // garble one exchange on the wire, but it never answers one.
    let spoiled = reads_spoiled(&bus, &READ_2, &ANSWER_2, 10).await;
    assert!(spoiled <= 1, "{spoiled} reads spoiled by one broken reply");
    let rest = &frames_from(&line, Source::Slave(2))[1];
    assert_eq!(rest.len(), 4, "the rest of the reply did go out");
}

#[tokio::test(start_paused = true)]
async fn a_reply_judged_by_silence_ends_at_the_pause_fails_its_crc_and_gets_0x0b() {
    // User-defined function code 41H: the gateway cannot know the reply's length, so t3.5 of
    // silence ends it. A pause longer than that cuts the frame in two; the first part fails its
    // CRC, and a write (anything user-defined is one) is tried again only with retry_writes.
    let (line, bus, metrics) =
        counted_line_with_faulty_slave_2(line_9600().retries(1).key("retry_writes", true), &[]);
    let reply = [0x41, 0xDE, 0xAD, 0xBE, 0xEF];
    let pause = Pause {
        after: 3,
        gap: Duration::from_millis(60),
    };
    let plan = (0..2).map(|_| Some(Transmission::frame(3, &reply, Duration::ZERO)));
    let faults = Faults {
        reply_gap: Some(pause),
        ..Faults::default()
    };
    line.add_slave(3, Faulty::new(Scripted::new(plan), faults, 3));
    settle(&bus).await;
    let (outcome, elapsed) = bus_call(&bus, 3, &[0x41, 0x01]).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert!(elapsed < pause.gap, "waited for the rest: {elapsed:?}");
    assert_eq!(counted(&metrics, 3, 0x41, "crc_error"), 1.0);
    let tries = line
        .frames()
        .iter()
        .filter(|f| f.from == Source::Master && f.bytes[0] == 3)
        .count();
    assert_eq!(tries, 2, "one try and one retry");
    // Both rests arrive later, on an idle line or in another exchange; neither answers it.
    for _ in 0..10 {
        let (outcome, _) = bus_call(&bus, 1, &READ_2).await;
        if let Ok(answer) = outcome {
            assert_eq!(answer, Answer::Reply(ANSWER_2.to_vec()));
        }
    }
    let (outcome, _) = bus_call(&bus, 1, &READ).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn a_reply_to_the_wrong_function_is_never_forwarded_and_reads_are_retried() {
    let (line, bus, metrics) =
        counted_line_with_faulty_slave_2(line_9600().retries(2), &[("reply_function", 4.into())]);
    settle(&bus).await;
    let (outcome, elapsed) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert!(
        elapsed >= 3 * TIMEOUT,
        "each try waited out the timeout: {elapsed:?}"
    );
    let replies = frames_from(&line, Source::Slave(2));
    assert_eq!(replies.len(), 3, "one try and two retries, each answered");
    assert!(replies.iter().all(|r| r[1] == 0x04));
    assert_eq!(counted(&metrics, 2, 0x03, "timeout"), 1.0);
    assert_eq!(
        line_count(&metrics, "modbus_gateway_discarded_frames_total"),
        3.0
    );
    // A write is not retried: its reply is lost, but it may have been carried out.
    let (outcome, _) = bus_call(&bus, 2, &[0x06, 0x00, 0x01, 0x00, 0x07]).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert_eq!(frames_from(&line, Source::Slave(2)).len(), 4);
    let (outcome, _) = bus_call(&bus, 1, &READ).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn a_truncated_reply_gets_0x0b_after_the_deadline_and_never_a_partial_answer() {
    let (line, bus, metrics) =
        counted_line_with_faulty_slave_2(line_9600(), &[("truncate_reply", 5.into())]);
    settle(&bus).await;
    let (outcome, elapsed) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert!(
        elapsed >= TIMEOUT,
        "gave up before the deadline: {elapsed:?}"
    );
    assert_eq!(
        frames_from(&line, Source::Slave(2)),
        [vec![2, 0x03, 0x02, 0, 0]]
    );
    assert_eq!(counted(&metrics, 2, 0x03, "frame_error"), 1.0);
    // An exception is 5 bytes long, so it survives the cut whole: the same slave's next answer
    // comes through untouched, and so does another slave's.
    let (outcome, _) = bus_call(&bus, 2, &[0x03, 0x00, 0x00, 0x00, 0x7E]).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(vec![0x83, 0x03]));
    let (outcome, _) = bus_call(&bus, 1, &READ).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn during_a_retry_a_late_reply_is_taken_only_if_it_has_the_retried_requests_form() {
    let (line, bus, metrics) =
        counted_line_with_faulty_slave_2(line_9600().retries(1), &[("late_reply", "300ms".into())]);
    settle(&bus).await;
    // A write, not retried, times out; its reply comes 100 ms into the next request's wait.
    let write = [0x06, 0x00, 0x00, 0x00, 0x07];
    let (outcome, _) = bus_call(&bus, 2, &write).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    // The read's own reply, late, comes 100 ms into the retry's wait. It answers the same request in the same form: on the wire
    // it cannot be told from the retry's own answer, and its data is right for it.
    let (outcome, elapsed) = bus_call(&bus, 2, &READ_2).await;
    assert_eq!(
        outcome.unwrap(),
        Answer::Reply(vec![0x03, 0x04, 0x00, 0x07, 0x00, 0x00])
    );
    // The read waits out the write's late-reply window first (one more timeout), in which the
    // write's echo arrives and is discarded as stray bytes, never taken for the read's answer.
    // Then the first try times out, and the retry takes the first try's late reply.
    assert!(
        elapsed > 2 * TIMEOUT + Duration::from_millis(100) && elapsed < 3 * TIMEOUT,
        "answered by the first try's late reply, in the retry's wait: {elapsed:?}"
    );
    assert_eq!(counted(&metrics, 2, 0x06, "timeout"), 1.0);
    assert_eq!(counted(&metrics, 2, 0x03, "ok"), 1.0);
    // The retry's own reply comes 300 ms later still, and answers nothing after it.
    let spoiled = reads_spoiled(&bus, &READ, &ANSWER, 20).await;
    assert!(spoiled <= 1, "{spoiled} reads spoiled by one late reply");
    assert_eq!(frames_from(&line, Source::Slave(2)).len(), 3);
}

#[tokio::test(start_paused = true)]
async fn a_line_that_does_not_fall_silent_within_the_timeout_gets_0x0b_until_it_does() {
    // 256 bytes of noise after slave 2's reply keep the line busy for 293 ms at 9600 baud, longer
    // than the 200 ms a frame may wait for its gap.
    let (_line, bus, metrics) =
        counted_line_with_faulty_slave_2(line_9600(), &[("garbage_after", 256.into())]);
    settle(&bus).await;
    let (outcome, _) = bus_call(&bus, 2, &READ).await;
    assert_eq!(
        outcome.unwrap(),
        Answer::Reply(ANSWER.to_vec()),
        "complete by length"
    );
    let (outcome, elapsed) = bus_call(&bus, 1, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert!(
        elapsed >= TIMEOUT && elapsed < TIMEOUT + Duration::from_millis(10),
        "{elapsed:?}"
    );
    assert_eq!(counted(&metrics, 1, 0x03, "line_busy"), 1.0);
    let (outcome, _) = bus_call(&bus, 1, &READ).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER.to_vec()));
    assert_eq!(
        line_count(&metrics, "modbus_gateway_stray_bytes_total"),
        256.0
    );
}

#[tokio::test(start_paused = true)]
async fn a_port_lost_in_the_middle_of_a_reply_answers_0x0a_and_the_rest_never_arrives() {
    let (line, bus, metrics) = counted_line_with_faulty_slave_2(
        line_9600().key("reopen_delay", "50ms"),
        &[("reply_gap", "100ms".into()), ("reply_gap_after", 3.into())],
    );
    settle(&bus).await;
    let waiting = bus.submit(1, 2, READ.to_vec());
    // The request, t3.5 and three bytes are on the wire by 20 ms; the rest is 100 ms away.
    tokio::time::sleep(Duration::from_millis(40)).await;
    line.unplug();
    let outcome = waiting.await.expect("bus answers");
    assert!(
        matches!(&outcome, Err(e) if e.exception_code() as u8 == 0x0A),
        "{outcome:?}"
    );
    assert_eq!(counted(&metrics, 2, 0x03, "port_down"), 1.0);
    line.plug();
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(bus.is_up(), "reopened");
    let (outcome, _) = bus_call(&bus, 1, &READ_2).await;
    assert_eq!(outcome.unwrap(), Answer::Reply(ANSWER_2.to_vec()));
    assert_eq!(
        line_count(&metrics, "modbus_gateway_port_reopens_total"),
        1.0
    );
    assert_eq!(
        line_count(&metrics, "modbus_gateway_stray_bytes_total"),
        0.0,
        "nothing of the old reply came through the new port"
    );
}

#[tokio::test(start_paused = true)]
async fn each_older_fault_is_counted_under_its_outcome() {
    let line = line_9600()
        .sim_slave("2", &[("offline", true.into())])
        .sim_slave("3", &[("crc_error_rate", 1.0.into())])
        .sim_slave("4", &[("garbage_before", 4.into())])
        .sim_slave("5", &[("reply_address", 9.into())])
        .sim_slave("6", &[("garbage_after", 6.into())])
        .sim_slave("7", &[("extra_delay", "300ms".into())]);
    let config = GatewayConfig::new().bus(line).load();
    let metrics = Metrics::new();
    let (_line, bus) = sim_bus_counted(config.bus.into_iter().next().expect("one bus"), &metrics);
    settle(&bus).await;
    for slave in 2..=7 {
        let _ = bus_call(&bus, slave, &READ).await;
        // Let slave 7's late reply pass before the next request.
        tokio::time::sleep(TIMEOUT).await;
    }
    for (slave, outcome) in [
        (2, "timeout"),
        (3, "crc_error"),
        (4, "crc_error"),
        (5, "timeout"),
        (6, "ok"),
        (7, "timeout"),
    ] {
        assert_eq!(
            counted(&metrics, slave, 0x03, outcome),
            1.0,
            "slave {slave}"
        );
    }
    assert_eq!(
        line_count(&metrics, "modbus_gateway_discarded_frames_total"),
        1.0,
        "slave 5's frame"
    );
    assert_eq!(
        line_count(&metrics, "modbus_gateway_stray_bytes_total"),
        6.0 + 7.0,
        "slave 6's garbage and slave 7's late reply, both on an idle line"
    );
}

#[tokio::test]
async fn over_tcp_each_broken_slave_gets_0x0b_while_the_healthy_one_answers() {
    let gateway = GatewayConfig::new()
        .bus(
            Bus::sim("line")
                .baud(19_200)
                .response_timeout("100ms")
                .sim_slaves("1")
                .sim_slave("2", &[("offline", true.into())])
                .sim_slave("3", &[("reply_address", 30.into())])
                .sim_slave("4", &[("crc_error_rate", 1.0.into())])
                .sim_slave("5", &[("late_reply", "400ms".into())]),
        )
        .start()
        .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    for unit in 2..=5 {
        assert_eq!(
            master.call(u16::from(unit), unit, &READ).await,
            [0x83, 0x0B],
            "unit {unit}"
        );
        assert_eq!(
            master.call(100, 1, &READ).await,
            ANSWER,
            "after unit {unit}"
        );
    }
}

/// Replies from the slave asked, with a good CRC and the request's function code, whose shape
/// does not fit the request: (request, reply).
fn replies_that_do_not_fit() -> [(&'static str, Vec<u8>, Vec<u8>); 3] {
    [
        (
            // Two registers asked for, one sent: byte count 2, not 4.
            "a wrong byte count",
            READ_2.to_vec(),
            vec![0x03, 0x02, 0x12, 0x34],
        ),
        (
            // Two registers written from 0004H; the echo says three.
            "a wrong quantity echo to FC 10",
            vec![0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32],
            vec![0x10, 0x00, 0x04, 0x00, 0x03],
        ),
        (
            // 1388H written to 0004H; the echo says 0001H.
            "a wrong echo to FC 06",
            vec![0x06, 0x00, 0x04, 0x13, 0x88],
            vec![0x06, 0x00, 0x04, 0x00, 0x01],
        ),
    ]
}

/// A reply that does not fit the request is counted with outcome `malformed_reply`.
#[tokio::test(start_paused = true)]
async fn a_reply_not_fitting_the_request_is_forwarded_at_once_counted_malformed() {
    for (what, request, reply) in replies_that_do_not_fit() {
        let (line, bus, metrics) = counted_line_with_faulty_slave_2(line_9600(), &[]);
        line.add_slave(
            3,
            Scripted::new([Some(Transmission::frame(3, &reply, Duration::ZERO))]),
        );
        settle(&bus).await;
        let (outcome, elapsed) = bus_call(&bus, 3, &request).await;
        assert_eq!(outcome.unwrap(), Answer::Malformed(reply.clone()), "{what}");
        // The request, t3.5 of the slave's turnaround, the reply: then at most a few characters.
        let t = line.timing();
        let last_byte = t.frame_time(request.len() + 3) + t.t35 + t.frame_time(reply.len() + 3);
        assert!(
            elapsed <= last_byte + 3 * t.char_time,
            "{what}: answered {elapsed:?} after the request, the reply was in at {last_byte:?}"
        );
        assert_eq!(
            counted(&metrics, 3, request[0], "malformed_reply"),
            1.0,
            "{what}"
        );
        assert_eq!(counted(&metrics, 3, request[0], "timeout"), 0.0, "{what}");
        assert_eq!(
            line_count(&metrics, "modbus_gateway_discarded_frames_total"),
            0.0,
            "{what}"
        );
    }
}

/// A reply that does not fit while a late reply may come is discarded; 0x0B follows the timeout.
#[tokio::test(start_paused = true)]
async fn a_reply_not_fitting_while_a_late_one_may_come_is_dropped_then_0x0b() {
    for (what, request, reply) in replies_that_do_not_fit() {
        // The first try is met with silence, so its reply may still come during the retry: the
        // frame that does not fit may be that reply, and is not taken for the retry's answer.
        let (line, bus, metrics) =
            counted_line_with_faulty_slave_2(line_9600().retries(1).key("retry_writes", true), &[]);
        let plan = [None, Some(Transmission::frame(3, &reply, Duration::ZERO))];
        line.add_slave(3, Scripted::new(plan));
        settle(&bus).await;
        let (outcome, elapsed) = bus_call(&bus, 3, &request).await;
        assert!(is_0x0b(&outcome), "{what}: {outcome:?}");
        assert!(elapsed >= 2 * TIMEOUT, "{what}: {elapsed:?}");
        assert_eq!(counted(&metrics, 3, request[0], "timeout"), 1.0, "{what}");
        assert_eq!(
            counted(&metrics, 3, request[0], "malformed_reply"),
            0.0,
            "{what}"
        );
        assert_eq!(
            line_count(&metrics, "modbus_gateway_discarded_frames_total"),
            1.0,
            "{what}"
        );
        assert_eq!(frames_from(&line, Source::Slave(3)), [encode(3, &reply)]);
    }
}

#[tokio::test]
async fn over_tcp_a_master_gets_the_slaves_malformed_reply_byte_for_byte() {
    let gateway = GatewayConfig::new()
        .bus(Bus::sim("line").baud(19_200).response_timeout("1s"))
        .start()
        .await;
    let line = gateway.sim_line("line").expect("a simulated line");
    let plan = replies_that_do_not_fit()
        .map(|(_, _, reply)| Some(Transmission::frame(4, &reply, Duration::ZERO)));
    line.add_slave(4, Scripted::new(plan));
    let mut master = RawMaster::connect(addr(&gateway)).await;
    for (id, (what, request, reply)) in (1..).zip(replies_that_do_not_fit()) {
        assert_eq!(master.call(id, 4, &request).await, reply, "{what}");
    }
}
