//! The gateway as a service: a graceful stop that finishes the transaction on the wire and
//! answers what is queued, in-process and as the binary receiving SIGTERM; the binary talking to
//! systemd over a notify socket (READY=1, STATUS=, watchdog pings, STOPPING=1, and no pings
//! while a bus task is stuck); a reload on SIGHUP applied to open connections, and refused for a
//! broken file; `check-config --quiet`.

use crate::support::{
    addr, connect_when_listening, exit_status, free_addr, http_get, signal, until_logged, within,
    Bus, GatewayConfig, RawMaster, Scrape, Value,
};
use std::process::{Command, Stdio};
use std::time::Duration;

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// Write 5000 to holding register 0004H (the drives' manuals' worked example); echoed back.
const WRITE: [u8; 5] = [0x06, 0x00, 0x04, 0x13, 0x88];

/// One 115200 baud simulated line whose slave 1 takes `delay` to answer.
fn slow_line(delay: &str, shutdown_timeout: &str) -> GatewayConfig {
    GatewayConfig::new()
        .server("shutdown_timeout", shutdown_timeout)
        .metrics_listen("127.0.0.1:0")
        .bus(
            Bus::sim("sim")
                .baud(115_200)
                .response_timeout("5s")
                .queue_timeout("30s")
                .sim_slave("1", &[("processing_delay", delay.into())]),
        )
}

/// Wait until the bus has taken `n` requests off its queue (the last one is on the wire).
async fn until_taken(metrics: std::net::SocketAddr, n: f64) {
    within("the bus takes the request", async {
        loop {
            let (_, text) = http_get(metrics, "/metrics").await;
            let scrape = Scrape::parse(text);
            if scrape.get("modbus_gateway_queue_wait_seconds_count{bus=\"sim\",class=\"normal\"}")
                == Some(n)
            {
                return;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
}

#[tokio::test]
async fn a_stop_serves_the_queue_until_the_timeout_then_answers_0x0a_and_closes() {
    // Each answer takes 1 s; the stop allows 1.5 s: the request on the wire and the next one
    // are served, the third would start after the deadline.
    let gateway = slow_line("1s", "1500ms").start().await;
    let metrics = gateway.metrics_addr();
    let modbus = addr(&gateway);
    let mut masters = Vec::new();
    for tid in 0..3u16 {
        let mut master = RawMaster::connect(modbus).await;
        master.send(tid, 1, &WRITE).await;
        masters.push(master);
        if tid == 0 {
            until_taken(metrics, 1.0).await;
        }
    }
    // All three are queued or on the wire when the stop comes.
    within("the other two are queued", async {
        loop {
            let scrape = Scrape::of(&gateway).await;
            if scrape.get("modbus_gateway_queue_depth{bus=\"sim\"}") == Some(2.0) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    let stopped = tokio::spawn(gateway.shutdown());
    let mut replies = Vec::new();
    for master in &mut masters {
        replies.push(master.recv().await.pdu);
    }
    assert_eq!(
        replies[0], WRITE,
        "the write on the wire is answered by the slave"
    );
    assert_eq!(
        replies[1], WRITE,
        "the next one started before the deadline"
    );
    assert_eq!(
        replies[2],
        [0x86, 0x0A],
        "the last one would have started after it"
    );
    for master in &mut masters {
        assert!(master.is_closed().await, "connections close once answered");
    }
    within("the gateway stops", stopped).await.unwrap();
    assert!(
        tokio::net::TcpStream::connect(modbus).await.is_err(),
        "no longer accepting"
    );
}

#[tokio::test]
async fn sigterm_while_a_write_is_on_the_wire_still_delivers_the_slaves_reply_and_exits_0() {
    let path = std::env::temp_dir().join(format!("mbgw-stop-{}.toml", std::process::id()));
    let (listen_addr, metrics_addr) = (free_addr(), free_addr());
    // A shutdown timeout far past `exit_status`'s patience: an exit that waited for it fails.
    let config = slow_line("1s", "10m")
        .listen(listen_addr)
        .metrics_listen(metrics_addr)
        .to_toml();
    std::fs::write(&path, config).unwrap();
    let child = Command::new(BINARY)
        .args(["--config", path.to_str().unwrap(), "run"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut master = connect_when_listening(listen_addr).await;
    master.send(1, 1, &WRITE).await;
    until_taken(metrics_addr, 1.0).await;
    signal(&child, "TERM");
    assert_eq!(master.recv().await.pdu, WRITE, "the slave's own reply");
    assert!(master.is_closed().await);
    let status = exit_status(child).await;
    let _ = std::fs::remove_file(&path);
    assert_eq!(status.code(), Some(0));
}

/// A notify socket like systemd's, bound at a fresh path.
struct NotifySocket {
    path: std::path::PathBuf,
    socket: tokio::net::UnixDatagram,
}

impl NotifySocket {
    fn bind(name: &str) -> Self {
        let path = std::env::temp_dir().join(format!("mbgw-notify-{}-{name}", std::process::id()));
        let _ = std::fs::remove_file(&path);
        let socket = tokio::net::UnixDatagram::bind(&path).expect("bind notify socket");
        NotifySocket { path, socket }
    }

    /// Start `command` as systemd would with this socket and a 200 ms watchdog (pings every
    /// 100 ms).
    fn run(&self, command: &mut Command) -> std::process::Child {
        command
            .env("RUST_LOG", "warn")
            .env("NOTIFY_SOCKET", &self.path)
            .env("WATCHDOG_USEC", "200000")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("the gateway starts")
    }

    /// The next message, its lines.
    async fn next(&self) -> Vec<String> {
        let mut buf = vec![0u8; 4096];
        let n = within("a notify message", self.socket.recv(&mut buf))
            .await
            .unwrap();
        String::from_utf8_lossy(&buf[..n])
            .lines()
            .map(str::to_owned)
            .collect()
    }
}

impl Drop for NotifySocket {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

#[tokio::test]
async fn under_systemd_it_reports_ready_pings_the_watchdog_and_says_when_it_stops() {
    let notify = NotifySocket::bind("ready");
    let child = notify.run(
        Command::new(BINARY)
            .args(["--config", crate::support::demo_path(), "run"])
            .env("MBGW__SERVER__LISTEN", free_addr().to_string())
            .env("MBGW__METRICS__LISTEN", free_addr().to_string()),
    );
    let first = notify.next().await;
    assert!(first.contains(&"READY=1".to_owned()), "{first:?}");
    let status = first
        .iter()
        .find(|l| l.starts_with("STATUS="))
        .expect("a status");
    assert_eq!(status, "STATUS=0 masters connected; serving demo");
    let mut pings = 0;
    while pings < 3 {
        let message = notify.next().await;
        assert!(
            message.iter().any(|l| l.starts_with("STATUS=")),
            "{message:?}"
        );
        pings += usize::from(message.contains(&"WATCHDOG=1".to_owned()));
    }
    signal(&child, "TERM");
    let stopping = within("STOPPING=1", async {
        loop {
            let message = notify.next().await;
            if message.contains(&"STOPPING=1".to_owned()) {
                return message;
            }
        }
    })
    .await;
    assert!(
        stopping.contains(&"STATUS=stopping".to_owned()),
        "{stopping:?}"
    );
    let exit = exit_status(child).await;
    assert_eq!(exit.code(), Some(0));
}

/// Write 123 registers (the most one request may) from 0000H: a 255-byte frame.
fn long_write() -> Vec<u8> {
    let mut pdu = vec![0x10, 0x00, 0x00, 0x00, 123, 246];
    pdu.resize(pdu.len() + 246, 0xA5);
    pdu
}

#[tokio::test]
async fn a_bus_task_stuck_on_its_port_stops_the_watchdog_pings_until_it_moves_again() {
    use tokio::io::AsyncReadExt;
    use tokio_serial::SerialPort;
    // The far end of a pty that nobody reads: once its buffer is full, the gateway's write to
    // the port never completes, as with a serial driver stuck on flow control.
    let (mut far_end, tty) = tokio_serial::SerialStream::pair().expect("pty pair");
    let device = tty.name().expect("pty path");
    let (listen, metrics) = (free_addr(), free_addr());
    let path = std::env::temp_dir().join(format!("mbgw-stuck-{}.toml", std::process::id()));
    let pty = Bus::on("pty", &device)
        .baud(921_600)
        .parity("none")
        .response_timeout("1ms")
        .queue_timeout("60s")
        .key("slave_down_after", 0);
    std::fs::write(
        &path,
        GatewayConfig::new()
            .listen(listen)
            .metrics_listen(metrics)
            .bus(pty)
            .to_toml(),
    )
    .unwrap();
    let notify = NotifySocket::bind("stuck");
    let child = notify.run(Command::new(BINARY).args(["--config", path.to_str().unwrap(), "run"]));
    let is_ping = |message: &[String]| message.iter().any(|l| l == "WATCHDOG=1");
    assert!(notify.next().await.contains(&"READY=1".to_owned()));
    within("a first ping", async {
        while !is_ping(&notify.next().await) {}
    })
    .await;

    // 100 long writes fill the pty's 20 KB buffer and more; nobody answers them.
    let mut master = RawMaster::connect(listen).await;
    for tid in 0..100 {
        master.send(tid, 1, &long_write()).await;
    }
    // STATUS= keeps coming every 100 ms; the pings stop.
    within("the pings stop", async {
        let mut without = 0;
        while without < 5 {
            without = if is_ping(&notify.next().await) {
                0
            } else {
                without + 1
            };
        }
    })
    .await;

    // Drain the pty: the write completes, the bus moves, the pings come back.
    let drain = tokio::spawn(async move {
        let mut buf = vec![0u8; 4096];
        while far_end.read(&mut buf).await.is_ok_and(|n| n > 0) {}
    });
    within("the pings resume", async {
        while !is_ping(&notify.next().await) {}
    })
    .await;

    signal(&child, "KILL");
    let _ = exit_status(child).await;
    drain.abort();
    drop(tty);
    let _ = std::fs::remove_file(&path);
}

#[test]
fn check_config_quiet_prints_nothing_for_a_valid_file_and_the_errors_for_a_bad_one() {
    let out = Command::new(BINARY)
        .args([
            "--config",
            crate::support::demo_path(),
            "check-config",
            "--quiet",
        ])
        .output()
        .unwrap();
    assert!(out.status.success());
    assert!(out.stdout.is_empty() && out.stderr.is_empty());
    let out = Command::new(BINARY)
        .args([
            "--config",
            "/nonexistent/gateway.toml",
            "check-config",
            "--quiet",
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/gateway.toml"));
}

/// Write `text` to `path` the way an editor saving over the file does.
fn save(path: &std::path::Path, text: &str) {
    std::fs::write(path, text).unwrap();
}

/// Wait until the gateway's log (in `path`) says `what`.
const READ: [u8; 5] = [0x03, 0x00, 0x04, 0x00, 0x01];

/// On an open connection; a broken file keeps the timeout and route as they were.
#[tokio::test]
async fn sighup_applies_a_new_timeout_and_route_live_and_keeps_them_on_a_broken_file() {
    let (listen, metrics) = (free_addr(), free_addr());
    // Slave 1 takes 200 ms to answer; its 100 ms timeout is too short. Unit 100 goes to slave
    // 100, which does not exist.
    let config = |baud: Value, slave_timeout: &str| {
        GatewayConfig::new()
            .listen(listen)
            .metrics_listen(metrics)
            .bus(
                Bus::sim("sim")
                    .key("baud", baud)
                    .response_timeout("100ms")
                    .slave(1, &[("response_timeout", slave_timeout.into())])
                    .sim_slave("1", &[("processing_delay", "200ms".into())]),
            )
    };
    let before = config(115_200.into(), "100ms").to_toml();
    // Slave 1 gets 1 s; unit 100 is routed to slave 1.
    let after = config(115_200.into(), "1s")
        .route("100", "sim", 1)
        .to_toml();
    // The same with a baud rate that is not a number.
    let broken = config("fast".into(), "1s").route("100", "sim", 1).to_toml();
    assert_ne!(before, after);
    let path = std::env::temp_dir().join(format!("mbgw-reload-{}.toml", std::process::id()));
    let log = std::env::temp_dir().join(format!("mbgw-reload-{}.log", std::process::id()));
    save(&path, &before);
    let child = Command::new(BINARY)
        .args(["--config", path.to_str().unwrap(), "run"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut master = connect_when_listening(listen).await;
    let answer = [0x03, 0x02, 0x00, 0x00];
    assert_eq!(
        master.call(1, 1, &READ).await,
        [0x83, 0x0B],
        "100 ms is too short"
    );
    assert_eq!(
        master.call(2, 100, &READ).await,
        [0x83, 0x0B],
        "no slave 100"
    );

    // Let slave 1's late replies to those pass before anything else is asked.
    tokio::time::sleep(Duration::from_millis(300)).await;

    save(&path, &after);
    signal(&child, "HUP");
    until_logged(&log, "configuration reloaded").await;
    assert_eq!(master.call(3, 1, &READ).await, answer, "1 s is long enough");
    assert_eq!(
        master.call(4, 100, &READ).await,
        answer,
        "routed to slave 1"
    );

    // A broken file: the running configuration stays, and so does the connection.
    save(&path, &broken);
    signal(&child, "HUP");
    until_logged(&log, "configuration not reloaded").await;
    assert_eq!(master.call(5, 1, &READ).await, answer);
    assert_eq!(master.call(6, 100, &READ).await, answer);

    signal(&child, "TERM");
    let status = exit_status(child).await;
    assert_eq!(status.code(), Some(0));
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("bus[0].baud"), "the bad key is named: {text}");
    let _ = std::fs::remove_file(&path);
    let _ = std::fs::remove_file(&log);
}

#[tokio::test]
async fn a_reload_reopens_only_a_changed_line_starts_added_buses_and_retires_removed_ones() {
    let a = Bus::sim("a").baud(9600).sim_slaves("1");
    let two_buses = GatewayConfig::new()
        .bus(a.clone())
        .bus(Bus::sim("b").baud(9600).sim_slaves("1"))
        .route("1", "a", 1)
        .route("2", "b", 1);
    let gateway = two_buses.start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let answer = [0x03, 0x02, 0x00, 0x00];
    assert_eq!(master.call(1, 1, &READ).await, answer);
    assert_eq!(master.call(2, 2, &READ).await, answer);
    let (line_a, line_b) = (
        gateway.sim_line("a").unwrap(),
        gateway.sim_line("b").unwrap(),
    );

    // a: a new timeout (same line); b: a new baud rate (a new line); c: added, for unit 3.
    let config = |config: GatewayConfig| {
        let mut config = config.load();
        config.metrics.listen = ([127, 0, 0, 1], 0).into();
        config
    };
    let (a, c) = (a.response_timeout("2s"), Bus::sim("c").sim_slaves("1"));
    let changed = GatewayConfig::new()
        .bus(a.clone())
        .bus(Bus::sim("b").baud(19_200).sim_slaves("1"))
        .bus(c.clone())
        .route("1", "a", 1)
        .route("2", "b", 1)
        .route("3", "c", 1);
    let done = gateway.reload(&config(changed)).unwrap();
    assert_eq!(
        done.applied,
        [
            "bus a: reconfigured",
            "bus b: reopened",
            "bus c: added",
            "routes"
        ]
    );
    assert!(done.need_restart.is_empty());
    assert!(
        gateway.sim_line("a").unwrap().same_line(&line_a),
        "a kept its line"
    );
    assert!(
        !gateway.sim_line("b").unwrap().same_line(&line_b),
        "b has a new one"
    );
    for unit in 1..=3 {
        assert_eq!(
            master.call(u16::from(unit), unit, &READ).await,
            answer,
            "unit {unit}"
        );
    }

    // b removed: unit 2 has no route; its series go once it has stopped.
    let without_b = GatewayConfig::new()
        .bus(a)
        .bus(c)
        .route("1", "a", 1)
        .route("3", "c", 1);
    let done = gateway.reload(&config(without_b)).unwrap();
    assert_eq!(done.applied, ["bus b: removed", "routes"]);
    assert_eq!(master.call(4, 2, &READ).await, [0x83, 0x0A]);
    assert_eq!(master.call(5, 3, &READ).await, answer, "same connection");
    within("b's series are gone", async {
        while Scrape::of(&gateway)
            .await
            .get("modbus_gateway_port_up{bus=\"b\"}")
            .is_some()
        {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
}

#[tokio::test]
async fn a_reload_changes_the_log_level_of_the_running_gateway() {
    let listen = free_addr();
    let config = |level: &str| {
        GatewayConfig::new()
            .listen(listen)
            .metrics_listen(free_addr())
            .table("log", &[("level", level.into())])
            .bus(Bus::sim("sim").sim_slaves("1"))
            .to_toml()
    };
    let path = std::env::temp_dir().join(format!("mbgw-level-{}.toml", std::process::id()));
    let log = std::env::temp_dir().join(format!("mbgw-level-{}.log", std::process::id()));
    save(&path, &config("warn"));
    let child = Command::new(BINARY)
        .args(["--config", path.to_str().unwrap(), "run"])
        .env_remove("RUST_LOG")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    drop(connect_when_listening(listen).await);
    let quiet = std::fs::read_to_string(&log).unwrap();
    assert!(!quiet.contains("INFO"), "at warn, no info lines: {quiet}");
    // The metrics address changes too: that one takes a restart, and the log says so.
    save(&path, &config("info"));
    signal(&child, "HUP");
    until_logged(&log, "configuration reloaded").await;
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("log.level"), "{text}");
    assert!(text.contains("metrics.listen"), "{text}");
    signal(&child, "TERM");
    assert_eq!(exit_status(child).await.code(), Some(0));
    let _ = std::fs::remove_file(&path);
    let _ = std::fs::remove_file(&log);
}
