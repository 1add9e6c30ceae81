//! `modbus-gateway-bench`: measures the gateway against the physics of its line. For each
//! scenario it starts the `modbus-gateway` binary (the one next to this one, or `--gateway`) on a
//! generated configuration, drives N concurrent Modbus TCP masters from this process for a fixed
//! time, and reports transactions per second, bus efficiency (the physical minimum of every
//! completed transaction over the wall time), latency percentiles, fairness (Jain's index over the
//! masters' completions), and the gateway process's own RSS and CPU per transaction (from
//! /proc, so the masters' cost is not in it; the simulated slaves', inside the gateway, is).
//! A workspace member of its own: `cargo install` and the Debian package carry only the daemon.

use clap::Parser;
use mio_serial::SerialPort;
use modbus_gateway::bus::Port;
use modbus_gateway::line::{rtu, Framing, LineTiming, Parity, SerialFormat};
use modbus_gateway::sim::responder::Responder;
use modbus_gateway::sim::RegisterBank;
use serde::Serialize;
use std::net::{Ipv4Addr, SocketAddr};
use std::path::PathBuf;
use std::process::{Child, Command, ExitCode, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream, UdpSocket};
use tokio_rustls::client::TlsStream;
use tokio_rustls::rustls::pki_types::ServerName;

mod tls;

/// Read 10 holding registers from 0000H: 8 bytes on the wire, 25 back. Each master reads a block
/// of its own of the same size (from 10 x its index) but in the `Same` load.
const READ_10: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x0A];
/// Write holding register 0001H: 8 bytes each way.
const WRITE_1: [u8; 5] = [0x06, 0x00, 0x01, 0x12, 0x34];
/// Slaves on the simulated line; masters spread their requests over them.
const SLAVES: u8 = 247;
/// The local address the priority master connects from, and `server.priority`.
const PRIORITY_IP: Ipv4Addr = Ipv4Addr::new(127, 0, 0, 2);

#[derive(Parser)]
#[command(about = "Benchmark modbus-gateway: bus efficiency, latency, fairness, memory, CPU")]
struct Cli {
    /// Scenarios to run: a name as listed by --list, or its leading part up to a `-` (`sim-9600`
    /// selects every 9600 baud one); default: all.
    scenarios: Vec<String>,
    /// Measure each scenario at least this long, in seconds (longer when the masters need it to
    /// each complete `--rounds` requests).
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// Requests each master should complete at least, so that fairness means something.
    #[arg(long, default_value_t = 5)]
    rounds: u32,
    /// One JSON object per scenario instead of the table.
    #[arg(long)]
    json: bool,
    /// List the scenarios and exit.
    #[arg(long)]
    list: bool,
    /// The gateway binary (default: `modbus-gateway` next to this program).
    #[arg(long)]
    gateway: Option<PathBuf>,
    /// A reader on the gateway's `GET /trace` from before the warm-up to the end: one that reads
    /// every event, or one that never reads (and loses events).
    #[arg(long, value_enum)]
    trace: Option<TraceReader>,
}

#[derive(Clone, Copy, PartialEq, clap::ValueEnum)]
enum TraceReader {
    Reading,
    Stalled,
}

/// A trace reader while it lives.
enum Watching {
    Reading(tokio::task::JoinHandle<()>),
    Stalled(#[allow(dead_code)] TcpStream),
}

impl Drop for Watching {
    fn drop(&mut self) {
        if let Watching::Reading(task) = self {
            task.abort();
        }
    }
}

/// Open `GET /trace` on the metrics endpoint at `addr` and read it as `how` says.
async fn watch_trace(addr: SocketAddr, how: TraceReader) -> Result<Watching, String> {
    let mut stream = http_get(addr, "/trace", "opening the trace").await?;
    Ok(match how {
        TraceReader::Stalled => Watching::Stalled(stream),
        TraceReader::Reading => Watching::Reading(tokio::spawn(async move {
            let mut buf = vec![0; 64 * 1024];
            while matches!(stream.read(&mut buf).await, Ok(n) if n > 0) {}
        })),
    })
}

#[derive(Clone, Copy, PartialEq)]
enum Line {
    /// The built-in simulated line, timed at its baud rate.
    Sim,
    /// A pty pair with an RTU slave in this process that answers at once: no line timing.
    Pty,
}

#[derive(Clone, Copy, PartialEq)]
enum Load {
    /// Read 10 holding registers (a block of its own), back to back, from each slave in turn.
    Read,
    /// Every fourth request a write of one register, the rest reads of 10.
    Mix,
    /// Connected, sending nothing.
    Idle,
    /// Every master reads the same 10 holding registers of slave 1, back to back: coalescing.
    Same,
    /// Every master reads its own 10 holding registers of slave 1, back to back: nothing to
    /// coalesce.
    Own,
}

/// How the bench's masters talk to the gateway.
#[derive(Clone, Copy, PartialEq)]
enum Kind {
    /// Modbus TCP.
    Tcp,
    /// RTU frames on a TCP connection.
    RtuOverTcp,
    /// Modbus UDP.
    Udp,
    /// Modbus/TCP Security: Modbus TCP inside TLS, with a client certificate.
    Tls,
    /// The three kinds in turn, master by master.
    Mixed,
}

struct Scenario {
    name: String,
    line: Line,
    kind: Kind,
    framing: Framing,
    format: SerialFormat,
    masters: usize,
    load: Load,
    /// `[[bus]] coalesce_reads` (the gateway's default: on).
    coalesce: bool,
    /// One more master, connecting from 127.0.0.2 (in `server.priority`), reading a block of its
    /// own: back to back (`Some(ZERO)`) or one read per period.
    priority: Option<Duration>,
}

impl Scenario {
    /// Modbus TCP masters on the simulated RTU line, reads coalescing, no priority master.
    fn sim(name: String, format: SerialFormat, masters: usize, load: Load) -> Scenario {
        Scenario {
            name,
            line: Line::Sim,
            kind: Kind::Tcp,
            framing: Framing::Rtu,
            format,
            masters,
            load,
            coalesce: true,
            priority: None,
        }
    }
}

fn scenarios() -> Vec<Scenario> {
    let format = |baud, parity| SerialFormat {
        baud,
        data_bits: 8,
        parity,
        stop_bits: 1,
    };
    let ascii_7e1 = SerialFormat {
        data_bits: 7,
        ..format(9600, Parity::Even)
    };
    let sim_9600 = format(9600, Parity::Even);
    let sim_115200 = format(115_200, Parity::None);
    let mut all = Vec::new();
    for (baud, parity, label) in [(9600, Parity::Even, "8E1"), (115_200, Parity::None, "8N1")] {
        for masters in [1, 10, 100, 1000] {
            let name = format!("sim-{baud}-{label}-read-{masters}");
            all.push(Scenario::sim(
                name,
                format(baud, parity),
                masters,
                Load::Read,
            ));
        }
        let name = format!("sim-{baud}-{label}-mix-100");
        all.push(Scenario::sim(name, format(baud, parity), 100, Load::Mix));
    }
    for masters in [1, 100] {
        all.push(Scenario {
            framing: Framing::Ascii,
            ..Scenario::sim(
                format!("ascii-9600-7E1-read-{masters}"),
                ascii_7e1,
                masters,
                Load::Read,
            )
        });
    }
    for (kind, label) in [
        (Kind::RtuOverTcp, "rtu-over-tcp"),
        (Kind::Udp, "udp"),
        (Kind::Tls, "tls"),
        (Kind::Mixed, "mixed-kinds"),
    ] {
        // A mix of one master is one Modbus TCP master: the mix has 99, 33 of each kind.
        let counts: &[usize] = if kind == Kind::Mixed { &[99] } else { &[1, 99] };
        for &masters in counts {
            let name = format!("sim-115200-8N1-{label}-read-{masters}");
            all.push(Scenario {
                kind,
                ..Scenario::sim(name, sim_115200, masters, Load::Read)
            });
        }
    }
    // Over TLS too: with no line timing to hide it, what a TLS record costs shows.
    for (kind, name) in [(Kind::Tcp, "read"), (Kind::Tls, "tls-read")] {
        let name = format!("pty-115200-untimed-{name}-1");
        all.push(Scenario {
            line: Line::Pty,
            kind,
            ..Scenario::sim(name, sim_115200, 1, Load::Read)
        });
    }
    // Many masters, one read: coalescing, and what it costs when there is nothing to coalesce.
    for (baud, parity, label) in [(9600, Parity::Even, "8E1"), (115_200, Parity::None, "8N1")] {
        for masters in [1, 10, 100] {
            let name = format!("many-{baud}-{label}-same-{masters}");
            all.push(Scenario::sim(
                name,
                format(baud, parity),
                masters,
                Load::Same,
            ));
        }
    }
    for (coalesce, suffix) in [(true, ""), (false, "-uncoalesced")] {
        let name = format!("many-9600-8E1-own-100{suffix}");
        all.push(Scenario {
            coalesce,
            ..Scenario::sim(name, sim_9600, 100, Load::Own)
        });
    }
    // A priority master among 100 that saturate the line: polling back to back (the share
    // limit decides), then every 200 ms (a fifth of the line).
    for (period, label) in [(Duration::ZERO, ""), (Duration::from_millis(200), "-200ms")] {
        let name = format!("many-9600-8E1-priority{label}-100");
        all.push(Scenario {
            priority: Some(period),
            ..Scenario::sim(name, sim_9600, 100, Load::Own)
        });
    }
    for masters in [0, 1000] {
        all.push(Scenario::sim(
            format!("idle-{masters}"),
            sim_9600,
            masters,
            Load::Idle,
        ));
    }
    all
}

#[derive(Serialize)]
struct Report {
    scenario: String,
    baud: u32,
    masters: usize,
    transactions: u64,
    tx_per_s: f64,
    /// Sum of the physical minimum of the completed transactions over the wall time (sim only).
    efficiency: Option<f64>,
    p50_ms: Option<f64>,
    p99_ms: Option<f64>,
    max_ms: Option<f64>,
    /// Latency above the physical minimum at the median, for one master on the sim line.
    added_p50_ms: Option<f64>,
    added_p99_ms: Option<f64>,
    fairness: Option<f64>,
    rss_mb: f64,
    cpu_us_per_tx: Option<f64>,
    seconds: f64,
    /// Connection set-up, one master after another: TCP connect to connected (plain TCP, RTU
    /// over TCP) or to the TLS handshake complete (TLS), median and slowest over the masters.
    connect_p50_ms: Option<f64>,
    connect_max_ms: Option<f64>,
    /// The gateway's CPU time across the connect phase, per master.
    connect_cpu_us: Option<f64>,
    /// From the gateway's metrics, scraped at the window's ends (sim only): transactions on the
    /// line (`modbus_gateway_round_trip_seconds_count`), per second, per answered request, and
    /// requests answered by another's (`modbus_gateway_coalesced_requests_total`).
    line_tx: Option<u64>,
    line_tx_per_s: Option<f64>,
    line_tx_per_answer: Option<f64>,
    coalesced: Option<u64>,
    /// The physical rate of the read, 1 / t_min, in transactions per second.
    physical_tx_per_s: Option<f64>,
    /// Masters reading the same block: answered reads per second over (masters x
    /// physical_tx_per_s).
    answered_vs_physical: Option<f64>,
    /// The priority master (priority scenarios): its answered reads, its latency and its wait
    /// (latency less one t_min) in transaction times (t_min), and the other masters' share of
    /// the answered reads (here, of the line's transactions). `fairness` is then over the others.
    priority_tx: Option<u64>,
    priority_p50_tmin: Option<f64>,
    priority_p99_tmin: Option<f64>,
    priority_max_tmin: Option<f64>,
    priority_wait_p50_tmin: Option<f64>,
    priority_wait_p99_tmin: Option<f64>,
    others_share: Option<f64>,
    /// The gateway's mean queue wait by class (`modbus_gateway_queue_wait_seconds` sum over
    /// count), in t_min.
    queue_wait_priority_tmin: Option<f64>,
    queue_wait_normal_tmin: Option<f64>,
}

fn free_addr() -> std::io::Result<SocketAddr> {
    std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()
}

/// The gateway process, stopped when dropped.
struct Gateway {
    child: Child,
    listen: SocketAddr,
    listen_rtu_over_tcp: SocketAddr,
    listen_udp: SocketAddr,
    metrics: SocketAddr,
    /// The TLS listener and the certificates (TLS scenarios only).
    tls: Option<(SocketAddr, tls::Pki)>,
    _config: tempfile_path::TempPath,
}

impl Drop for Gateway {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A file removed when dropped.
mod tempfile_path {
    pub struct TempPath(pub std::path::PathBuf);
    impl Drop for TempPath {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.0);
        }
    }
}

impl Gateway {
    async fn start(binary: &PathBuf, scenario: &Scenario, device: &str) -> Result<Gateway, String> {
        let listen = free_addr().map_err(|e| e.to_string())?;
        let listen_rtu_over_tcp = free_addr().map_err(|e| e.to_string())?;
        let listen_udp = std::net::UdpSocket::bind("127.0.0.1:0")
            .and_then(|s| s.local_addr())
            .map_err(|e| e.to_string())?;
        let metrics = free_addr().map_err(|e| e.to_string())?;
        let f = &scenario.format;
        let parity = match f.parity {
            Parity::None => "none",
            Parity::Even => "even",
            Parity::Odd => "odd",
        };
        let masters = scenario.masters.max(1) + usize::from(scenario.priority.is_some());
        let mut config = format!(
            "[server]\nlisten = \"{listen}\"\nlisten_rtu_over_tcp = \"{listen_rtu_over_tcp}\"\n\
             listen_udp = \"{listen_udp}\"\nmax_connections = {}\n",
            masters + 16,
        );
        if scenario.priority.is_some() {
            config += &format!("priority = [\"{PRIORITY_IP}\"]\n");
        }
        let tls = if scenario.kind == Kind::Tls {
            let listen_tls = free_addr().map_err(|e| e.to_string())?;
            let pki = tls::Pki::new(&scenario.name)?;
            config += &format!("listen_tls = [\"{listen_tls}\"]\n{}", pki.table);
            Some((listen_tls, pki))
        } else {
            None
        };
        config += &format!(
            "[metrics]\nlisten = \"{metrics}\"\n[log]\nlevel = \"warn\"\n\
             [[bus]]\nname = \"bench\"\ndevice = \"{device}\"\nframing = \"{}\"\nbaud = {}\n\
             data_bits = {}\nparity = \"{parity}\"\n\
             stop_bits = {}\nqueue_depth = {}\nqueue_timeout = \"1h\"\n",
            scenario.framing.name(),
            f.baud,
            f.data_bits,
            f.stop_bits,
            masters * 2 + 16,
        );
        if !scenario.coalesce {
            config += "coalesce_reads = false\n";
        }
        if scenario.line == Line::Sim {
            config += &format!("[[bus.sim_slave]]\naddress = \"1-{SLAVES}\"\n");
        }
        let path = std::env::temp_dir().join(format!(
            "mbgw-bench-{}-{}.toml",
            std::process::id(),
            scenario.name
        ));
        std::fs::write(&path, config).map_err(|e| e.to_string())?;
        let child = Command::new(binary)
            .args(["--config", &path.to_string_lossy(), "run"])
            .env_remove("RUST_LOG")
            .stdout(Stdio::null())
            .spawn()
            .map_err(|e| format!("{}: {e}", binary.display()))?;
        let gateway = Gateway {
            child,
            listen,
            listen_rtu_over_tcp,
            listen_udp,
            metrics,
            tls,
            _config: tempfile_path::TempPath(path),
        };
        let started = Instant::now();
        while TcpStream::connect(listen).await.is_err() {
            if started.elapsed() > Duration::from_secs(10) {
                return Err("the gateway did not start listening within 10 s".into());
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // The TLS listener may come up later: a whole handshake, as a bare connection closed
        // at once would be logged as a failed one.
        if let Some((listen_tls, pki)) = &gateway.tls {
            while tls_connect(*listen_tls, pki).await.is_err() {
                if started.elapsed() > Duration::from_secs(10) {
                    return Err("the gateway did not start its TLS listener within 10 s".into());
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
        Ok(gateway)
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }
}

/// CPU time of process `pid` so far, all its threads: the first field of each thread's
/// schedstat, in nanoseconds (the tick counts of /proc/PID/stat are only 10 ms fine).
fn cpu_time(pid: u32) -> Duration {
    let Ok(threads) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return Duration::ZERO;
    };
    let nanos: u64 = threads
        .filter_map(|t| {
            let stat = std::fs::read_to_string(t.ok()?.path().join("schedstat")).ok()?;
            stat.split_whitespace().next()?.parse::<u64>().ok()
        })
        .sum();
    Duration::from_nanos(nanos)
}

/// Resident memory of process `pid` now, in MB.
fn rss_mb(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1024.0)
}

/// A line that takes no time: no character time, and no t3.5 before a reply.
const UNTIMED: LineTiming = LineTiming {
    char_time: Duration::ZERO,
    t15: Duration::ZERO,
    t35: Duration::ZERO,
};

/// RTU slaves on the far end of a pty that answer every request at once: the library's
/// responder (as `simulate` serves) with a register slave at every address, on an untimed line.
/// A frame cut short still ends after the real line's t3.5 of silence.
fn untimed_slave(format: &SerialFormat) -> Result<(String, tokio::task::JoinHandle<()>), String> {
    let (far, tty) = mio_serial::SerialStream::pair().map_err(|e| e.to_string())?;
    let path = tty.name().ok_or("the pty has no path")?;
    let mut port = Port::serial(far).map_err(|e| e.to_string())?;
    let mut responder = Responder::new(UNTIMED, LineTiming::new(format).t35);
    for address in 1..=SLAVES {
        responder.add_slave(address, Box::new(RegisterBank::new(Duration::ZERO)));
    }
    let task = tokio::spawn(async move {
        let _tty = tty;
        responder.serve(&mut port).await;
    });
    Ok((path, task))
}

/// One master's way to the gateway.
enum Conn {
    Tcp(TcpStream),
    RtuOverTcp(TcpStream),
    Udp(UdpSocket),
    Tls(Box<TlsStream<TcpStream>>),
}

/// One Modbus TCP transaction on `stream`: the MBAP request, then the reply by its own length.
async fn mbap_exchange<S: AsyncRead + AsyncWrite + Unpin>(
    stream: &mut S,
    tid: u16,
    slave: u8,
    pdu: &[u8],
    reply: &mut [u8],
) -> std::io::Result<bool> {
    stream.write_all(&mbap(tid, slave, pdu)).await?;
    stream.read_exact(&mut reply[..7]).await?;
    let len = usize::from(u16::from_be_bytes([reply[4], reply[5]]));
    stream.read_exact(&mut reply[7..6 + len]).await?;
    Ok(reply[..2] == tid.to_be_bytes() && reply[7] & 0x80 == 0)
}

impl Conn {
    /// Send `pdu` to `slave` and wait for its answer; true if it is a normal reply.
    async fn exchange(
        &mut self,
        tid: u16,
        slave: u8,
        pdu: &[u8],
        reply: &mut [u8],
    ) -> std::io::Result<bool> {
        match self {
            Conn::Tcp(stream) => mbap_exchange(stream, tid, slave, pdu, reply).await,
            Conn::Tls(stream) => mbap_exchange(stream.as_mut(), tid, slave, pdu, reply).await,
            Conn::RtuOverTcp(stream) => {
                stream.write_all(&rtu::encode(slave, pdu)).await?;
                // Address and function, then the rest by the reply's own length.
                stream.read_exact(&mut reply[..3]).await?;
                let len = match rtu::reply_len(&reply[..3], slave, pdu) {
                    rtu::FrameLen::Exact(n) => n,
                    _ => return Ok(false),
                };
                stream.read_exact(&mut reply[3..len]).await?;
                Ok(rtu::crc_ok(&reply[..len]) && reply[1] & 0x80 == 0)
            }
            Conn::Udp(socket) => {
                socket.send(&mbap(tid, slave, pdu)).await?;
                let len = socket.recv(reply).await?;
                Ok(len > 7 && reply[..2] == tid.to_be_bytes() && reply[7] & 0x80 == 0)
            }
        }
    }
}

/// The MBAP request for `pdu` to `unit`.
fn mbap(tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut adu = Vec::with_capacity(7 + pdu.len());
    adu.extend_from_slice(&tid.to_be_bytes());
    adu.extend_from_slice(&[0, 0]);
    adu.extend_from_slice(&u16::try_from(pdu.len() + 1).unwrap_or(0).to_be_bytes());
    adu.push(unit);
    adu.extend_from_slice(pdu);
    adu
}

/// One master's loop: request, reply, again (after `period` from the last request, if not
/// zero), until `stop`. Returns (completed at, latency).
async fn master(
    mut conn: Conn,
    index: usize,
    load: Load,
    period: Duration,
    stop: Arc<AtomicBool>,
) -> std::io::Result<Vec<(Instant, Duration, bool)>> {
    let mut done = Vec::new();
    let mut slave = match load {
        Load::Same | Load::Own => 1,
        _ => u8::try_from(index % usize::from(SLAVES)).unwrap_or(0) + 1,
    };
    // Its own block, 10 registers from 10 x index, so that no two masters' reads are identical
    // and none is coalesced (but in `Same`): the same length as READ_10, the same time on the
    // line.
    let [hi, lo] = u16::try_from(index * 10).unwrap_or(0).to_be_bytes();
    let own = [0x03, hi, lo, 0x00, 0x0A];
    let mut tid: u16 = 0;
    let mut reply = vec![0u8; 512];
    let mut next = tokio::time::Instant::now();
    while !stop.load(Ordering::Relaxed) {
        if !period.is_zero() {
            tokio::time::sleep_until(next).await;
            next += period;
        }
        tid = tid.wrapping_add(1);
        let write = load == Load::Mix && tid.is_multiple_of(4);
        let pdu: &[u8] = if write {
            &WRITE_1
        } else if load == Load::Same {
            &READ_10
        } else {
            &own
        };
        let sent = Instant::now();
        if !conn.exchange(tid, slave, pdu, &mut reply).await? {
            return Err(std::io::Error::other(format!(
                "master {index}: unexpected reply {:02X?}",
                &reply[..16]
            )));
        }
        let now = Instant::now();
        done.push((now, now - sent, write));
        if !matches!(load, Load::Same | Load::Own) {
            slave = slave % SLAVES + 1;
        }
    }
    Ok(done)
}

fn percentile(sorted: &[Duration], p: f64) -> Option<f64> {
    let last = sorted.len().checked_sub(1)?;
    let rank = (last as f64 * p).round() as usize;
    Some(sorted[rank].as_secs_f64() * 1e3)
}

/// A TLS session with the gateway's TLS listener at `listen`, presenting the master certificate.
async fn tls_connect(listen: SocketAddr, pki: &tls::Pki) -> std::io::Result<TlsStream<TcpStream>> {
    let stream = TcpStream::connect(listen).await?;
    stream.set_nodelay(true)?;
    let name = ServerName::IpAddress(listen.ip().into());
    pki.connector.connect(name, stream).await
}

/// `n` masters of `kind` (the three kinds in turn for `Kind::Mixed`), connected one after
/// another, and how long each connection took to set up (TCP connect to connected, or to the TLS
/// handshake complete; none for UDP).
async fn connect_all(
    gateway: &Gateway,
    kind: Kind,
    n: usize,
) -> Result<(Vec<Conn>, Vec<Duration>), String> {
    let failed = |e: std::io::Error| format!("connect: {e} (raise `ulimit -n` for many masters)");
    let kinds = [Kind::Tcp, Kind::RtuOverTcp, Kind::Udp];
    let mut conns = Vec::with_capacity(n);
    let mut setup = Vec::with_capacity(n);
    for i in 0..n {
        let kind = if kind == Kind::Mixed {
            kinds[i % 3]
        } else {
            kind
        };
        let began = Instant::now();
        conns.push(match kind {
            Kind::Udp => {
                let socket = UdpSocket::bind("127.0.0.1:0").await.map_err(failed)?;
                socket.connect(gateway.listen_udp).await.map_err(failed)?;
                Conn::Udp(socket)
            }
            Kind::RtuOverTcp => {
                let stream = TcpStream::connect(gateway.listen_rtu_over_tcp)
                    .await
                    .map_err(failed)?;
                stream.set_nodelay(true).map_err(|e| e.to_string())?;
                Conn::RtuOverTcp(stream)
            }
            Kind::Tcp | Kind::Mixed => {
                let stream = TcpStream::connect(gateway.listen).await.map_err(failed)?;
                stream.set_nodelay(true).map_err(|e| e.to_string())?;
                Conn::Tcp(stream)
            }
            Kind::Tls => {
                let (listen, pki) = gateway.tls.as_ref().ok_or("no TLS listener")?;
                let stream = tls_connect(*listen, pki)
                    .await
                    .map_err(|e| format!("master {i}: TLS: {e}"))?;
                Conn::Tls(Box::new(stream))
            }
        });
        if kind != Kind::Udp {
            setup.push(began.elapsed());
        }
    }
    Ok((conns, setup))
}

/// The priority master: a Modbus TCP connection from 127.0.0.2, which `server.priority` names.
async fn priority_connect(gateway: &Gateway) -> Result<Conn, String> {
    let failed = |e: std::io::Error| format!("priority master: {e}");
    let socket = TcpSocket::new_v4().map_err(failed)?;
    socket
        .bind(SocketAddr::new(PRIORITY_IP.into(), 0))
        .map_err(failed)?;
    let stream = socket.connect(gateway.listen).await.map_err(failed)?;
    stream.set_nodelay(true).map_err(failed)?;
    Ok(Conn::Tcp(stream))
}

/// A connection to the gateway's metrics endpoint at `addr` that has asked for `path` (the
/// server closes it after the answer, or keeps streaming); errors say they happened `doing`.
async fn http_get(addr: SocketAddr, path: &str, doing: &str) -> Result<TcpStream, String> {
    let failed = |e: std::io::Error| format!("{doing}: {e}");
    let mut stream = TcpStream::connect(addr).await.map_err(failed)?;
    let request = format!("GET {path} HTTP/1.1\r\nHost: bench\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.map_err(failed)?;
    Ok(stream)
}

/// The gateway's metrics page.
async fn scrape(addr: SocketAddr) -> Result<String, String> {
    let failed = |e: std::io::Error| format!("scraping the metrics: {e}");
    let mut stream = http_get(addr, "/metrics", "scraping the metrics").await?;
    let mut page = String::new();
    stream.read_to_string(&mut page).await.map_err(failed)?;
    Ok(page)
}

/// The sum of the samples of `name` on the bench's bus with every one of `labels`.
fn sample(page: &str, name: &str, labels: &[&str]) -> f64 {
    page.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let (series, value) = l.rsplit_once(' ')?;
            let (metric, set) = series.split_once('{').unwrap_or((series, ""));
            (metric == name
                && set.contains("bus=\"bench\"")
                && labels.iter().all(|x| set.contains(x)))
            .then(|| value.parse::<f64>().ok())?
        })
        .sum()
}

/// What the window's metrics say: line transactions, coalesced requests, and the queue wait's
/// sum and count by class.
#[derive(Default)]
struct Counters {
    line_tx: f64,
    coalesced: f64,
    wait: [(f64, f64); 2],
}

impl Counters {
    fn of(page: &str) -> Counters {
        let wait = |class| {
            let class = format!("class=\"{class}\"");
            (
                sample(page, "modbus_gateway_queue_wait_seconds_sum", &[&class]),
                sample(page, "modbus_gateway_queue_wait_seconds_count", &[&class]),
            )
        };
        Counters {
            line_tx: sample(page, "modbus_gateway_round_trip_seconds_count", &[]),
            coalesced: sample(page, "modbus_gateway_coalesced_requests_total", &[]),
            wait: [wait("normal"), wait("priority")],
        }
    }
}

async fn run(cli: &Cli, binary: &PathBuf, s: &Scenario) -> Result<Report, String> {
    let timing = LineTiming::new(&s.format);
    let (device, slave) = match s.line {
        Line::Sim => ("sim".to_owned(), None),
        Line::Pty => {
            let (path, task) = untimed_slave(&s.format)?;
            (path, Some(task))
        }
    };
    let gateway = Gateway::start(binary, s, &device).await?;
    let pid = gateway.pid();
    let cpu_before = cpu_time(pid);
    let (mut streams, mut setup) = connect_all(&gateway, s.kind, s.masters).await?;
    if s.priority.is_some() {
        streams.push(priority_connect(&gateway).await?);
    }
    // The gateway's side of the last handshake (a TLS 1.3 server checks the master's
    // certificate after the master is done) and of the last accept.
    tokio::time::sleep(Duration::from_millis(50)).await;
    let connect_cpu = cpu_time(pid) - cpu_before;
    setup.sort();
    let mut report = Report {
        scenario: s.name.clone(),
        baud: s.format.baud,
        masters: s.masters,
        transactions: 0,
        tx_per_s: 0.0,
        efficiency: None,
        p50_ms: None,
        p99_ms: None,
        max_ms: None,
        added_p50_ms: None,
        added_p99_ms: None,
        fairness: None,
        rss_mb: 0.0,
        cpu_us_per_tx: None,
        seconds: 0.0,
        connect_p50_ms: percentile(&setup, 0.5),
        connect_max_ms: setup.last().map(|d| d.as_secs_f64() * 1e3),
        connect_cpu_us: (!setup.is_empty())
            .then(|| connect_cpu.as_secs_f64() * 1e6 / setup.len() as f64),
        line_tx: None,
        line_tx_per_s: None,
        line_tx_per_answer: None,
        coalesced: None,
        physical_tx_per_s: None,
        answered_vs_physical: None,
        priority_tx: None,
        priority_p50_tmin: None,
        priority_p99_tmin: None,
        priority_max_tmin: None,
        priority_wait_p50_tmin: None,
        priority_wait_p99_tmin: None,
        others_share: None,
        queue_wait_priority_tmin: None,
        queue_wait_normal_tmin: None,
    };
    if s.load == Load::Idle {
        tokio::time::sleep(Duration::from_secs(2)).await;
        report.rss_mb = rss_mb(pid);
        drop(streams);
        if let Some(slave) = slave {
            slave.abort();
        }
        return Ok(report);
    }
    let read_min = s
        .framing
        .transaction_minimum(&timing, READ_10.len(), 2 + 20);
    let write_min = s
        .framing
        .transaction_minimum(&timing, WRITE_1.len(), WRITE_1.len());
    // Long enough for every master to complete `rounds` requests at the line's pace.
    let pace = if s.line == Line::Sim {
        read_min
    } else {
        timing.t35
    };
    // Masters reading the same block are answered together.
    let turns = if s.load == Load::Same { 1 } else { s.masters };
    let needed = pace * (cli.rounds * u32::try_from(turns).unwrap_or(u32::MAX));
    let length = Duration::from_secs_f64(cli.seconds).max(needed);
    let warm_up = Duration::from_secs(1).max(pace * u32::try_from(s.masters).unwrap_or(1));

    let _trace = match cli.trace {
        Some(how) => Some(watch_trace(gateway.metrics, how).await?),
        None => None,
    };
    let stop = Arc::new(AtomicBool::new(false));
    let tasks: Vec<_> = streams
        .into_iter()
        .enumerate()
        .map(|(i, stream)| {
            let period = if i == s.masters {
                s.priority.unwrap_or_default()
            } else {
                Duration::ZERO
            };
            tokio::spawn(master(stream, i, s.load, period, stop.clone()))
        })
        .collect();
    tokio::time::sleep(warm_up).await;
    let sim = s.line == Line::Sim;
    let before = if sim {
        Some(scrape(gateway.metrics).await?)
    } else {
        None
    };
    let (start, cpu_start) = (Instant::now(), cpu_time(pid));
    tokio::time::sleep(length).await;
    let (end, cpu_end) = (Instant::now(), cpu_time(pid));
    let after = if sim {
        Some(scrape(gateway.metrics).await?)
    } else {
        None
    };
    report.rss_mb = rss_mb(pid);
    stop.store(true, Ordering::Relaxed);

    let mut latencies = Vec::new();
    let mut per_master = Vec::with_capacity(s.masters);
    let mut physical = Duration::ZERO;
    let mut priority = Vec::new();
    for (i, task) in tasks.into_iter().enumerate() {
        let done = task
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| e.to_string())?;
        let within: Vec<_> = done
            .into_iter()
            .filter(|(at, _, _)| *at >= start && *at <= end)
            .collect();
        if i == s.masters {
            priority = within.iter().map(|(_, latency, _)| *latency).collect();
        } else {
            per_master.push(within.len() as f64);
        }
        for (_, latency, write) in within {
            latencies.push(latency);
            physical += if write { write_min } else { read_min };
        }
    }
    if let Some(slave) = slave {
        slave.abort();
    }
    let wall = (end - start).as_secs_f64();
    let transactions = latencies.len() as u64;
    latencies.sort();
    let sum: f64 = per_master.iter().sum();
    let squares: f64 = per_master.iter().map(|x| x * x).sum();
    report.transactions = transactions;
    report.tx_per_s = transactions as f64 / wall;
    report.seconds = wall;
    report.p50_ms = percentile(&latencies, 0.5);
    report.p99_ms = percentile(&latencies, 0.99);
    report.max_ms = latencies.last().map(|d| d.as_secs_f64() * 1e3);
    report.fairness =
        (s.masters > 1 && squares > 0.0).then(|| sum * sum / (per_master.len() as f64 * squares));
    let t_min = read_min.as_secs_f64();
    if s.priority.is_some() {
        priority.sort();
        let in_tmin = |p| percentile(&priority, p).map(|ms| ms / 1e3 / t_min);
        report.priority_tx = Some(priority.len() as u64);
        report.priority_p50_tmin = in_tmin(0.5);
        report.priority_p99_tmin = in_tmin(0.99);
        report.priority_max_tmin = in_tmin(1.0);
        report.priority_wait_p50_tmin = in_tmin(0.5).map(|t| t - 1.0);
        report.priority_wait_p99_tmin = in_tmin(0.99).map(|t| t - 1.0);
        report.others_share = (transactions > 0)
            .then(|| (transactions - priority.len() as u64) as f64 / transactions as f64);
    }
    if let (Some(before), Some(after)) = (before, after) {
        let (before, after) = (Counters::of(&before), Counters::of(&after));
        let line_tx = after.line_tx - before.line_tx;
        report.line_tx = Some(line_tx as u64);
        report.line_tx_per_s = Some(line_tx / wall);
        report.line_tx_per_answer = (transactions > 0).then(|| line_tx / transactions as f64);
        report.coalesced = Some((after.coalesced - before.coalesced) as u64);
        report.physical_tx_per_s = Some(1.0 / t_min);
        if s.load == Load::Same {
            report.answered_vs_physical = Some(report.tx_per_s * t_min / s.masters as f64);
        }
        let mean_wait = |class: usize| {
            let (sum, count) = (
                after.wait[class].0 - before.wait[class].0,
                after.wait[class].1 - before.wait[class].1,
            );
            (count > 0.0).then(|| sum / count / t_min)
        };
        report.queue_wait_normal_tmin = mean_wait(0);
        report.queue_wait_priority_tmin = mean_wait(1);
    }
    report.cpu_us_per_tx =
        (transactions > 0).then(|| (cpu_end - cpu_start).as_secs_f64() * 1e6 / transactions as f64);
    if s.line == Line::Sim {
        report.efficiency = Some(physical.as_secs_f64() / wall);
        // Coalesced reads took no time of the line: count its transactions instead.
        if s.load == Load::Same {
            report.efficiency = report.line_tx.map(|tx| tx as f64 * t_min / wall);
        }
        if s.masters == 1 && s.load == Load::Read {
            let floor = read_min.as_secs_f64() * 1e3;
            report.added_p50_ms = report.p50_ms.map(|p| p - floor);
            report.added_p99_ms = report.p99_ms.map(|p| p - floor);
        }
    }
    Ok(report)
}

fn cell(value: Option<f64>, precision: usize) -> String {
    value.map_or("-".into(), |v| format!("{v:.precision$}"))
}

/// The many-masters scenarios' own columns: answered reads against the line's transactions.
fn print_line_table(reports: &[Report]) {
    let rows: Vec<_> = reports
        .iter()
        .filter(|r| r.scenario.starts_with("many-") && r.line_tx.is_some())
        .collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "\n{:<30} {:>7} {:>10} {:>10} {:>8} {:>10} {:>9} {:>9}",
        "scenario",
        "masters",
        "answered/s",
        "line tx/s",
        "phys/s",
        "ans/(K*phys)",
        "tx/answer",
        "coalesced"
    );
    for r in rows {
        println!(
            "{:<30} {:>7} {:>10.1} {:>10} {:>8.2} {:>12} {:>9} {:>9}",
            r.scenario,
            r.masters,
            r.tx_per_s,
            cell(r.line_tx_per_s, 2),
            r.physical_tx_per_s.unwrap_or_default(),
            cell(r.answered_vs_physical, 3),
            cell(r.line_tx_per_answer, 4),
            r.coalesced.map_or("-".into(), |c| c.to_string()),
        );
    }
}

/// The priority scenarios' own columns, in transaction times (t_min).
fn print_priority_table(reports: &[Report]) {
    let rows: Vec<_> = reports.iter().filter(|r| r.priority_tx.is_some()).collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "\n{:<30} {:>7} {:>8} {:>8} {:>8} {:>9} {:>9} {:>10} {:>10} {:>8}",
        "scenario (t_min units)",
        "prio tx",
        "lat p50",
        "lat p99",
        "lat max",
        "wait p50",
        "wait p99",
        "gw wait P",
        "gw wait N",
        "others"
    );
    for r in rows {
        println!(
            "{:<30} {:>7} {:>8} {:>8} {:>8} {:>9} {:>9} {:>10} {:>10} {:>8}",
            r.scenario,
            r.priority_tx.unwrap_or_default(),
            cell(r.priority_p50_tmin, 2),
            cell(r.priority_p99_tmin, 2),
            cell(r.priority_max_tmin, 2),
            cell(r.priority_wait_p50_tmin, 2),
            cell(r.priority_wait_p99_tmin, 2),
            cell(r.queue_wait_priority_tmin, 2),
            cell(r.queue_wait_normal_tmin, 1),
            cell(r.others_share, 3),
        );
    }
}

#[tokio::main]
async fn main() -> ExitCode {
    let cli = Cli::parse();
    // As in the daemon: the untimed slave's replies are due at once, and tokio's timer would
    // hold each one to the next whole millisecond.
    modbus_gateway::timer::use_precise_timer();
    let all = scenarios();
    if cli.list {
        for s in &all {
            println!("{}", s.name);
        }
        return ExitCode::SUCCESS;
    }
    let chosen: Vec<&Scenario> = all
        .iter()
        .filter(|s| {
            cli.scenarios.is_empty()
                || cli.scenarios.iter().any(|c| {
                    s.name == *c
                        || s.name
                            .strip_prefix(c.as_str())
                            .is_some_and(|r| r.starts_with('-'))
                })
        })
        .collect();
    if chosen.is_empty() {
        eprintln!("modbus-gateway-bench: no scenario matches; see --list");
        return ExitCode::from(2);
    }
    let binary = cli.gateway.clone().unwrap_or_else(|| {
        std::env::current_exe()
            .map(|exe| exe.with_file_name("modbus-gateway"))
            .unwrap_or_else(|_| PathBuf::from("modbus-gateway"))
    });
    if !cli.json {
        println!(
            "{:<30} {:>7} {:>9} {:>6} {:>6} {:>8} {:>8} {:>8} {:>8} {:>6} {:>7} {:>8} {:>8} {:>8} {:>8}",
            "scenario",
            "masters",
            "tx",
            "tx/s",
            "eff",
            "p50 ms",
            "p99 ms",
            "max ms",
            "+p50 ms",
            "jain",
            "rss MB",
            "cpu us/tx",
            "conn p50",
            "conn max",
            "cpu us/conn"
        );
    }
    let mut failed = false;
    let mut reports = Vec::new();
    for s in chosen {
        match run(&cli, &binary, s).await {
            Ok(r) if cli.json => match serde_json::to_string(&r) {
                Ok(line) => println!("{line}"),
                Err(e) => {
                    eprintln!("{}: {e}", s.name);
                    failed = true;
                }
            },
            Ok(r) => {
                println!(
                "{:<30} {:>7} {:>9} {:>6.1} {:>6} {:>8} {:>8} {:>8} {:>8} {:>6} {:>7.1} {:>8} {:>8} {:>8} {:>8}",
                r.scenario,
                r.masters,
                r.transactions,
                r.tx_per_s,
                cell(r.efficiency, 3),
                cell(r.p50_ms, 2),
                cell(r.p99_ms, 2),
                cell(r.max_ms, 1),
                cell(r.added_p50_ms, 2),
                cell(r.fairness, 3),
                r.rss_mb,
                cell(r.cpu_us_per_tx, 1),
                cell(r.connect_p50_ms, 2),
                cell(r.connect_max_ms, 2),
                cell(r.connect_cpu_us, 0),
                );
                reports.push(r);
            }
            Err(e) => {
                eprintln!("{}: {e}", s.name);
                failed = true;
            }
        }
    }
    print_line_table(&reports);
    print_priority_table(&reports);
    if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    }
}
