//! A bus on the simulated line, started by hand (no gateway around it), and the shipped demo
//! configuration it is usually made from.

use crate::config::{Bus, GatewayConfig};
use modbus_gateway::gateway::load_config;
use modbus_gateway::testing::bus::{BusHandle, BusTask, Device};
use modbus_gateway::testing::error::Outcome;
use modbus_gateway::testing::metrics::Metrics;
use modbus_gateway::testing::shutdown::Stopping;
use modbus_gateway::testing::sim::SimLine;
use modbus_gateway::Config;
use std::path::Path;
use std::time::Duration;

/// Let a bus open its port and the line fall quiet (on the paused clock).
pub async fn settle(handle: &BusHandle) {
    for _ in 0..100 {
        if handle.is_up() {
            break;
        }
        tokio::task::yield_now().await;
    }
    assert!(handle.is_up(), "bus never opened its port");
    tokio::time::sleep(Duration::from_millis(50)).await;
}

/// One request straight to a bus, as master 1; the outcome and how long it took.
pub async fn bus_call(handle: &BusHandle, slave: u8, pdu: &[u8]) -> (Outcome, Duration) {
    let started = tokio::time::Instant::now();
    let outcome = handle
        .submit(1, slave, pdu.to_vec())
        .await
        .expect("bus answers");
    (outcome, started.elapsed())
}

/// The shipped demo configuration.
pub fn demo_path() -> &'static str {
    concat!(env!("CARGO_MANIFEST_DIR"), "/../config/demo.toml")
}

/// The demo configuration as shipped, listening on free loopback ports instead of 5020 and 9020.
pub fn demo_config() -> Config {
    let env = [
        ("MBGW__SERVER__LISTEN".to_owned(), "127.0.0.1:0".to_owned()),
        ("MBGW__METRICS__LISTEN".to_owned(), "127.0.0.1:0".to_owned()),
    ];
    load_config(Path::new(demo_path()), env).expect("config/demo.toml is valid")
}

/// The demo as shipped, but its Goodrive300 at unit 2 polled every 300 ms and ramping to
/// 50 Hz in 3.0 s (P00.11) rather than 15: a test's patience is shorter. Polling may take the
/// whole line (`poll_share`, 0.2 shipped): at 9600 baud the drive's five reads every 300 ms take
/// two thirds of it.
pub fn demo_with_a_quick_drive_2() -> Config {
    let mut config = demo_config();
    let bus = &mut config.bus[0];
    bus.poll_share = 1.0;
    let unit_2 = bus.slave.iter_mut().find(|s| s.address == 2);
    let unit_2 = unit_2.expect("the demo's unit 2");
    assert_eq!(unit_2.template.as_deref(), Some("goodrive300"));
    unit_2.poll_interval = Some(std::time::Duration::from_millis(300));
    let drive = bus.sim_slave.iter_mut().find(|s| s.address.contains(2));
    let drive = drive.expect("the demo's drive 2");
    drive.params.insert("P00.11".to_owned(), 30);
    config
}

/// The demo's bus with its simulated drives, its task running: call on the paused clock.
pub fn demo_bus() -> (SimLine, BusHandle) {
    sim_bus_of(demo_config().bus.remove(0))
}

/// A simulated bus from its settings, slaves powered on now, its task running.
pub fn sim_bus_of(settings: modbus_gateway::config::Bus) -> (SimLine, BusHandle) {
    sim_bus_counted(settings, &Metrics::new())
}

/// [`sim_bus_of`], counting into `metrics`.
pub fn sim_bus_counted(
    settings: modbus_gateway::config::Bus,
    metrics: &Metrics,
) -> (SimLine, BusHandle) {
    sim_bus_filled(settings, metrics, |_| {})
}

/// A simulated bus from its settings: its configured slaves powered on now, then `fill` adding
/// slaves of its own to the line; its task running, counting into `metrics`. The one place a
/// test builds a bus on the simulated line by hand.
pub fn sim_bus_filled(
    settings: modbus_gateway::config::Bus,
    metrics: &Metrics,
    fill: impl FnOnce(&SimLine),
) -> (SimLine, BusHandle) {
    let line =
        modbus_gateway::gateway::power_on_line(&settings).expect("simulated slaves power on");
    fill(&line);
    let bus = BusTask::new(settings, Device::Sim(line.clone()), metrics);
    let handle = bus.handle();
    tokio::spawn(bus.run(Stopping::never()));
    (line, handle)
}

/// The settings of a bus named "line" on the simulated line, from its other keys as TOML text.
pub fn sim_bus_settings(keys: &str) -> modbus_gateway::config::Bus {
    GatewayConfig::new()
        .bus(Bus::sim("line").text(keys))
        .load()
        .bus
        .remove(0)
}

/// The frames `from` put on the simulated line so far, in order.
pub fn frames_from(line: &SimLine, from: modbus_gateway::testing::sim::Source) -> Vec<Vec<u8>> {
    line.frames()
        .into_iter()
        .filter(|f| f.from == from)
        .map(|f| f.bytes)
        .collect()
}
