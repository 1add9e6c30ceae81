//! What the integration tests share: a gateway started from TOML text on a loopback port, a raw
//! Modbus TCP master that sees every byte, and an RTU slave on a pty pair (the real serial path).

pub mod tls;

use modbus_gateway::bus::{BusHandle, BusTask, Device};
use modbus_gateway::error::Outcome;
use modbus_gateway::gateway::{config_from_toml, load_config};
use modbus_gateway::line::rtu::{self, FrameLen};
use modbus_gateway::metrics::Metrics;
use modbus_gateway::shutdown::Stopping;
use modbus_gateway::sim::{RegisterBank, SimLine, Slave};
use modbus_gateway::{Config, Gateway};
use std::cell::Cell;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::{Arc, Mutex, Once};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::task::JoinHandle;
use tokio_serial::{SerialPort, SerialStream};

/// Upper bound for anything a test waits for; a test that hits it has failed, not passed.
pub const PATIENCE: Duration = Duration::from_secs(20);
/// A pty passes a frame in one write; a user-defined frame is taken as complete after this pause.
const PTY_FRAME_PAUSE: Duration = Duration::from_millis(20);

thread_local! {
    static PANICS: Cell<usize> = const { Cell::new(0) };
}
static COUNT_PANICS: Once = Once::new();

/// Panics raised so far on this thread. A `#[tokio::test]` runtime runs the gateway's tasks on
/// the test's own thread, and tokio turns a panicking session into a merely closed connection, so
/// tests of hostile input compare this before and after.
pub fn panics_on_this_thread() -> usize {
    COUNT_PANICS.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            PANICS.with(|p| p.set(p.get() + 1));
            previous(info);
        }));
    });
    PANICS.with(Cell::get)
}

pub async fn within<F: std::future::Future>(what: &str, future: F) -> F::Output {
    tokio::time::timeout(PATIENCE, future)
        .await
        .unwrap_or_else(|_| panic!("{what}: no result within {PATIENCE:?}"))
}

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
    concat!(env!("CARGO_MANIFEST_DIR"), "/config/demo.toml")
}

/// The demo configuration as shipped, listening on free loopback ports instead of 5020 and 9020.
pub fn demo_config() -> Config {
    let env = [
        ("MBGW__SERVER__LISTEN".to_owned(), "127.0.0.1:0".to_owned()),
        ("MBGW__METRICS__LISTEN".to_owned(), "127.0.0.1:0".to_owned()),
    ];
    load_config(Path::new(demo_path()), env).expect("config/demo.toml is valid")
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
    let line =
        modbus_gateway::gateway::power_on_line(&settings).expect("simulated slaves power on");
    let bus = BusTask::new(settings, Device::Sim(line.clone()), metrics);
    let handle = bus.handle();
    tokio::spawn(bus.run(Stopping::never()));
    (line, handle)
}

/// Start a gateway on `toml`, which should listen on 127.0.0.1:0. Its metrics endpoint goes on a
/// free loopback port too, so tests never contend for the default one.
pub async fn start(toml: &str) -> Gateway {
    let mut config = config_from_toml(toml).unwrap_or_else(|e| panic!("test config: {e}"));
    config.metrics.listen = SocketAddr::from(([127, 0, 0, 1], 0));
    Gateway::start(&config).await.expect("gateway starts")
}

/// A gateway on one simulated 9600 8E1 line named "sim" with register-bank slaves 1-4, plus `extra`
/// bus keys.
pub async fn start_sim(extra: &str) -> Gateway {
    start(&sim_config(extra)).await
}

pub fn sim_config(extra: &str) -> String {
    format!(
        "[server]\nlisten = \"127.0.0.1:0\"\n\
         [[bus]]\nname = \"sim\"\ndevice = \"sim\"\nbaud = 9600\nparity = \"even\"\n{extra}\n\
         [[bus.sim_slave]]\naddress = \"1-4\"\n"
    )
}

/// [`sim_config`] with `[server]` keys added.
pub fn sim_config_with_server(server: &str, bus: &str) -> String {
    sim_config(bus).replace(
        "listen = \"127.0.0.1:0\"\n",
        &format!("listen = \"127.0.0.1:0\"\n{server}\n"),
    )
}

/// The frames `from` put on the simulated line so far, in order.
pub fn frames_from(line: &SimLine, from: modbus_gateway::sim::Source) -> Vec<Vec<u8>> {
    line.frames()
        .into_iter()
        .filter(|f| f.from == from)
        .map(|f| f.bytes)
        .collect()
}

pub fn addr(gateway: &Gateway) -> SocketAddr {
    gateway.local_addrs()[0]
}

/// Wait until bus `name` has (`up`) or has lost (`!up`) its port.
pub async fn wait_for_bus(gateway: &Gateway, name: &str, up: bool) {
    let what = format!(
        "bus {name} {}",
        if up {
            "opens its port"
        } else {
            "loses its port"
        }
    );
    within(&what, async {
        while gateway.bus_up(name) != Some(up) {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
}

/// A TCP connection to `addr` from the loopback address `source` (127.0.0.x: Linux answers for
/// all of 127/8), as from a host of its own.
pub async fn connect_from(source: [u8; 4], addr: SocketAddr) -> TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().expect("a socket");
    socket
        .bind(SocketAddr::from((source, 0)))
        .expect("bind a loopback address");
    within("connect", socket.connect(addr))
        .await
        .expect("gateway accepts")
}

/// What a master talks over: a TCP connection, or a TLS session on one.
pub trait Duplex: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send {}
impl<S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send> Duplex for S {}

/// A Modbus TCP master that writes and reads raw ADUs.
pub struct RawMaster {
    stream: Box<dyn Duplex>,
}

/// A reply as the master received it.
#[derive(Debug, PartialEq, Eq)]
pub struct Reply {
    pub transaction: u16,
    pub unit: u8,
    pub pdu: Vec<u8>,
}

impl RawMaster {
    pub async fn connect(addr: SocketAddr) -> Self {
        let stream = within("connect", TcpStream::connect(addr))
            .await
            .expect("gateway accepts");
        Self::over(stream)
    }

    /// A master connecting from the loopback address `source` (127.0.0.x), as from a host of
    /// its own.
    pub async fn connect_from(source: [u8; 4], addr: SocketAddr) -> Self {
        Self::over(connect_from(source, addr).await)
    }

    /// A master on a stream already connected (a TLS session, say).
    pub fn over(stream: impl Duplex + 'static) -> Self {
        RawMaster {
            stream: Box::new(stream),
        }
    }

    pub fn adu(transaction: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
        let mut adu = transaction.to_be_bytes().to_vec();
        adu.extend_from_slice(&[0, 0]);
        adu.extend_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
        adu.push(unit);
        adu.extend_from_slice(pdu);
        adu
    }

    pub async fn send_raw(&mut self, bytes: &[u8]) {
        self.stream.write_all(bytes).await.expect("send");
    }

    /// One request and its reply PDU; `None` if the gateway closed the connection instead.
    pub async fn try_call(&mut self, transaction: u16, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
        self.stream
            .write_all(&Self::adu(transaction, unit, pdu))
            .await
            .ok()?;
        let reply = self.try_recv().await?;
        assert_eq!((reply.transaction, reply.unit), (transaction, unit));
        Some(reply.pdu)
    }

    pub async fn send(&mut self, transaction: u16, unit: u8, pdu: &[u8]) {
        self.send_raw(&Self::adu(transaction, unit, pdu)).await;
    }

    pub async fn recv(&mut self) -> Reply {
        self.try_recv()
            .await
            .expect("a reply, not a closed connection")
    }

    async fn try_recv(&mut self) -> Option<Reply> {
        let mut header = [0u8; 7];
        within("reply header", self.stream.read_exact(&mut header))
            .await
            .ok()?;
        assert_eq!(&header[2..4], &[0, 0], "protocol id");
        let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
        assert!((2..=254).contains(&length), "length field {length}");
        let mut pdu = vec![0u8; length - 1];
        within("reply body", self.stream.read_exact(&mut pdu))
            .await
            .ok()?;
        Some(Reply {
            transaction: u16::from_be_bytes([header[0], header[1]]),
            unit: header[6],
            pdu,
        })
    }

    /// One request, one reply with the same transaction and unit ids; the reply PDU.
    pub async fn call(&mut self, transaction: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
        self.send(transaction, unit, pdu).await;
        let reply = self.recv().await;
        assert_eq!((reply.transaction, reply.unit), (transaction, unit));
        reply.pdu
    }

    /// True once the gateway has closed the connection (EOF or reset).
    pub async fn is_closed(&mut self) -> bool {
        let mut byte = [0u8; 1];
        matches!(
            tokio::time::timeout(PATIENCE, self.stream.read(&mut byte)).await,
            Ok(Ok(0) | Err(_))
        )
    }
}

type Responder = Box<dyn FnMut(&[u8]) -> Option<Vec<u8>> + Send>;

/// An RTU slave on the far end of a pty pair; the gateway opens `path` like a serial device.
pub struct PtySlave {
    pub path: String,
    received: Arc<Mutex<Vec<Vec<u8>>>>,
    task: JoinHandle<()>,
    /// Kept open so the pty stays usable until the gateway opens it.
    _tty: SerialStream,
}

impl PtySlave {
    /// `respond` gets each whole request frame and returns the bytes to answer with, if any.
    pub fn start(respond: impl FnMut(&[u8]) -> Option<Vec<u8>> + Send + 'static) -> Self {
        let (mut master, tty) = SerialStream::pair().expect("pty pair");
        let path = tty.name().expect("pty has a path");
        let received = Arc::new(Mutex::new(Vec::new()));
        let log = received.clone();
        let mut respond: Responder = Box::new(respond);
        let task = tokio::spawn(async move {
            let mut buf = Vec::new();
            let mut chunk = [0u8; 512];
            loop {
                let complete = match rtu::request_len(&buf) {
                    FrameLen::Exact(n) if buf.len() >= n => Some(n),
                    FrameLen::Invalid => Some(buf.len()),
                    _ => None,
                };
                if let Some(n) = complete {
                    let request: Vec<u8> = buf.drain(..n).collect();
                    log.lock().unwrap().push(request.clone());
                    if let Some(reply) = respond(&request) {
                        if master.write_all(&reply).await.is_err() {
                            return;
                        }
                    }
                    continue;
                }
                let by_silence = rtu::request_len(&buf) == FrameLen::BySilence;
                let read = master.read(&mut chunk);
                let n = if by_silence {
                    match tokio::time::timeout(PTY_FRAME_PAUSE, read).await {
                        Ok(result) => result,
                        Err(_) => {
                            let request: Vec<u8> = std::mem::take(&mut buf);
                            log.lock().unwrap().push(request.clone());
                            if let Some(reply) = respond(&request) {
                                if master.write_all(&reply).await.is_err() {
                                    return;
                                }
                            }
                            continue;
                        }
                    }
                } else {
                    read.await
                };
                match n {
                    Ok(n) if n > 0 => buf.extend_from_slice(&chunk[..n]),
                    _ => return,
                }
            }
        });
        PtySlave {
            path,
            received,
            task,
            _tty: tty,
        }
    }

    /// Register-bank slaves at every address, answering like the simulated ones.
    pub fn registers() -> Self {
        let mut bank = RegisterBank::new(Duration::ZERO);
        Self::start(move |request| {
            if !rtu::crc_ok(request) {
                return None;
            }
            let now = tokio::time::Instant::now();
            bank.handle(request[0], rtu::pdu_of(request), now)
                .map(|t| t.bytes)
        })
    }

    /// Every request frame received so far, byte for byte.
    pub fn received(&self) -> Vec<Vec<u8>> {
        self.received.lock().unwrap().clone()
    }

    /// Pull the plug: the pty goes away and the gateway's reads fail.
    pub fn unplug(self) {
        self.task.abort();
    }
}

impl Drop for PtySlave {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A gateway configuration with one serial bus named "pty" on `path` (8N2: ptys refuse parity).
pub fn pty_config(path: &str, extra: &str) -> String {
    format!(
        "[server]\nlisten = \"127.0.0.1:0\"\n\
         [[bus]]\nname = \"pty\"\ndevice = \"{path}\"\nbaud = 115200\nparity = \"none\"\n{extra}\n"
    )
}

/// One HTTP/1.1 GET over a fresh connection: the status code and the body.
pub async fn http_get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut stream = within("connect to the metrics endpoint", TcpStream::connect(addr))
        .await
        .expect("metrics endpoint accepts");
    let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.expect("send");
    let mut response = String::new();
    within("HTTP response", stream.read_to_string(&mut response))
        .await
        .expect("read the response");
    let (head, body) = response
        .split_once("\r\n\r\n")
        .unwrap_or_else(|| panic!("not an HTTP response: {response:?}"));
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|code| code.parse().ok())
        .unwrap_or_else(|| panic!("no status in {head:?}"));
    (status, body.to_owned())
}

/// One scrape of `/metrics`, parsed: every sample by its series, `name{label="value",...}`, with
/// labels sorted as the gateway writes them.
pub struct Scrape {
    pub text: String,
    samples: std::collections::BTreeMap<String, f64>,
}

impl Scrape {
    pub async fn of(gateway: &Gateway) -> Scrape {
        let (status, text) = http_get(gateway.metrics_addr(), "/metrics").await;
        assert_eq!(status, 200, "{text}");
        Scrape::parse(text)
    }

    pub fn parse(text: String) -> Scrape {
        let samples = text
            .lines()
            .filter(|line| !line.starts_with('#') && !line.is_empty())
            .map(|line| {
                let (series, value) = line
                    .rsplit_once(' ')
                    .unwrap_or_else(|| panic!("not a sample: {line}"));
                let value = value
                    .parse()
                    .unwrap_or_else(|_| panic!("not a number: {line}"));
                (series.to_owned(), value)
            })
            .collect();
        Scrape { text, samples }
    }

    /// The value of `series`, if the gateway exports it.
    pub fn get(&self, series: &str) -> Option<f64> {
        self.samples.get(series).copied()
    }

    /// The value of `series`, which must be exported.
    pub fn value(&self, series: &str) -> f64 {
        self.get(series)
            .unwrap_or_else(|| panic!("no series {series} in\n{}", self.text))
    }

    /// How much `series` grew since `before` (absent counts as 0).
    pub fn delta(&self, before: &Scrape, series: &str) -> f64 {
        self.get(series).unwrap_or(0.0) - before.get(series).unwrap_or(0.0)
    }

    /// Every series of metric `name` (any labels).
    pub fn series_of(&self, name: &str) -> Vec<(&str, f64)> {
        self.samples
            .iter()
            .filter(|(series, _)| series.split('{').next() == Some(name))
            .map(|(series, value)| (series.as_str(), *value))
            .collect()
    }
}

/// An external tool on the PATH. Without it the calling test has nothing to check and says so;
/// with `MBGW_REQUIRE_TOOLS=1` (as `.ci/run` sets) its absence fails the test instead.
pub fn tool(name: &str) -> Option<std::path::PathBuf> {
    let found = std::env::var_os("PATH").and_then(|path| {
        std::env::split_paths(&path)
            .map(|dir| dir.join(name))
            .find(|candidate| candidate.is_file())
    });
    if found.is_none() {
        assert!(
            std::env::var_os("MBGW_REQUIRE_TOOLS").is_none(),
            "{name} is required (MBGW_REQUIRE_TOOLS is set) but not on the PATH"
        );
        eprintln!("{name} is not on the PATH: this test checks nothing here");
    }
    found
}

/// A loopback address nobody listens on right now, for a gateway process to bind.
pub fn free_addr() -> SocketAddr {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("a free port");
    listener.local_addr().expect("bound")
}

/// A raw master on a gateway process, once the process listens on `addr`.
pub async fn connect_when_listening(addr: SocketAddr) -> RawMaster {
    within("the gateway listens", async {
        loop {
            if let Ok(stream) = TcpStream::connect(addr).await {
                drop(stream);
                return RawMaster::connect(addr).await;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await
}

/// Wait (bounded) until the log file at `path` contains `what`.
pub async fn until_logged(path: &Path, what: &str) {
    within(&format!("the log says {what:?}"), async {
        while !std::fs::read_to_string(path).unwrap().contains(what) {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

/// Send signal `name` (TERM, HUP, KILL...) to a child process.
pub fn signal(child: &std::process::Child, name: &str) {
    let status = std::process::Command::new("kill")
        .args(["-s", name, &child.id().to_string()])
        .status()
        .expect("kill runs");
    assert!(status.success(), "kill -s {name}");
}

/// Wait (bounded) for a child process to exit.
pub async fn exit_status(mut child: std::process::Child) -> std::process::ExitStatus {
    within(
        "the gateway exits",
        tokio::task::spawn_blocking(move || child.wait()),
    )
    .await
    .expect("the waiting task runs")
    .expect("wait for the child")
}

/// The completions of many masters polling at once, counted in a window after a warm-up, for
/// judging whether the line was shared fairly.
pub struct Rotation {
    total: std::sync::atomic::AtomicUsize,
    over: std::sync::atomic::AtomicBool,
    /// Completions before counting starts, so that every master has joined the rotation.
    warm_up: usize,
    /// Completions counted.
    window: usize,
}

impl Rotation {
    /// For `masters` masters: a warm-up of two rounds, a window of five.
    pub fn new(masters: usize) -> Arc<Rotation> {
        Arc::new(Rotation {
            total: std::sync::atomic::AtomicUsize::new(0),
            over: std::sync::atomic::AtomicBool::new(false),
            warm_up: 2 * masters,
            window: 5 * masters,
        })
    }

    /// A master completed a request: whether it counts, or `None` once the window is over.
    pub fn completed(&self) -> Option<bool> {
        use std::sync::atomic::Ordering::Relaxed;
        let n = self.total.fetch_add(1, Relaxed) + 1;
        if self.over.load(Relaxed) {
            return None;
        }
        if n >= self.warm_up + self.window {
            self.over.store(true, Relaxed);
        }
        Some(n > self.warm_up)
    }
}

/// Wait for every master's count of completions in the window, and check that none got less
/// than half of what another got.
pub async fn assert_fair(masters: Vec<JoinHandle<usize>>, what: &str) {
    let mut counts = Vec::new();
    for master in masters {
        counts.push(
            within("every master finishes", master)
                .await
                .expect("master task"),
        );
    }
    let min = *counts.iter().min().unwrap();
    let max = *counts.iter().max().unwrap();
    eprintln!("completions per {what}: min {min}, max {max}");
    assert!(min >= 1, "a {what} got nothing: {counts:?}");
    assert!(max <= 2 * min, "unfair: min {min}, max {max}: {counts:?}");
}

/// A gateway configuration with one simulated line at 115200 baud, fast enough that a trace
/// reader that does not read is soon blocked.
pub fn fast_sim_config() -> String {
    "[server]\nlisten = \"127.0.0.1:0\"\n\
     [[bus]]\nname = \"sim\"\ndevice = \"sim\"\nbaud = 115200\nparity = \"even\"\n\
     [[bus.sim_slave]]\naddress = \"1-4\"\n"
        .to_owned()
}

/// A master reading 125 registers of slave 1 back to back until aborted, so that the trace has
/// about a kilobyte to send per read.
pub fn keep_line_busy(gateway: SocketAddr) -> JoinHandle<()> {
    tokio::spawn(async move {
        let mut master = RawMaster::connect(gateway).await;
        for transaction in (0..=u16::MAX).cycle() {
            if master
                .try_call(transaction, 1, &[0x03, 0x00, 0x00, 0x00, 0x7D])
                .await
                .is_none()
            {
                return;
            }
        }
    })
}

/// `GET /trace` from a client that never reads: its receive buffer made small before it
/// connects, so that its stream blocks after a few events. Keep it to keep it connected.
pub async fn stalled_trace_reader(metrics: SocketAddr) -> TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().expect("a socket");
    socket.set_recv_buffer_size(1024).expect("SO_RCVBUF");
    let mut stream = within("connect to the metrics endpoint", socket.connect(metrics))
        .await
        .expect("metrics endpoint accepts");
    let request = format!("GET /trace HTTP/1.1\r\nHost: {metrics}\r\n\r\n");
    stream.write_all(request.as_bytes()).await.expect("send");
    stream
}

/// As many stalled trace readers as the endpoint takes ([`stalled_trace_reader`]), once a
/// further reader is refused (503). Keep them to keep them connected.
pub async fn fill_trace_with_stalled_readers(metrics: SocketAddr) -> Vec<TcpStream> {
    let mut stalled = Vec::new();
    for _ in 0..modbus_gateway::trace::MAX_READERS {
        stalled.push(stalled_trace_reader(metrics).await);
    }
    within("the stalled readers hold every place of the trace", async {
        while status_line(metrics, "/trace").await != Some(503) {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    stalled
}

/// The status code of a GET of `path` on a fresh connection, read from the status line alone
/// (a trace stream's body never ends); `None` if the endpoint closed the connection instead.
pub async fn status_line(addr: SocketAddr, path: &str) -> Option<u16> {
    let mut stream = TcpStream::connect(addr).await.ok()?;
    let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n");
    stream.write_all(request.as_bytes()).await.ok()?;
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n") {
        match within("a status line", stream.read(&mut byte)).await {
            Ok(1) => head.push(byte[0]),
            _ => return None,
        }
    }
    let head = String::from_utf8_lossy(&head).into_owned();
    head.split(' ').nth(1)?.parse().ok()
}

/// [`http_get`], bounded by `limit`, that says what went wrong instead of failing the test.
pub async fn try_http_get(
    addr: SocketAddr,
    path: &str,
    limit: Duration,
) -> Result<(u16, String), String> {
    let get = async {
        let mut stream = TcpStream::connect(addr)
            .await
            .map_err(|e| format!("connect: {e}"))?;
        let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
        stream
            .write_all(request.as_bytes())
            .await
            .map_err(|e| format!("send: {e}"))?;
        let mut response = String::new();
        stream
            .read_to_string(&mut response)
            .await
            .map_err(|e| format!("receive: {e}"))?;
        let (head, body) = response
            .split_once("\r\n\r\n")
            .ok_or_else(|| format!("not an HTTP response: {response:?}"))?;
        let status = head
            .split(' ')
            .nth(1)
            .and_then(|code| code.parse().ok())
            .ok_or_else(|| format!("no status in {head:?}"))?;
        Ok((status, body.to_owned()))
    };
    tokio::time::timeout(limit, get)
        .await
        .unwrap_or_else(|_| Err(format!("no answer within {limit:?}")))
}

/// A client that connects to `addr` and sends nothing, connecting again whenever it is closed
/// (after `pause`) and at least every 9 s, until aborted.
pub fn silent_socket(addr: SocketAddr, pause: Duration) -> JoinHandle<()> {
    tokio::spawn(async move {
        loop {
            if let Ok(mut stream) = TcpStream::connect(addr).await {
                let mut byte = [0u8; 1];
                let _ = tokio::time::timeout(Duration::from_secs(9), stream.read(&mut byte)).await;
            }
            tokio::time::sleep(pause).await;
        }
    })
}

/// A gateway configuration for floods: Modbus TCP and UDP listeners, one simulated line at `baud`
/// with register slaves 1 and 2, `queue_depth` places and a queue timeout no read reaches.
pub fn flood_target(baud: u32, queue_depth: usize) -> String {
    format!(
        "[server]\nlisten = \"127.0.0.1:0\"\nlisten_udp = \"127.0.0.1:0\"\n\
         [[bus]]\nname = \"sim\"\ndevice = \"sim\"\nbaud = {baud}\nparity = \"none\"\n\
         queue_depth = {queue_depth}\nqueue_timeout = \"60s\"\n\
         [[bus.sim_slave]]\naddress = \"1-2\"\n"
    )
}

/// Masters flooding a gateway (an attack): when to stop, and how many of their requests it
/// refused with 0x06.
#[derive(Default)]
pub struct Flood {
    stopped: std::sync::atomic::AtomicBool,
    refused: std::sync::atomic::AtomicUsize,
}

impl Flood {
    pub fn new() -> Arc<Flood> {
        Arc::default()
    }

    pub fn stop(&self) {
        self.stopped
            .store(true, std::sync::atomic::Ordering::Relaxed);
    }

    pub fn is_stopped(&self) -> bool {
        self.stopped.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// One of the flood's requests got 0x06.
    pub fn refused(&self) {
        self.refused
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }

    /// Wait (bounded) until `n` of the flood's requests were refused: the queue is full.
    pub async fn until_refused(&self, n: usize) {
        within("the flood fills the queue", async {
            while self.refused.load(std::sync::atomic::Ordering::Relaxed) < n {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await;
    }
}

/// A polite master: `reads` reads of input register 1000 of `unit` (a register-bank slave), one
/// at a time. How many were answered; the others must have got 0x06.
pub async fn polite_reads(at: SocketAddr, unit: u8, reads: u16) -> u16 {
    let mut master = RawMaster::connect(at).await;
    let mut answered = 0;
    for transaction in 0..reads {
        // Input register N reads N.
        match &master
            .call(transaction, unit, &[0x04, 0x03, 0xE8, 0x00, 0x01])
            .await[..]
        {
            [0x04, 0x02, 0x03, 0xE8] => answered += 1,
            refused => assert_eq!(refused, [0x84, 0x06], "read {transaction}"),
        }
    }
    answered
}
