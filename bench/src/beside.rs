//! What the tcp-device scenarios measure beside the gateway, on the same in-process device: one
//! client reading from the device directly (no gateway), and the scenario's masters through
//! modbus-proxy, a separate program (run as a process, never linked), if it is installed. The
//! direct client is a process of its own (this program again, `--direct-client`), as a master
//! is: a client in the device's own process would cross no process boundary at all, and the
//! gateway's masters cross two to reach it and two to come back. The masters' loop here
//! (`drive_every`) also drives the `mqtt-` scenarios' masters, each reading at a period beside
//! the gateway's polls and publishing.

use crate::gateway::{cpu_time, free_addr, START_LIMIT};
use crate::masters::{master, Conn, Done};
use crate::scenarios::Load;
use crate::Cli;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitCode, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpStream;

/// Where the bench looks for modbus-proxy unless told: a venv in the target directory, the
/// parent of this program's own (`python3 -m venv target/modbus-proxy-venv`).
const PROXY_IN_TARGET: &str = "modbus-proxy-venv/bin/modbus-proxy";
/// Masters reading back to back before the window opens.
const WARM_UP: Duration = Duration::from_secs(1);
/// The flag that makes this program the direct client instead of the bench: `--direct-client
/// ADDR SECONDS`.
pub(crate) const DIRECT_FLAG: &str = "--direct-client";

/// One load's figures in its window.
pub(crate) struct Driven {
    /// The window (none for the direct client's, which is taken in its own process).
    pub(crate) window: Option<(Instant, Instant)>,
    pub(crate) tx_per_s: f64,
    /// Latencies, sorted.
    pub(crate) latencies: Vec<Duration>,
    /// The CPU time across the window of the process in between, if there is one.
    pub(crate) cpu: Option<Duration>,
}

/// Modbus TCP masters on `conns` reading back to back: a warm-up, then a window of `seconds`,
/// across which the CPU time of process `pid` (if any) is taken.
async fn drive(seconds: f64, conns: Vec<Conn>, pid: Option<u32>) -> Result<Driven, String> {
    drive_every(seconds, conns, pid, Duration::ZERO).await
}

/// Modbus TCP masters on `conns` reading back to back, or each one read every `period` (if not
/// zero), the masters' turns spread evenly over it: a warm-up, then a window of `seconds`,
/// across which the CPU time of process `pid` (if any) is taken.
pub(crate) async fn drive_every(
    seconds: f64,
    conns: Vec<Conn>,
    pid: Option<u32>,
    period: Duration,
) -> Result<Driven, String> {
    let stop = Arc::new(AtomicBool::new(false));
    let n = u32::try_from(conns.len()).unwrap_or(u32::MAX).max(1);
    let tasks: Vec<_> = conns
        .into_iter()
        .enumerate()
        .map(|(i, conn)| {
            let stop = stop.clone();
            let offset = period * u32::try_from(i).unwrap_or(0) / n;
            tokio::spawn(async move {
                tokio::time::sleep(offset).await;
                master(conn, i, Load::Read, period, stop).await
            })
        })
        .collect();
    tokio::time::sleep(WARM_UP.max(period)).await;
    let (start, cpu_start) = (Instant::now(), pid.map(cpu_time));
    tokio::time::sleep(Duration::from_secs_f64(seconds)).await;
    let (end, cpu_end) = (Instant::now(), pid.map(cpu_time));
    stop.store(true, Ordering::Relaxed);
    let mut latencies = Vec::new();
    for task in tasks {
        let done: Vec<Done> = task
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| e.to_string())?
            .done;
        latencies.extend(
            done.iter()
                .filter(|(at, _, _)| (start..=end).contains(at))
                .map(|(_, latency, _)| *latency),
        );
    }
    latencies.sort();
    Ok(Driven {
        window: Some((start, end)),
        tx_per_s: latencies.len() as f64 / (end - start).as_secs_f64(),
        latencies,
        cpu: cpu_end.zip(cpu_start).map(|(e, s)| e - s),
    })
}

/// `n` Modbus TCP connections to `addr`.
pub(crate) async fn connect(addr: SocketAddr, n: usize) -> Result<Vec<Conn>, String> {
    let mut conns = Vec::with_capacity(n);
    for _ in 0..n {
        let stream = TcpStream::connect(addr)
            .await
            .map_err(|e| format!("connect to {addr}: {e}"))?;
        stream.set_nodelay(true).map_err(|e| e.to_string())?;
        conns.push(Conn::Tcp(stream));
    }
    Ok(conns)
}

/// One client reading from the device at `device` back to back, with nothing in between: this
/// program as `--direct-client`, in a process of its own, for the run's length. Its figures
/// come back on its stdout: the rate, then every latency in nanoseconds, one line each.
pub(crate) async fn direct(cli: &Cli, device: SocketAddr) -> Result<Driven, String> {
    let exe = std::env::current_exe().map_err(|e| format!("the bench's own path: {e}"))?;
    let child = Command::new(exe)
        .arg(DIRECT_FLAG)
        .arg(device.to_string())
        .arg(cli.seconds.to_string())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .spawn()
        .map_err(|e| format!("the direct client's process: {e}"))?;
    let waiting = tokio::task::spawn_blocking(move || child.wait_with_output());
    let limit = WARM_UP + Duration::from_secs_f64(cli.seconds) + START_LIMIT;
    let output = match tokio::time::timeout(limit, waiting).await {
        Ok(Ok(Ok(output))) if output.status.success() => output.stdout,
        Ok(Ok(Ok(output))) => return Err(format!("the direct client: {}", output.status)),
        Ok(Ok(Err(e))) => return Err(format!("the direct client: {e}")),
        Ok(Err(e)) => return Err(e.to_string()),
        Err(_) => return Err(format!("the direct client took more than {limit:?}")),
    };
    let text = String::from_utf8_lossy(&output);
    let mut lines = text.lines();
    let tx_per_s = lines.next().and_then(|rate| rate.parse().ok());
    let latencies: Option<Vec<Duration>> = lines
        .map(|nanos| nanos.parse().ok().map(Duration::from_nanos))
        .collect();
    match (tx_per_s, latencies) {
        (Some(tx_per_s), Some(latencies)) => Ok(Driven {
            window: None,
            tx_per_s,
            latencies,
            cpu: None,
        }),
        _ => Err("the direct client's figures do not parse".into()),
    }
}

/// Be the direct client (`--direct-client ADDR SECONDS`): one connection to the device at ADDR
/// reading back to back on one thread, as [`direct`] reads its figures.
pub(crate) fn direct_here(args: &[String]) -> ExitCode {
    let (Some(Ok(device)), Some(Ok(seconds))) = (
        args.first().map(|a| a.parse::<SocketAddr>()),
        args.get(1).map(|s| s.parse::<f64>()),
    ) else {
        eprintln!("usage: modbus-gateway-bench {DIRECT_FLAG} ADDR SECONDS");
        return ExitCode::from(2);
    };
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build();
    let driven = runtime.map_err(|e| e.to_string()).and_then(|runtime| {
        runtime.block_on(async { drive(seconds, connect(device, 1).await?, None).await })
    });
    match driven {
        Ok(driven) => {
            let mut out = format!("{}\n", driven.tx_per_s);
            for latency in &driven.latencies {
                out.push_str(&format!("{}\n", latency.as_nanos()));
            }
            print!("{out}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("the direct client: {e}");
            ExitCode::FAILURE
        }
    }
}

/// The modbus-proxy program the run uses: `--modbus-proxy`, or the one in the target directory.
fn proxy_program(cli: &Cli) -> Option<PathBuf> {
    cli.modbus_proxy.clone().or_else(|| {
        let exe = std::env::current_exe().ok()?;
        Some(exe.parent()?.parent()?.join(PROXY_IN_TARGET))
    })
}

/// modbus-proxy in front of `device`, listening on `listen`, stopped when dropped.
struct Proxy(Child);

impl Drop for Proxy {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Proxy {
    async fn start(
        program: &Path,
        listen: SocketAddr,
        device: SocketAddr,
    ) -> Result<Proxy, String> {
        let child = Command::new(program)
            .arg("--bind")
            .arg(format!("tcp://{listen}"))
            .arg("--modbus")
            .arg(format!("tcp://{device}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("{}: {e}", program.display()))?;
        let proxy = Proxy(child);
        let started = Instant::now();
        while TcpStream::connect(listen).await.is_err() {
            if started.elapsed() > START_LIMIT {
                return Err("modbus-proxy did not start listening within 10 s".into());
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        Ok(proxy)
    }
}

/// `masters` Modbus TCP masters reading back to back through modbus-proxy in front of the device
/// at `device`, or nothing (and why, on stderr) if the program is not there.
pub(crate) async fn through_proxy(
    cli: &Cli,
    masters: usize,
    device: SocketAddr,
) -> Result<Option<Driven>, String> {
    let Some(program) = proxy_program(cli).filter(|p| p.is_file()) else {
        eprintln!(
            "modbus-proxy not found (--modbus-proxy, or python3 -m venv target/modbus-proxy-venv \
             and its pip install modbus-proxy): measured without it"
        );
        return Ok(None);
    };
    let listen = free_addr().map_err(|e| e.to_string())?;
    let proxy = Proxy::start(&program, listen, device).await?;
    let conns = connect(listen, masters).await?;
    let driven = drive(cli.seconds, conns, Some(proxy.0.id())).await?;
    Ok(Some(driven))
}
