//! The figures of a run: a JSON object per scenario, computed from its window, its minimum and
//! the reports it is compared with. How they are shown, as the table and the scenarios' own
//! tables, is `tables`'s.

mod listen;
mod mqtt;
mod tables;

pub(crate) use listen::print_listen_table;

pub(crate) use tables::{
    print_device_server_table, print_header, print_journal_table, print_line_table,
    print_mqtt_table, print_plant_table, print_priority_table, print_row, print_scrape_table,
    print_tcp_device_table, print_virtual_table,
};

use crate::beside::Driven;
use crate::mqtt::MqttWindow;
use crate::plant::{Gets, PlantWindow};
use crate::run::{Minimum, Window};
use crate::scenarios::{journal_off_twin, Line, Load, Scenario};
use crate::virtual_unit;
use crate::watch::Counters;
pub(crate) use listen::ListenFigures;
pub(crate) use mqtt::MqttFigures;
use serde::Serialize;
use std::time::Duration;

#[derive(Serialize, Default)]
pub(crate) struct Report {
    pub(crate) scenario: String,
    /// None on a Modbus TCP device: no serial line.
    baud: Option<u32>,
    masters: usize,
    transactions: u64,
    tx_per_s: f64,
    /// Sum of the physical minimum of the completed transactions over the wall time (timed
    /// lines: the simulated one, local or behind a device server).
    efficiency: Option<f64>,
    p50_ms: Option<f64>,
    p99_ms: Option<f64>,
    max_ms: Option<f64>,
    /// Latency above the physical minimum at the median, for one master on a timed line; on a
    /// Modbus TCP device, above the direct client's.
    added_p50_ms: Option<f64>,
    added_p99_ms: Option<f64>,
    fairness: Option<f64>,
    pub(crate) rss_mb: f64,
    cpu_us_per_tx: Option<f64>,
    /// The device server's (`simulate --listen`'s) CPU per transaction, on that line: the
    /// simulated line's share, which the gateway's figure carries on the local one.
    simulate_cpu_us_per_tx: Option<f64>,
    seconds: f64,
    /// Connection set-up, one master after another: TCP connect to connected (plain TCP, RTU
    /// over TCP) or to the TLS handshake complete (TLS), median and slowest over the masters.
    connect_p50_ms: Option<f64>,
    connect_max_ms: Option<f64>,
    /// The gateway's CPU time across the connect phase, per master.
    connect_cpu_us: Option<f64>,
    /// From the gateway's metrics, scraped at the window's ends (timed lines only): transactions on the
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
    /// On a Modbus TCP device: one client, in a process of its own, reading from it directly,
    /// back to back, for as long (its rate and median), and the gateway's rate over its.
    direct_tx_per_s: Option<f64>,
    direct_p50_ms: Option<f64>,
    tx_vs_direct: Option<f64>,
    /// The same masters through modbus-proxy in front of the same device, if it is installed.
    proxy_tx_per_s: Option<f64>,
    proxy_p50_ms: Option<f64>,
    proxy_p99_ms: Option<f64>,
    proxy_cpu_us_per_tx: Option<f64>,
    /// With `--scrape` only: the scraper's scrapes in the window, their time (median, 99th
    /// percentile, slowest) and the size of the last page.
    #[serde(skip_serializing_if = "Option::is_none")]
    scrapes: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    scrape_p50_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    scrape_p99_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    scrape_max_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    scrape_bytes: Option<u64>,
    /// The `values-` scenario only.
    #[serde(flatten)]
    plant: Option<PlantFigures>,
    /// The mixed load only.
    #[serde(flatten)]
    journal: Option<JournalFigures>,
    /// The virtual load only.
    #[serde(flatten)]
    pub(crate) virtual_unit: Option<VirtualFigures>,
    /// The `mqtt-` scenarios only.
    #[serde(flatten)]
    pub(crate) mqtt: Option<MqttFigures>,
    /// The `listen-` scenario only.
    #[serde(flatten)]
    pub(crate) listen: Option<ListenFigures>,
}

/// The `virtual-unit-` scenario's: masters reading a virtual unit, answered from memory while
/// the line polls the values it shows.
#[derive(Serialize)]
pub(crate) struct VirtualFigures {
    /// Always true: the reads took no line time, so there is no efficiency (`efficiency` is
    /// null) and `tx_per_s` is the gateway's own rate.
    answered_from_memory: bool,
    /// Registers each read asks for, and reads answered with an exception in the window (0x0B:
    /// a value it shows too old or never read): errors, not among the `transactions`.
    pub(crate) virtual_registers: u16,
    pub(crate) exceptions: u64,
    /// The gateway's polls of the drives a second in the window (`modbus_gateway_polls_total`);
    /// `line_tx_per_s` beside it is every transaction on the line, the same when no master's
    /// read went there.
    pub(crate) line_polls_per_s: Option<f64>,
}

/// The mixed load's writes, and what the audit journal took for them.
#[derive(Serialize)]
pub(crate) struct JournalFigures {
    /// `[audit]`: `off` (none), `on`, or `fsync` (`fsync = true`).
    journal: &'static str,
    /// Writes the masters completed in the window (of `transactions`), and their latency
    /// alone: median and 99th percentile; beside it the reads' median, taken in the same
    /// window, so in the same state of the machine.
    writes: u64,
    write_p50_ms: Option<f64>,
    write_p99_ms: Option<f64>,
    read_p50_ms: Option<f64>,
    /// The journal's growth across the window per write: its entry and its outcome's.
    #[serde(skip_serializing_if = "Option::is_none")]
    journal_bytes_per_write: Option<f64>,
    /// The type of the file system the journal is on (`/proc/self/mounts`).
    #[serde(skip_serializing_if = "Option::is_none")]
    journal_fs: Option<String>,
    /// Against the `-journal-off` scenario of the same run: the rate over its; the gateway's
    /// CPU time per write more than its (the difference in CPU per transaction, times
    /// transactions per write); the wall time per write more than its, the same way (what
    /// each write held the line up by); and the writes' median latency less its.
    #[serde(skip_serializing_if = "Option::is_none")]
    tx_vs_journal_off: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    cpu_us_per_write_vs_journal_off: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    wall_ms_per_write_vs_journal_off: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    write_p50_ms_vs_journal_off: Option<f64>,
}

/// The figures of the `values-` scenarios: the gateway polling plant values, no master.
#[derive(Serialize)]
pub(crate) struct PlantFigures {
    /// The values configured, as `GET /values` lists them.
    plant_values: u64,
    /// From the gateway listening until every value had been read once (to within the
    /// bench's 250 ms between looks).
    first_pass_s: f64,
    /// While the gateway only polls (`--seconds`, after the first pass): its polls
    /// (`modbus_gateway_polls_total`) and CPU time a second, and on the device-server line
    /// `simulate`'s, which on the local line is in the gateway's.
    polls_per_s: f64,
    poll_cpu_ms_per_s: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    simulate_poll_cpu_ms_per_s: Option<f64>,
    /// The gateway's memory after that window, before any page was fetched (`rss_mb` is at
    /// the end, after them).
    rss_polling_mb: f64,
    /// Each page fetched back to back (for `--seconds`, at least `--rounds` times) by a client
    /// that acknowledges at once: how many times; the gateway's CPU time per fetch, as
    /// measured (the polls going on meanwhile included) and less the polling window's CPU a
    /// second over the fetch's wall time; the wall time per fetch; then the wall time per fetch
    /// of a client that delays its ACKs as Linux does by default (`--rounds` times, as curl or
    /// Prometheus would); and the size of the body.
    metrics_gets: u64,
    metrics_cpu_us_per_get: f64,
    metrics_cpu_us_per_get_less_polling: f64,
    metrics_ms_per_get: f64,
    metrics_ms_per_get_plain_client: f64,
    metrics_bytes: u64,
    values_gets: u64,
    values_cpu_us_per_get: f64,
    values_cpu_us_per_get_less_polling: f64,
    values_ms_per_get: f64,
    values_ms_per_get_plain_client: f64,
    values_bytes: u64,
    history_gets: u64,
    history_cpu_us_per_get: f64,
    history_cpu_us_per_get_less_polling: f64,
    history_ms_per_get: f64,
    history_ms_per_get_plain_client: f64,
    history_bytes: u64,
    /// Readings per value in the last `GET /values?history=1`, on average: its size and cost
    /// grow with them, up to 10 minutes' worth.
    history_points: f64,
}

/// The slowest of `sorted`, in milliseconds.
fn slowest(sorted: &[Duration]) -> Option<f64> {
    sorted.last().map(|d| d.as_secs_f64() * 1e3)
}

impl JournalFigures {
    /// The figures of scenario `s`'s window, whose writes and reads took `writes` and `reads`
    /// and whose journal (if any) grew by `journal_bytes`; those against the journal-off one
    /// come later.
    fn of(
        s: &Scenario,
        mut writes: Vec<Duration>,
        mut reads: Vec<Duration>,
        journal_bytes: Option<u64>,
    ) -> JournalFigures {
        writes.sort();
        reads.sort();
        let count = writes.len() as u64;
        JournalFigures {
            journal: s.journal.label(),
            writes: count,
            write_p50_ms: percentile(&writes, 0.5),
            write_p99_ms: percentile(&writes, 0.99),
            read_p50_ms: percentile(&reads, 0.5),
            journal_bytes_per_write: journal_bytes
                .filter(|_| count > 0)
                .map(|bytes| bytes as f64 / count as f64),
            journal_fs: None,
            tx_vs_journal_off: None,
            cpu_us_per_write_vs_journal_off: None,
            wall_ms_per_write_vs_journal_off: None,
            write_p50_ms_vs_journal_off: None,
        }
    }
}

/// One page's figures, as [`PlantFigures`] has them.
struct PerGet {
    gets: u64,
    cpu_us: f64,
    less_polling_us: f64,
    ms: f64,
    plain_ms: f64,
    bytes: u64,
}

impl PerGet {
    /// The figures of `g`, the gateway's polling costing `poll_cpu` (a fraction of a CPU).
    fn of(g: &Gets, poll_cpu: f64) -> PerGet {
        let n = g.count.max(1) as f64;
        let (cpu, wall) = (g.cpu.as_secs_f64() / n, g.wall.as_secs_f64() / n);
        PerGet {
            gets: g.count,
            cpu_us: cpu * 1e6,
            less_polling_us: (cpu - poll_cpu * wall) * 1e6,
            ms: wall * 1e3,
            plain_ms: g.plain.as_secs_f64() * 1e3,
            bytes: g.bytes as u64,
        }
    }
}

/// The `p` quantile of `sorted`, in milliseconds (nearest rank).
fn percentile(sorted: &[Duration], p: f64) -> Option<f64> {
    let last = sorted.len().checked_sub(1)?;
    #[allow(
        clippy::cast_possible_truncation,
        reason = "p is within 0..=1, so the rank is within 0..=last"
    )]
    let rank = (last as f64 * p).round() as usize;
    Some(sorted[rank].as_secs_f64() * 1e3)
}

/// A counter's growth as a count: a whole number, far below 2^53.
#[allow(
    clippy::cast_possible_truncation,
    reason = "the difference of two counters of whole events"
)]
fn count(delta: f64) -> u64 {
    delta as u64
}

/// CPU time `cpu` per transaction, in µs, if there were any.
fn per_tx(cpu: Duration, transactions: u64) -> Option<f64> {
    (transactions > 0).then(|| cpu.as_secs_f64() * 1e6 / transactions as f64)
}

impl Report {
    /// The report of scenario `s` before its window: how its masters connected (`setup`
    /// sorted) and the gateway's CPU time for it.
    pub(crate) fn new(s: &Scenario, setup: &[Duration], connect_cpu: Duration) -> Report {
        Report {
            scenario: s.name.clone(),
            baud: (s.line != Line::TcpDevice).then_some(s.format.baud),
            masters: s.masters,
            connect_p50_ms: percentile(setup, 0.5),
            connect_max_ms: setup.last().map(|d| d.as_secs_f64() * 1e3),
            connect_cpu_us: (!setup.is_empty())
                .then(|| connect_cpu.as_secs_f64() * 1e6 / setup.len() as f64),
            ..Report::default()
        }
    }

    /// The figures of the window `w` of scenario `s`, whose transactions take at least `min`.
    pub(crate) fn measured(&mut self, s: &Scenario, w: &Window, min: &Minimum) {
        self.rss_mb = w.rss_mb;
        let mut latencies = Vec::new();
        let mut per_master = Vec::with_capacity(s.masters);
        let mut physical = Duration::ZERO;
        let mut priority = Vec::new();
        let (mut writes, mut reads) = (Vec::new(), Vec::new());
        for (i, done) in w.masters.iter().enumerate() {
            let within: Vec<_> = done
                .iter()
                .filter(|(at, _, _)| *at >= w.start && *at <= w.end)
                .collect();
            if i == s.masters {
                priority = within.iter().map(|(_, latency, _)| *latency).collect();
            } else {
                per_master.push(within.len() as f64);
            }
            for (_, latency, write) in within {
                latencies.push(*latency);
                physical += if *write { min.write } else { min.read };
                if *write {
                    writes.push(*latency);
                } else {
                    reads.push(*latency);
                }
            }
        }
        let wall = (w.end - w.start).as_secs_f64();
        let transactions = latencies.len() as u64;
        latencies.sort();
        let sum: f64 = per_master.iter().sum();
        let squares: f64 = per_master.iter().map(|x| x * x).sum();
        self.transactions = transactions;
        self.tx_per_s = transactions as f64 / wall;
        self.seconds = wall;
        self.p50_ms = percentile(&latencies, 0.5);
        self.p99_ms = percentile(&latencies, 0.99);
        self.max_ms = latencies.last().map(|d| d.as_secs_f64() * 1e3);
        self.fairness = (s.masters > 1 && squares > 0.0)
            .then(|| sum * sum / (per_master.len() as f64 * squares));
        let t_min = min.read.as_secs_f64();
        if s.priority.is_some() {
            self.priority(&mut priority, t_min);
        }
        if s.load == Load::Virtual {
            self.virtual_figures(w);
        } else if let Some((before, after)) = &w.metrics {
            self.counters(s, &Counters::of(before), &Counters::of(after), t_min);
        }
        self.cpu_us_per_tx = per_tx(w.cpu, transactions);
        self.simulate_cpu_us_per_tx = w.far_cpu.and_then(|cpu| per_tx(cpu, transactions));
        if s.on_the_line() {
            self.efficiency = Some(physical.as_secs_f64() / wall);
            // Coalesced reads took no time of the line: count its transactions instead.
            if s.load == Load::Same {
                self.efficiency = self.line_tx.map(|tx| tx as f64 * t_min / wall);
            }
            if s.masters == 1 && s.load == Load::Read {
                let floor = min.read.as_secs_f64() * 1e3;
                self.added_p50_ms = self.p50_ms.map(|p| p - floor);
                self.added_p99_ms = self.p99_ms.map(|p| p - floor);
            }
        }
        if let Some(scrapes) = &w.scrapes {
            self.scrapes(scrapes);
        }
        if s.load == Load::Mix {
            self.journal = Some(JournalFigures::of(s, writes, reads, w.journal_bytes));
        }
    }

    /// The type of the file system the audit journal was on, if there was a journal.
    pub(crate) fn journal_kept(&mut self, file_system: Option<String>) {
        if let Some(figures) = &mut self.journal {
            figures.journal_fs = file_system;
        }
    }

    /// A `-journal-on` or `-journal-fsync` scenario's figures against its `-journal-off`
    /// twin's, if that is among the `earlier` reports of the run.
    pub(crate) fn against_journal_off(&mut self, earlier: &[Report]) {
        let Some(twin) = journal_off_twin(&self.scenario) else {
            return;
        };
        let Some(off) = earlier.iter().rev().find(|r| r.scenario == twin) else {
            return;
        };
        let (Some(figures), Some(cpu), Some(cpu_off), Some(off_figures)) = (
            &mut self.journal,
            self.cpu_us_per_tx,
            off.cpu_us_per_tx,
            &off.journal,
        ) else {
            return;
        };
        if figures.writes == 0 || self.tx_per_s <= 0.0 || off.tx_per_s <= 0.0 {
            return;
        }
        let tx_per_write = self.transactions as f64 / figures.writes as f64;
        figures.tx_vs_journal_off = Some(self.tx_per_s / off.tx_per_s);
        figures.cpu_us_per_write_vs_journal_off = Some((cpu - cpu_off) * tx_per_write);
        let wall_ms = |tx_per_s: f64| 1e3 / tx_per_s;
        figures.wall_ms_per_write_vs_journal_off =
            Some((wall_ms(self.tx_per_s) - wall_ms(off.tx_per_s)) * tx_per_write);
        figures.write_p50_ms_vs_journal_off = figures
            .write_p50_ms
            .zip(off_figures.write_p50_ms)
            .map(|(p, off)| p - off);
    }

    /// The figures of the `values-` scenarios' window `w`.
    pub(crate) fn plant(&mut self, w: &PlantWindow) {
        let polling = w.polling.as_secs_f64();
        let poll_cpu = w.polling_cpu.as_secs_f64() / polling;
        let metrics = PerGet::of(&w.metrics, poll_cpu);
        let values = PerGet::of(&w.values_gets, poll_cpu);
        let history = PerGet::of(&w.history, poll_cpu);
        self.rss_mb = w.rss_mb;
        self.seconds = polling;
        self.plant = Some(PlantFigures {
            plant_values: w.values as u64,
            first_pass_s: w.first_pass.as_secs_f64(),
            polls_per_s: w.polls / polling,
            poll_cpu_ms_per_s: poll_cpu * 1e3,
            simulate_poll_cpu_ms_per_s: w.far_polling_cpu.map(|c| c.as_secs_f64() * 1e3 / polling),
            rss_polling_mb: w.rss_polling_mb,
            metrics_gets: metrics.gets,
            metrics_cpu_us_per_get: metrics.cpu_us,
            metrics_cpu_us_per_get_less_polling: metrics.less_polling_us,
            metrics_ms_per_get: metrics.ms,
            metrics_ms_per_get_plain_client: metrics.plain_ms,
            metrics_bytes: metrics.bytes,
            values_gets: values.gets,
            values_cpu_us_per_get: values.cpu_us,
            values_cpu_us_per_get_less_polling: values.less_polling_us,
            values_ms_per_get: values.ms,
            values_ms_per_get_plain_client: values.plain_ms,
            values_bytes: values.bytes,
            history_gets: history.gets,
            history_cpu_us_per_get: history.cpu_us,
            history_cpu_us_per_get_less_polling: history.less_polling_us,
            history_ms_per_get: history.ms,
            history_ms_per_get_plain_client: history.plain_ms,
            history_bytes: history.bytes,
            history_points: w.history_points,
        });
    }

    /// The report of the `mqtt-` scenario `s`, whose gateways saw `w`.
    pub(crate) fn mqtt(s: &Scenario, w: &MqttWindow) -> Report {
        let masters = &w.with.masters;
        Report {
            transactions: masters.latencies.len() as u64,
            tx_per_s: masters.tx_per_s,
            p50_ms: percentile(&masters.latencies, 0.5),
            p99_ms: percentile(&masters.latencies, 0.99),
            max_ms: slowest(&masters.latencies),
            rss_mb: w.with.rss_mb,
            seconds: w.with.polling.as_secs_f64(),
            mqtt: Some(MqttFigures::of(w)),
            ..Report::new(s, &[], Duration::ZERO)
        }
    }

    /// The figures of the direct client and of modbus-proxy (if it ran) beside the gateway's on
    /// the Modbus TCP device of scenario `s`.
    pub(crate) fn beside(&mut self, s: &Scenario, direct: &Driven, proxy: Option<&Driven>) {
        self.direct_tx_per_s = Some(direct.tx_per_s);
        self.direct_p50_ms = percentile(&direct.latencies, 0.5);
        self.tx_vs_direct = (direct.tx_per_s > 0.0).then(|| self.tx_per_s / direct.tx_per_s);
        if s.masters == 1 {
            self.added_p50_ms = self.p50_ms.zip(self.direct_p50_ms).map(|(p, d)| p - d);
            self.added_p99_ms = self.p99_ms.zip(self.direct_p50_ms).map(|(p, d)| p - d);
        }
        if let Some(proxy) = proxy {
            self.proxy_tx_per_s = Some(proxy.tx_per_s);
            self.proxy_p50_ms = percentile(&proxy.latencies, 0.5);
            self.proxy_p99_ms = percentile(&proxy.latencies, 0.99);
            self.proxy_cpu_us_per_tx = proxy
                .cpu
                .and_then(|cpu| per_tx(cpu, proxy.latencies.len() as u64));
        }
    }

    /// The priority master's figures from its latencies in the window, in `t_min` units.
    fn priority(&mut self, priority: &mut [Duration], t_min: f64) {
        let transactions = self.transactions;
        priority.sort();
        let in_tmin = |p| percentile(priority, p).map(|ms| ms / 1e3 / t_min);
        self.priority_tx = Some(priority.len() as u64);
        self.priority_p50_tmin = in_tmin(0.5);
        self.priority_p99_tmin = in_tmin(0.99);
        self.priority_max_tmin = in_tmin(1.0);
        self.priority_wait_p50_tmin = in_tmin(0.5).map(|t| t - 1.0);
        self.priority_wait_p99_tmin = in_tmin(0.99).map(|t| t - 1.0);
        self.others_share = (transactions > 0)
            .then(|| (transactions - priority.len() as u64) as f64 / transactions as f64);
    }

    /// The virtual load's figures: its exceptions, and the line's transactions and polls from
    /// the gateway's metrics at the window's ends.
    fn virtual_figures(&mut self, w: &Window) {
        let wall = self.seconds;
        let counts = w
            .metrics
            .as_ref()
            .map(|(before, after)| (Counters::of(before), Counters::of(after)));
        if let Some((before, after)) = &counts {
            let line_tx = after.line_tx - before.line_tx;
            self.line_tx = Some(count(line_tx));
            self.line_tx_per_s = Some(line_tx / wall);
        }
        self.virtual_unit = Some(VirtualFigures {
            answered_from_memory: true,
            virtual_registers: virtual_unit::REGISTERS,
            exceptions: w.exceptions,
            line_polls_per_s: counts.map(|(before, after)| (after.polls - before.polls) / wall),
        });
    }

    /// The figures from the gateway's metrics at the window's ends.
    fn counters(&mut self, s: &Scenario, before: &Counters, after: &Counters, t_min: f64) {
        let (transactions, wall) = (self.transactions, self.seconds);
        let line_tx = after.line_tx - before.line_tx;
        self.line_tx = Some(count(line_tx));
        self.line_tx_per_s = Some(line_tx / wall);
        self.line_tx_per_answer = (transactions > 0).then(|| line_tx / transactions as f64);
        self.coalesced = Some(count(after.coalesced - before.coalesced));
        self.physical_tx_per_s = Some(1.0 / t_min);
        if s.load == Load::Same {
            self.answered_vs_physical = Some(self.tx_per_s * t_min / s.masters as f64);
        }
        let mean_wait = |class: usize| {
            let (sum, count) = (
                after.wait[class].0 - before.wait[class].0,
                after.wait[class].1 - before.wait[class].1,
            );
            (count > 0.0).then(|| sum / count / t_min)
        };
        self.queue_wait_normal_tmin = mean_wait(0);
        self.queue_wait_priority_tmin = mean_wait(1);
    }

    /// The `--scrape` scraper's figures.
    fn scrapes(&mut self, scrapes: &[crate::watch::Scraped]) {
        let mut times: Vec<Duration> = scrapes.iter().map(|(_, took, _)| *took).collect();
        times.sort();
        self.scrapes = Some(times.len() as u64);
        self.scrape_p50_ms = percentile(&times, 0.5);
        self.scrape_p99_ms = percentile(&times, 0.99);
        self.scrape_max_ms = times.last().map(|d| d.as_secs_f64() * 1e3);
        self.scrape_bytes = scrapes.last().map(|(_, _, bytes)| *bytes as u64);
    }
}

#[cfg(test)]
mod tests {
    use super::{JournalFigures, Report};

    /// A report of `scenario`: `transactions` in 10 s, `writes` of them writes, at `cpu_us`
    /// of the gateway's CPU each.
    fn report(scenario: &str, transactions: u64, writes: u64, cpu_us: f64) -> Report {
        Report {
            scenario: scenario.to_owned(),
            transactions,
            tx_per_s: transactions as f64 / 10.0,
            cpu_us_per_tx: Some(cpu_us),
            journal: Some(JournalFigures {
                journal: "on",
                writes,
                write_p50_ms: Some(2.0),
                write_p99_ms: Some(3.0),
                read_p50_ms: Some(2.0),
                journal_bytes_per_write: None,
                journal_fs: None,
                tx_vs_journal_off: None,
                cpu_us_per_write_vs_journal_off: None,
                wall_ms_per_write_vs_journal_off: None,
                write_p50_ms_vs_journal_off: None,
            }),
            ..Report::default()
        }
    }

    #[test]
    fn the_journal_s_cost_per_write_is_the_difference_per_transaction_times_transactions_per_write()
    {
        let off = report("pty-mix-100-journal-off", 5000, 1250, 80.0);
        // The same rate, 5 us more a transaction: 20 us more for each write, one in four.
        let mut on = report("pty-mix-100-journal-on", 5000, 1250, 85.0);
        on.against_journal_off(&[off]);
        let on = on.journal.unwrap();
        assert_eq!(on.tx_vs_journal_off, Some(1.0));
        assert!((on.cpu_us_per_write_vs_journal_off.unwrap() - 20.0).abs() < 1e-9);
        assert!(on.wall_ms_per_write_vs_journal_off.unwrap().abs() < 1e-9);
    }

    #[test]
    fn a_slower_rate_is_the_wall_time_each_write_held_the_line_up_by() {
        let off = report("sim-mix-100-journal-off", 5000, 1250, 80.0);
        // 2.5 ms a transaction where it was 2 ms: 0.5 ms more each, 2 ms a write.
        let mut fsync = report("sim-mix-100-journal-fsync", 4000, 1000, 80.0);
        if let Some(figures) = &mut fsync.journal {
            figures.write_p50_ms = Some(4.5);
        }
        fsync.against_journal_off(&[off]);
        let fsync = fsync.journal.unwrap();
        assert_eq!(fsync.tx_vs_journal_off, Some(0.8));
        assert!((fsync.wall_ms_per_write_vs_journal_off.unwrap() - 2.0).abs() < 1e-9);
        // The writes' own median, 2 ms without the journal.
        assert_eq!(fsync.write_p50_ms_vs_journal_off, Some(2.5));
    }

    #[test]
    fn only_a_journal_scenario_with_its_off_twin_in_the_run_is_compared() {
        let off = report("sim-mix-100-journal-off", 5000, 1250, 80.0);
        let other = report("pty-mix-100-journal-off", 5000, 1250, 10.0);
        let mut twinless = report("pty-mix-100-journal-on", 5000, 1250, 85.0);
        twinless.against_journal_off(std::slice::from_ref(&off));
        assert!(twinless.journal.unwrap().tx_vs_journal_off.is_none());
        let mut itself = report("sim-mix-100-journal-off", 5000, 1250, 85.0);
        itself.against_journal_off(&[off, other]);
        assert!(itself.journal.unwrap().tx_vs_journal_off.is_none());
    }
}
