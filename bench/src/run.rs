//! One scenario's run: the gateway started, the masters connected, a warm-up, then a window in
//! which the masters' completions, the gateway's CPU time, (on a timed line) its metrics and
//! (with an audit journal) the journal's growth are taken; on the tcp-device line with reads, one
//! direct client before and modbus-proxy after; with no master but plant values to poll, `plant`'s;
//! with masters reading a virtual unit, a wait first until it answers (`virtual_unit`); with the
//! plant values published over MQTT, `mqtt`'s, which starts its own two gateways; on a
//! listen-only line, `listen`'s.
//! The figures are `report`'s.

use crate::beside;
use crate::device_server::DeviceServer;
use crate::gateway::{cpu_time, rss_mb, Gateway};
use crate::journal::JournalDir;
use crate::listen;
use crate::masters::{connect_all, master, priority_connect, untimed_slave, Done, Served};
use crate::mqtt;
use crate::plant;
use crate::report::Report;
use crate::scenarios::{Journal, Line, Load, Scenario, READ_10, WRITE_1};
use crate::tcp_device::TcpDevice;
use crate::virtual_unit;
use crate::watch::{scrape, watch_trace, Scraped, Scraper};
use crate::Cli;
use modbus_gateway::testing::line::LineTiming;
use std::ops::RangeInclusive;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The physical minimum of one transaction of the scenario's load, by the line's timing.
pub(crate) struct Minimum {
    pub(crate) read: Duration,
    pub(crate) write: Duration,
}

/// What the window saw.
pub(crate) struct Window {
    pub(crate) start: Instant,
    pub(crate) end: Instant,
    /// The gateway's CPU time across the window.
    pub(crate) cpu: Duration,
    /// The device server's (`simulate`'s) CPU time across the window, on that line.
    pub(crate) far_cpu: Option<Duration>,
    pub(crate) rss_mb: f64,
    /// Every master's completions, in the order the masters were connected (the priority
    /// master last); `start..=end` is the window's share.
    pub(crate) masters: Vec<Vec<Done>>,
    /// Requests answered with an exception within the window (the virtual load only: in any
    /// other, one ends the run).
    pub(crate) exceptions: u64,
    /// The metrics page at the window's start and end (timed lines only).
    pub(crate) metrics: Option<(String, String)>,
    /// The `--scrape` scraper's scrapes within the window.
    pub(crate) scrapes: Option<Vec<Scraped>>,
    /// How many bytes the audit journal grew by across the window, if there is one.
    pub(crate) journal_bytes: Option<u64>,
}

impl Minimum {
    fn of(s: &Scenario, timing: &LineTiming) -> Minimum {
        Minimum {
            read: s.framing.transaction_minimum(timing, READ_10.len(), 2 + 20),
            write: s
                .framing
                .transaction_minimum(timing, WRITE_1.len(), WRITE_1.len()),
        }
    }
}

/// What the scenario's line is, beyond the gateway: its `device` setting and what serves it.
struct FarEnd {
    device: String,
    /// The pty's slave, on that line.
    slave: Option<tokio::task::JoinHandle<()>>,
    far: Option<DeviceServer>,
    tcp: Option<TcpDevice>,
}

impl FarEnd {
    async fn start(binary: &Path, s: &Scenario) -> Result<FarEnd, String> {
        let (mut slave, mut far, mut tcp) = (None, None, None);
        let device = match s.line {
            Line::Sim => "sim".to_owned(),
            Line::Pty => {
                let (path, task) = untimed_slave(&s.format)?;
                slave = Some(task);
                path
            }
            Line::DeviceServer => far
                .insert(DeviceServer::start(binary, s).await?)
                .device
                .clone(),
            Line::TcpDevice => tcp.insert(TcpDevice::start(s.device_delay).await?).device(),
        };
        Ok(FarEnd {
            device,
            slave,
            far,
            tcp,
        })
    }
}

/// Run scenario `s` on the gateway binary at `binary`.
pub(crate) async fn run(cli: &Cli, binary: &Path, s: &Scenario) -> Result<Report, String> {
    if s.load == Load::Mqtt {
        // Two gateways of its own, one after the other, on the simulated line.
        let window = mqtt::measure(cli, binary, s, "sim").await?;
        return Ok(Report::mqtt(s, &window));
    }
    if s.load == Load::Listen {
        let window = listen::measure(cli, binary, s).await?;
        let mut report = Report::new(s, &[], Duration::ZERO);
        report.listen(&window);
        return Ok(report);
    }
    run_gateway(cli, binary, s).await
}

/// Run scenario `s` (any but the MQTT load) on one gateway, the binary at `binary`.
async fn run_gateway(cli: &Cli, binary: &Path, s: &Scenario) -> Result<Report, String> {
    let timing = LineTiming::new(&s.format);
    let FarEnd {
        device,
        slave,
        far,
        tcp,
    } = FarEnd::start(binary, s).await?;
    // The direct client first, on the device alone; it and modbus-proxy's masters read, so
    // they are the yardstick of reads only.
    let direct = match &tcp {
        Some(device) if s.load == Load::Read => Some(beside::direct(cli, device.addr).await?),
        _ => None,
    };
    let journal = match s.journal {
        Journal::Off => None,
        Journal::On | Journal::Fsync => Some(JournalDir::make(&cli.journal_dir(), &s.name)?),
    };
    let file_system = journal.as_ref().and_then(JournalDir::file_system);
    let gateway = Gateway::start(binary, s, &device, journal).await?;
    let listening = Instant::now();
    if s.load == Load::Virtual {
        virtual_unit::until_answered(&gateway).await?;
    }
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
    let mut report = Report::new(s, &setup, connect_cpu);
    if s.load == Load::Values {
        let far_pid = far.as_ref().map(DeviceServer::pid);
        report.plant(&plant::measure(cli, (&gateway, far_pid), listening).await?);
        return Ok(report);
    }
    if s.load == Load::Idle {
        tokio::time::sleep(Duration::from_secs(2)).await;
        report.rss_mb = rss_mb(pid);
        drop(streams);
        if let Some(slave) = slave {
            slave.abort();
        }
        return Ok(report);
    }
    let minimum = Minimum::of(s, &timing);
    // Long enough for every master to complete `rounds` requests at the line's pace; a read
    // answered from memory has none.
    let pace = match (s.load, s.line.timed()) {
        (Load::Virtual, _) => Duration::ZERO,
        (_, true) => minimum.read,
        (_, false) => timing.t35,
    };
    let far_pid = far.as_ref().map(DeviceServer::pid);
    let window = measure(cli, (&gateway, far_pid), s, streams, pace).await?;
    if let Some(slave) = slave {
        slave.abort();
    }
    report.measured(s, &window, &minimum);
    report.journal_kept(file_system);
    if let (Some(device), Some(direct)) = (&tcp, direct) {
        // modbus-proxy alone in front of the device, as the gateway was.
        drop(gateway);
        let proxy = beside::through_proxy(cli, s.masters, device.addr).await?;
        report.beside(s, &direct, proxy.as_ref());
    }
    Ok(report)
}

/// Start the masters on `streams`, warm up, and take the window; `far` is the device server's
/// process, if the line has one.
async fn measure(
    cli: &Cli,
    (gateway, far): (&Gateway, Option<u32>),
    s: &Scenario,
    streams: Vec<crate::masters::Conn>,
    pace: Duration,
) -> Result<Window, String> {
    let pid = gateway.pid();
    // Masters reading the same block are answered together.
    let turns = if s.load == Load::Same { 1 } else { s.masters };
    let needed = pace * (cli.rounds * u32::try_from(turns).unwrap_or(u32::MAX));
    let length = Duration::from_secs_f64(cli.seconds).max(needed);
    let warm_up = Duration::from_secs(1).max(pace * u32::try_from(s.masters).unwrap_or(1));

    let _trace = match cli.trace {
        Some(how) => Some(watch_trace(gateway.metrics, how).await?),
        None => None,
    };
    let scraper = cli.scrape.then(|| Scraper::start(gateway.metrics));
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
    let timed = s.line.timed();
    let before = if timed {
        Some(scrape(gateway.metrics).await?)
    } else {
        None
    };
    let far_start = far.map(cpu_time);
    let journal_start = gateway.journal.as_ref().map(JournalDir::bytes);
    let (start, cpu_start) = (Instant::now(), cpu_time(pid));
    tokio::time::sleep(length).await;
    let (end, cpu_end) = (Instant::now(), cpu_time(pid));
    let journal_end = gateway.journal.as_ref().map(JournalDir::bytes);
    let far_cpu = far.map(cpu_time).zip(far_start).map(|(e, s)| e - s);
    let after = if timed {
        Some(scrape(gateway.metrics).await?)
    } else {
        None
    };
    let rss_mb = rss_mb(pid);
    stop.store(true, Ordering::Relaxed);
    let scrapes = scraper.map(|scraper| scraper.within(start, end));
    let (masters, exceptions) = join(tasks, start..=end).await?;
    Ok(Window {
        start,
        end,
        cpu: cpu_end - cpu_start,
        far_cpu,
        rss_mb,
        masters,
        exceptions,
        metrics: before.zip(after),
        scrapes,
        journal_bytes: journal_end
            .zip(journal_start)
            .map(|(e, s)| e.saturating_sub(s)),
    })
}

/// The masters' completions, once each has stopped, in order; and how many of their requests
/// were answered with an exception within `window`.
async fn join(
    tasks: Vec<tokio::task::JoinHandle<std::io::Result<Served>>>,
    window: RangeInclusive<Instant>,
) -> Result<(Vec<Vec<Done>>, u64), String> {
    let mut masters = Vec::with_capacity(tasks.len());
    let mut exceptions = 0;
    for task in tasks {
        let served = task
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| e.to_string())?;
        let within = served.exceptions.iter().filter(|&&at| window.contains(&at));
        exceptions += within.count() as u64;
        masters.push(served.done);
    }
    Ok((masters, exceptions))
}
