//! The `listen-` scenario's figures (`ListenFigures`) and their table, made of what its two
//! windows saw: the gateway only hearing, then with a master reading the shadow.

use super::tables::cell;
use super::{count, percentile, Report};
use crate::listen::{self, ListenWindow, Phase};
use serde::Serialize;

/// The `listen-` scenario's: the other master's transactions on a saturated listen line against
/// what the gateway heard and paired (`modbus_gateway_observed_*`), its CPU for them, and a
/// master reading the shadow. `transactions`, `tx_per_s`, `efficiency` and `cpu_us_per_tx` are
/// the paired ones of the window without the master (`efficiency`: their physical minimum over
/// the wall time, the line as full as the other master keeps it); `p50_ms`, `p99_ms` and
/// `max_ms` the shadow reads'.
#[derive(Serialize)]
pub(crate) struct ListenFigures {
    /// The other master's round of reads back to back, and its transactions a second: what
    /// the physics allow, which the simulated master keeps exactly.
    pub(crate) round_ms: f64,
    pub(crate) made_per_s: f64,
    /// The window without the master: the transactions the other master made in it (by the
    /// physics), the requests the gateway heard, those it paired (a reply that answered it,
    /// normal or exception, or its timeout), and paired over made and over heard.
    pub(crate) made: f64,
    pub(crate) heard: u64,
    pub(crate) paired: u64,
    pub(crate) paired_of_made: Option<f64>,
    pub(crate) paired_of_heard: Option<f64>,
    /// Of the paired: exceptions, timeouts; and what was discarded (CRC errors among it).
    pub(crate) exceptions: u64,
    pub(crate) timeouts: u64,
    pub(crate) crc_errors: u64,
    pub(crate) discarded: u64,
    /// The gateway's CPU a second hearing the line (the simulated line's share, inside it,
    /// included).
    pub(crate) cpu_ms_per_s: f64,
    /// The window with one master reading the shadow (every `listen::SHADOW_PERIOD`, 2 ms):
    /// its reads a second and those answered 0x0B, paired over made then, and the gateway's
    /// CPU a second (against `cpu_ms_per_s`: 500 reads a second cost less than two windows'
    /// CPU differ by).
    pub(crate) shadow_reads_per_s: f64,
    pub(crate) shadow_exceptions: u64,
    pub(crate) shadow_paired_of_made: Option<f64>,
    pub(crate) shadow_cpu_ms_per_s: f64,
    /// From the gateway listening until the shadow answered, and until every plant value of
    /// the line had been read from it; how many there are.
    pub(crate) shadowed_s: f64,
    pub(crate) values_read_s: f64,
    pub(crate) plant_values: u64,
}

/// Paired (replies and timeouts) in `phase`.
fn paired(phase: &Phase) -> f64 {
    phase.heard.replies + phase.heard.timeouts
}

fn ratio(a: f64, b: f64) -> Option<f64> {
    (b > 0.0).then(|| a / b)
}

impl ListenFigures {
    fn of(w: &ListenWindow) -> ListenFigures {
        let made_per_s = listen::READS.len() as f64 / listen::round(&w.timing).as_secs_f64();
        let (hearing, reading) = (&w.hearing, &w.reading);
        let (wall, shadow_wall) = (hearing.wall.as_secs_f64(), reading.wall.as_secs_f64());
        let made = made_per_s * wall;
        let cpu_ms_per_s = hearing.cpu.as_secs_f64() * 1e3 / wall;
        let shadow_cpu_ms_per_s = reading.cpu.as_secs_f64() * 1e3 / shadow_wall;
        let shadow_reads_per_s = reading.shadow.len() as f64 / shadow_wall;
        ListenFigures {
            round_ms: listen::round(&w.timing).as_secs_f64() * 1e3,
            made_per_s,
            made,
            heard: count(hearing.heard.requests),
            paired: count(paired(hearing)),
            paired_of_made: ratio(paired(hearing), made),
            paired_of_heard: ratio(paired(hearing), hearing.heard.requests),
            exceptions: count(hearing.heard.exceptions),
            timeouts: count(hearing.heard.timeouts),
            crc_errors: count(hearing.heard.crc_errors),
            discarded: count(hearing.heard.discarded),
            cpu_ms_per_s,
            shadow_reads_per_s,
            shadow_exceptions: reading.shadow_exceptions,
            shadow_paired_of_made: ratio(paired(reading), made_per_s * shadow_wall),
            shadow_cpu_ms_per_s,
            shadowed_s: w.shadowed.as_secs_f64(),
            values_read_s: w.values_read.as_secs_f64(),
            plant_values: w.values as u64,
        }
    }
}

impl Report {
    /// The figures of the `listen-` scenario's window `w`.
    pub(crate) fn listen(&mut self, w: &ListenWindow) {
        let hearing = &w.hearing;
        let wall = hearing.wall.as_secs_f64();
        let transactions = count(paired(hearing));
        let physical: f64 = listen::READS
            .iter()
            .zip(&hearing.heard.by_read)
            .map(|(read, replies)| read.minimum(&w.timing).as_secs_f64() * replies)
            .sum();
        let mut shadow = w.reading.shadow.clone();
        shadow.sort();
        self.transactions = transactions;
        self.tx_per_s = transactions as f64 / wall;
        self.seconds = wall;
        self.efficiency = Some(physical / wall);
        self.cpu_us_per_tx = super::per_tx(hearing.cpu, transactions);
        self.p50_ms = percentile(&shadow, 0.5);
        self.p99_ms = percentile(&shadow, 0.99);
        self.max_ms = super::slowest(&shadow);
        self.rss_mb = w.rss_mb;
        self.listen = Some(ListenFigures::of(w));
    }
}

/// The `listen-` scenario's own columns: made, heard, paired, the gateway's CPU, the shadow.
pub(crate) fn print_listen_table(reports: &[Report]) {
    let rows: Vec<_> = reports
        .iter()
        .filter_map(|r| r.listen.as_ref().map(|l| (r, l)))
        .collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "\n{:<33} {:>7} {:>6} {:>6} {:>6} {:>7} {:>7} {:>4} {:>4} {:>9} {:>8} {:>8} {:>7} {:>8}",
        "scenario",
        "made/s",
        "made",
        "heard",
        "paired",
        "p/made",
        "p/heard",
        "t/o",
        "crc",
        "cpu us/tx",
        "cpu ms/s",
        "shadow/s",
        "p/made",
        "cpu ms/s"
    );
    for (r, l) in rows {
        println!(
            "{:<33} {:>7.1} {:>6.0} {:>6} {:>6} {:>7} {:>7} {:>4} {:>4} {:>9} {:>8.1} {:>8.0} {:>7} {:>8.1}",
            r.scenario,
            l.made_per_s,
            l.made,
            l.heard,
            l.paired,
            cell(l.paired_of_made, 4),
            cell(l.paired_of_heard, 4),
            l.timeouts,
            l.crc_errors,
            cell(r.cpu_us_per_tx, 1),
            l.cpu_ms_per_s,
            l.shadow_reads_per_s,
            cell(l.shadow_paired_of_made, 4),
            l.shadow_cpu_ms_per_s,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::listen::{Observed, READS};
    use modbus_gateway::testing::line::{LineTiming, Parity, SerialFormat};
    use std::time::Duration;

    fn phase(replies_per_read: f64, cpu_ms: u64) -> Phase {
        let n = replies_per_read * READS.len() as f64;
        Phase {
            wall: Duration::from_secs(10),
            cpu: Duration::from_millis(cpu_ms),
            heard: Observed {
                requests: n,
                replies: n,
                by_read: vec![replies_per_read; READS.len()],
                ..Observed::default()
            },
            shadow: vec![Duration::from_micros(200); 5000],
            shadow_exceptions: 0,
        }
    }

    #[test]
    fn a_line_heard_whole_is_paired_in_full_and_as_efficient_as_the_other_master() {
        let timing = LineTiming::new(&SerialFormat {
            baud: 115_200,
            data_bits: 8,
            parity: Parity::None,
            stop_bits: 1,
        });
        // Ten seconds of whole rounds, every transaction paired.
        let rounds = 10.0 / listen::round(&timing).as_secs_f64();
        let window = ListenWindow {
            timing,
            shadowed: Duration::from_millis(100),
            values_read: Duration::from_millis(300),
            values: 20,
            hearing: phase(rounds, 500),
            reading: phase(rounds, 1000),
            rss_mb: 10.0,
        };
        let mut report = Report::default();
        report.listen(&window);
        let figures = report.listen.as_ref().unwrap();
        assert!((figures.paired_of_made.unwrap() - 1.0).abs() < 1e-9);
        assert_eq!(figures.paired_of_heard, Some(1.0));
        assert!((report.efficiency.unwrap() - 1.0).abs() < 1e-9);
        assert!((figures.shadow_cpu_ms_per_s - 100.0).abs() < 1e-9);
        assert!((figures.shadow_reads_per_s - 500.0).abs() < 1e-9);
        let per_tx = 500e3 / report.transactions as f64;
        assert_eq!(report.transactions, count(rounds * READS.len() as f64));
        assert!((report.cpu_us_per_tx.unwrap() - per_tx).abs() < 1e-6);
    }
}
