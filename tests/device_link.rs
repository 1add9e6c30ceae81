//! A bus behind a serial device server (`device = "tcp://..."`), against device servers written
//! here to misbehave as converters do: bytes left in the socket, a late reply, a converter that
//! vanishes and comes back, and (pymodbus's) Modbus TCP server where a converter in raw mode
//! should be. Each device server here is a plain TCP listener on loopback that answers the
//! gateway's RTU frames as a slave on the far line would.

use crate::support::{
    connect_when_listening, exit_status, free_addr, http_get, rtu, signal, within, Bus,
    GatewayConfig, RawMaster, Scrape,
};
use std::process::Stdio;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// Read holding registers `register`, one of them.
fn read(register: u16) -> [u8; 5] {
    let [hi, lo] = register.to_be_bytes();
    [0x03, hi, lo, 0x00, 0x01]
}

/// Slave 1's answer to [`read`] of `register`: the register's own number as its value.
fn answer(register: u16) -> Vec<u8> {
    let [hi, lo] = register.to_be_bytes();
    vec![0x03, 0x02, hi, lo]
}

/// The next whole 8-byte RTU request from the gateway, as (register asked, raw frame).
async fn next_request(socket: &mut TcpStream) -> Option<u16> {
    let mut frame = [0u8; 8];
    socket.read_exact(&mut frame).await.ok()?;
    assert_eq!(&frame[..2], [0x01, 0x03], "a read of slave 1: {frame:02X?}");
    Some(u16::from_be_bytes([frame[2], frame[3]]))
}

/// A gateway whose bus `remote` is the device server at `port`, with `keys` on the bus.
async fn gateway_on(port: u16, keys: &str) -> modbus_gateway::Gateway {
    GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(
            Bus::on("remote", &format!("tcp://127.0.0.1:{port}"))
                .baud(115_200)
                .parity("none")
                .response_timeout("200ms")
                .text(keys),
        )
        .start()
        .await
}

#[tokio::test]
async fn the_gateway_connects_to_the_device_server_at_start_before_any_request() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = gateway_on(port, "").await;
    // No master has asked anything: the connection is there already, and the link measured.
    let (_socket, _) = within("the gateway connects", server.accept())
        .await
        .unwrap();
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value("modbus_gateway_port_up{bus=\"remote\"}"), 1.0);
    assert!(scrape
        .get("modbus_gateway_link_budget_seconds{bus=\"remote\"}")
        .is_some_and(|budget| (0.001..=1.0).contains(&budget)));
    assert_eq!(
        scrape.value(
            "modbus_gateway_bus_info{bus=\"remote\",format=\"115200 baud 8N2\",\
             framing=\"rtu\",mode=\"master\",transport=\"tcp\"}"
        ),
        1.0
    );
    // The link's series pass Prometheus's own lint.
    crate::metrics::assert_promtool_finds_nothing_to_lint(&scrape.text).await;
}

/// Bytes left in the socket before a request.
#[tokio::test]
async fn stale_bytes_before_a_request_are_discarded_counted_and_never_an_answer() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = gateway_on(port, "").await;
    let (mut socket, _) = server.accept().await.unwrap();
    // What a converter buffered before the gateway came: the tail of a reply, and a whole frame
    // that looks like slave 1's answer to a read of register 7.
    let mut stale = vec![0x5A, 0xA5, 0x00];
    stale.extend(rtu(1, &answer(7)));
    socket.write_all(&stale).await.unwrap();
    socket.flush().await.unwrap();
    let device = tokio::spawn(async move {
        while let Some(register) = next_request(&mut socket).await {
            socket.write_all(&rtu(1, &answer(register))).await.unwrap();
        }
    });
    let stray = "modbus_gateway_stray_bytes_total{bus=\"remote\"}";
    let counted = stale.len() as f64;
    within("the stale bytes are read and counted", async {
        while Scrape::of(&gateway).await.value(stray) < counted {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    let mut master = RawMaster::connect(crate::support::addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &read(3)).await, answer(3));
    assert_eq!(Scrape::of(&gateway).await.value(stray), counted);
    drop(gateway);
    device.abort();
}

#[tokio::test]
async fn a_late_reply_from_across_the_link_never_answers_the_next_request() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = gateway_on(port, "").await;
    let (mut socket, _) = server.accept().await.unwrap();
    let device = tokio::spawn(async move {
        // The first read is answered 300 ms late (its timeout is 200 ms); the rest at once.
        let first = next_request(&mut socket).await.unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        socket.write_all(&rtu(1, &answer(first))).await.unwrap();
        while let Some(register) = next_request(&mut socket).await {
            socket.write_all(&rtu(1, &answer(register))).await.unwrap();
        }
    });
    let addr = crate::support::addr(&gateway);
    let mut first = RawMaster::connect(addr).await;
    let mut second = RawMaster::connect(addr).await;
    first.send(1, 1, &read(100)).await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    second.send(2, 1, &read(200)).await;
    // 0x0B to the first; the second gets register 200's answer, never the late one for 100.
    assert_eq!(first.recv().await.pdu, [0x83, 0x0B]);
    assert_eq!(second.recv().await.pdu, answer(200));
    device.abort();
}

#[tokio::test]
async fn a_device_server_that_goes_away_gets_0x0a_at_once_and_is_reconnected_when_back() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = gateway_on(
        port,
        "reopen_delay = \"50ms\"\nreopen_delay_max = \"200ms\"\n",
    )
    .await;
    let (socket, _) = server.accept().await.unwrap();
    // The converter restarts: its connection and its listening socket are gone.
    drop(socket);
    drop(server);
    crate::support::wait_for_bus(&gateway, "remote", false).await;
    let mut master = RawMaster::connect(crate::support::addr(&gateway)).await;
    // 0x0A, not a timeout's 0x0B: answered without waiting for the line.
    assert_eq!(master.call(1, 1, &read(5)).await, [0x83, 0x0A]);
    // Back on the same port: the gateway finds it with its back-off and serves again.
    let server = TcpListener::bind(("127.0.0.1", port)).await.unwrap();
    let (mut socket, _) = within("the gateway reconnects", server.accept())
        .await
        .unwrap();
    let device = tokio::spawn(async move {
        while let Some(register) = next_request(&mut socket).await {
            socket.write_all(&rtu(1, &answer(register))).await.unwrap();
        }
    });
    crate::support::wait_for_bus(&gateway, "remote", true).await;
    assert_eq!(master.call(2, 1, &read(5)).await, answer(5));
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_port_reopens_total{bus=\"remote\"}"),
        1.0
    );
    device.abort();
}

/// pymodbus's Modbus TCP server on a free port, or `None` (and why) without pymodbus. It exits
/// when the child's stdin closes, with the `Child` dropped.
pub(crate) async fn pymodbus_tcp_server() -> Option<(std::process::Child, u16)> {
    pymodbus_tcp_server_with(&[]).await
}

/// [`pymodbus_tcp_server`] with the script's `args` (`tls CERT KEY CA`: its TLS server).
pub(crate) async fn pymodbus_tcp_server_with(args: &[&str]) -> Option<(std::process::Child, u16)> {
    let python = crate::peers::python_with_pymodbus()?;
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/peers/pymodbus_tcp_server.py"
    );
    let mut child = std::process::Command::new(python)
        .arg(script)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("python runs");
    let stdout = child.stdout.take().unwrap();
    let line = within(
        "pymodbus listens",
        tokio::task::spawn_blocking(move || {
            let mut line = String::new();
            std::io::BufRead::read_line(&mut std::io::BufReader::new(stdout), &mut line)
                .map(|_| line)
        }),
    )
    .await
    .unwrap()
    .unwrap();
    let port = line
        .trim()
        .strip_prefix("listening ")
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("unexpected: {line:?}"));
    Some((child, port))
}

/// A Modbus TCP server where the converter should be; the one error names the fix.
#[tokio::test]
async fn a_modbus_tcp_server_in_the_converters_place_gets_one_error_and_0x0b() {
    let Some((_server, port)) = pymodbus_tcp_server().await else {
        return;
    };
    let (listen, metrics) = (free_addr(), free_addr());
    let device = format!("tcp://127.0.0.1:{port}");
    let config = GatewayConfig::new()
        .listen(listen)
        .metrics_listen(metrics)
        .bus(
            Bus::on("remote", &device)
                .baud(115_200)
                .parity("none")
                .response_timeout("200ms")
                .retries(2),
        )
        .to_toml();
    let dir = std::env::temp_dir();
    let path = dir.join(format!("mbgw-wrong-mode-{}.toml", std::process::id()));
    let log = dir.join(format!("mbgw-wrong-mode-{}.log", std::process::id()));
    std::fs::write(&path, config).unwrap();
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_modbus-gateway"))
        .args(["--config", path.to_str().unwrap(), "run"])
        .env_remove("RUST_LOG")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut master = connect_when_listening(listen).await;
    // Read 2 holding registers from 0000H: its RTU frame reads as an MBAP request to pymodbus,
    // which answers it in Modbus TCP. Each master gets 0x0B, after one try (no retry).
    for transaction in 1..=3 {
        let pdu = master
            .call(transaction, 1, &[0x03, 0x00, 0x00, 0x00, 0x02])
            .await;
        assert_eq!(pdu, [0x83, 0x0B]);
    }
    let (_, scrape) = http_get(metrics, "/metrics").await;
    let scrape = Scrape::parse(scrape);
    let retries = "modbus_gateway_retries_total{bus=\"remote\",slave=\"1\"}";
    assert_eq!(scrape.get(retries).unwrap_or(0.0), 0.0);
    signal(&child, "TERM");
    assert!(exit_status(child).await.success());
    let text = std::fs::read_to_string(&log).unwrap();
    let errors: Vec<&str> = text
        .lines()
        .filter(|line| line.contains("answers in Modbus TCP (MBAP)"))
        .collect();
    assert_eq!(errors.len(), 1, "once per connection: {text}");
    assert!(errors[0].contains("ERROR"), "{}", errors[0]);
    assert!(
        errors[0].contains("raw (transparent) TCP mode"),
        "{}",
        errors[0]
    );
    assert!(errors[0].contains(&device), "{}", errors[0]);
    let _ = std::fs::remove_file(path);
    let _ = std::fs::remove_file(log);
}

/// Answer slave 1's reads on every connection `server` accepts; counts the connections.
fn serve_reads(server: TcpListener) -> std::sync::Arc<std::sync::atomic::AtomicUsize> {
    let accepted = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let count = accepted.clone();
    tokio::spawn(async move {
        while let Ok((mut socket, _)) = server.accept().await {
            count.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            tokio::spawn(async move {
                while let Some(register) = next_request(&mut socket).await {
                    socket.write_all(&rtu(1, &answer(register))).await.unwrap();
                }
            });
        }
    });
    accepted
}

#[tokio::test]
async fn a_reload_reconnects_only_for_another_device_server_and_other_keys_apply_in_place() {
    let first = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let second = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let ports = [
        first.local_addr().unwrap().port(),
        second.local_addr().unwrap().port(),
    ];
    let (to_first, to_second) = (serve_reads(first), serve_reads(second));
    let config = |port: u16, packing: &str| {
        let mut config = GatewayConfig::new()
            .listen("127.0.0.1:0")
            .bus(
                Bus::on("remote", &format!("tcp://127.0.0.1:{port}"))
                    .baud(115_200)
                    .parity("none")
                    .key("packing_delay", packing),
            )
            .load();
        config.metrics.listen = ([127, 0, 0, 1], 0).into();
        config
    };
    let gateway = modbus_gateway::Gateway::start(&config(ports[0], "0ms"))
        .await
        .unwrap();
    let mut master = RawMaster::connect(crate::support::addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &read(1)).await, answer(1));
    let done = gateway.reload(&config(ports[0], "40ms")).unwrap();
    assert_eq!(done.applied, ["bus remote: reconfigured"]);
    assert_eq!(master.call(2, 1, &read(2)).await, answer(2));
    let done = gateway.reload(&config(ports[1], "40ms")).unwrap();
    assert_eq!(done.applied, ["bus remote: reopened"]);
    let connections =
        |count: &std::sync::atomic::AtomicUsize| count.load(std::sync::atomic::Ordering::SeqCst);
    // Requests meanwhile get 0x0A, as while any port reopens; then the new server answers.
    within("the bus connects to the new device server", async {
        while connections(&to_second) == 0 || gateway.bus_up("remote") != Some(true) {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    assert_eq!(master.call(3, 1, &read(3)).await, answer(3));
    assert_eq!((connections(&to_first), connections(&to_second)), (1, 1));
}

/// By host name or IPv6 address.
#[tokio::test]
async fn a_device_server_is_reached_by_host_name_or_ipv6_and_its_echo_taken_off() {
    // A converter whose transceiver hands back every frame sent, before the slave's reply.
    let echoing = |server: TcpListener| {
        tokio::spawn(async move {
            let (mut socket, _) = server.accept().await.unwrap();
            while let Some(register) = next_request(&mut socket).await {
                let [hi, lo] = register.to_be_bytes();
                let mut bytes = rtu(1, &[0x03, hi, lo, 0x00, 0x01]);
                bytes.extend(rtu(1, &answer(register)));
                socket.write_all(&bytes).await.unwrap();
            }
        })
    };
    let v6 = TcpListener::bind("[::1]:0").await.unwrap();
    let v4 = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let devices = [
        format!("tcp://[::1]:{}", v6.local_addr().unwrap().port()),
        format!("tcp://localhost:{}", v4.local_addr().unwrap().port()),
    ];
    let servers = [echoing(v6), echoing(v4)];
    let mut config = GatewayConfig::new().listen("127.0.0.1:0");
    for (i, device) in devices.iter().enumerate() {
        let bus = Bus::on(&format!("remote{i}"), device)
            .baud(115_200)
            .parity("none")
            .text("[bus.rs485]\necho = true\n");
        config = config
            .bus(bus)
            .route(&format!("{}", i + 1), &format!("remote{i}"), 1);
    }
    let gateway = config.start().await;
    let mut master = RawMaster::connect(crate::support::addr(&gateway)).await;
    for unit in [1, 2] {
        assert_eq!(master.call(unit.into(), unit, &read(9)).await, answer(9));
    }
    for server in servers {
        server.abort();
    }
}

/// A reply to a request cut off by a lost connection never answers a request after the reconnect.
#[tokio::test]
async fn a_reply_cut_off_by_a_lost_connection_never_answers_after_the_reconnect() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(
            Bus::on("remote", &format!("tcp://127.0.0.1:{port}"))
                .baud(115_200)
                .parity("none")
                .response_timeout("500ms")
                .key("reopen_delay", "50ms"),
        )
        .start()
        .await;
    let device = tokio::spawn(async move {
        // The first connection drops as soon as the request on it is in: the slave has it.
        let (mut first, _) = server.accept().await.unwrap();
        let cut_off = next_request(&mut first).await.unwrap();
        let heard = tokio::time::Instant::now();
        drop(first);
        // On the next one, the slave's answer to it comes 300 ms after it heard it (within
        // its 500 ms timeout, after the reconnect and its settling), then every answer in turn.
        let (mut second, _) = server.accept().await.unwrap();
        tokio::time::sleep_until(heard + Duration::from_millis(300)).await;
        second.write_all(&rtu(1, &answer(cut_off))).await.unwrap();
        while let Some(register) = next_request(&mut second).await {
            second.write_all(&rtu(1, &answer(register))).await.unwrap();
        }
    });
    let addr = crate::support::addr(&gateway);
    let mut first = RawMaster::connect(addr).await;
    let mut second = RawMaster::connect(addr).await;
    assert_eq!(first.call(1, 1, &read(100)).await, [0x83, 0x0A]);
    let reopened = "modbus_gateway_port_reopens_total{bus=\"remote\"}";
    within("the gateway reconnects", async {
        while Scrape::of(&gateway).await.value(reopened) < 1.0 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    // The next read of that slave waits until its late answer can no longer come: register
    // 200's answer, never register 100's.
    assert_eq!(second.call(2, 1, &read(200)).await, answer(200));
    device.abort();
}
