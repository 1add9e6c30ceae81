//! The gateway under test as a process: its configuration written for the scenario, the binary
//! started on it and stopped when dropped, and what /proc says of its CPU time and memory.

use crate::journal::JournalDir;
use crate::listen;
use crate::plant;
use crate::scenarios::{Journal, Kind, Line, Load, Scenario, PRIORITY_IP, SLAVES};
use crate::virtual_unit;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use test_support::tls::{Pki, Role};
use test_support::{Bus, GatewayConfig};
use tokio::net::TcpStream;
use tokio_rustls::client::TlsStream;
use tokio_rustls::rustls::pki_types::ServerName;
use tokio_rustls::TlsConnector;

/// The bench's bus's name.
pub(crate) const BUS: &str = "bench";
/// The role of the bench's master certificate, given read-only access in `[server.tls]`.
const ROLE: &str = "bench";
/// How long the gateway (or the device server's `simulate`) may take to listen.
pub(crate) const START_LIMIT: Duration = Duration::from_secs(10);

/// The TLS listener of a TLS scenario, and the masters' way in: a connector that trusts the
/// scenario's CA and presents the master certificate.
pub(crate) struct Tls {
    pub(crate) listen: SocketAddr,
    pub(crate) connector: TlsConnector,
    /// The certificates' files, removed when dropped.
    _pki: Pki,
}

/// The gateway process, stopped when dropped.
pub(crate) struct Gateway {
    child: Child,
    pub(crate) listen: SocketAddr,
    pub(crate) listen_rtu_over_tcp: SocketAddr,
    pub(crate) listen_udp: SocketAddr,
    pub(crate) metrics: SocketAddr,
    /// The TLS listener and the certificates (TLS scenarios only).
    pub(crate) tls: Option<Tls>,
    /// The audit journal's directory, if it keeps one; removed after the gateway is stopped.
    pub(crate) journal: Option<JournalDir>,
    /// The link to the pty of its serial master port (`priority_on_port` scenarios), which the
    /// priority master opens; removed when dropped, as a killed gateway leaves it.
    pub(crate) port: Option<TempPath>,
    _config: TempPath,
}

impl Drop for Gateway {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A file removed when dropped.
pub(crate) struct TempPath(pub(crate) PathBuf);

impl Drop for TempPath {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// `config` with the scenario's serial master port, if its priority master sits on one: a
/// `pty:` port with `priority = true` at the bus's baud rate (a pty takes no parity), and its
/// link.
fn serial_port(scenario: &Scenario, config: GatewayConfig) -> (GatewayConfig, Option<TempPath>) {
    if !scenario.priority_on_port {
        return (config, None);
    }
    let link = TempPath(std::env::temp_dir().join(format!(
        "mbgw-bench-port-{}-{}",
        std::process::id(),
        scenario.name
    )));
    let config = config.server_table(&format!(
        "[[server.serial]]\nname = \"bench\"\ndevice = \"pty:{}\"\nbaud = {}\n\
         parity = \"none\"\nstop_bits = 1\npriority = true\nanswer_within = \"1s\"\n",
        link.0.display(),
        scenario.format.baud
    ));
    (config, Some(link))
}

pub(crate) fn free_addr() -> std::io::Result<SocketAddr> {
    std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()
}

/// A private PKI for `scenario` (ECDSA P-256, rcgen's default key): a CA, the gateway's
/// certificate for 127.0.0.1, and one master certificate with the read-only role, in a
/// directory named after the scenario.
fn tls_for(scenario: &str, listen: SocketAddr) -> (String, Tls) {
    let dir =
        std::env::temp_dir().join(format!("mbgw-bench-tls-{}-{scenario}", std::process::id()));
    let pki = Pki::in_dir(dir, "modbus-gateway-bench CA");
    let server = pki.server("server", "modbus-gateway", 3650);
    let master = pki.master("bench-master", Role::Named(ROLE));
    let table = pki.tls_table(&server, &format!("roles = {{ {ROLE} = \"read_only\" }}"));
    let connector = pki.connector(Some(&master));
    let tls = Tls {
        listen,
        connector,
        _pki: pki,
    };
    (table, tls)
}

/// The bench's bus on `device`: the scenario's line (its serial format, but for a Modbus TCP
/// device), a queue for every master twice over, the plant values' `[[bus.slave]]`s in the
/// `values-` and `mqtt-` scenarios, and the simulated slaves if `device` is the simulated line;
/// in the `virtual-unit-` scenario, the demo's drives instead, each polled by its template.
pub(crate) fn bus(scenario: &Scenario, device: &str) -> Bus {
    let f = &scenario.format;
    let masters = connections(scenario);
    let mut bus = Bus::on(BUS, device)
        .framing(scenario.framing.name())
        .key("queue_depth", masters * 2 + 16)
        .key("queue_timeout", "1h");
    // A Modbus TCP device has no serial format.
    if scenario.line != Line::TcpDevice {
        bus = bus
            .baud(f.baud)
            .key("data_bits", f.data_bits)
            .parity(f.parity.name())
            .key("stop_bits", f.stop_bits);
    }
    if let Some(timeout) = scenario.byte_timeout {
        bus = bus.key("byte_timeout", format!("{}ms", timeout.as_millis()));
    }
    if !scenario.coalesce {
        bus = bus.key("coalesce_reads", false);
    }
    if scenario.in_flight > 1 {
        bus = bus.key("max_in_flight", scenario.in_flight);
    }
    if matches!(scenario.load, Load::Values | Load::Mqtt) {
        bus = bus.text(&plant::slaves());
    }
    if scenario.load == Load::Virtual {
        bus = virtual_unit::drives(bus);
    } else if scenario.load == Load::Listen {
        bus = listen::line(bus);
    } else if device == "sim" {
        bus = bus.sim_slaves(&format!("1-{SLAVES}"));
    }
    bus
}

/// The masters the bench connects in `scenario`: at least one, and the priority master.
fn connections(scenario: &Scenario) -> usize {
    scenario.masters.max(1) + usize::from(scenario.priority.is_some())
}

impl Gateway {
    /// The gateway binary at `binary`, started on a configuration for `scenario` with its bus on
    /// `device` and its audit journal (if the scenario has one) in `journal`, once it listens.
    pub(crate) async fn start(
        binary: &Path,
        scenario: &Scenario,
        device: &str,
        journal: Option<JournalDir>,
    ) -> Result<Gateway, String> {
        Gateway::start_with(binary, scenario, device, journal, "").await
    }

    /// As [`Gateway::start`], with `tables` (TOML: whole tables, such as `[mqtt]`) at the end of
    /// its configuration.
    pub(crate) async fn start_with(
        binary: &Path,
        scenario: &Scenario,
        device: &str,
        journal: Option<JournalDir>,
        tables: &str,
    ) -> Result<Gateway, String> {
        let listen = free_addr().map_err(|e| e.to_string())?;
        let listen_rtu_over_tcp = free_addr().map_err(|e| e.to_string())?;
        let listen_udp = std::net::UdpSocket::bind("127.0.0.1:0")
            .and_then(|s| s.local_addr())
            .map_err(|e| e.to_string())?;
        let metrics = free_addr().map_err(|e| e.to_string())?;
        let masters = connections(scenario);
        let mut config = GatewayConfig::new()
            .listen(listen)
            .listen_rtu_over_tcp(listen_rtu_over_tcp)
            .listen_udp(listen_udp)
            .max_connections(masters + 16);
        if scenario.priority.is_some() {
            config = config.server("priority", [PRIORITY_IP.to_string().as_str()]);
        }
        let tls = if scenario.kind == Kind::Tls {
            let listen_tls = free_addr().map_err(|e| e.to_string())?;
            let (table, tls) = tls_for(&scenario.name, listen_tls);
            config = config
                .server("listen_tls", [listen_tls.to_string().as_str()])
                .server_table(&table);
            Some(tls)
        } else {
            None
        };
        let (mut config, port) = serial_port(scenario, config);
        if let Some(journal) = &journal {
            let path = journal.file().to_string_lossy().into_owned();
            let fsync = scenario.journal == Journal::Fsync;
            config = config.table("audit", &[("path", path.into()), ("fsync", fsync.into())]);
        }
        let config = config
            .metrics_listen(metrics)
            .table("log", &[("level", "warn".into())])
            .bus(bus(scenario, device));
        let path = std::env::temp_dir().join(format!(
            "mbgw-bench-{}-{}.toml",
            std::process::id(),
            scenario.name
        ));
        let mut text = config.to_toml();
        if scenario.load == Load::Virtual {
            text.push_str(&virtual_unit::table(BUS));
        }
        text.push_str(tables);
        std::fs::write(&path, text).map_err(|e| e.to_string())?;
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
            journal,
            port,
            _config: TempPath(path),
        };
        gateway.until_listening().await?;
        Ok(gateway)
    }

    /// Wait (at most [`START_LIMIT`]) until the gateway accepts Modbus TCP and, in a TLS
    /// scenario, completes a TLS handshake.
    async fn until_listening(&self) -> Result<(), String> {
        let started = Instant::now();
        while TcpStream::connect(self.listen).await.is_err() {
            if started.elapsed() > START_LIMIT {
                return Err("the gateway did not start listening within 10 s".into());
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        if let Some(link) = &self.port {
            while !link.0.exists() {
                if started.elapsed() > START_LIMIT {
                    return Err("the gateway did not link its serial port's pty within 10 s".into());
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
        // The TLS listener may come up later: a whole handshake, as a bare connection closed
        // at once would be logged as a failed one.
        if let Some(tls) = &self.tls {
            while tls_connect(tls).await.is_err() {
                if started.elapsed() > START_LIMIT {
                    return Err("the gateway did not start its TLS listener within 10 s".into());
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
        Ok(())
    }

    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }
}

/// A TLS session with the gateway's TLS listener, presenting the master certificate.
pub(crate) async fn tls_connect(tls: &Tls) -> std::io::Result<TlsStream<TcpStream>> {
    let stream = TcpStream::connect(tls.listen).await?;
    stream.set_nodelay(true)?;
    let name = ServerName::IpAddress(tls.listen.ip().into());
    tls.connector.connect(name, stream).await
}

/// CPU time of process `pid` so far, all its threads: the first field of each thread's
/// schedstat, in nanoseconds (the tick counts of /proc/PID/stat are only 10 ms fine).
pub(crate) fn cpu_time(pid: u32) -> Duration {
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
pub(crate) fn rss_mb(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1024.0)
}
