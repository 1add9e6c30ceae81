//! Plant values for Prometheus (docs/plant-values.md): a drive's values polled by the gateway on
//! the simulated line and exported in their units, a slave that stops answering losing its
//! values and getting them back, promtool's verdict on a scrape with values, `GET /values` and
//! its query (percent-encoded too), and every bad value or template refused in one run, naming
//! its key. How polls share the line is
//! measured on tokio's paused clock in `src/values/`.

use crate::support::{within, Bus, GatewayConfig, RawMaster, Scrape};
use modbus_gateway::testing::sim::{RegisterBank, Scripted};
use std::time::Duration;

/// The demo's Goodrive300 at unit 2, taking run commands and its reference from the bus, with
/// its output frequency, reference and identifying code listed as values read every 200 ms,
/// and a 1 s ramp (P00.11 = 1.0 s from 0 to 50.00 Hz).
fn drive_bus() -> Bus {
    Bus::on("demo", "sim").baud(115_200).parity("none").text(
        r#"
[[bus.slave]]
address = 2
poll_interval = "200ms"

[[bus.slave.value]]
name = "drive_output_frequency_hertz"
register = 0x3000
scale = 0.01
unit = "Hz"
help = "Output frequency"

[[bus.slave.value]]
name = "drive_reference_frequency_hertz"
register = 0x3001
scale = 0.01
unit = "Hz"
help = "Frequency reference"

[[bus.slave.value]]
name = "drive_identifying_code"
register = 0x2103
help = "The drive's identifying code"

[[bus.sim_slave]]
address = 2
model = "gd300"
params = { "P00.01" = 2, "P00.06" = 8, "P00.11" = 10 }
"#,
    )
}

async fn drive_gateway() -> modbus_gateway::Gateway {
    GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(drive_bus())
        .start()
        .await
}

/// Scrape until `series` has a value `done` accepts; every value seen on the way, in order.
async fn watch(
    gateway: &modbus_gateway::Gateway,
    series: &str,
    done: impl Fn(f64) -> bool,
) -> Vec<f64> {
    within(series, async {
        let mut seen: Vec<f64> = Vec::new();
        loop {
            if let Some(value) = Scrape::of(gateway).await.get(series) {
                if seen.last() != Some(&value) {
                    seen.push(value);
                }
                if done(value) {
                    return seen;
                }
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
}

const FREQUENCY: &str = "drive_output_frequency_hertz{bus=\"demo\",slave=\"2\"}";

/// Set to 50 Hz and run; the output frequency reads in Hz.
#[tokio::test]
async fn the_demos_unit_2_run_at_50_hz_shows_its_output_frequency_ramping_to_50_hz() {
    // The demo as shipped, its Goodrive300 exporting its template's values.
    let config = crate::support::demo_with_a_quick_drive_2();
    let gateway = modbus_gateway::Gateway::start(&config)
        .await
        .expect("the demo starts");
    let identity = "drive_identifying_code{bus=\"demo\",slave=\"2\"}";
    // Goodrive300's identifying code, 010AH.
    assert_eq!(
        watch(&gateway, identity, |v| v > 0.0).await.last(),
        Some(&266.0)
    );
    assert_eq!(watch(&gateway, FREQUENCY, |_| true).await, [0.0], "stopped");
    let mut master = RawMaster::connect(crate::support::addr(&gateway)).await;
    // 2001H = 5000 (50.00 Hz), then 2000H = 0001H (run forward): Goodrive300 manual 10.4.
    let set = [0x06, 0x20, 0x01, 0x13, 0x88];
    assert_eq!(master.call(1, 2, &set).await, set);
    let run = [0x06, 0x20, 0x00, 0x00, 0x01];
    assert_eq!(master.call(2, 2, &run).await, run);
    let ramp = watch(&gateway, FREQUENCY, |v| v >= 50.0).await;
    assert_eq!(ramp.last(), Some(&50.0), "in Hz, not in 0.01 Hz: {ramp:?}");
    assert!(
        ramp.iter().any(|&v| v > 0.0 && v < 50.0),
        "seen on the way up: {ramp:?}"
    );
    assert!(ramp.windows(2).all(|w| w[0] <= w[1]), "rising: {ramp:?}");
    let scrape = Scrape::of(&gateway).await;
    let reference = "drive_reference_frequency_hertz{bus=\"demo\",slave=\"2\"}";
    assert_eq!(scrape.value(reference), 50.0);
    // The GD300's motor at 50 Hz: 11.1 A (tests/templates_expected.md).
    let current = "drive_output_current_amperes{bus=\"demo\",slave=\"2\"}";
    assert_eq!(
        watch(&gateway, current, |v| v > 11.0).await.last(),
        Some(&11.1)
    );
    crate::metrics::assert_promtool_finds_nothing_to_lint(&scrape.text).await;
}

/// The timeouts are counted.
#[tokio::test]
async fn a_slave_that_stops_answering_loses_its_values_and_gets_them_back() {
    let gateway = drive_gateway().await;
    watch(&gateway, FREQUENCY, |_| true).await;
    let line = gateway.sim_line("demo").expect("a simulated line");
    // Unit 2 falls silent: nothing answers at its address.
    line.add_slave(2, Scripted::new([]));
    within("the values vanish", async {
        while Scrape::of(&gateway).await.get(FREQUENCY).is_some() {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    let scrape = Scrape::of(&gateway).await;
    let timeouts = "modbus_gateway_poll_errors_total{bus=\"demo\",outcome=\"timeout\",slave=\"2\"}";
    assert!(scrape.value(timeouts) >= 1.0, "{}", scrape.text);
    let (status, body) = crate::support::http_get(gateway.metrics_addr(), "/values?slave=2").await;
    assert_eq!(status, 200);
    let listing: serde_json::Value = serde_json::from_str(&body).unwrap();
    let frequency = &listing["values"][0];
    assert_eq!(frequency["name"], "drive_output_frequency_hertz");
    assert!(frequency["value"].is_null(), "{frequency}");
    assert_eq!(frequency["error"], "timeout");
    assert!(
        frequency["read_at"].is_string(),
        "the last good read stays known"
    );
    // The status page counts the polls of a slave no master asks, so it is not "not asked yet".
    let (_, body) = crate::support::http_get(gateway.metrics_addr(), "/status").await;
    let status: serde_json::Value = serde_json::from_str(&body).unwrap();
    let slaves = status["buses"][0]["slaves"].as_array().unwrap();
    let unit_2 = slaves.iter().find(|s| s["address"] == 2).unwrap();
    assert!(unit_2["polls"].as_u64().is_some_and(|n| n > 0), "{unit_2}");
    assert_eq!(unit_2["up"], false);
    // Back on the line (a plain register bank: its registers hold 0).
    line.add_slave(2, RegisterBank::new(Duration::ZERO));
    assert_eq!(watch(&gateway, FREQUENCY, |_| true).await, [0.0]);
}

#[tokio::test]
async fn values_are_listed_as_json_with_their_units_and_when_they_were_read() {
    let gateway = drive_gateway().await;
    watch(&gateway, FREQUENCY, |_| true).await;
    let (status, body) =
        crate::support::http_get(gateway.metrics_addr(), "/values?bus=demo&history=1").await;
    assert_eq!(status, 200, "{body}");
    let listing: serde_json::Value = serde_json::from_str(&body).unwrap();
    let values = listing["values"].as_array().unwrap();
    let names: Vec<&str> = values.iter().map(|v| v["name"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "drive_output_frequency_hertz",
            "drive_reference_frequency_hertz",
            "drive_identifying_code"
        ]
    );
    assert_eq!(values[0]["unit"], "Hz");
    assert_eq!(
        values[0]["help"], "Output frequency",
        "the status page's label"
    );
    assert_eq!(values[0]["slave"], 2);
    assert!(values[0]["history"]
        .as_array()
        .is_some_and(|h| !h.is_empty()));
    let (status, _) = crate::support::http_get(gateway.metrics_addr(), "/values?bus=nope").await;
    assert_eq!(status, 404);
}

/// Which values a `/values` answer lists: (bus, slave, name) of each.
fn listed(body: &str) -> Vec<(String, u64, String)> {
    let listing: serde_json::Value = serde_json::from_str(body).unwrap_or_else(|e| {
        panic!("not JSON ({e}): {body}");
    });
    let values = listing["values"].as_array().cloned().unwrap_or_default();
    values
        .iter()
        .map(|v| {
            let text = |key: &str| v[key].as_str().unwrap_or_default().to_owned();
            (
                text("bus"),
                v["slave"].as_u64().unwrap_or(256),
                text("name"),
            )
        })
        .collect()
}

#[tokio::test]
async fn a_percent_encoded_query_picks_what_its_plain_form_does_and_bad_escapes_get_400() {
    let gateway = drive_gateway().await;
    let at = gateway.metrics_addr();
    let (status, plain) = crate::support::http_get(at, "/values?bus=demo&slave=2").await;
    assert_eq!(status, 200, "{plain}");
    assert_eq!(listed(&plain).len(), 3, "{plain}");
    // Keys and values encoded: `%75` is `u`, `%61` `a`, `%64` `d`, `%32` `2`.
    let (status, encoded) =
        crate::support::http_get(at, "/values?b%75s=%64emo&sl%61ve=%32&history=%30").await;
    assert_eq!(status, 200, "{encoded}");
    assert_eq!(listed(&encoded), listed(&plain));
    // An encoded `&` and `=` are the value's own, not separators.
    let (status, body) = crate::support::http_get(at, "/values?bus=demo%26slave%3D2").await;
    assert_eq!(status, 404, "{body}");
    assert!(body.contains("no bus named `demo&slave=2`"), "{body}");
    // A `%` without two hex digits after it; /trace reads its query the same way.
    for (path, escape) in [
        ("/values?bus=%zzdemo", "%zz"),
        ("/values?slave=%3", "%3"),
        ("/values?history=1%", "%"),
        ("/trace?bus=de%6Xmo", "%6X"),
    ] {
        let (status, body) = crate::support::http_get(at, path).await;
        assert_eq!(status, 400, "{path}: {body}");
        assert!(
            body.contains(&format!("bad escape `{escape}`")),
            "{path}: {body}"
        );
    }
}

#[test]
fn every_bad_value_and_template_is_refused_in_one_run_naming_its_key() {
    let dir = std::env::temp_dir().join(format!("mbgw-templates-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("mine")).unwrap();
    std::fs::write(
        dir.join("mine/pump.toml"),
        "description = \"a pump\"\n[[value]]\nname = \"pump_speed\"\nregister = 1\ntype = \"u17\"\n",
    )
    .unwrap();
    let config = dir.join("gateway.toml");
    std::fs::write(
        &config,
        r#"template_dir = "mine"

[[bus]]
name = "line"
device = "sim"

[[bus.slave]]
address = 1
template = "nothing-by-this-name"

[[bus.slave.value]]
name = "speed"
register = 0
type = "u17"

[[bus.slave.value]]
name = "2speed"
register = 0

[[bus.slave.value]]
name = "energy"
register = 65534
type = "u64"

[[bus.slave.value]]
name = "flags"
register = 0
type = "u32"
bit = 3
"#,
    )
    .unwrap();
    let errors = modbus_gateway::gateway::load_config(&config, std::iter::empty())
        .expect_err("refused")
        .to_string();
    std::fs::remove_dir_all(&dir).unwrap();
    for expected in [
        "template_dir: ",
        "mine/pump.toml: value[0].type: `u17` is not u16, i16, u32, i32, u64, i64, f32, f64 or bool",
        "bus[0].slave[0].value[0].type: `u17` is not u16, i16, u32",
        "bus[0].slave[0].template: no template `nothing-by-this-name`",
        "bus[0].slave[0].value[1].name: `2speed` is no Prometheus metric name",
        "bus[0].slave[0].value[2].register: 65534 with 4 register(s) of u64 ends at 65537, past 65535",
        "bus[0].slave[0].value[3].bit: picks one bit of a 16-bit register",
    ] {
        assert!(errors.contains(expected), "missing `{expected}` in:\n{errors}");
    }
}

#[tokio::test]
async fn a_reload_polls_the_new_values_drops_the_old_ones_and_leaves_the_line_as_it_was() {
    let gateway = drive_gateway().await;
    let mut master = RawMaster::connect(crate::support::addr(&gateway)).await;
    watch(&gateway, FREQUENCY, |_| true).await;
    // The identifying code goes; the drive's state word 1 (2100H) comes.
    let text = GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(drive_bus().text(
            r#"
[[bus.slave.value]]
name = "drive_state"
register = 0x2100
help = "State word 1"
"#,
        ))
        .to_toml()
        .replace(
            "[[bus.slave.value]]\nname = \"drive_identifying_code\"\nregister = 0x2103\nhelp = \"The drive's identifying code\"\n",
            "",
        );
    let mut config = modbus_gateway::Config::from_toml_str(&text).expect("the new config");
    config.metrics.listen = ([127, 0, 0, 1], 0).into();
    let done = gateway.reload(&config).unwrap();
    assert_eq!(
        done.applied,
        ["plant values"],
        "the bus itself is as it was"
    );
    let state = "drive_state{bus=\"demo\",slave=\"2\"}";
    // Stopped: 0003H (Goodrive300 manual, 2100H).
    assert_eq!(watch(&gateway, state, |_| true).await, [3.0]);
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.get("drive_identifying_code{bus=\"demo\",slave=\"2\"}"),
        None
    );
    assert_eq!(scrape.value(FREQUENCY), 0.0, "kept across the reload");
    let read = [0x03, 0x21, 0x00, 0x00, 0x01];
    assert_eq!(master.call(1, 2, &read).await, [0x03, 0x02, 0x00, 0x03]);
}

#[tokio::test]
async fn a_master_flooding_the_line_with_pipelined_reads_cannot_starve_the_polls() {
    let gateway = drive_gateway().await;
    watch(&gateway, FREQUENCY, |_| true).await;
    let addr = crate::support::addr(&gateway);
    // Eight reads in flight at all times, each of its own registers: nothing to coalesce.
    let flood = tokio::spawn(async move {
        let mut master = RawMaster::connect(addr).await;
        for round in 0u16.. {
            for n in 0..8u16 {
                master
                    .send(8 * round + n, 2, &[0x03, 0x30, n as u8, 0x00, 0x01])
                    .await;
            }
            for _ in 0..8 {
                master.recv().await;
            }
        }
    });
    let polls = "modbus_gateway_polls_total{bus=\"demo\",slave=\"2\"}";
    let before = Scrape::of(&gateway).await.value(polls);
    within("polls go on under the flood", async {
        while Scrape::of(&gateway).await.value(polls) < before + 5.0 {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    let scrape = Scrape::of(&gateway).await;
    assert!(scrape.get(FREQUENCY).is_some(), "the values stay exported");
    flood.abort();
}
