//! The `modbus-gateway-bench` binary as a user runs it, against the gateway binary built next to
//! it: `cargo test --workspace` builds both.

use std::path::PathBuf;
use std::process::{Command, Stdio};

const BENCH: &str = env!("CARGO_BIN_EXE_modbus-gateway-bench");

/// The daemon's binary in the shared target directory, where the bench looks by default. Cargo
/// builds another package's binary only when asked, so a run of this package alone may lack it.
fn gateway() -> PathBuf {
    let path = PathBuf::from(BENCH).with_file_name("modbus-gateway");
    assert!(
        path.is_file(),
        "{} is missing: run `cargo test --workspace`, which builds the gateway too",
        path.display()
    );
    path
}

/// Run the bench with `--json`, one short round, on `scenarios`: its child and the report lines
/// once it succeeded.
fn bench_json(scenarios: &[&str], started: impl FnOnce(u32)) -> Vec<serde_json::Value> {
    bench_json_for("1", scenarios, started)
}

/// As [`bench_json`], each scenario run for `seconds`.
fn bench_json_for(
    seconds: &str,
    scenarios: &[&str],
    started: impl FnOnce(u32),
) -> Vec<serde_json::Value> {
    let child = Command::new(BENCH)
        .args(["--json", "--seconds", seconds, "--rounds", "1"])
        .args(scenarios)
        .arg("--gateway")
        .arg(gateway())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the bench runs");
    started(child.id());
    let out = child.wait_with_output().expect("the bench ends");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect()
}

#[test]
fn the_bench_reports_every_field_never_beats_physics_and_drives_the_pty_slave() {
    let scenarios = [
        "sim-115200-8N1-read-10",
        "pty-115200-untimed-read-1",
        "idle-0",
    ];
    let reports = bench_json(&scenarios, |_| {});
    assert_eq!(reports.len(), 3);
    let sim = &reports[0];
    assert_eq!(sim["scenario"], "sim-115200-8N1-read-10");
    assert_eq!(
        (sim["baud"].as_u64(), sim["masters"].as_u64()),
        (Some(115_200), Some(10))
    );
    assert!(sim["transactions"].as_u64().unwrap() > 0, "{sim}");
    // No gateway can carry more than the line's physical minimum allows.
    let efficiency = sim["efficiency"].as_f64().unwrap();
    assert!(efficiency > 0.0 && efficiency <= 1.0, "{sim}");
    for field in [
        "p50_ms",
        "p99_ms",
        "max_ms",
        "fairness",
        "cpu_us_per_tx",
        "rss_mb",
        "connect_p50_ms",
        "connect_max_ms",
        "connect_cpu_us",
    ] {
        assert!(
            sim[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {sim}"
        );
    }
    // The pty's slave (the library's responder, untimed) answered every request, in order.
    let pty = &reports[1];
    assert_eq!(pty["scenario"], "pty-115200-untimed-read-1");
    assert!(pty["transactions"].as_u64().unwrap() > 0, "{pty}");
    assert!(pty["efficiency"].is_null(), "{pty}");
    assert!(reports[2]["rss_mb"].as_f64().unwrap() > 0.0);
}

/// The bench reports the TLS masters' handshakes.
#[test]
fn tls_masters_present_a_role_certificate_and_handshakes_are_reported() {
    let scenario = "sim-115200-8N1-tls-read-1";
    let mut pki = PathBuf::new();
    let tls = bench_json(&[scenario], |id| {
        pki = std::env::temp_dir().join(format!("mbgw-bench-tls-{id}-{scenario}"));
    })
    .remove(0);
    assert_eq!(tls["scenario"], scenario);
    // Refused requests would have failed the run: the role gave read access.
    assert!(tls["transactions"].as_u64().unwrap() > 0, "{tls}");
    for field in [
        "efficiency",
        "cpu_us_per_tx",
        "connect_p50_ms",
        "connect_max_ms",
        "connect_cpu_us",
    ] {
        assert!(
            tls[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {tls}"
        );
    }
    assert!(!pki.exists(), "{} is left behind", pki.display());
}

#[test]
fn masters_reading_the_same_block_share_the_line_s_transactions() {
    let scenario = "many-9600-8E1-same-10";
    let same = bench_json(&[scenario], |_| {}).remove(0);
    assert_eq!(same["scenario"], scenario);
    // The line's transactions come from the gateway's metrics: ten masters, far fewer.
    let answered = same["transactions"].as_u64().unwrap();
    let line = same["line_tx"].as_u64().unwrap();
    assert!(line > 0 && line * 2 <= answered, "{same}");
    assert!(same["coalesced"].as_u64().unwrap() > 0, "{same}");
    for field in [
        "line_tx_per_answer",
        "physical_tx_per_s",
        "answered_vs_physical",
    ] {
        assert!(
            same[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {same}"
        );
    }
    assert!(same["priority_tx"].is_null(), "{same}");
}

/// Processes whose command line mentions `needle`.
fn processes_mentioning(needle: &str) -> Vec<String> {
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|entry| std::fs::read(entry.ok()?.path().join("cmdline")).ok())
        .map(|cmdline| String::from_utf8_lossy(&cmdline).replace('\0', " "))
        .filter(|cmdline| cmdline.contains(needle))
        .collect()
}

#[test]
fn the_device_server_line_is_measured_as_the_sim_line_and_its_simulate_is_stopped() {
    let scenario = "device-server-115200-8N1-read-1";
    let mut config = PathBuf::new();
    let ds = bench_json(&[scenario], |id| {
        config = std::env::temp_dir().join(format!("mbgw-bench-{id}-{scenario}-simulate.toml"));
    })
    .remove(0);
    assert_eq!(ds["scenario"], scenario);
    assert!(ds["transactions"].as_u64().unwrap() > 0, "{ds}");
    // The line's timing holds in the other process: still no faster than physics.
    let efficiency = ds["efficiency"].as_f64().unwrap();
    assert!(efficiency > 0.0 && efficiency <= 1.0, "{ds}");
    for field in [
        "cpu_us_per_tx",
        "simulate_cpu_us_per_tx",
        "added_p50_ms",
        "line_tx_per_s",
    ] {
        assert!(ds[field].as_f64().is_some_and(|v| v > 0.0), "{field}: {ds}");
    }
    assert!(!config.exists(), "{} is left behind", config.display());
    let left = processes_mentioning(&config.to_string_lossy());
    assert!(left.is_empty(), "still running: {left:?}");
}

/// modbus-proxy only if it is installed.
#[test]
fn the_tcp_device_line_is_measured_beside_a_direct_client_and_modbus_proxy() {
    let scenario = "tcp-device-read-1";
    let tcp = bench_json(&[scenario], |_| {}).remove(0);
    assert_eq!(tcp["scenario"], scenario);
    assert!(tcp["transactions"].as_u64().unwrap() > 0, "{tcp}");
    // No serial line: no baud rate, no efficiency.
    assert!(
        tcp["baud"].is_null() && tcp["efficiency"].is_null(),
        "{tcp}"
    );
    for field in [
        "p50_ms",
        "cpu_us_per_tx",
        "direct_tx_per_s",
        "direct_p50_ms",
        "tx_vs_direct",
    ] {
        assert!(
            tcp[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {tcp}"
        );
    }
    // For one master: the gateway's median less the direct client's.
    assert!(tcp["added_p50_ms"].as_f64().is_some(), "{tcp}");
    if tcp["proxy_tx_per_s"].is_null() {
        eprintln!("modbus-proxy is not installed in target/modbus-proxy-venv: its figures skipped");
    } else {
        for field in ["proxy_tx_per_s", "proxy_p50_ms", "proxy_p99_ms"] {
            assert!(
                tcp[field].as_f64().is_some_and(|v| v > 0.0),
                "{field}: {tcp}"
            );
        }
    }
}

/// The scenario waits until every plant value is read before it measures.
#[test]
fn the_values_scenario_measures_polling_and_each_page_once_every_value_is_read() {
    let scenario = "values-247x20";
    let values = bench_json(&[scenario], |_| {}).remove(0);
    assert_eq!(values["scenario"], scenario);
    assert_eq!(values["masters"].as_u64(), Some(0), "{values}");
    // 247 slaves of 20 values each, every one read before the measurements began.
    assert_eq!(values["plant_values"].as_u64(), Some(247 * 20), "{values}");
    assert!(
        values["history_points"].as_f64().unwrap() >= 1.0,
        "{values}"
    );
    for field in ["first_pass_s", "rss_polling_mb", "rss_mb"] {
        assert!(
            values[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {values}"
        );
    }
    // The second pass may not have begun within a one-second window: a rate, not a positive one.
    for field in ["polls_per_s", "poll_cpu_ms_per_s"] {
        assert!(values[field].as_f64().is_some(), "{field}: {values}");
    }
    for page in ["metrics", "values", "history"] {
        assert!(
            values[format!("{page}_gets")].as_u64().unwrap() >= 1,
            "{page}: {values}"
        );
        for figure in ["cpu_us_per_get", "ms_per_get", "ms_per_get_plain_client"] {
            let field = format!("{page}_{figure}");
            assert!(
                values[&field].as_f64().is_some_and(|v| v > 0.0),
                "{field}: {values}"
            );
        }
        let field = format!("{page}_cpu_us_per_get_less_polling");
        assert!(values[&field].as_f64().is_some(), "{field}: {values}");
    }
    // Every value is on /metrics, and the history adds to each one of /values.
    let bytes = |page: &str| values[format!("{page}_bytes")].as_u64().unwrap();
    assert!(bytes("metrics") > 247 * 20 * 30, "{values}");
    assert!(bytes("history") > bytes("values"), "{values}");
    // The simulated line is in the gateway's process: no `simulate` to count apart.
    assert!(values["simulate_poll_cpu_ms_per_s"].is_null(), "{values}");
}

/// Each journal scenario is measured against the one with the journal off.
#[test]
fn the_journal_scenarios_journal_every_write_and_compare_with_journal_off() {
    let mut dirs = Vec::new();
    // The line carries about 3.6 rounds of the 100 masters a second: two seconds make sure that
    // every master makes four requests or more in the window, so one of them is a write.
    let reports = bench_json_for("2", &["pty-115200-untimed-mix-100-journal"], |id| {
        dirs = ["on", "fsync"]
            .map(|j| {
                std::env::temp_dir().join(format!(
                    "mbgw-bench-audit-{id}-pty-115200-untimed-mix-100-journal-{j}"
                ))
            })
            .to_vec();
    });
    let names: Vec<_> = reports.iter().map(|r| r["scenario"].clone()).collect();
    assert_eq!(
        names,
        [
            "pty-115200-untimed-mix-100-journal-off",
            "pty-115200-untimed-mix-100-journal-on",
            "pty-115200-untimed-mix-100-journal-fsync"
        ]
    );
    for (report, journal) in reports.iter().zip(["off", "on", "fsync"]) {
        assert_eq!(report["journal"], journal, "{report}");
        // Every fourth request of each master is a write: of the n requests a master made in the
        // window (after the warm-up, so from any place in its cycle), n / 4 rounded down or up
        // were writes, so the writes are a quarter of the transactions, give or take three
        // quarters a master.
        let (tx, writes, masters) = (
            report["transactions"].as_u64().unwrap(),
            report["writes"].as_u64().unwrap(),
            report["masters"].as_u64().unwrap(),
        );
        assert!(
            writes > 0 && writes * 4 <= tx + 3 * masters && writes * 4 + 3 * masters >= tx,
            "{report}"
        );
        for field in ["write_p50_ms", "read_p50_ms"] {
            assert!(
                report[field].as_f64().is_some_and(|v| v > 0.0),
                "{field}: {report}"
            );
        }
    }
    let off = &reports[0];
    assert!(off["journal_bytes_per_write"].is_null(), "{off}");
    assert!(off["cpu_us_per_write_vs_journal_off"].is_null(), "{off}");
    for report in &reports[1..] {
        // A write's entry and its outcome: far more than nothing, far less than a kilobyte.
        let bytes = report["journal_bytes_per_write"].as_f64().unwrap();
        assert!((100.0..1000.0).contains(&bytes), "{report}");
        assert!(report["journal_fs"].as_str().is_some(), "{report}");
        for field in [
            "tx_vs_journal_off",
            "cpu_us_per_write_vs_journal_off",
            "wall_ms_per_write_vs_journal_off",
            "write_p50_ms_vs_journal_off",
        ] {
            assert!(report[field].as_f64().is_some(), "{field}: {report}");
        }
    }
    for dir in dirs {
        assert!(!dir.exists(), "{} is left behind", dir.display());
    }
}

#[test]
fn the_serial_port_scenarios_priority_master_polls_through_the_ports_pty_and_its_link_goes() {
    let scenario = "serial-port-9600-8E1-priority-100ms-100";
    let report = bench_json(&[scenario], |_| {}).remove(0);
    assert_eq!(report["scenario"], scenario);
    // The port's master had its reads answered, at its period, among 100 TCP masters.
    let port_reads = report["priority_tx"].as_u64().unwrap();
    assert!(port_reads >= 5, "{report}");
    assert!(report["line_tx"].as_u64().unwrap() > port_reads, "{report}");
    let links = std::fs::read_dir(std::env::temp_dir())
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|name| name.starts_with("mbgw-bench-port-") && name.ends_with(scenario))
        .count();
    assert_eq!(links, 0, "the port's pty link is left behind");
}

/// The scenario starts its masters once the unit answers; from then on no value it shows is
/// too old.
#[test]
fn masters_reading_a_virtual_unit_are_answered_from_memory_every_read_normally() {
    let scenario = "virtual-unit-100";
    let report = bench_json(&[scenario], |_| {}).remove(0);
    assert_eq!(report["scenario"], scenario);
    assert_eq!(report["masters"].as_u64(), Some(100), "{report}");
    // A read answered with an exception is counted apart; an unexpected reply fails the run.
    assert!(report["transactions"].as_u64().unwrap() > 0, "{report}");
    assert_eq!(report["exceptions"].as_u64(), Some(0), "{report}");
    assert_eq!(report["virtual_registers"].as_u64(), Some(8), "{report}");
    // No line time: no efficiency, and every transaction on the line one of the gateway's polls
    // (give or take one in flight at each end of the window).
    assert_eq!(report["answered_from_memory"], true, "{report}");
    assert!(report["efficiency"].is_null(), "{report}");
    let seconds = report["seconds"].as_f64().unwrap();
    let (polls, line) = (
        report["line_polls_per_s"].as_f64().unwrap() * seconds,
        report["line_tx_per_s"].as_f64().unwrap() * seconds,
    );
    assert!(polls > 0.0 && (polls - line).abs() <= 2.0, "{report}");
    for field in ["p50_ms", "p99_ms", "cpu_us_per_tx", "fairness"] {
        assert!(
            report[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {report}"
        );
    }
}

/// The listen-only line by lengths (the twin that tolerates a host's scheduling jitter): the
/// other master's transactions heard and paired, none lost, the plant values and the shadow
/// read from what was heard, nothing but reads.
#[test]
fn a_saturated_listen_line_is_heard_and_paired_whole_and_its_shadow_answers() {
    let scenario = "listen-115200-byte-timeout-10ms";
    let report = bench_json(&[scenario], |_| {}).remove(0);
    assert_eq!(report["scenario"], scenario);
    let made = report["made"].as_f64().unwrap();
    let (heard, paired) = (
        report["heard"].as_f64().unwrap(),
        report["paired"].as_f64().unwrap(),
    );
    // Every request heard is paired; what was made and what was heard differ only by the
    // transactions under way at the window's ends.
    assert!(made > 100.0, "{report}");
    assert_eq!(heard, paired, "{report}");
    assert!((made - paired).abs() <= 2.0, "{report}");
    for field in [
        "timeouts",
        "crc_errors",
        "discarded",
        "exceptions",
        "shadow_exceptions",
    ] {
        assert_eq!(report[field].as_u64(), Some(0), "{field}: {report}");
    }
    let efficiency = report["efficiency"].as_f64().unwrap();
    assert!(efficiency > 0.97 && efficiency <= 1.01, "{report}");
    assert_eq!(report["plant_values"].as_u64(), Some(20), "{report}");
    assert!(
        report["shadow_reads_per_s"].as_f64().unwrap() > 100.0,
        "{report}"
    );
    for field in ["p50_ms", "cpu_us_per_tx", "cpu_ms_per_s", "rss_mb"] {
        assert!(
            report[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {report}"
        );
    }
}

/// mosquitto and its clients, as the MQTT scenarios need them; if one is missing, nothing to
/// check (what test-support's `tool` says, and it fails the test if MBGW_REQUIRE_TOOLS is set).
fn mosquitto_installed() -> bool {
    let broker = std::path::Path::new("/usr/sbin/mosquitto").is_file()
        || test_support::process::tool("mosquitto").is_some();
    let clients = ["mosquitto_sub", "mosquitto_pub"].map(test_support::process::tool);
    broker && clients.iter().all(Option::is_some)
}

/// The gateway without MQTT first, then publishing to the bench's mosquitto: every value and
/// discovery config received, nothing lost, the masters read beside both. About 30 s: two first
/// passes of 9 s and two short windows each.
#[test]
fn the_mqtt_scenario_receives_every_value_and_config_and_measures_the_masters_beside_both() {
    if !mosquitto_installed() {
        return;
    }
    let scenario = "mqtt-247x20";
    let mut dir = String::new();
    let mqtt = bench_json(&[scenario], |id| dir = format!("mbgw-mosquitto-{id}-")).remove(0);
    assert_eq!(mqtt["scenario"], scenario);
    assert_eq!(mqtt["plant_values"].as_u64(), Some(247 * 20), "{mqtt}");
    assert_eq!(mqtt["publish_interval_s"].as_f64(), Some(10.0), "{mqtt}");
    for (field, topics) in [
        ("value_topics", 247 * 20),
        ("discovery_topics", 247 * 20),
        ("availability_topics", 247),
    ] {
        assert_eq!(mqtt[field].as_u64(), Some(topics), "{field}: {mqtt}");
    }
    // The status, every config, value and availability: the first publication came whole.
    let first = mqtt["first_publication_messages"].as_u64().unwrap();
    assert!(first > 2 * 247 * 20 + 247, "{mqtt}");
    // The gateway counts a message as it leaves, the subscriber as it comes: at the end, about
    // the same (not exactly: some are on their way either side of the count).
    for field in ["published", "received"] {
        assert!(mqtt[field].as_u64().unwrap() >= first, "{field}: {mqtt}");
    }
    assert_eq!(mqtt["mqtt_connected"].as_u64(), Some(1), "{mqtt}");
    for field in ["dropped", "set_refused", "connection_failures"] {
        assert_eq!(mqtt[field].as_u64(), Some(0), "{field}: {mqtt}");
    }
    for field in [
        "first_pass_s",
        "first_pass_s_without_mqtt",
        "discovery_s",
        "first_publication_s",
        "poll_cpu_ms_per_s",
        "poll_cpu_ms_per_s_without_mqtt",
        "rss_polling_mb",
        "rss_polling_mb_without_mqtt",
        "p50_ms",
        "p99_ms",
        "p50_ms_without_mqtt",
        "p99_ms_without_mqtt",
        "tx_per_s_without_mqtt",
        "masters_cpu_ms_per_s",
    ] {
        assert!(
            mqtt[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {mqtt}"
        );
    }
    // A one-second window may fall between two rounds of republishing: rates, not positive ones.
    for field in ["received_per_s", "published_per_s", "broker_cpu_ms_per_s"] {
        assert!(mqtt[field].as_f64().is_some(), "{field}: {mqtt}");
    }
    assert!(mqtt["transactions"].as_u64().unwrap() > 0, "{mqtt}");
    // The broker's temp dir is removed with it.
    let left = std::fs::read_dir(std::env::temp_dir())
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|name| name.starts_with(&dir))
        .count();
    assert_eq!(left, 0, "the broker's dir is left behind");
    assert!(
        processes_mentioning(&dir).is_empty(),
        "mosquitto still runs"
    );
}
