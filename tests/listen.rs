//! Listen-only lines (`mode = "listen"`) on a shared line of ptys (test-support's `tap`):
//! pymodbus's serial client (`tests/peers/pymodbus_line_master.py`) masters the line and polls
//! pymodbus's serial server (`tests/peers/pymodbus_slave.py`, device 10); the relay copies every
//! byte both ways to the gateway's pty and keeps every byte the gateway writes, of which there
//! must be none, whatever happens. The gateway runs as the real binary, so that it can be
//! reloaded and its memory read:
//! - the whole run: plant values follow the slave's registers as the other master reads and
//!   writes them, the trace shows the frames, exceptions, timeouts and CRC errors are counted,
//!   Modbus TCP masters are answered from what was seen (0x0B for what was not, or is too old;
//!   0x01 for anything but a read), through a reload and a lost and reopened port;
//! - a hostile line: frames to and from slaves nobody asked, of the wrong length, replies to
//!   nobody, random bytes at full speed;
//! - `check-config` refusing the keys that would transmit.
//!
//! Python comes as for `peers` (`MBGW_PYTHON`, else a `python3` with pymodbus, else the test
//! checks nothing and says so, or fails under `MBGW_REQUIRE_TOOLS=1`).

use crate::peers::{python_with_pymodbus, Pymodbus};
use crate::support::tap::Tap;
use crate::support::{
    connect_when_listening, exit_status, free_addr, http_get, rtu, signal, until_logged, within,
    Bus, GatewayConfig, RawMaster, Scrape, TempDir,
};
use bytes::Bytes;
use http_body_util::{BodyExt, Empty};
use modbus_gateway::testing::line::rtu as codec;
use serde_json::Value;
use std::io::{BufRead, BufReader, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::net::TcpStream;
use tokio_modbus::client::{tcp, Reader, Writer};
use tokio_modbus::{ExceptionCode, Slave};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");
const MASTER_SCRIPT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/peers/pymodbus_line_master.py"
);
/// The listen line's name.
const BUS: &str = "line2";
/// pymodbus_slave.py's device id.
const SLAVE: u8 = 10;
/// A slave address nobody answers at on the line (the tap mutes pymodbus's answers to it).
const ABSENT: u8 = 20;
/// The whole run's `max_age`: short, so that the test sees the shadow age.
const MAX_AGE: Duration = Duration::from_secs(1);
/// The other master's round: holding registers 0-9, input registers 0-3, coils 0-7, discrete
/// inputs 0-7 of the slave (FC:UNIT:ADDRESS:COUNT, the script's READ).
const ROUND: &str = "poll 100 3:10:0:10 4:10:0:4 1:10:0:8 2:10:0:8";
/// How often a condition the test waits for is looked at again.
const POLL: Duration = Duration::from_millis(20);

// ---------------------------------------------------------------------------------------------
// The other master

/// The other master's script, running; killed when dropped.
struct LineMaster {
    child: Child,
    stdin: std::process::ChildStdin,
    state: Arc<Mutex<MasterState>>,
}

#[derive(Default)]
struct MasterState {
    ready: bool,
    polled: u64,
    results: Vec<String>,
}

impl LineMaster {
    async fn start(python: &std::ffi::OsStr, path: &str) -> LineMaster {
        let mut child = Command::new(python)
            .arg(MASTER_SCRIPT)
            .arg(path)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("python starts");
        let stdin = child.stdin.take().expect("piped stdin");
        let stdout = child.stdout.take().expect("piped stdout");
        let state = Arc::new(Mutex::new(MasterState::default()));
        let log = Arc::clone(&state);
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { return };
                let mut state = log.lock().unwrap();
                if line == "ready" {
                    state.ready = true;
                } else if let Some(n) = line.strip_prefix("polled ") {
                    state.polled = n.parse().expect("the script counts its rounds");
                } else if let Some(result) = line.strip_prefix("result ") {
                    state.results.push(result.to_owned());
                }
            }
        });
        let master = LineMaster {
            child,
            stdin,
            state,
        };
        within("the other master opens its port", async {
            while !master.state.lock().unwrap().ready {
                tokio::time::sleep(POLL).await;
            }
        })
        .await;
        master
    }

    fn command(&mut self, line: &str) {
        writeln!(self.stdin, "{line}").expect("the script reads its commands");
        self.stdin.flush().expect("the script reads its commands");
    }

    fn polled(&self) -> u64 {
        self.state.lock().unwrap().polled
    }

    /// Wait (bounded) until `n` more rounds are done.
    async fn rounds(&self, n: u64) {
        let target = self.polled() + n;
        within(&format!("{n} more rounds of the other master"), async {
            while self.polled() < target {
                tokio::time::sleep(POLL).await;
            }
        })
        .await;
    }

    /// Run one `once` or `write` command and return its outcome.
    async fn ask(&mut self, command: &str) -> String {
        let key = command.split_whitespace().collect::<Vec<_>>().join("_");
        let before = self.state.lock().unwrap().results.len();
        self.command(command);
        within(&format!("the other master's {command}"), async {
            loop {
                {
                    let state = self.state.lock().unwrap();
                    if let Some(result) = state.results[before..]
                        .iter()
                        .find_map(|r| r.strip_prefix(&format!("{key} ")))
                    {
                        return result.to_owned();
                    }
                }
                tokio::time::sleep(POLL).await;
            }
        })
        .await
    }
}

impl Drop for LineMaster {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The third parties of a shared line: the slave, the tap, the master (not polling yet). `None`
/// without Python.
async fn shared_line(dir: &TempDir) -> Option<(Pymodbus, Tap, LineMaster)> {
    let python = python_with_pymodbus()?;
    let slave = Pymodbus::start("rtu").await?;
    let tap = Tap::start(&slave.path, dir.path());
    tap.mute_replies_from(ABSENT);
    let master = LineMaster::start(&python, tap.master_path()).await;
    Some((slave, tap, master))
}

// ---------------------------------------------------------------------------------------------
// The gateway as a process

/// The gateway binary on a configuration file of its own; killed when dropped.
struct Daemon {
    child: Option<Child>,
    config: PathBuf,
    log: PathBuf,
    tcp: SocketAddr,
    metrics: SocketAddr,
}

impl Daemon {
    /// Run the binary on `[server]`, `[metrics]` and the `bus` TOML, once it listens.
    async fn start(dir: &TempDir, bus: &str) -> Daemon {
        let tcp = free_addr();
        let metrics = free_addr();
        let config = dir.join("gateway.toml");
        let log = dir.join("gateway.log");
        std::fs::write(&config, Self::toml(tcp, metrics, bus)).unwrap();
        let child = Command::new(BINARY)
            .args(["--config", config.to_str().unwrap(), "run"])
            .env("RUST_LOG", "info")
            .env_remove("JOURNAL_STREAM")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("the binary runs");
        let daemon = Daemon {
            child: Some(child),
            config,
            log,
            tcp,
            metrics,
        };
        connect_when_listening(tcp).await;
        daemon
    }

    fn toml(tcp: SocketAddr, metrics: SocketAddr, bus: &str) -> String {
        format!("[server]\nlisten = [\"{tcp}\"]\n[metrics]\nlisten = \"{metrics}\"\n{bus}")
    }

    fn child(&self) -> &Child {
        self.child.as_ref().expect("running")
    }

    /// A new `bus`, by SIGHUP, once the gateway says it reloaded.
    async fn reload(&self, bus: &str) {
        std::fs::write(&self.config, Self::toml(self.tcp, self.metrics, bus)).unwrap();
        signal(self.child(), "HUP");
        until_logged(&self.log, "configuration reloaded").await;
    }

    /// Resident memory now, from /proc.
    fn rss_kib(&self) -> u64 {
        let status =
            std::fs::read_to_string(format!("/proc/{}/status", self.child().id())).unwrap();
        status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .expect("VmRSS")
    }

    async fn scrape(&self) -> Scrape {
        let (status, text) = http_get(self.metrics, "/metrics").await;
        assert_eq!(status, 200, "{text}");
        Scrape::parse(text)
    }

    /// A scrape once `done` holds for it (bounded).
    async fn scrape_when(&self, what: &str, done: impl Fn(&Scrape) -> bool) -> Scrape {
        within(what, async {
            loop {
                let scrape = self.scrape().await;
                if done(&scrape) {
                    return scrape;
                }
                tokio::time::sleep(POLL).await;
            }
        })
        .await
    }

    /// The value named `name` on `GET /values`, if it has one.
    async fn value(&self, name: &str) -> Option<f64> {
        let (status, body) = http_get(self.metrics, "/values").await;
        assert_eq!(status, 200, "{body}");
        let listing: Value = serde_json::from_str(&body).expect("/values is JSON");
        listing["values"]
            .as_array()
            .expect("a list of values")
            .iter()
            .find(|v| v["name"] == name)
            .and_then(|v| v["value"].as_f64())
    }

    /// Wait (bounded) until `/values` gives `name` the number `expected`.
    async fn until_value(&self, name: &str, expected: f64) {
        within(&format!("{name} is {expected} on /values"), async {
            while self.value(name).await != Some(expected) {
                tokio::time::sleep(POLL).await;
            }
        })
        .await;
    }

    async fn stop(mut self) -> std::process::ExitStatus {
        let child = self.child.take().expect("running");
        signal(&child, "TERM");
        exit_status(child).await
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// The bus listening on `device`, its `max_age`, `response_timeout` 300 ms, and `slaves`
/// (`[[bus.slave]]` tables), as TOML.
fn listen_bus(device: &Path, max_age: Duration, slaves: &str) -> String {
    let keys = format!(
        "mode = \"listen\"\nmax_age = \"{}ms\"\nreopen_delay = \"100ms\"\n\
         reopen_delay_max = \"200ms\"\n{slaves}",
        max_age.as_millis()
    );
    let bus = Bus::on(BUS, &device.display().to_string())
        .baud(115_200)
        .parity("none")
        .response_timeout("300ms")
        .text(&keys);
    bus.to_toml()
}

/// The trace's frames, as `GET /trace` sends them, collected from the moment it is open.
struct TraceLog {
    frames: Arc<Mutex<Vec<Value>>>,
    task: tokio::task::JoinHandle<()>,
}

impl TraceLog {
    async fn open(metrics: SocketAddr) -> TraceLog {
        let stream = within("connect", TcpStream::connect(metrics))
            .await
            .unwrap();
        let (mut sender, connection) =
            hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream))
                .await
                .unwrap();
        tokio::spawn(connection);
        let request = hyper::Request::get("/trace")
            .header(hyper::header::HOST, metrics.to_string())
            .body(Empty::<Bytes>::new())
            .unwrap();
        let mut response = within("the trace answers", sender.send_request(request))
            .await
            .unwrap();
        assert_eq!(response.status(), 200);
        let frames = Arc::new(Mutex::new(Vec::new()));
        let log = Arc::clone(&frames);
        let (opened, open) = tokio::sync::oneshot::channel();
        let task = tokio::spawn(async move {
            let _sender = sender;
            let mut opened = Some(opened);
            let mut pending = String::new();
            while let Some(Ok(frame)) = response.body_mut().frame().await {
                let Ok(data) = frame.into_data() else {
                    continue;
                };
                pending.push_str(std::str::from_utf8(&data).expect("UTF-8 events"));
                while let Some(end) = pending.find("\n\n") {
                    let event: String = pending.drain(..end + 2).collect();
                    if event.starts_with(": ") {
                        // The stream's opening comment, then keepalives.
                        if let Some(opened) = opened.take() {
                            let _ = opened.send(());
                        }
                        continue;
                    }
                    if let Some(data) = event
                        .lines()
                        .find_map(|line| line.strip_prefix("data: "))
                        .filter(|_| event.starts_with("event: frame"))
                    {
                        let frame: Value = serde_json::from_str(data).expect("a frame as JSON");
                        log.lock().unwrap().push(frame);
                    }
                }
            }
        });
        within("the trace opens", open).await.expect("its comment");
        TraceLog { frames, task }
    }

    fn frames(&self) -> Vec<Value> {
        self.frames.lock().unwrap().clone()
    }

    /// The first frame `matches` finds, once there is one (bounded).
    async fn find(&self, what: &str, matches: impl Fn(&Value) -> bool) -> Value {
        within(&format!("the trace shows {what}"), async {
            loop {
                if let Some(frame) = self.frames().into_iter().find(&matches) {
                    return frame;
                }
                tokio::time::sleep(POLL).await;
            }
        })
        .await
    }
}

impl Drop for TraceLog {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A trace frame's direction, slave, function and outcome.
fn is(frame: &Value, direction: &str, slave: u8, function: u8, outcome: &str) -> bool {
    frame["bus"] == BUS
        && frame["direction"] == direction
        && frame["slave"] == slave
        && frame["function"] == function
        && frame["outcome"] == outcome
}

/// `01 03 00 00`: the trace's hex.
fn hex(bytes: &[u8]) -> String {
    let pairs: Vec<String> = bytes.iter().map(|b| format!("{b:02x}")).collect();
    pairs.join(" ")
}

/// A series of a listen line's metric, its labels after `bus` as the gateway sorts them.
fn series(name: &str, labels: &str) -> String {
    if labels.is_empty() {
        format!("{name}{{bus=\"{BUS}\"}}")
    } else {
        format!("{name}{{bus=\"{BUS}\",{labels}}}")
    }
}

/// The answer to a read of holding registers `from..from + count` of the slave, as
/// pymodbus_slave.py holds them (1000 + n), after its register 0 was written `first`.
fn holding(from: u16, count: u16, first: u16) -> Vec<u16> {
    (from..from + count)
        .map(|n| if n == 0 { first } else { 1000 + n })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// The rig alone

/// The rig checked without the gateway: its relay carries the master's polls to the slave and
/// back, copies both ways to G, keeps what G's user writes, corrupts on demand and survives a
/// lost G; so that the gateway's tests below can trust it, and it can fail.
#[tokio::test]
async fn the_tap_relays_both_ways_copies_to_the_gateway_port_and_logs_its_writes() {
    let dir = TempDir::new("listen-rig");
    let Some((_slave, mut tap, mut master)) = shared_line(&dir).await else {
        return;
    };
    // The gateway's side, played by the test: open the link as the gateway would.
    let open = |path: &Path| {
        use tokio_serial::SerialPortBuilderExt;
        tokio_serial::new(path.to_str().unwrap(), 115_200)
            .open_native_async()
            .expect("the link opens as a serial port")
    };
    let mut port = open(tap.gateway_path());
    assert_eq!(master.ask("once 3:10:0:2").await, "1000 1001");
    // Read 2 holding registers from 0 of slave 10, and its answer (byte count 4, 1000, 1001).
    let request = rtu(SLAVE, &[0x03, 0x00, 0x00, 0x00, 0x02]);
    let reply = rtu(SLAVE, &[0x03, 0x04, 0x03, 0xE8, 0x03, 0xE9]);
    let line = tap.line();
    assert_eq!(line.to_slave, request, "the master's request crossed");
    assert_eq!(line.to_master, reply, "the slave's reply crossed");
    let mut seen = Vec::new();
    let wanted: Vec<u8> = [request.clone(), reply.clone()].concat();
    read_until(&mut port, &mut seen, wanted.len()).await;
    assert_eq!(seen, wanted, "G got both directions, in order");

    // The corrupt knob: the master still gets a good reply; G gets its last byte changed.
    tap.corrupt_next_reply();
    assert_eq!(master.ask("once 3:10:0:2").await, "1000 1001");
    tap.until_corrupted(1).await;
    seen.clear();
    read_until(&mut port, &mut seen, wanted.len()).await;
    assert_eq!(seen[..request.len()], request[..]);
    assert!(!codec::crc_ok(&seen[request.len()..]), "{seen:02X?}");

    // Injected bytes go to G alone.
    tap.inject_written(&[0xAA, 0x55]).await;
    seen.clear();
    read_until(&mut port, &mut seen, 2).await;
    assert_eq!(seen, [0xAA, 0x55]);
    assert_eq!(
        tap.line().to_slave,
        [request.clone(), request.clone()].concat()
    );

    // What G's user writes is kept, as the gateway's would be.
    assert!(tap.written_by_gateway().is_empty());
    tokio::io::AsyncWriteExt::write_all(&mut port, &[0x01, 0x02, 0x03])
        .await
        .unwrap();
    within("the relay logs the write", async {
        while tap.written_by_gateway() != [0x01, 0x02, 0x03] {
            tokio::time::sleep(POLL).await;
        }
    })
    .await;

    // A lost G: the port reads its end; the line goes on; a new G behind the same link.
    tap.lose_gateway_port();
    let mut chunk = [0u8; 16];
    let lost = within(
        "the lost port's read ends",
        tokio::io::AsyncReadExt::read(&mut port, &mut chunk),
    )
    .await;
    assert!(matches!(lost, Ok(0) | Err(_)), "{lost:?}");
    assert_eq!(master.ask("once 3:10:0:2").await, "1000 1001");
    tap.reopen_gateway_port();
    drop(port);
    let mut port = open(tap.gateway_path());
    assert_eq!(master.ask("once 3:10:0:2").await, "1000 1001");
    seen.clear();
    read_until(&mut port, &mut seen, wanted.len()).await;
    assert_eq!(seen, wanted, "the new G gets the line");
}

async fn read_until(port: &mut tokio_serial::SerialStream, seen: &mut Vec<u8>, n: usize) {
    within(&format!("{n} bytes on G"), async {
        let mut chunk = [0u8; 256];
        while seen.len() < n {
            let got = tokio::io::AsyncReadExt::read(port, &mut chunk)
                .await
                .unwrap();
            seen.extend_from_slice(&chunk[..got]);
        }
    })
    .await;
}

// ---------------------------------------------------------------------------------------------
// The whole run

/// The slave's values on the listen line: register 0 (changed by the other master's writes).
const VALUES: &str = "[[bus.slave]]\naddress = 10\n\
                      [[bus.slave.value]]\nname = \"line_register_0\"\nregister = 0\ntype = \"u16\"\n";
/// The same after the reload: one more, input register 0.
const VALUES_RELOADED: &str = "[[bus.slave]]\naddress = 10\n\
    [[bus.slave.value]]\nname = \"line_register_0\"\nregister = 0\ntype = \"u16\"\n\
    [[bus.slave.value]]\nname = \"line_input_0\"\ntable = \"input\"\nregister = 0\ntype = \"u16\"\n";

#[tokio::test]
async fn a_listen_line_follows_another_masters_line_and_never_writes_a_byte() {
    let dir = TempDir::new("listen-run");
    let Some((_slave, mut tap, mut master)) = shared_line(&dir).await else {
        return;
    };
    let gateway = Daemon::start(&dir, &listen_bus(tap.gateway_path(), MAX_AGE, VALUES)).await;
    let up = series("modbus_gateway_port_up", "");
    gateway
        .scrape_when("the listen line's port is open", |s| {
            s.get(&up) == Some(1.0)
        })
        .await;
    let trace = TraceLog::open(gateway.metrics).await;
    let scrape = gateway.scrape().await;
    let info: Vec<_> = scrape.series_of("modbus_gateway_bus_info");
    assert!(
        info.iter().any(|(s, v)| *v == 1.0
            && s.contains(&format!("bus=\"{BUS}\""))
            && s.contains("mode=\"listen\"")),
        "{info:?}"
    );

    // Nothing seen yet: every read is 0x0B, every write 0x01.
    let mut raw = RawMaster::connect(gateway.tcp).await;
    assert_eq!(
        raw.call(1, SLAVE, &[0x03, 0x00, 0x00, 0x00, 0x02]).await,
        [0x83, 0x0B],
        "nothing seen yet"
    );

    // The other master polls; the values follow, with no poll of the gateway's.
    master.command(ROUND);
    gateway.until_value("line_register_0", 1000.0).await;
    master.rounds(2).await;

    // A Modbus TCP master (tokio-modbus) reads what was seen, and subsets of it, table by table.
    let mut ctx = tcp::connect_slave(gateway.tcp, Slave(SLAVE)).await.unwrap();
    let words = ctx.read_holding_registers(0, 10).await.unwrap();
    assert_eq!(words, Ok(holding(0, 10, 1000)), "holding 0-9 as seen");
    let words = ctx.read_holding_registers(2, 3).await.unwrap();
    assert_eq!(words, Ok(holding(2, 3, 1000)), "a subset of a block seen");
    let words = ctx.read_input_registers(0, 4).await.unwrap();
    assert_eq!(words, Ok(vec![2000, 2001, 2002, 2003]), "input 0-3, apart");
    // Coils 0-7: on at 0, 3, 6 (0x49); discrete inputs 0-7: on where odd (0xAA).
    let pdu = raw.call(2, SLAVE, &[0x01, 0x00, 0x00, 0x00, 0x08]).await;
    assert_eq!(pdu, [0x01, 0x01, 0x49], "coils 0-7 as seen");
    let pdu = raw.call(3, SLAVE, &[0x02, 0x00, 0x00, 0x00, 0x08]).await;
    assert_eq!(pdu, [0x02, 0x01, 0xAA], "discrete inputs 0-7 as seen");
    // Coils 3-5: on, off, off.
    let pdu = raw.call(4, SLAVE, &[0x01, 0x00, 0x03, 0x00, 0x03]).await;
    assert_eq!(pdu, [0x01, 0x01, 0x01], "a subset of the coils seen");

    // Never seen, or only partly: 0x0B, each table apart.
    for (what, request, answer) in [
        (
            "input 4-5, never read",
            [0x04, 0x00, 0x04, 0x00, 0x02],
            [0x84, 0x0B],
        ),
        (
            "holding 8-11, half seen",
            [0x03, 0x00, 0x08, 0x00, 0x04],
            [0x83, 0x0B],
        ),
        (
            "holding 100, never read",
            [0x03, 0x00, 0x64, 0x00, 0x01],
            [0x83, 0x0B],
        ),
        (
            "discrete 8-15, never read",
            [0x02, 0x00, 0x08, 0x00, 0x08],
            [0x82, 0x0B],
        ),
    ] {
        assert_eq!(raw.call(5, SLAVE, &request).await, answer, "{what}");
    }
    assert_eq!(
        raw.call(6, 2, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x83, 0x0B],
        "a slave never heard"
    );

    // Anything that is not a read: 0x01, and nothing on the line.
    for (what, request) in [
        ("write single register", vec![0x06, 0x00, 0x00, 0x12, 0x34]),
        ("write single coil", vec![0x05, 0x00, 0x00, 0xFF, 0x00]),
        (
            "write multiple registers",
            vec![0x10, 0x00, 0x00, 0x00, 0x01, 0x02, 0x12, 0x34],
        ),
        (
            "write multiple coils",
            vec![0x0F, 0x00, 0x00, 0x00, 0x01, 0x01, 0x01],
        ),
        (
            "read/write multiple registers",
            vec![
                0x17, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x01, 0x02, 0x12, 0x34,
            ],
        ),
        ("diagnostics", vec![0x08, 0x00, 0x00, 0x12, 0x34]),
        ("a user-defined code", vec![0x41, 0x01]),
    ] {
        assert_eq!(
            raw.call(7, SLAVE, &request).await,
            [request[0] | 0x80, 0x01],
            "{what}"
        );
    }
    assert_eq!(
        ctx.write_single_register(0, 1).await.unwrap(),
        Err(ExceptionCode::IllegalFunction),
        "tokio-modbus's write"
    );
    assert_eq!(
        master.ask("once 3:10:0:1").await,
        "1000",
        "the slave is untouched"
    );

    // The other master writes register 0: the value follows when it next reads it.
    assert_eq!(master.ask("write 10:0:4321").await, "4321");
    gateway.until_value("line_register_0", 4321.0).await;
    let gauge = format!("line_register_0{{bus=\"{BUS}\",slave=\"{SLAVE}\"}}");
    gateway
        .scrape_when("the value's gauge follows", |s| {
            s.get(&gauge) == Some(4321.0)
        })
        .await;
    assert_eq!(
        ctx.read_holding_registers(0, 2).await.unwrap(),
        Ok(holding(0, 2, 4321))
    );

    // An exception on the line (holding 100 is no register of the slave's: 02), a request
    // nobody answers, and a reply the gateway hears with a bad CRC: each counted.
    assert_eq!(master.ask("once 3:10:100:2").await, "exception 2");
    assert_eq!(master.ask(&format!("once 3:{ABSENT}:0:1")).await, "none");
    tap.corrupt_next_reply();
    tap.until_corrupted(1).await;
    let exceptions = series(
        "modbus_gateway_observed_replies_total",
        &format!("function=\"0x03\",outcome=\"exception\",slave=\"{SLAVE}\""),
    );
    let timeouts = series("modbus_gateway_observed_timeouts_total", "slave=\"other\"");
    let crc = series("modbus_gateway_observed_crc_errors_total", "");
    let scrape = gateway
        .scrape_when("an exception, a timeout and a CRC error counted", |s| {
            s.get(&exceptions) >= Some(1.0)
                && s.get(&timeouts) >= Some(1.0)
                && s.get(&crc) >= Some(1.0)
        })
        .await;
    let requests = series(
        "modbus_gateway_observed_requests_total",
        &format!("function=\"0x03\",slave=\"{SLAVE}\""),
    );
    let ok = series(
        "modbus_gateway_observed_replies_total",
        &format!("function=\"0x03\",outcome=\"ok\",slave=\"{SLAVE}\""),
    );
    let writes = series(
        "modbus_gateway_observed_requests_total",
        &format!("function=\"0x06\",slave=\"{SLAVE}\""),
    );
    assert!(scrape.value(&requests) >= 3.0, "{}", scrape.text);
    assert!(scrape.value(&ok) >= 3.0, "{}", scrape.text);
    assert_eq!(scrape.value(&writes), 1.0, "the other master's one write");
    assert_eq!(scrape.value(&exceptions), 1.0);
    assert_eq!(scrape.value(&timeouts), 1.0);
    let answered = series(
        "modbus_gateway_observed_response_seconds_count",
        &format!("slave=\"{SLAVE}\""),
    );
    assert!(scrape.value(&answered) >= 3.0, "{}", scrape.text);
    let interval = scrape.value(&series(
        "modbus_gateway_observed_poll_interval_seconds",
        &format!("slave=\"{SLAVE}\""),
    ));
    // The master's round is every 100 ms: the same read comes again about then (give or take
    // how long the reads before it in a round took), where two reads of a round are a few ms
    // apart.
    assert!(
        interval > 0.03 && interval < 5.0,
        "poll interval {interval}"
    );

    // The trace shows the other master's requests and the slave's replies, with outcomes.
    let read_0_9 = rtu(SLAVE, &[0x03, 0x00, 0x00, 0x00, 0x0A]);
    let frame = trace
        .find("a request of holding 0-9", |f| {
            is(f, "request", SLAVE, 0x03, "ok") && f["hex"] == hex(&read_0_9)
        })
        .await;
    assert_eq!(frame["framing"], "rtu");
    trace
        .find("a reply to it", |f| {
            is(f, "reply", SLAVE, 0x03, "ok")
                && f["hex"]
                    .as_str()
                    .is_some_and(|h| h.starts_with("0a 03 14 10 e1 03 e9"))
        })
        .await;
    trace
        .find("the exception", |f| {
            is(f, "reply", SLAVE, 0x83, "exception")
        })
        .await;
    trace
        .find("the request nobody answered", |f| {
            is(f, "request", ABSENT, 0x03, "timeout")
        })
        .await;
    trace
        .find("the corrupted reply", |f| {
            f["bus"] == BUS && f["outcome"] == "crc_error"
        })
        .await;
    assert!(tap.written_by_gateway().is_empty(), "before the reload");

    // A reload adds a value: it follows the line at once.
    gateway
        .reload(&listen_bus(tap.gateway_path(), MAX_AGE, VALUES_RELOADED))
        .await;
    gateway.until_value("line_input_0", 2000.0).await;
    assert_eq!(
        raw.call(8, SLAVE, &[0x10, 0x00, 0x00, 0x00, 0x01, 0x02, 0x12, 0x34])
            .await,
        [0x90, 0x01],
        "a write after the reload"
    );
    assert_eq!(
        ctx.read_holding_registers(0, 1).await.unwrap(),
        Ok(vec![4321]),
        "the shadow after the reload"
    );
    assert!(tap.written_by_gateway().is_empty(), "after the reload");

    // The port is lost and comes back: the gateway listens again, still writing nothing.
    let reopens = series("modbus_gateway_port_reopens_total", "");
    let reopened_before = gateway.scrape().await.get(&reopens).unwrap_or(0.0);
    tap.lose_gateway_port();
    gateway
        .scrape_when("the lost port is down", |s| s.get(&up) == Some(0.0))
        .await;
    // A master's write while the port is down is refused as ever, and not kept for later.
    assert_eq!(
        raw.call(9, SLAVE, &[0x06, 0x00, 0x00, 0x12, 0x34]).await,
        [0x86, 0x01],
        "a write with the port down"
    );
    tap.reopen_gateway_port();
    gateway
        .scrape_when("the port is reopened", |s| {
            s.get(&up) == Some(1.0) && s.get(&reopens) > Some(reopened_before)
        })
        .await;
    assert_eq!(master.ask("write 10:0:777").await, "777");
    gateway.until_value("line_register_0", 777.0).await;
    assert_eq!(
        ctx.read_holding_registers(0, 1).await.unwrap(),
        Ok(vec![777]),
        "the shadow after the reopen"
    );

    // The other master stops: once the data is older than max_age, 0x0B.
    master.command("poll");
    let stopped = Instant::now();
    within("the shadow ages past max_age", async {
        while ctx.read_holding_registers(0, 1).await.unwrap()
            != Err(ExceptionCode::GatewayTargetDevice)
        {
            tokio::time::sleep(POLL).await;
        }
    })
    .await;
    // Its last reply came at most a round (and a timeout in it) before the stop.
    assert!(
        stopped.elapsed() + Duration::from_millis(700) >= MAX_AGE,
        "served stale: 0x0B after {:?}",
        stopped.elapsed()
    );
    // The coils, read a little later in the master's last round, a little later.
    within("the coils age past max_age too", async {
        while raw.call(10, SLAVE, &[0x01, 0x00, 0x00, 0x00, 0x08]).await != [0x81, 0x0B] {
            tokio::time::sleep(POLL).await;
        }
    })
    .await;

    // The whole run: not one byte from the gateway.
    drop(ctx);
    drop(raw);
    let status = gateway.stop().await;
    assert_eq!(status.code(), Some(0));
    assert_eq!(
        tap.written_by_gateway(),
        Vec::<u8>::new(),
        "the gateway wrote on the line"
    );
    assert!(tap.delivered_to_gateway() > 0);
}

// ---------------------------------------------------------------------------------------------
// A hostile line

/// The hostile test's slaves: 1 (a value on register 0), heard only from injected frames.
const HOSTILE_VALUES: &str = "[[bus.slave]]\naddress = 1\n\
    [[bus.slave.value]]\nname = \"hostile_register_0\"\nregister = 0\ntype = \"u16\"\n";
/// Longer than the test: what slave 1 said stays served.
const HOSTILE_MAX_AGE: Duration = Duration::from_secs(120);
/// Silence between injected frames: far above t3.5 (1.75 ms at 115200), below the 300 ms
/// response timeout.
const GAP: Duration = Duration::from_millis(20);
/// How long random bytes go to G at full speed.
const BURST: Duration = Duration::from_secs(3);

/// A small xorshift: the random bytes are the same in every run.
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    fn bytes(&mut self, n: usize) -> Vec<u8> {
        (0..n).map(|_| self.next() as u8).collect()
    }
}

#[tokio::test]
async fn a_hostile_line_never_makes_the_gateway_write_cross_slaves_or_grow() {
    let dir = TempDir::new("listen-hostile");
    let Some((_slave, tap, mut master)) = shared_line(&dir).await else {
        return;
    };
    let gateway = Daemon::start(
        &dir,
        &listen_bus(tap.gateway_path(), HOSTILE_MAX_AGE, HOSTILE_VALUES),
    )
    .await;
    let up = series("modbus_gateway_port_up", "");
    gateway
        .scrape_when("the listen line's port is open", |s| {
            s.get(&up) == Some(1.0)
        })
        .await;
    let mut raw = RawMaster::connect(gateway.tcp).await;
    // Read holding registers 0-1 of slave 1; its answer (byte count 4, 1234H, 5678H).
    let read_1 = rtu(1, &[0x03, 0x00, 0x00, 0x00, 0x02]);
    assert_eq!(hex(&read_1), "01 03 00 00 00 02 c4 0b", "the spec's CRC");
    let answer_1 = rtu(1, &[0x03, 0x04, 0x12, 0x34, 0x56, 0x78]);
    let served_1 = [0x03, 0x04, 0x12, 0x34, 0x56, 0x78];
    // The same read answered by slave 2 (byte count 4, DEADH, BEEFH).
    let answer_2 = rtu(2, &[0x03, 0x04, 0xDE, 0xAD, 0xBE, 0xEF]);
    let read_pdu = [0x03, 0x00, 0x00, 0x00, 0x02];

    // The line is quiet (the other master not polling): slave 1 heard once, in a good pair.
    tap.inject_written(&read_1).await;
    tokio::time::sleep(GAP).await; // scenario: the slave's turnaround
    tap.inject_written(&answer_1).await;
    within("slave 1's registers served", async {
        while raw.call(1, 1, &read_pdu).await != served_1 {
            tokio::time::sleep(POLL).await;
        }
    })
    .await;
    gateway.until_value("hostile_register_0", 4660.0).await;

    let timeouts_1 = series("modbus_gateway_observed_timeouts_total", "slave=\"1\"");
    let discarded = |s: &Scrape| -> f64 {
        s.series_of("modbus_gateway_observed_discarded_total")
            .iter()
            .filter(|(name, _)| name.contains(&format!("bus=\"{BUS}\"")))
            .map(|(_, v)| v)
            .sum()
    };
    let unpaired = series(
        "modbus_gateway_observed_discarded_total",
        "reason=\"unpaired\"",
    );

    // Slave 2 answers a request to slave 1: not slave 1's, not slave 2's.
    let before = gateway.scrape().await;
    tap.inject_written(&read_1).await;
    tokio::time::sleep(GAP).await; // scenario: the wrong slave's turnaround
    tap.inject_written(&answer_2).await;
    let after = gateway
        .scrape_when("the request to slave 1 unanswered", |s| {
            s.delta(&before, &timeouts_1) >= 1.0
        })
        .await;
    assert!(
        after.delta(&before, &unpaired) >= 1.0 || discarded(&after) > discarded(&before),
        "slave 2's reply to slave 1's request discarded:\n{}",
        after.text
    );
    assert_eq!(raw.call(2, 1, &read_pdu).await, served_1, "slave 1 kept");
    assert_eq!(
        raw.call(3, 2, &read_pdu).await,
        [0x83, 0x0B],
        "slave 2 never asked"
    );

    // A reply to nobody: slave 2's read reply, good CRC, no request before it.
    let before = gateway.scrape().await;
    tap.inject_written(&answer_2).await;
    gateway
        .scrape_when("the reply to nobody discarded as unpaired", |s| {
            s.delta(&before, &unpaired) >= 1.0
        })
        .await;
    assert_eq!(
        raw.call(4, 2, &read_pdu).await,
        [0x83, 0x0B],
        "slave 2 still unknown"
    );

    // Frames of the wrong length, each with a good CRC over its bytes: a request one byte
    // short and one byte long, replies to slave 1's read with one register instead of two, and
    // a byte count of 4 over two bytes; none of them is slave 1's answer.
    let before = gateway.scrape().await;
    let wrong: [Vec<u8>; 6] = [
        rtu(1, &[0x03, 0x00, 0x00, 0x00]),
        read_1.clone(),
        rtu(1, &[0x03, 0x02, 0xAB, 0xCD]),
        read_1.clone(),
        rtu(1, &[0x03, 0x04, 0xAB, 0xCD]),
        rtu(1, &[0x03, 0x00, 0x00, 0x00, 0x02, 0x00]),
    ];
    for frame in &wrong {
        tap.inject_written(frame).await;
        tokio::time::sleep(GAP).await; // scenario: silence between frames
    }
    gateway
        .scrape_when("the wrong lengths discarded", |s| {
            discarded(s) >= discarded(&before) + 2.0
        })
        .await;
    assert_eq!(raw.call(5, 1, &read_pdu).await, served_1, "slave 1 kept");
    assert_eq!(gateway.value("hostile_register_0").await, Some(4660.0));
    assert!(tap.written_by_gateway().is_empty(), "the gateway wrote");

    // Random bytes at full speed, the other master polling slave 10 beneath them, and the
    // shaped frames again among them: memory stays put.
    master.command("poll 20 3:10:0:10");
    let mut noise = Noise(0x9E37_79B9_7F4A_7C15);
    let burst = |noise: &mut Noise| {
        let len = 1 + (noise.next() % 256) as usize;
        noise.bytes(len)
    };
    let warm_up = Instant::now();
    while warm_up.elapsed() < BURST / 4 {
        tap.inject(&burst(&mut noise)).await;
    }
    let rss_before = gateway.rss_kib();
    let delivered_before = tap.delivered_to_gateway();
    let started = Instant::now();
    let mut n = 0u64;
    while started.elapsed() < BURST {
        n += 1;
        let chunk = if n.is_multiple_of(64) {
            wrong[(n / 64) as usize % wrong.len()].clone()
        } else {
            burst(&mut noise)
        };
        tap.inject(&chunk).await;
    }
    let rss_after = gateway.rss_kib();
    let flood = tap.delivered_to_gateway() - delivered_before;
    eprintln!(
        "hostile burst: {flood} bytes in {:?}, VmRSS {rss_before} kB -> {rss_after} kB",
        started.elapsed()
    );
    assert!(flood > 100_000, "a burst worth the name: {flood} bytes");
    assert!(
        rss_after < rss_before + 8 * 1024,
        "VmRSS grew from {rss_before} kB to {rss_after} kB"
    );

    // After the noise: the line is decoded again, slave 10 as its master reads it, slave 1 as
    // it was, slave 2 never.
    within("slave 10 served after the noise", async {
        while raw.call(6, SLAVE, &[0x03, 0x00, 0x00, 0x00, 0x02]).await
            != [0x03, 0x04, 0x03, 0xE8, 0x03, 0xE9]
        {
            tokio::time::sleep(POLL).await;
        }
    })
    .await;
    assert_eq!(raw.call(7, 1, &read_pdu).await, served_1, "slave 1 kept");
    assert_eq!(
        raw.call(8, 2, &read_pdu).await,
        [0x83, 0x0B],
        "slave 2 never asked"
    );
    let scrape = gateway.scrape().await;
    let broken = series(
        "modbus_gateway_observed_discarded_total",
        "reason=\"broken\"",
    );
    assert!(scrape.value(&broken) > 0.0, "{}", scrape.text);
    master.command("poll");
    drop(raw);
    let status = gateway.stop().await;
    assert_eq!(status.code(), Some(0));
    assert_eq!(
        tap.written_by_gateway(),
        Vec::<u8>::new(),
        "the gateway wrote on the line"
    );
}

// ---------------------------------------------------------------------------------------------
// Refusals

/// `check-config` on `text`: its exit code and standard error.
fn check_config(dir: &TempDir, name: &str, text: &str) -> (Option<i32>, String) {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    let out = Command::new(BINARY)
        .args(["--config", path.to_str().unwrap(), "check-config"])
        .env_remove("RUST_LOG")
        .output()
        .expect("the binary runs");
    (out.status.code(), String::from_utf8(out.stderr).unwrap())
}

#[test]
fn check_config_refuses_every_key_that_would_transmit_on_a_listen_line_naming_it() {
    let dir = TempDir::new("listen-refusals");
    let base = listen_bus(Path::new("/dev/ttyUSB1"), MAX_AGE, "");
    let (code, err) = check_config(&dir, "good.toml", &format!("{base}{VALUES}"));
    assert_eq!(code, Some(0), "a plain listen line is fine: {err}");

    let text = format!(
        "{base}retries = 1\nretry_writes = true\nmax_in_flight = 2\n\
         [bus.rs485]\nmode = \"kernel\"\n\
         [[bus.slave]]\naddress = 10\ncache = \"1s\"\npoll_interval = \"1s\"\n\
         [[bus.slave.value]]\nname = \"v\"\nregister = 0\ntype = \"u16\"\nwritable = true\n\
         poll_interval = \"1s\"\n"
    );
    let (code, err) = check_config(&dir, "transmits.toml", &text);
    assert_eq!(code, Some(2), "{err}");
    for key in [
        "bus[0].retries",
        "bus[0].retry_writes",
        "bus[0].max_in_flight",
        "bus[0].rs485.mode",
        "bus[0].slave[0].cache",
        "bus[0].slave[0].poll_interval",
        "bus[0].slave[0].value[0].writable",
        "bus[0].slave[0].value[0].poll_interval",
    ] {
        assert!(
            err.contains(&format!("{key}: ")),
            "{key} is not named:\n{err}"
        );
    }

    let master_line = GatewayConfig::new()
        .bus(Bus::on("line1", "/dev/ttyUSB0").key("max_age", "5s"))
        .to_toml();
    let (code, err) = check_config(&dir, "master-max-age.toml", &master_line);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("bus[0].max_age: "), "{err}");
}
