//! Each fault knob of a simulated slave, and what the gateway makes of it: at the bus on tokio's
//! paused clock, against the line's record of the wire, and once over a real TCP socket.

use crate::support::{addr, bus_call, settle, sim_bus_of, start, RawMaster};
use modbus_gateway::bus::BusHandle;
use modbus_gateway::error::Outcome;
use modbus_gateway::sim::{SimLine, Source};
use modbus_gateway::Config;
use std::time::Duration;

const TIMEOUT: Duration = Duration::from_millis(200);
/// Read one holding register from 0000H.
const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];
const ANSWER: [u8; 4] = [0x03, 0x02, 0x00, 0x00];

/// A 9600 8E1 sim line with a healthy register slave at 1 and one with `knobs` at 2.
fn line_with_faulty_slave_2(bus_keys: &str, knobs: &str) -> (SimLine, BusHandle) {
    let text = format!(
        "[[bus]]\nname = \"line\"\ndevice = \"sim\"\nbaud = 9600\nresponse_timeout = \"200ms\"\n{bus_keys}\n\
         [[bus.sim_slave]]\naddress = 1\n\
         [[bus.sim_slave]]\naddress = 2\n{knobs}\n"
    );
    let config = Config::from_toml_str(&text).expect("test config");
    sim_bus_of(config.bus.into_iter().next().expect("one bus"))
}

fn is_0x0b(outcome: &Outcome) -> bool {
    matches!(outcome, Err(e) if e.exception_code() as u8 == 0x0B)
}

fn frames_from(line: &SimLine, from: Source) -> Vec<Vec<u8>> {
    line.frames()
        .into_iter()
        .filter(|f| f.from == from)
        .map(|f| f.bytes)
        .collect()
}

#[tokio::test(start_paused = true)]
async fn an_offline_slave_gets_0x0b_after_the_timeout_and_nothing_on_the_wire() {
    let (line, bus) = line_with_faulty_slave_2("", "offline = true");
    settle(&bus).await;
    let (outcome, elapsed) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    assert!(elapsed >= TIMEOUT, "{elapsed:?}");
    assert!(frames_from(&line, Source::Slave(2)).is_empty());
}

#[tokio::test(start_paused = true)]
async fn an_extra_delay_within_the_timeout_only_slows_the_answer() {
    let (_line, bus) = line_with_faulty_slave_2("", "extra_delay = \"80ms\"");
    settle(&bus).await;
    // Each timed call follows another, so each waits the same gap first.
    assert!(bus_call(&bus, 1, &READ).await.0.is_ok());
    let (healthy, normal) = bus_call(&bus, 1, &READ).await;
    let (slow, slowed) = bus_call(&bus, 2, &READ).await;
    assert_eq!(healthy.unwrap(), Some(ANSWER.to_vec()));
    assert_eq!(slow.unwrap(), Some(ANSWER.to_vec()));
    let extra = slowed - normal;
    assert!(
        extra >= Duration::from_millis(80) && extra <= Duration::from_millis(82),
        "{extra:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_late_reply_gets_0x0b_and_never_answers_a_later_request() {
    let (line, bus) = line_with_faulty_slave_2("", "late_reply = \"300ms\"");
    settle(&bus).await;
    // Slave 2 is asked for two registers, slave 1 for one: a crossed reply would show.
    let (outcome, _) = bus_call(&bus, 2, &[0x03, 0x00, 0x00, 0x00, 0x02]).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    let timed_out_at = tokio::time::Instant::now();
    let mut spoiled = 0;
    for _ in 0..20 {
        match bus_call(&bus, 1, &READ).await.0 {
            Ok(answer) => assert_eq!(answer, Some(ANSWER.to_vec())),
            // The late reply may collide with one exchange on the wire: that one times out.
            Err(e) if e.exception_code() as u8 == 0x0B => spoiled += 1,
            Err(e) => panic!("{e:?}"),
        }
    }
    assert!(spoiled <= 1, "{spoiled} reads spoiled by one late reply");
    let late = line
        .frames()
        .iter()
        .any(|f| f.from == Source::Slave(2) && f.start > timed_out_at);
    assert!(late, "the late reply never went out after the 0x0B");
}

#[tokio::test(start_paused = true)]
async fn corrupted_crcs_get_0x0b_after_every_retry_failed() {
    let (line, bus) = line_with_faulty_slave_2("retries = 2", "crc_error_rate = 1.0");
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
    assert_eq!(outcome.unwrap(), Some(ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn garbage_after_a_reply_is_ignored_and_the_next_frame_waits_for_silence() {
    let (line, bus) = line_with_faulty_slave_2("", "garbage_after = 6");
    settle(&bus).await;
    for _ in 0..5 {
        let (outcome, _) = bus_call(&bus, 2, &READ).await;
        assert_eq!(outcome.unwrap(), Some(ANSWER.to_vec()));
        let (outcome, _) = bus_call(&bus, 1, &READ).await;
        assert_eq!(outcome.unwrap(), Some(ANSWER.to_vec()));
    }
    assert_eq!(line.stats().gap_violations, 0);
    assert_eq!(line.stats().collisions, 0);
}

#[tokio::test(start_paused = true)]
async fn garbage_before_a_reply_makes_it_unreadable_so_0x0b() {
    let (_line, bus) = line_with_faulty_slave_2("", "garbage_before = 4");
    settle(&bus).await;
    let (outcome, _) = bus_call(&bus, 2, &READ).await;
    assert!(is_0x0b(&outcome), "{outcome:?}");
    let (outcome, _) = bus_call(&bus, 1, &READ).await;
    assert_eq!(outcome.unwrap(), Some(ANSWER.to_vec()));
}

#[tokio::test(start_paused = true)]
async fn a_reply_from_the_wrong_address_is_dropped_so_0x0b() {
    let (line, bus) = line_with_faulty_slave_2("", "reply_address = 9");
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

#[tokio::test]
async fn over_tcp_each_broken_slave_gets_0x0b_while_the_healthy_one_answers() {
    let gateway = start(
        "[server]\nlisten = \"127.0.0.1:0\"\n\
         [[bus]]\nname = \"line\"\ndevice = \"sim\"\nbaud = 19200\nresponse_timeout = \"100ms\"\n\
         [[bus.sim_slave]]\naddress = 1\n\
         [[bus.sim_slave]]\naddress = 2\noffline = true\n\
         [[bus.sim_slave]]\naddress = 3\nreply_address = 30\n\
         [[bus.sim_slave]]\naddress = 4\ncrc_error_rate = 1.0\n\
         [[bus.sim_slave]]\naddress = 5\nlate_reply = \"400ms\"\n",
    )
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
