//! The `modbus-gateway` binary as a user runs it: `check-config` prints the resolved config, a
//! bad one exits 2 naming each key and why, the environment overrides the file, `run` serves
//! the demo line and stops cleanly on SIGTERM, and each log line is one JSON object or carries
//! the journal's priority.

use crate::support::{
    connect_when_listening, demo_path, exit_status, free_addr, signal, within, Bus, GatewayConfig,
};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

fn temp_config(name: &str, text: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mbgw-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

fn gateway(args: &[&str], env: &[(&str, &str)]) -> Output {
    Command::new(BINARY)
        .args(args)
        .envs(env.iter().copied())
        .env_remove("RUST_LOG")
        .output()
        .expect("binary runs")
}

#[test]
fn check_config_prints_the_resolved_demo_config_with_its_line_timing() {
    let out = gateway(&["--config", demo_path(), "check-config"], &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.contains("9600 baud 8E1, character 1.146 ms, t3.5 4.010 ms"),
        "{text}"
    );
    assert!(
        text.contains("stop_bits = 1"),
        "the default is filled in: {text}"
    );
    assert!(text.contains("listen = [\"127.0.0.1:5020\"]"), "{text}");
    assert!(text.contains("listen = \"127.0.0.1:9020\""), "{text}");
    assert!(text.contains("model = \"pd-inverter\""), "{text}");
    assert!(text.contains("wide_read_count = true"), "{text}");
}

#[test]
fn a_drive_parameter_the_model_refuses_exits_2_naming_it() {
    let path = temp_config(
        "bad-param.toml",
        "[[bus]]\nname = \"a\"\ndevice = \"sim\"\n\
         [[bus.sim_slave]]\naddress = 1\nmodel = \"gd20\"\nparams = { \"P00.01\" = 3 }\n\
         [[bus.sim_slave]]\naddress = 2\nmodel = \"registers\"\ntrip = 18\n",
    );
    let out = gateway(&["--config", path.to_str().unwrap(), "check-config"], &[]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("bus[0].sim_slave[0].params.\"P00.01\": 3 is outside 0..=2"),
        "{err}"
    );
    assert!(
        err.contains("bus[0].sim_slave[1].trip: only drive models"),
        "{err}"
    );
}

#[test]
fn a_bad_config_exits_2_naming_the_key_and_the_reason() {
    let path = temp_config(
        "bad.toml",
        "[[bus]]\nname = \"a\"\ndevice = \"sim\"\nparity = \"evn\"\n",
    );
    for command in ["check-config", "run"] {
        let out = gateway(&["--config", path.to_str().unwrap(), command], &[]);
        assert_eq!(out.status.code(), Some(2), "{command}");
        let err = String::from_utf8(out.stderr).unwrap();
        assert!(
            err.contains("bus[0].parity: `evn` is not none, even or odd"),
            "{err}"
        );
    }
}

#[test]
fn a_file_with_three_mistakes_reports_all_three_in_one_run_with_a_suggestion() {
    let path = temp_config(
        "three.toml",
        "[[bus]]\nname = \"a\"\ndevice = \"sim\"\nparty = \"even\"\n\
         response_timeout = \"0s\"\n[[bus.slave]]\naddress = 1\ntimeout = \"1s\"\n",
    );
    let out = gateway(&["--config", path.to_str().unwrap(), "check-config"], &[]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    let lines: Vec<&str> = err.lines().collect();
    let file = path.display();
    assert_eq!(
        lines,
        [
            format!("modbus-gateway: {file}: bus[0].party: unknown field `party`; did you mean `parity`?"),
            format!("modbus-gateway: {file}: bus[0].slave[0].timeout: unknown field `timeout`; did you mean `response_timeout`?"),
            format!("modbus-gateway: {file}: bus[0].response_timeout: must be longer than 0"),
        ],
    );
}

/// `command` on the configuration at `path` exits 2: the keys its errors name, in order, and
/// the whole of standard error.
fn refused_keys(path: &Path, command: &str) -> (Vec<String>, String) {
    let out = gateway(&["--config", path.to_str().unwrap(), command], &[]);
    assert_eq!(out.status.code(), Some(2), "{command}");
    let err = String::from_utf8(out.stderr).unwrap();
    let keys = err
        .lines()
        .filter_map(|line| line.split(": ").nth(2))
        .map(str::to_owned)
        .collect();
    (keys, err)
}

#[test]
fn bad_serial_master_ports_exit_2_naming_every_key_in_one_run() {
    // A missing device, baud 0, framing "tcp", a duplicate name, units past 247, and a port on
    // the device a bus opens (a loop).
    let ports = "[[server.serial]]\nname = \"a\"\nbaud = 0\nframing = \"tcp\"\n\
                 [[server.serial]]\nname = \"a\"\ndevice = \"/dev/ttyS2\"\nunits = \"1-250\"\n\
                 [[server.serial]]\nname = \"b\"\ndevice = \"/dev/ttyS3\"\n";
    let config = GatewayConfig::new()
        .server_table(ports)
        .bus(Bus::on("line", "/dev/ttyS3"))
        .to_toml();
    let path = temp_config("bad-ports.toml", &config);
    for command in ["check-config", "run"] {
        let (keys, err) = refused_keys(&path, command);
        assert_eq!(
            keys,
            [
                "server.serial[0].device",
                "server.serial[0].baud",
                "server.serial[0].framing",
                "server.serial[1].name",
                "server.serial[1].units",
                "server.serial[2].device",
            ],
            "{command}: {err}"
        );
        assert!(
            err.contains("bus[0].device"),
            "the loop names both keys: {err}"
        );
    }
}

#[test]
fn bad_virtual_units_exit_2_naming_every_key_in_one_run() {
    // A routed unit, unit 0, a value that does not exist, overlapping registers, a coil of u16,
    // a template without a source, and a register past 65535 for its width.
    let units = r#"
[[virtual]]
unit = 5
name = "routed"
[[virtual.register]]
register = 0
value = "line1/2/nope"
[[virtual.register]]
register = 0
value = "line1/2/power_watts"
type = "f32"
[[virtual.register]]
register = 1
value = "line1/2/power_watts"
[[virtual.register]]
register = 0
table = "coil"
type = "u16"
value = "line1/2/power_watts"

[[virtual]]
unit = 0
name = "meter"
template = "eastron-sdm120"
[[virtual.register]]
register = 65535
type = "u32"
value = "line1/2/power_watts"
"#;
    let config = GatewayConfig::new()
        .bus(Bus::sim("line1").text(
            "[[bus.slave]]\naddress = 2\n[[bus.slave.value]]\nname = \"power_watts\"\n\
             register = 0\ntype = \"f32\"\n",
        ))
        .bus(Bus::sim("line2"))
        .route("1-10", "line1", None)
        .tables(units)
        .to_toml();
    let path = temp_config("bad-virtual.toml", &config);
    for command in ["check-config", "run"] {
        let (keys, err) = refused_keys(&path, command);
        assert_eq!(
            keys,
            [
                "virtual[0].unit",
                "virtual[1].unit",
                "virtual[0].register[0].value",
                "virtual[0].register[3].type",
                "virtual[0].register[2]",
                "virtual[1].source",
                "virtual[1].register[0].register",
            ],
            "{command}: {err}"
        );
        assert!(err.contains("its values are power_watts"), "{err}");
        assert!(err.contains("by route[0]"), "{err}");
    }
}

#[test]
fn check_config_says_what_mqtt_publishes_and_which_sets_write() {
    let env = [
        ("MBGW__MQTT__URL", "mqtt://127.0.0.1:1883"),
        ("MBGW__MQTT__WRITES", "true"),
    ];
    let out = gateway(&["--config", demo_path(), "check-config"], &env);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.contains("# mqtt: 100 values of 4 slaves published to mqtt://127.0.0.1:1883"),
        "{text}"
    );
    // The demo's GD300 and GD10 take their 2001H; the GD20's is write-only, so not polled.
    for set in [
        "demo/2/drive_frequency_setpoint_hertz/set",
        "demo/3/drive_frequency_setpoint_hertz/set",
    ] {
        assert!(
            text.contains(&format!("#   modbus-gateway/{set}\n")),
            "{text}"
        );
    }
    assert!(!text.contains("demo/1/drive_frequency_setpoint"), "{text}");
}

#[test]
fn a_bad_mqtt_table_exits_2_naming_every_key_in_one_run() {
    // A url that is no broker's, qos 2, a password written inline, a password file that is not
    // there, a negative deadband, and a writable input register.
    let mqtt = r#"
[mqtt]
url = "http://127.0.0.1:1883"
qos = 2
username = "gw"
password = "secret"
password_file = "/nonexistent/mqtt.password"
"#;
    let config = GatewayConfig::new()
        .bus(Bus::sim("line1").text(
            "[[bus.slave]]\naddress = 2\n[[bus.slave.value]]\nname = \"power_watts\"\n\
             register = 0\ndeadband = -1.5\n[[bus.slave.value]]\nname = \"energy\"\n\
             register = 1\ntable = \"input\"\nwritable = true\n",
        ))
        .tables(mqtt)
        .to_toml();
    let path = temp_config("bad-mqtt.toml", &config);
    for command in ["check-config", "run"] {
        let (keys, err) = refused_keys(&path, command);
        assert_eq!(
            keys,
            [
                "bus[0].slave[0].value[0].deadband",
                "bus[0].slave[0].value[1].writable",
                "mqtt.url",
                "mqtt.qos",
                "mqtt.password",
                "mqtt.password_file",
            ],
            "{command}: {err}"
        );
        assert!(err.contains("/nonexistent/mqtt.password"), "{err}");
        assert!(
            !err.contains("secret"),
            "the password is never shown: {err}"
        );
    }
}

#[test]
fn the_manual_page_and_completions_need_no_configuration_and_name_every_subcommand() {
    let missing = "/nonexistent/gateway.toml";
    let out = gateway(&["--config", missing, "man"], &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let page = String::from_utf8(out.stdout).unwrap();
    assert!(page.starts_with(".ie"), "roff: {page}");
    for section in [
        "NAME",
        "SYNOPSIS",
        "OPTIONS",
        "SUBCOMMANDS",
        "FILES",
        "EXIT STATUS",
    ] {
        assert!(
            page.contains(&format!(".SH {section}")),
            "{section}: {page}"
        );
    }
    for subcommand in ["check\\-config", "simulate", "health", "completions"] {
        assert!(page.contains(subcommand), "{subcommand}: {page}");
    }
    let dir = temp_config("unused", "").with_file_name("man");
    let out = gateway(&["man", "--out-dir", dir.to_str().unwrap()], &[]);
    assert!(out.status.success());
    for file in [
        "modbus-gateway.1",
        "modbus-gateway-check-config.1",
        "modbus-gateway-run.1",
    ] {
        assert!(dir.join(file).is_file(), "{file}");
    }
    let out = gateway(&["--config", missing, "completions", "bash"], &[]);
    assert!(out.status.success());
    let script = String::from_utf8(out.stdout).unwrap();
    assert!(script.contains("complete -F _modbus__gateway"), "{script}");
    assert!(script.contains("check-config"), "{script}");
}

#[test]
fn a_missing_config_file_exits_2_naming_it() {
    let out = gateway(
        &["--config", "/nonexistent/gateway.toml", "check-config"],
        &[],
    );
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/gateway.toml"));
}

#[test]
fn environment_variables_override_the_file() {
    let out = gateway(
        &["--config", demo_path(), "check-config"],
        &[
            ("MBGW__BUS__0__BAUD", "19200"),
            ("MBGW__SERVER__LISTEN", "[::1]:1502"),
        ],
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("baud = 19200"), "{text}");
    assert!(text.contains("listen = [\"[::1]:1502\"]"), "{text}");
    let out = gateway(
        &["--config", demo_path(), "check-config"],
        &[("MBGW__BUS__0__BAUDRATE", "1")],
    );
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("baudrate"));
}

#[tokio::test]
async fn run_serves_the_demo_line_and_stops_cleanly_on_sigterm() {
    let listen = free_addr();
    let child = Command::new(BINARY)
        .args(["--config", demo_path(), "run"])
        .env("MBGW__SERVER__LISTEN", listen.to_string())
        .env("MBGW__METRICS__LISTEN", free_addr().to_string())
        .env("MBGW__LOG__LEVEL", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut master = connect_when_listening(listen).await;
    assert_eq!(
        master.call(1, 2, &[0x06, 0x00, 0x04, 0x13, 0x88]).await,
        [0x06, 0x00, 0x04, 0x13, 0x88]
    );
    assert_eq!(
        master.call(2, 2, &[0x03, 0x00, 0x04, 0x00, 0x01]).await,
        [0x03, 0x02, 0x13, 0x88]
    );
    signal(&child, "TERM");
    let status = exit_status(child).await;
    assert_eq!(status.code(), Some(0));
}

/// `health` of the gateway configured by `config`, with `args`, until it
/// says something other than that it cannot reach it (the endpoint may not listen yet).
fn health_of(config: &Path, args: &[&str]) -> Output {
    let config = config.to_str().unwrap();
    for _ in 0..100 {
        let out = gateway(&[&["--config", config, "health"], args].concat(), &[]);
        if !String::from_utf8_lossy(&out.stderr).contains("cannot reach") {
            return out;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    panic!("the metrics endpoint never listened");
}

#[tokio::test]
async fn health_says_ok_and_ready_of_a_running_gateway_and_exits_1_when_it_cannot() {
    let metrics = free_addr();
    let text = std::fs::read_to_string(demo_path()).unwrap();
    let text = text
        .replace("127.0.0.1:5020", &free_addr().to_string())
        .replace("127.0.0.1:9020", &metrics.to_string());
    let config = temp_config("health.toml", &text);
    let child = Command::new(BINARY)
        .args(["--config", config.to_str().unwrap(), "run"])
        .env("MBGW__LOG__LEVEL", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let alive = health_of(&config, &[]);
    assert_eq!(alive.status.code(), Some(0), "{alive:?}");
    assert_eq!(String::from_utf8_lossy(&alive.stdout), "ok\n");
    let ready = health_of(&config, &["--ready"]);
    assert_eq!(ready.status.code(), Some(0), "{ready:?}");
    assert_eq!(String::from_utf8_lossy(&ready.stdout), "ready\n");
    // Another path of the endpoint: its status and its words.
    let url = format!("http://{metrics}/nothing");
    let missing = gateway(&["health", "--url", &url], &[]);
    assert_eq!(missing.status.code(), Some(1));
    let said = String::from_utf8_lossy(&missing.stderr);
    assert!(said.contains("404 Not Found"), "{said}");
    signal(&child, "TERM");
    assert_eq!(exit_status(child).await.code(), Some(0));
    // Stopped: nothing answers, and it says so.
    let gone = gateway(&["--config", config.to_str().unwrap(), "health"], &[]);
    assert_eq!(gone.status.code(), Some(1));
    let said = String::from_utf8_lossy(&gone.stderr);
    assert!(
        said.contains("cannot reach the gateway's metrics endpoint"),
        "{said}"
    );
    let wrong = gateway(&["health", "--url", "ftp://example"], &[]);
    assert_eq!(wrong.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&wrong.stderr).contains("an http:// URL"));
}

#[test]
fn run_exits_non_zero_naming_an_address_it_cannot_listen_on() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let taken = taken.local_addr().unwrap().to_string();
    let free = free_addr().to_string();
    // The Modbus TCP listener, then the metrics endpoint, each named by its key.
    for (modbus, metrics, key) in [
        (&taken, &free, "server.listen"),
        (&free, &taken, "metrics.listen"),
    ] {
        let out = gateway(
            &["--config", demo_path(), "run"],
            &[
                ("MBGW__SERVER__LISTEN", modbus.as_str()),
                ("MBGW__METRICS__LISTEN", metrics.as_str()),
            ],
        );
        assert_eq!(out.status.code(), Some(1));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains(&format!("{key}: cannot listen on {taken}")),
            "{err}"
        );
    }
}

/// Run the demo gateway with `env` until it reports running, stop it, and return its stderr.
async fn log_of_a_run(name: &str, env: &[(&str, String)]) -> String {
    let path = std::env::temp_dir().join(format!("mbgw-log-{}-{name}", std::process::id()));
    let stderr = std::fs::File::create(&path).unwrap();
    let mut command = Command::new(BINARY);
    command
        .args(["--config", demo_path(), "run"])
        .env("MBGW__SERVER__LISTEN", free_addr().to_string())
        .env("MBGW__METRICS__LISTEN", free_addr().to_string())
        .env_remove("RUST_LOG")
        .env_remove("JOURNAL_STREAM")
        .stdout(Stdio::null())
        .stderr(stderr);
    for (key, value) in env {
        command.env(key, value);
    }
    let child = command.spawn().unwrap();
    within("the gateway reports running", async {
        while !std::fs::read_to_string(&path)
            .unwrap()
            .contains("modbus-gateway running")
        {
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    })
    .await;
    signal(&child, "TERM");
    let status = exit_status(child).await;
    assert!(status.success());
    let log = std::fs::read_to_string(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    log
}

#[tokio::test]
async fn with_log_format_json_every_log_line_is_one_json_object() {
    let log = log_of_a_run("json", &[("MBGW__LOG__FORMAT", "json".into())]).await;
    let lines: Vec<serde_json::Value> = log
        .lines()
        .map(|line| serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line}")))
        .collect();
    let running = lines
        .iter()
        .find(|l| l["message"] == "modbus-gateway running")
        .expect("the start-up line");
    assert_eq!(running["level"], "INFO");
    assert_eq!(running["version"], env!("CARGO_PKG_VERSION"));
    assert!(running["timestamp"].is_string(), "{running}");
    assert!(lines
        .iter()
        .any(|l| l["message"] == "serial port open" && l["bus"] == "demo"));
}

#[tokio::test]
async fn under_the_journal_lines_carry_their_priority_and_no_timestamp() {
    // systemd names the journal socket it gives as stderr; here stderr is a file, named the same way.
    let path = std::env::temp_dir().join(format!("mbgw-log-{}-journal", std::process::id()));
    std::fs::File::create(&path).unwrap();
    let meta = std::fs::metadata(&path).unwrap();
    let stream = {
        use std::os::unix::fs::MetadataExt;
        format!("{}:{}", meta.dev(), meta.ino())
    };
    let log = log_of_a_run("journal", &[("JOURNAL_STREAM", stream)]).await;
    assert!(
        log.lines()
            .any(|l| l.starts_with("<6>") && l.contains("modbus-gateway running")),
        "{log}"
    );
    for line in log.lines() {
        assert!(line.starts_with('<'), "no priority: {line}");
        assert!(!line.contains(" INFO "), "level named twice: {line}");
        assert!(!line.starts_with("<6>20"), "timestamp: {line}");
    }

    let plain = log_of_a_run("plain", &[]).await;
    let first = plain.lines().next().expect("a log line");
    assert!(
        first.starts_with("20") && first.contains(" INFO "),
        "{first}"
    );
}

#[test]
fn an_unknown_log_format_exits_2_naming_the_key() {
    let out = gateway(
        &["--config", demo_path(), "check-config"],
        &[("MBGW__LOG__FORMAT", "xml")],
    );
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("log.format: `xml` is not text or json"),
        "{err}"
    );
}

#[test]
fn config_errors_written_to_the_journal_carry_error_priority() {
    let path = temp_config("journal-bad.toml", "[log]\nformat = \"xml\"\n");
    let log = std::env::temp_dir().join(format!("mbgw-log-{}-bad", std::process::id()));
    let stderr = std::fs::File::create(&log).unwrap();
    let stream = {
        use std::os::unix::fs::MetadataExt;
        let meta = stderr.metadata().unwrap();
        format!("{}:{}", meta.dev(), meta.ino())
    };
    let status = Command::new(BINARY)
        .args(["--config", path.to_str().unwrap(), "run"])
        .env("JOURNAL_STREAM", stream)
        .stderr(stderr)
        .status()
        .unwrap();
    assert_eq!(status.code(), Some(2));
    let text = std::fs::read_to_string(&log).unwrap();
    let _ = std::fs::remove_file(&log);
    assert!(
        text.starts_with("<3>modbus-gateway: ") && text.contains("log.format: `xml`"),
        "{text}"
    );
}

#[test]
fn the_installed_default_config_is_valid_and_names_every_key() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/gateway.toml");
    let text = std::fs::read_to_string(path).unwrap();
    let config = modbus_gateway::gateway::load_config(std::path::Path::new(path), Vec::new())
        .expect("config/gateway.toml is valid");
    // Every key the resolved configuration has, every default filled in; plus those of the
    // optional tables, which the default leaves out.
    let resolved = config.to_toml();
    let mut keys: Vec<&str> = resolved
        .lines()
        .filter_map(|line| line.split_once(" = ").map(|(key, _)| key.trim()))
        .collect();
    keys.extend([
        "address",
        "response_timeout",
        "wide_read_count",
        "units",
        "bus",
        "offset",
        "listen_tls",
        "certificate",
        "private_key",
        "client_ca",
        "crl",
        "roles",
        "default_role_access",
        "handshake_timeout",
        "priority",
        "coalesce_reads",
        "cache",
        "latency_timer",
        "mode",
        "rts_on_send",
        "rts_after_send",
        "delay_before_send",
        "delay_after_send",
        "rx_during_tx",
        "echo",
    ]);
    for key in keys {
        let set = format!("\n{key} = ");
        let commented = format!("\n#{key} = ");
        assert!(
            text.contains(&set) || text.contains(&commented),
            "config/gateway.toml does not name `{key}`"
        );
    }
}

#[test]
fn every_test_the_failure_behaviour_section_names_exists() {
    let section = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/failure-behaviour.md"
    ))
    .unwrap();
    let mut named = 0;
    for quoted in section.split('`').skip(1).step_by(2) {
        let Some((module, test)) = quoted.split_once("::") else {
            continue;
        };
        if !module.chars().all(|c| c.is_ascii_lowercase() || c == '_') {
            continue;
        }
        let path = format!("{}/tests/{module}.rs", env!("CARGO_MANIFEST_DIR"));
        let source =
            std::fs::read_to_string(&path).unwrap_or_else(|_| panic!("{path} for `{quoted}`"));
        assert!(
            source.contains(&format!("fn {test}(")),
            "docs/failure-behaviour.md names `{quoted}`, which {path} does not have"
        );
        named += 1;
    }
    assert!(named > 30, "only {named} tests named");
}

/// A stand-in for a gateway's /trace: one event, then the stream stays open.
fn one_event_trace() -> String {
    use std::io::{Read, Write};
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        let Ok((mut stream, _)) = listener.accept() else {
            return;
        };
        let mut request = [0; 1024];
        let _ = stream.read(&mut request);
        let _ = stream.write_all(
            b"HTTP/1.1 200 OK\r\ncontent-type: text/event-stream\r\nconnection: close\r\n\r\n\
              event: lost\ndata: {\"lost\":3}\n\n",
        );
        std::thread::sleep(std::time::Duration::from_secs(10));
    });
    format!("http://{addr}/trace")
}

#[test]
fn every_subcommand_writing_to_stdout_exits_0_quietly_when_its_reader_is_gone() {
    let trace_url = one_event_trace();
    let demo = demo_path();
    let cases: [&[&str]; 5] = [
        &["completions", "bash"],
        &["man"],
        &["--config", demo, "check-config"],
        &["--config", demo, "simulate", "--device", "pty"],
        &["trace", "--url", &trace_url],
    ];
    for args in cases {
        // The read end is closed before the command starts, so its first write finds no reader.
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let mut child = Command::new(BINARY)
            .args(args)
            .env_remove("RUST_LOG")
            .env("RUST_BACKTRACE", "1")
            .stdout(writer)
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        while child.try_wait().unwrap().is_none() {
            if std::time::Instant::now() > deadline {
                let _ = child.kill();
                panic!("{args:?}: still running with no reader of its stdout");
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !err.contains("panicked") && !err.contains("Broken pipe"),
            "{args:?}: {err}"
        );
        assert_eq!(out.status.code(), Some(0), "{args:?}: {err}");
    }
}

/// A TLS certificate that cannot be read is reported in the same run as the other errors.
#[test]
fn an_unreadable_tls_certificate_is_reported_beside_the_other_errors() {
    let path = temp_config(
        "tls-and-parity.toml",
        "[server]\nlisten_tls = \"127.0.0.1:0\"\n\
         [server.tls]\ncertificate = \"/nonexistent/server.pem\"\n\
         private_key = \"/nonexistent/server.key\"\nclient_ca = \"/nonexistent/ca.pem\"\n\
         [[bus]]\nname = \"a\"\ndevice = \"sim\"\nparity = \"evn\"\n",
    );
    let out = gateway(&["--config", path.to_str().unwrap(), "check-config"], &[]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("bus[0].parity: `evn`"), "{err}");
    assert!(
        err.contains("server.tls.certificate: cannot read /nonexistent/server.pem"),
        "{err}"
    );
}

#[test]
fn the_manual_pages_name_no_page_that_is_not_generated() {
    let dir = temp_config("unused", "").with_file_name("man-pages-named");
    let out = gateway(&["man", "--out-dir", dir.to_str().unwrap()], &[]);
    assert!(out.status.success());
    let mut named = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let page = std::fs::read_to_string(entry.unwrap().path()).unwrap();
        let page = page.replace("\\-", "-");
        for (at, _) in page.match_indices("(1)") {
            let start = page[..at]
                .rfind(|c: char| !(c.is_ascii_alphanumeric() || c == '-'))
                .map_or(0, |i| i + 1);
            let name = &page[start..at];
            if name.starts_with("modbus-gateway") {
                named.push(name.to_owned());
            }
        }
    }
    assert!(
        !named.is_empty(),
        "the main page lists the subcommands' pages"
    );
    for name in named {
        assert!(dir.join(format!("{name}.1")).is_file(), "{name}(1)");
    }
}

#[test]
fn a_missing_file_or_a_toml_syntax_error_names_the_file_once() {
    let out = gateway(&["--config", "/nonexistent/mbgw.toml", "check-config"], &[]);
    assert_eq!(out.status.code(), Some(2));
    assert_eq!(
        String::from_utf8_lossy(&out.stderr),
        "modbus-gateway: /nonexistent/mbgw.toml: not found (`--config FILE` reads another)\n"
    );
    let path = temp_config("syntax", "[[bus]\nname = \"a\"\n");
    let out = gateway(&["--config", path.to_str().unwrap(), "check-config"], &[]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    let named = format!(
        "modbus-gateway: {}: TOML parse error at line 1",
        path.display()
    );
    assert!(err.starts_with(&named), "{err}");
    let file_name = path.file_name().unwrap().to_str().unwrap();
    assert_eq!(err.matches(file_name).count(), 1, "{err}");
}

/// A page's SYNOPSIS line, and the header lines of its OPTIONS entries (`.TP`'s next line).
fn synopsis_and_options(page: &str) -> (&str, Vec<&str>) {
    let lines: Vec<&str> = page
        .lines()
        .filter(|line| !line.starts_with(".ie") && !line.starts_with(".el"))
        .collect();
    let at = lines
        .iter()
        .position(|line| *line == ".SH SYNOPSIS")
        .expect("a SYNOPSIS section");
    let options = lines
        .windows(2)
        .skip_while(|pair| pair[0] != ".SH OPTIONS")
        .take_while(|pair| !pair[1].starts_with(".SH") || pair[0] == ".SH OPTIONS")
        .filter(|pair| pair[0] == ".TP")
        .map(|pair| pair[1])
        .collect();
    (lines[at + 1], options)
}

#[test]
fn every_manual_pages_synopsis_names_the_argument_of_each_option() {
    let dir = temp_config("unused", "").with_file_name("man-synopsis");
    let out = gateway(&["man", "--out-dir", dir.to_str().unwrap()], &[]);
    assert!(out.status.success());
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let page = std::fs::read_to_string(&path).unwrap();
        let (synopsis, options) = synopsis_and_options(&page);
        for header in options {
            // `\fB\-\-config\fR \fI<CONFIG>\fR [default: ...]`: the option and its argument.
            let Some(value_at) = header.find(" \\fI<") else {
                continue;
            };
            let long_at = header[..value_at]
                .rfind("\\fB\\-\\-")
                .expect("a long option");
            let value_end = value_at + header[value_at..].find("\\fR").unwrap() + 3;
            let written = &header[long_at..value_end];
            assert!(
                synopsis.contains(written),
                "{}: the synopsis lacks {written}: {synopsis}",
                path.display()
            );
            checked += 1;
        }
    }
    assert!(checked >= 12, "only {checked} options with an argument");
    let main = std::fs::read_to_string(dir.join("modbus-gateway.1")).unwrap();
    assert!(
        synopsis_and_options(&main)
            .0
            .contains("[\\fB\\-c\\fR|\\fB\\-\\-config\\fR \\fI<CONFIG>\\fR]"),
        "{main}"
    );
    let simulate = std::fs::read_to_string(dir.join("modbus-gateway-simulate.1")).unwrap();
    assert!(
        synopsis_and_options(&simulate).0.contains(
            "<\\fB\\-\\-device\\fR \\fI<DEVICE>\\fR|\\fB\\-\\-listen\\fR \\fI<HOST:PORT>\\fR>"
        ),
        "one of the two is required: {simulate}"
    );
}
