//! The simulated drives of config/demo.toml as a master sees them: their identifying codes, the
//! manuals' exceptions for misuse, a trip and its reset, ramps in their acceleration time. Over a
//! real TCP socket for what they answer, at the bus on tokio's paused clock for what takes time.

use crate::support::{addr, bus_call, demo_bus, demo_config, settle, RawMaster};
use modbus_gateway::testing::error::Answer;
use modbus_gateway::Gateway;
use std::time::Duration;

/// Units of the demo: GD20, GD300, GD10, the Pd-series inverter.
const GD20: u8 = 1;
const GD300: u8 = 2;
const GD10: u8 = 3;
const PD: u8 = 4;

fn read(address: u16, count: u16) -> Vec<u8> {
    let [ah, al] = address.to_be_bytes();
    let [ch, cl] = count.to_be_bytes();
    vec![0x03, ah, al, ch, cl]
}

fn write(address: u16, value: u16) -> Vec<u8> {
    let [ah, al] = address.to_be_bytes();
    let [vh, vl] = value.to_be_bytes();
    vec![0x06, ah, al, vh, vl]
}

fn words(value: u16) -> Vec<u8> {
    let [h, l] = value.to_be_bytes();
    vec![0x03, 0x02, h, l]
}

async fn demo_gateway() -> (Gateway, RawMaster) {
    let gateway = Gateway::start(&demo_config()).await.expect("demo starts");
    let master = RawMaster::connect(addr(&gateway)).await;
    (gateway, master)
}

#[tokio::test]
async fn the_identifying_codes_of_units_1_2_3_read_gd20_gd300_gd10() {
    let (_gateway, mut master) = demo_gateway().await;
    for (unit, code) in [(GD20, 0x0106), (GD300, 0x010A), (GD10, 0x010D)] {
        assert_eq!(
            master.call(u16::from(unit), unit, &read(0x2103, 1)).await,
            words(code),
            "unit {unit}"
        );
    }
}

#[tokio::test]
async fn misuse_gets_the_exception_the_manual_names() {
    let (_gateway, mut master) = demo_gateway().await;
    // Goodrive: at most 16 words per read.
    assert_eq!(master.call(1, GD20, &read(0x3000, 17)).await, [0x83, 0x03]);
    assert_eq!(master.call(2, GD20, &read(0x3000, 16)).await.len(), 2 + 32);
    // The second inverter: at most 12.
    assert_eq!(master.call(3, PD, &read(0x1000, 13)).await, [0x83, 0x03]);
    assert_eq!(master.call(4, PD, &read(0x1000, 12)).await.len(), 2 + 24);
    // Status word 1 is read-only: 07, "parameters only for read".
    assert_eq!(master.call(5, GD300, &write(0x2100, 1)).await, [0x86, 0x07]);
    // P00.07 through its RAM alias may be written, never read: invalid address.
    assert_eq!(
        master.call(6, GD300, &write(0x8007, 1)).await,
        write(0x8007, 1)
    );
    assert_eq!(master.call(7, GD300, &read(0x8007, 1)).await, [0x83, 0x02]);
    assert_eq!(master.call(8, PD, &read(0x0D05, 1)).await, [0x83, 0x02]);
    // Out of range (the manuals' worked example: P00.01 = 3): 04, "operation failed".
    assert_eq!(master.call(9, GD20, &write(0x0001, 3)).await, [0x86, 0x04]);
    // Diagnostics 0000 echoes exactly.
    let echo = [0x08, 0x00, 0x00, 0x12, 0xAB];
    assert_eq!(master.call(10, GD20, &echo).await, echo);
}

#[tokio::test]
async fn a_parameter_that_cannot_change_while_running_gets_08_until_the_drive_stops() {
    let (_gateway, mut master) = demo_gateway().await;
    assert_eq!(
        master.call(1, GD20, &write(0x2000, 1)).await,
        write(0x2000, 1)
    );
    // P00.03, the maximum frequency, is marked ◎.
    assert_eq!(
        master.call(2, GD20, &write(0x0003, 6000)).await,
        [0x86, 0x08]
    );
    assert_eq!(
        master.call(3, GD20, &write(0x2000, 6)).await,
        write(0x2000, 6)
    );
    assert_eq!(
        master.call(4, GD20, &write(0x0003, 6000)).await,
        write(0x0003, 6000)
    );
}

#[tokio::test]
async fn the_tripped_drive_reports_its_fault_refuses_to_run_and_runs_after_a_reset() {
    let (_gateway, mut master) = demo_gateway().await;
    assert_eq!(
        master.call(1, GD10, &read(0x2100, 1)).await,
        words(4),
        "fault"
    );
    assert_eq!(
        master.call(2, GD10, &read(0x2102, 1)).await,
        words(35),
        "STo"
    );
    assert_eq!(master.call(3, GD10, &write(0x2000, 1)).await, [0x86, 0x01]);
    assert_eq!(
        master.call(4, GD10, &write(0x2000, 7)).await,
        write(0x2000, 7)
    );
    assert_eq!(master.call(5, GD10, &read(0x2102, 1)).await, words(0));
    assert_eq!(
        master.call(6, GD10, &write(0x2000, 1)).await,
        write(0x2000, 1)
    );
    assert_eq!(
        master.call(7, GD10, &read(0x2100, 1)).await,
        words(1),
        "running forward"
    );
}

#[tokio::test]
async fn the_inverter_in_non_standard_mode_reaches_masters_as_standard_modbus() {
    let (_gateway, mut master) = demo_gateway().await;
    // 3000H, state: stopped. The drive sends 01 03 00 02 00 03; the master gets 03 02 00 03.
    assert_eq!(master.call(1, PD, &read(0x3000, 1)).await, words(3));
    // Switched to the standard protocol over Modbus (Pd-05 = 1), it is still understood.
    assert_eq!(
        master.call(2, PD, &write(0xFD05, 1)).await,
        write(0xFD05, 1)
    );
    assert_eq!(master.call(3, PD, &read(0x3000, 1)).await, words(3));
}

#[tokio::test]
async fn without_the_wide_read_count_option_the_non_standard_reply_is_never_passed_on() {
    let mut config = demo_config();
    config.bus[0].slave.clear();
    config.bus[0].response_timeout = Duration::from_millis(100);
    let gateway = Gateway::start(&config).await.expect("starts");
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, PD, &read(0x3000, 1)).await, [0x83, 0x0B]);
    // Writes are echoed in the standard form either way.
    assert_eq!(
        master.call(2, PD, &write(0x1000, 5000)).await,
        write(0x1000, 5000)
    );
}

/// The bus's answer to `pdu` as a PDU, or the exception code the gateway made.
async fn ask(bus: &modbus_gateway::testing::bus::BusHandle, unit: u8, pdu: &[u8]) -> Vec<u8> {
    match bus_call(bus, unit, pdu).await.0 {
        Ok(Answer::Reply(reply)) => reply,
        other => panic!("unit {unit} {pdu:02X?}: {other:?}"),
    }
}

#[tokio::test(start_paused = true)]
async fn unit_2_ramps_to_50_hz_in_its_acceleration_time_and_back_to_0_when_stopped() {
    let (_line, bus) = demo_bus();
    settle(&bus).await;
    // GD300 factory ramp times: P00.11 = P00.12 = 15.0 s for 0 to P00.03 (50.00 Hz).
    assert_eq!(
        ask(&bus, GD300, &read(0x000B, 2)).await,
        [0x03, 0x04, 0, 150, 0, 150]
    );
    let accel = Duration::from_secs(15);
    ask(&bus, GD300, &write(0x2001, 5000)).await;
    ask(&bus, GD300, &write(0x2000, 0x0001)).await;
    let started = tokio::time::Instant::now();
    assert_eq!(
        ask(&bus, GD300, &read(0x2100, 1)).await,
        words(1),
        "running forward"
    );

    tokio::time::sleep_until(started + accel / 2).await;
    let halfway = ask(&bus, GD300, &read(0x3000, 1)).await;
    let halfway = u16::from_be_bytes([halfway[2], halfway[3]]);
    assert!(
        (2400..=2600).contains(&halfway),
        "{halfway} at half the ramp"
    );
    tokio::time::sleep_until(started + accel - Duration::from_millis(500)).await;
    assert_ne!(
        ask(&bus, GD300, &read(0x3000, 1)).await,
        words(5000),
        "too early"
    );
    tokio::time::sleep_until(started + accel).await;
    assert_eq!(ask(&bus, GD300, &read(0x3000, 1)).await, words(5000));
    // Output voltage and speed follow the frequency: rated values at 50 Hz.
    let values = ask(&bus, GD300, &read(0x3003, 3)).await;
    assert_eq!(&values[2..4], &380u16.to_be_bytes(), "output voltage");
    assert_eq!(&values[6..8], &1440u16.to_be_bytes(), "speed");

    ask(&bus, GD300, &write(0x2000, 0x0005)).await;
    let stopping = tokio::time::Instant::now();
    assert_eq!(
        ask(&bus, GD300, &read(0x2100, 1)).await,
        words(1),
        "still running down"
    );
    tokio::time::sleep_until(stopping + accel).await;
    assert_eq!(ask(&bus, GD300, &read(0x3000, 1)).await, words(0));
    assert_eq!(
        ask(&bus, GD300, &read(0x2100, 1)).await,
        words(3),
        "stopped"
    );
}

#[tokio::test(start_paused = true)]
async fn a_hundred_reads_take_at_least_their_time_on_the_wire() {
    let (line, bus) = demo_bus();
    settle(&bus).await;
    let timing = line.timing();
    let before = line.stats();
    let started = tokio::time::Instant::now();
    for _ in 0..100 {
        assert_eq!(ask(&bus, GD20, &read(0x2103, 1)).await, words(0x0106));
    }
    let elapsed = started.elapsed();
    // Request 8 bytes, reply 7: 15 characters and the t3.5 gap each, at 9600 8E1.
    let wire = 100 * (timing.frame_time(8 + 7) + timing.t35);
    assert!(
        elapsed >= wire,
        "{elapsed:?} for 100 reads: the line is not timed"
    );
    let after = line.stats();
    assert_eq!(after.busy - before.busy, 100 * timing.frame_time(15));
    assert_eq!(after.gap_violations, 0);
}
