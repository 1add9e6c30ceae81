//! How a run's figures are shown: the table of every scenario, one row each as it ends, then the
//! own tables of the scenarios that have them (line, priority, scrape, device-server, tcp-device,
//! plant-values, journal, virtual-unit, MQTT). It formats what `Report` holds, and a few ratios of
//! one scenario's figures to its twin's; the figures themselves are computed in the parent module.

use super::Report;

pub(super) fn cell(value: Option<f64>, precision: usize) -> String {
    value.map_or("-".into(), |v| format!("{v:.precision$}"))
}

/// The table's header.
pub(crate) fn print_header() {
    println!(
        "{:<33} {:>7} {:>9} {:>6} {:>6} {:>8} {:>8} {:>8} {:>8} {:>6} {:>7} {:>8} {:>8} {:>8} {:>8}",
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

/// The table's row for `r`.
pub(crate) fn print_row(r: &Report) {
    println!(
        "{:<33} {:>7} {:>9} {:>6.1} {:>6} {:>8} {:>8} {:>8} {:>8} {:>6} {:>7.1} {:>8} {:>8} {:>8} {:>8}",
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
}

/// The many-masters (and serial master port) scenarios' own columns: answered reads against the
/// line's transactions.
pub(crate) fn print_line_table(reports: &[Report]) {
    let rows: Vec<_> = reports
        .iter()
        .filter(|r| {
            (r.scenario.starts_with("many-") || r.scenario.starts_with("serial-port-"))
                && r.line_tx.is_some()
        })
        .collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "\n{:<33} {:>7} {:>10} {:>10} {:>8} {:>10} {:>9} {:>9}",
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
            "{:<33} {:>7} {:>10.1} {:>10} {:>8.2} {:>12} {:>9} {:>9}",
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
pub(crate) fn print_priority_table(reports: &[Report]) {
    let rows: Vec<_> = reports.iter().filter(|r| r.priority_tx.is_some()).collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "\n{:<33} {:>7} {:>8} {:>8} {:>8} {:>9} {:>9} {:>10} {:>10} {:>8}",
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
            "{:<33} {:>7} {:>8} {:>8} {:>8} {:>9} {:>9} {:>10} {:>10} {:>8}",
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

/// With `--scrape`: the scraper's columns, beside the line's efficiency they may have cost.
pub(crate) fn print_scrape_table(reports: &[Report]) {
    let rows: Vec<_> = reports.iter().filter(|r| r.scrapes.is_some()).collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "\n{:<33} {:>6} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "scenario (scraped)", "eff", "scrapes", "p50 ms", "p99 ms", "max ms", "bytes"
    );
    for r in rows {
        println!(
            "{:<33} {:>6} {:>8} {:>8} {:>8} {:>8} {:>8}",
            r.scenario,
            cell(r.efficiency, 3),
            r.scrapes.unwrap_or_default(),
            cell(r.scrape_p50_ms, 2),
            cell(r.scrape_p99_ms, 2),
            cell(r.scrape_max_ms, 1),
            r.scrape_bytes.map_or("-".into(), |b| b.to_string()),
        );
    }
}

/// Each device-server scenario beside its `sim-` twin, when both ran: efficiency and the
/// gateway's CPU per transaction on both lines, and their ratios (device server over local).
pub(crate) fn print_device_server_table(reports: &[Report]) {
    let pairs: Vec<_> = reports
        .iter()
        .filter_map(|ds| {
            let twin = format!("sim-{}", ds.scenario.strip_prefix("device-server-")?);
            Some((reports.iter().find(|r| r.scenario == twin)?, ds))
        })
        .collect();
    if pairs.is_empty() {
        return;
    }
    println!(
        "\n{:<33} {:>8} {:>8} {:>6} {:>6} {:>7} {:>9} {:>9} {:>7} {:>10}",
        "scenario (local vs ds)",
        "tx/s",
        "ds tx/s",
        "eff",
        "ds eff",
        "eff x",
        "cpu us/tx",
        "ds cpu",
        "cpu x",
        "sim cpu/tx"
    );
    let ratio = |a: Option<f64>, b: Option<f64>| a.zip(b).map(|(a, b)| b / a);
    for (sim, ds) in pairs {
        println!(
            "{:<33} {:>8.1} {:>8.1} {:>6} {:>6} {:>7} {:>9} {:>9} {:>7} {:>10}",
            ds.scenario,
            sim.tx_per_s,
            ds.tx_per_s,
            cell(sim.efficiency, 3),
            cell(ds.efficiency, 3),
            cell(ratio(sim.efficiency, ds.efficiency), 3),
            cell(sim.cpu_us_per_tx, 1),
            cell(ds.cpu_us_per_tx, 1),
            cell(ratio(sim.cpu_us_per_tx, ds.cpu_us_per_tx), 2),
            cell(ds.simulate_cpu_us_per_tx, 1),
        );
    }
}

/// The tcp-device scenarios' own columns: the gateway beside one direct client and beside
/// modbus-proxy, on the same device.
pub(crate) fn print_tcp_device_table(reports: &[Report]) {
    let rows: Vec<_> = reports
        .iter()
        .filter(|r| r.direct_tx_per_s.is_some())
        .collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "\n{:<33} {:>8} {:>8} {:>8} {:>8} {:>9} {:>9} {:>9} {:>8} {:>9} {:>9} {:>9}",
        "scenario (Modbus TCP device)",
        "tx/s",
        "p50 ms",
        "p99 ms",
        "+p50 ms",
        "cpu us/tx",
        "direct/s",
        "dir p50",
        "x direct",
        "proxy/s",
        "proxy p99",
        "proxy cpu"
    );
    for r in rows {
        println!(
            "{:<33} {:>8.1} {:>8} {:>8} {:>8} {:>9} {:>9} {:>9} {:>8} {:>9} {:>9} {:>9}",
            r.scenario,
            r.tx_per_s,
            cell(r.p50_ms, 3),
            cell(r.p99_ms, 3),
            cell(r.added_p50_ms, 3),
            cell(r.cpu_us_per_tx, 1),
            cell(r.direct_tx_per_s, 1),
            cell(r.direct_p50_ms, 3),
            cell(r.tx_vs_direct, 3),
            cell(r.proxy_tx_per_s, 1),
            cell(r.proxy_p99_ms, 3),
            cell(r.proxy_cpu_us_per_tx, 1),
        );
    }
}

/// The `values-` scenarios' own columns: the gateway polling alone, then each page it serves.
pub(crate) fn print_plant_table(reports: &[Report]) {
    for r in reports {
        let Some(p) = &r.plant else {
            continue;
        };
        println!(
            "\n{:<33} {:>7} {:>7} {:>8} {:>9} {:>9} {:>7} {:>7} {:>8}",
            "scenario (plant values)",
            "values",
            "pass s",
            "polls/s",
            "cpu ms/s",
            "sim ms/s",
            "rss pol",
            "rss MB",
            "hist pts"
        );
        println!(
            "{:<33} {:>7} {:>7.1} {:>8.2} {:>9.2} {:>9} {:>7.1} {:>7.1} {:>8.1}",
            r.scenario,
            p.plant_values,
            p.first_pass_s,
            p.polls_per_s,
            p.poll_cpu_ms_per_s,
            cell(p.simulate_poll_cpu_ms_per_s, 2),
            p.rss_polling_mb,
            r.rss_mb,
            p.history_points
        );
        println!(
            "{:<33} {:>7} {:>10} {:>10} {:>9} {:>9} {:>10}",
            "GET", "gets", "cpu us/get", "-polling", "ms/get", "plain ms", "bytes"
        );
        for (page, gets, cpu, net, ms, plain, bytes) in [
            (
                "/metrics",
                p.metrics_gets,
                p.metrics_cpu_us_per_get,
                p.metrics_cpu_us_per_get_less_polling,
                p.metrics_ms_per_get,
                p.metrics_ms_per_get_plain_client,
                p.metrics_bytes,
            ),
            (
                "/values",
                p.values_gets,
                p.values_cpu_us_per_get,
                p.values_cpu_us_per_get_less_polling,
                p.values_ms_per_get,
                p.values_ms_per_get_plain_client,
                p.values_bytes,
            ),
            (
                "/values?history=1",
                p.history_gets,
                p.history_cpu_us_per_get,
                p.history_cpu_us_per_get_less_polling,
                p.history_ms_per_get,
                p.history_ms_per_get_plain_client,
                p.history_bytes,
            ),
        ] {
            println!(
                "{page:<33} {gets:>7} {cpu:>10.0} {net:>10.0} {ms:>9.2} {plain:>9.2} {bytes:>10}"
            );
        }
    }
}

/// The journal scenarios' own columns: each beside the `-journal-off` one of its run.
pub(crate) fn print_journal_table(reports: &[Report]) {
    let rows: Vec<_> = reports
        .iter()
        .filter_map(|r| Some((r, r.journal.as_ref()?)))
        .filter(|(r, _)| r.scenario.contains("-journal-"))
        .collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "\n{:<40} {:>8} {:>7} {:>9} {:>7} {:>10} {:>10} {:>8} {:>8} {:>8} {:>9} {:>8} {:>6}",
        "scenario (audit journal)",
        "tx/s",
        "x off",
        "cpu us/tx",
        "writes",
        "+cpu us/w",
        "+wall ms/w",
        "r p50 ms",
        "w p50 ms",
        "w p99 ms",
        "+w p50 ms",
        "B/write",
        "fs"
    );
    for (r, j) in rows {
        println!(
            "{:<40} {:>8.1} {:>7} {:>9} {:>7} {:>10} {:>10} {:>8} {:>8} {:>8} {:>9} {:>8} {:>6}",
            r.scenario,
            r.tx_per_s,
            cell(j.tx_vs_journal_off, 3),
            cell(r.cpu_us_per_tx, 1),
            j.writes,
            cell(j.cpu_us_per_write_vs_journal_off, 1),
            cell(j.wall_ms_per_write_vs_journal_off, 3),
            cell(j.read_p50_ms, 3),
            cell(j.write_p50_ms, 3),
            cell(j.write_p99_ms, 3),
            cell(j.write_p50_ms_vs_journal_off, 3),
            cell(j.journal_bytes_per_write, 0),
            j.journal_fs.as_deref().unwrap_or("-"),
        );
    }
}

/// The virtual-unit scenarios' own columns: reads answered from memory, which take no line time,
/// so they have no efficiency; the rate, latency and CPU are the gateway's alone.
pub(crate) fn print_virtual_table(reports: &[Report]) {
    let rows: Vec<_> = reports
        .iter()
        .filter_map(|r| Some((r, r.virtual_unit.as_ref()?)))
        .collect();
    if rows.is_empty() {
        return;
    }
    println!("\nanswered from memory: no line time, so no efficiency");
    println!(
        "{:<33} {:>7} {:>5} {:>9} {:>8} {:>8} {:>8} {:>9} {:>10} {:>9} {:>10}",
        "scenario (virtual unit)",
        "masters",
        "regs",
        "tx/s",
        "p50 ms",
        "p99 ms",
        "max ms",
        "cpu us/tx",
        "exceptions",
        "polls/s",
        "line tx/s"
    );
    for (r, v) in rows {
        println!(
            "{:<33} {:>7} {:>5} {:>9.0} {:>8} {:>8} {:>8} {:>9} {:>10} {:>9} {:>10}",
            r.scenario,
            r.masters,
            v.virtual_registers,
            r.tx_per_s,
            cell(r.p50_ms, 3),
            cell(r.p99_ms, 3),
            cell(r.max_ms, 1),
            cell(r.cpu_us_per_tx, 1),
            v.exceptions,
            cell(v.line_polls_per_s, 1),
            cell(r.line_tx_per_s, 1),
        );
    }
}

/// The MQTT scenarios' own columns: the first publication, the steady rate, and the gateway with
/// MQTT beside itself without it (`w/o`): CPU while it only polls, memory, and the latency of the
/// masters reading beside it.
pub(crate) fn print_mqtt_table(reports: &[Report]) {
    for r in reports {
        let Some(m) = &r.mqtt else {
            continue;
        };
        println!(
            "\n{:<33} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8} {:>8} {:>9} {:>8} {:>8} {:>7} {:>7}",
            "scenario (MQTT)",
            "values",
            "every s",
            "gap s",
            "max gap",
            "pass s",
            "discov s",
            "publ s",
            "discov/s",
            "recv/s",
            "sent/s",
            "peak/s",
            "dropped"
        );
        println!(
            "{:<33} {:>7} {:>7.0} {:>7} {:>7} {:>7.1} {:>8} {:>8} {:>9} {:>8.1} {:>8.1} {:>7} {:>7}",
            r.scenario,
            m.plant_values,
            m.publish_interval_s,
            cell(m.value_gap_mean_s, 2),
            cell(m.value_gap_max_s, 2),
            m.first_pass_s,
            cell(m.discovery_s, 2),
            cell(m.first_publication_s, 2),
            cell(m.discovery_msgs_per_s, 0),
            m.received_per_s,
            m.published_per_s,
            m.peak_received_per_s,
            m.dropped
        );
        println!(
            "{:<33} {:>9} {:>9} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
            "with MQTT / without",
            "cpu ms/s",
            "w/o",
            "us/msg",
            "broker",
            "rss MB",
            "w/o",
            "p50 ms",
            "w/o",
            "p99 ms",
            "w/o"
        );
        println!(
            "{:<33} {:>9.2} {:>9.2} {:>8} {:>8} {:>8.1} {:>8.1} {:>8} {:>8} {:>8} {:>8}",
            format!("{} masters every {:.0} ms", r.masters, m.master_period_ms),
            m.poll_cpu_ms_per_s,
            m.poll_cpu_ms_per_s_without_mqtt,
            cell(m.mqtt_cpu_us_per_message, 1),
            cell(m.broker_cpu_ms_per_s, 2),
            m.rss_polling_mb,
            m.rss_polling_mb_without_mqtt,
            cell(r.p50_ms, 2),
            cell(m.p50_ms_without_mqtt, 2),
            cell(r.p99_ms, 2),
            cell(m.p99_ms_without_mqtt, 2),
        );
    }
}
