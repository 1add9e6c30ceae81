//! `modbus-gateway-bench`: measures the gateway against the physics of its line. For each
//! scenario it starts the `modbus-gateway` binary (the one next to this one, or `--gateway`) on a
//! generated configuration, drives N concurrent Modbus TCP masters from this process for a fixed
//! time, and reports transactions per second, bus efficiency (the physical minimum of every
//! completed transaction over the wall time), latency percentiles, fairness (Jain's index over the
//! masters' completions), and the gateway process's own RSS and CPU per transaction (from
//! /proc, so the masters' cost is not in it; the simulated slaves', inside the gateway, is, except
//! on the device-server line, whose simulated line runs in `simulate --listen` and is counted
//! apart). On a Modbus TCP device (the tcp-device scenarios), which has no line to measure against,
//! it measures the gateway beside one client reading from the device directly (this program
//! again, `--direct-client`, in a process of its own) and beside modbus-proxy, if installed.
//! With no master but 247 slaves' plant values to poll (the `values-` scenario, and its twin
//! behind a device server), it measures what polling costs the gateway, its memory, and each
//! page that serves the values. With the mixed load and the audit journal off, on, and synced to
//! the disk (the `-journal-` scenarios, run one after the other), it measures what the journal
//! costs each write against the same load without it. With 100 masters reading a virtual unit
//! (`virtual-unit-100`), answered from memory while the line polls the values it shows, it
//! measures the gateway's own rate, latency and CPU per read: no line time, so no efficiency.
//! With the `values-` scenario's slaves and their values published through a local mosquitto
//! (`mqtt-247x20`, every value again each 10 s, and `mqtt-1s-247x20`, each second), it measures
//! the first full publication, the rate of messages received and sent, the gateway's CPU and
//! memory against the same gateway without `[mqtt]`, the broker's CPU, and the latency of
//! masters reading beside it, with MQTT and without. On a listen-only line (`listen-115200`,
//! `mode = "listen"`) saturated by the simulated line's other master, it measures what the
//! gateway hears and pairs against what that master made, its CPU per observed transaction, and
//! a master reading the shadow; its twin ends frames by their lengths alone (`byte_timeout`).
//! A workspace member of its own: `cargo install` and the Debian package carry only the daemon.
//!
//! The modules, in the order a run goes through them: `scenarios` (what to measure),
//! `device_server` (the far end of the device-server line), `tcp_device` (the Modbus TCP device
//! of the tcp-device line), `beside` (what is measured beside the gateway on that line: a direct
//! client, modbus-proxy), `journal` (the audit journal's directory, its file system and what a
//! sync costs there), `gateway` (the process under test), `virtual_unit` (the drives and the
//! virtual unit of that scenario, and the wait until it answers), `masters` (the load), `plant`
//! (no load but the gateway's own polls of plant values: the cost of polling and of each page
//! serving them), `mqtt` (those values published through a local mosquitto, beside the gateway
//! without it), `listen` (a listen-only line, its other master and the shadow's reader),
//! `watch` (its HTTP endpoint: metrics, trace, scraper, pages), `run` (one scenario's warm-up
//! and window), `report` (the figures and their tables).

// The harness times other processes on the real clock, and paces its masters on tokio's
// timer; it has no paused clock to keep, nor the product's choice of precision to make.
#![allow(clippy::disallowed_types, clippy::disallowed_methods)]

mod beside;
mod device_server;
mod gateway;
mod journal;
mod listen;
mod masters;
mod mqtt;
mod plant;
mod report;
mod run;
mod scenarios;
mod tcp_device;
mod virtual_unit;
mod watch;

use clap::Parser;
use std::path::PathBuf;
use std::process::ExitCode;
use watch::TraceReader;

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
    /// A scraper fetching `/metrics` back to back from before the warm-up to the end; the
    /// scrapes in the window are reported (compare the efficiency with a run without it).
    #[arg(long)]
    scrape: bool,
    /// modbus-proxy, run beside the gateway in the tcp-device scenarios (default:
    /// `modbus-proxy-venv/bin/modbus-proxy` in the target directory this program is in); left
    /// out, with a message, if it is not there.
    #[arg(long)]
    modbus_proxy: Option<PathBuf>,
    /// Where the `-journal-on` and `-journal-fsync` scenarios keep the gateway's audit journal,
    /// each in a directory of its own that the bench removes (default: the system's temp
    /// directory). A sync on tmpfs costs nothing: to measure `fsync` give a directory on a disk
    /// if that one is tmpfs (the reports name the file system, `journal_fs`).
    #[arg(long)]
    journal_dir: Option<PathBuf>,
}

impl Cli {
    fn journal_dir(&self) -> PathBuf {
        self.journal_dir.clone().unwrap_or_else(std::env::temp_dir)
    }
}

fn main() -> ExitCode {
    // The direct client of the tcp-device line is this program again, in a process of its own.
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some(beside::DIRECT_FLAG) {
        return beside::direct_here(&args[2..]);
    }
    match tokio::runtime::Runtime::new() {
        Ok(runtime) => runtime.block_on(bench(Cli::parse())),
        Err(e) => {
            eprintln!("modbus-gateway-bench: the runtime: {e}");
            ExitCode::FAILURE
        }
    }
}

async fn bench(cli: Cli) -> ExitCode {
    // As in the daemon: the untimed slave's replies are due at once, and tokio's timer would
    // hold each one to the next whole millisecond.
    modbus_gateway::testing::timer::use_precise_timer();
    let all = scenarios::scenarios();
    if cli.list {
        for s in &all {
            println!("{}", s.name);
        }
        return ExitCode::SUCCESS;
    }
    let chosen = scenarios::select(&all, &cli.scenarios);
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
        report::print_header();
    }
    let mut failed = false;
    let mut reports = Vec::new();
    for s in chosen {
        match run::run(&cli, &binary, s).await {
            Ok(mut r) => {
                r.against_journal_off(&reports);
                if cli.json {
                    match serde_json::to_string(&r) {
                        Ok(line) => println!("{line}"),
                        Err(e) => {
                            eprintln!("{}: {e}", s.name);
                            failed = true;
                        }
                    }
                } else {
                    report::print_row(&r);
                }
                reports.push(r);
            }
            Err(e) => {
                eprintln!("{}: {e}", s.name);
                failed = true;
            }
        }
    }
    if !cli.json {
        print_tables(&reports);
    }
    if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    }
}

/// The tables after the main one, each for the scenarios that have its figures.
fn print_tables(reports: &[report::Report]) {
    report::print_line_table(reports);
    report::print_priority_table(reports);
    report::print_scrape_table(reports);
    report::print_device_server_table(reports);
    report::print_tcp_device_table(reports);
    report::print_plant_table(reports);
    report::print_journal_table(reports);
    report::print_virtual_table(reports);
    report::print_mqtt_table(reports);
    report::print_listen_table(reports);
}
