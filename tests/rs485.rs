//! `[bus.rs485]` on a pty: a device that refuses the direction control asked for fails the open
//! with one error naming the key (the bus then answers 0x0A), and a line that echoes every
//! request before the slave answers still gives the master the slave's answer.

use crate::support::{
    addr, exit_status, free_addr, http_get, pty_config, pty_line, signal, start, within, Bus,
    GatewayConfig, PtySlave, RawMaster, Scrape,
};
use modbus_gateway::config::{Rs485, Rs485Mode};
use modbus_gateway::testing::bus::{Device, SerialDriver};
use modbus_gateway::testing::line::{rtu, Parity, SerialFormat};
use std::process::{Command, Stdio};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");
/// Read one holding register from 0000H.
const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];
/// Its answer: 1234H.
const READ_ANSWER: [u8; 4] = [0x03, 0x02, 0x12, 0x34];
/// What a pty says to an RS-485 or RTS ioctl.
const ENOTTY: &str = "Inappropriate ioctl for device";

fn rs485_keys(mode: &str) -> String {
    format!("response_timeout = \"1h\"\n[bus.rs485]\nmode = \"{mode}\"")
}

#[tokio::test]
async fn a_pty_refuses_kernel_and_rts_mode_with_an_error_naming_the_key_and_its_answer() {
    let slave = PtySlave::start(|_| None);
    for (mode, what) in [
        (Rs485Mode::Kernel, "TIOCSRS485"),
        (Rs485Mode::Rts, "RTS control"),
    ] {
        let device = Device::Serial {
            path: slave.path.clone(),
            format: SerialFormat {
                baud: 115_200,
                data_bits: 8,
                parity: Parity::None,
                stop_bits: 2,
            },
            driver: SerialDriver {
                rs485: Rs485 {
                    mode,
                    ..Rs485::default()
                },
                latency_timer: None,
                key: "bus[2]".into(),
            },
        };
        let Err(error) = device.open().await else {
            panic!("a pty took rs485.mode = {mode:?}");
        };
        let text = error.to_string();
        let key = format!("bus[2].rs485.mode = \"{}\"", mode.as_str());
        assert!(text.starts_with(&key), "{text}");
        assert!(text.contains(what) && text.contains(ENOTTY), "{text}");
        assert_eq!(error.kind(), std::io::ErrorKind::Unsupported);
    }
}

#[tokio::test]
async fn a_bus_whose_device_refuses_rs485_mode_is_down_and_answers_0x0a() {
    for mode in ["kernel", "rts"] {
        let slave = PtySlave::start(|request| Some(rtu::encode(request[0], &READ_ANSWER)));
        let gateway = start(&pty_config(&slave.path, &rs485_keys(mode))).await;
        assert_eq!(gateway.bus_up("pty"), Some(false), "{mode}");
        let mut master = RawMaster::connect(addr(&gateway)).await;
        // With a one-hour timeout, an answer at all is an answer at once.
        assert_eq!(master.call(1, 1, &READ).await, [0x83, 0x0A], "{mode}");
        assert!(slave.received().is_empty(), "{mode}: nothing was sent");
        let scrape = Scrape::of(&gateway).await;
        assert_eq!(scrape.value("modbus_gateway_port_up{bus=\"pty\"}"), 0.0);
        assert!(scrape.value("modbus_gateway_port_open_errors_total{bus=\"pty\"}") >= 1.0);
    }
    // Without direction control the same pty serves.
    let slave = PtySlave::start(|request| Some(rtu::encode(request[0], &READ_ANSWER)));
    let gateway = start(&pty_config(&slave.path, &rs485_keys("off"))).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ).await, READ_ANSWER);
}

#[tokio::test]
async fn on_a_line_that_echoes_the_request_the_master_gets_the_slaves_answer() {
    // The far end hands back every request, as an adapter that echoes does, then answers with
    // the register's value by slave address, so a mixed-up answer shows.
    let slave = PtySlave::start(|request| {
        let answer = rtu::encode(request[0], &[0x03, 0x02, 0x12, request[0]]);
        Some([request, &answer[..]].concat())
    });
    let keys = "response_timeout = \"2s\"\n[bus.rs485]\necho = true";
    let gateway = start(&pty_config(&slave.path, keys)).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    for unit in [1, 7, 1] {
        assert_eq!(
            master.call(u16::from(unit), unit, &READ).await,
            [0x03, 0x02, 0x12, unit]
        );
    }
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_stray_bytes_total{bus=\"pty\"}"),
        0.0
    );
    assert_eq!(
        scrape.value("modbus_gateway_discarded_frames_total{bus=\"pty\"}"),
        0.0
    );
}

#[tokio::test]
async fn without_echo_set_an_echoing_line_gives_no_answer_and_with_a_wrong_echo_neither() {
    // The echo, taken for the slave's reply, is refused (it is the request); with echo = true an
    // echo that is not the request fails the try.
    let echoing = PtySlave::start(|request| {
        let answer = rtu::encode(request[0], &READ_ANSWER);
        Some([request, &answer[..]].concat())
    });
    let gateway = start(&pty_config(&echoing.path, "response_timeout = \"200ms\"")).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_ne!(master.call(1, 1, &READ).await, READ_ANSWER);

    let garbled = PtySlave::start(|request| {
        let mut echo = request.to_vec();
        echo[2] ^= 0x40;
        Some([echo, rtu::encode(request[0], &READ_ANSWER)].concat())
    });
    let keys = "response_timeout = \"200ms\"\n[bus.rs485]\necho = true";
    let gateway = start(&pty_config(&garbled.path, keys)).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ).await, [0x83, 0x0B]);
    let scrape = Scrape::of(&gateway).await;
    let frame_errors = scrape
        .series_of("modbus_gateway_requests_total")
        .into_iter()
        .filter(|(series, _)| series.contains("outcome=\"frame_error\""))
        .map(|(_, n)| n)
        .sum::<f64>();
    assert_eq!(frame_errors, 1.0, "{}", scrape.text);
}

#[tokio::test]
async fn the_daemon_logs_once_that_the_device_refuses_rs485_mode_naming_the_key() {
    let slave = PtySlave::start(|_| None);
    let dir = std::env::temp_dir().join(format!("mbgw-rs485-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("gateway.toml");
    let metrics = free_addr();
    let text = GatewayConfig::new()
        .listen(free_addr())
        .metrics_listen(metrics)
        .bus(
            pty_line(&slave.path)
                .key("reopen_delay", "10ms")
                .key("reopen_delay_max", "20ms")
                .text("[bus.rs485]\nmode = \"kernel\""),
        )
        .to_toml();
    std::fs::write(&config, text).unwrap();
    let log_path = dir.join("stderr");
    let child = Command::new(BINARY)
        .args(["--config", config.to_str().unwrap(), "run"])
        .env_remove("RUST_LOG")
        .env_remove("JOURNAL_STREAM")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log_path).unwrap())
        .spawn()
        .unwrap();
    within("the gateway reports running", async {
        while !std::fs::read_to_string(&log_path)
            .unwrap()
            .contains("modbus-gateway running")
        {
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    })
    .await;
    within("the open fails three times", async {
        loop {
            let (_, text) = http_get(metrics, "/metrics").await;
            let errors =
                Scrape::parse(text).get("modbus_gateway_port_open_errors_total{bus=\"pty\"}");
            if errors.is_some_and(|n| n >= 3.0) {
                break;
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    })
    .await;
    signal(&child, "TERM");
    assert!(exit_status(child).await.success());
    let log = std::fs::read_to_string(&log_path).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    let refusals: Vec<&str> = log
        .lines()
        .filter(|line| {
            line.contains("bus[0].rs485.mode = \\\"kernel\\\"")
                || line.contains("bus[0].rs485.mode = \"kernel\"")
        })
        .collect();
    assert_eq!(refusals.len(), 1, "{log}");
    assert!(refusals[0].contains(ENOTTY), "{log}");
    assert!(refusals[0].contains("answering 0x0A"), "{log}");
    assert!(refusals[0].contains("ERROR"), "logged as an error: {log}");
}

#[test]
fn check_config_prints_each_serial_buss_rs485_mode_and_latency_timer() {
    let dir = std::env::temp_dir().join(format!("mbgw-rs485-check-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("gateway.toml");
    let text = GatewayConfig::new()
        .default_listen()
        .bus(
            Bus::on("usb", "/dev/ttyUSB0")
                .key("latency_timer", "1ms")
                .rs485(&[("echo", true.into())]),
        )
        .bus(
            Bus::on("uart", "/dev/ttyS1")
                .rs485(&[("mode", "rts".into()), ("delay_after_send", "2ms".into())]),
        )
        .to_toml();
    std::fs::write(&config, text).unwrap();
    let out = Command::new(BINARY)
        .args(["--config", config.to_str().unwrap(), "check-config"])
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains(
            "# bus usb: rs485.mode off (the adapter switches the transceiver); each frame is \
             read back (echo); a USB adapter's latency timer is set to 1.000 ms.\n"
        ),
        "{text}"
    );
    assert!(
        text.contains(
            "# bus uart: rs485.mode rts (the gateway raises RTS for each frame, drops it 2.000 \
             ms after the last character); a USB adapter's latency timer is left as it is.\n"
        ),
        "{text}"
    );
}
