//! The `values-` scenarios: no master; the gateway polls every slave's plant values (each slave's
//! `[[bus.slave]]` listing [`PLANT_VALUES`], written here). It is waited on until every value has
//! been read once (`GET /values` until none is null), then measured: its CPU time a second while
//! it only polls, its memory, and the CPU time, wall time and size of each answer to `GET
//! /metrics`, `GET /values` and `GET /values?history=1`, fetched back to back by a client that
//! acknowledges at once, and the wall time of a fetch by an ordinary one. The figures are
//! `report`'s.

use crate::gateway::{cpu_time, rss_mb, Gateway};
use crate::scenarios::{plant_base, PLANT_VALUES, SLAVES};
use crate::watch::{get, sample, scrape, Acks};
use crate::Cli;
use std::fmt::Write as _;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// How long the first pass over every value may take. At 115200 8N1 with the default
/// `poll_share` (0.2), each slave's read of 24 registers (8 characters out, 53 back) takes the
/// line about 7.4 ms and polling leaves it four times as long to others: about 9 s for 247
/// slaves.
const FIRST_PASS_LIMIT: Duration = Duration::from_secs(120);
/// How often the bench looks whether every value has been read.
const FIRST_PASS_CHECK: Duration = Duration::from_millis(250);

/// The `[[bus.slave]]` of every simulated slave, each listing [`PLANT_VALUES`] in the input
/// registers of its own block, at the default `poll_interval` (10 s).
pub(crate) fn slaves() -> String {
    (1..=SLAVES).map(slave).collect()
}

/// The `[[bus.slave]]` of slave `address`, listing [`PLANT_VALUES`] in its block's input registers.
pub(crate) fn slave(address: u8) -> String {
    let mut toml = String::new();
    let base = plant_base(address);
    let _ = writeln!(toml, "[[bus.slave]]\naddress = {address}");
    for v in &PLANT_VALUES {
        let _ = writeln!(
            toml,
            "[[bus.slave.value]]\nname = \"{}\"\nregister = {}\ntable = \"input\"\n\
             type = \"{}\"\nscale = {:?}",
            v.name,
            base + v.offset,
            v.kind,
            v.scale
        );
        if let Some(bit) = v.bit {
            let _ = writeln!(toml, "bit = {bit}");
        }
        if v.words_little {
            toml.push_str("word_order = \"little\"\n");
        }
        if v.bytes_little {
            toml.push_str("byte_order = \"little\"\n");
        }
        if let Some(unit) = v.unit {
            let _ = writeln!(toml, "unit = \"{unit}\"");
        }
    }
    toml
}

/// One page fetched back to back: how many times, the gateway's CPU time and the wall time
/// across them, the wall time of one fetch by a client that delays its ACKs, and the size of
/// the last answer's body.
pub(crate) struct Gets {
    pub(crate) count: u64,
    pub(crate) cpu: Duration,
    pub(crate) wall: Duration,
    pub(crate) plain: Duration,
    pub(crate) bytes: usize,
}

/// What the scenario saw.
pub(crate) struct PlantWindow {
    /// The values `GET /values` lists.
    pub(crate) values: usize,
    /// From the gateway listening until every value had been read once.
    pub(crate) first_pass: Duration,
    /// The window in which the gateway only polled: its length, the gateway's CPU time across
    /// it, and the polls it sent (`modbus_gateway_polls_total`).
    pub(crate) polling: Duration,
    pub(crate) polling_cpu: Duration,
    /// The device server's (`simulate`'s) CPU time across it, on that line.
    pub(crate) far_polling_cpu: Option<Duration>,
    pub(crate) polls: f64,
    /// The gateway's memory after that window, before any page was fetched, and at the end.
    pub(crate) rss_polling_mb: f64,
    pub(crate) rss_mb: f64,
    pub(crate) metrics: Gets,
    pub(crate) values_gets: Gets,
    pub(crate) history: Gets,
    /// Readings per value in the last `GET /values?history=1`, on average.
    pub(crate) history_points: f64,
}

/// Wait for the first pass of the gateway's polls, then take the polling window (`--seconds`)
/// and fetch each page back to back (for `--seconds` and at least `--rounds` times); `far` is
/// the device server's process, if the line has one.
pub(crate) async fn measure(
    cli: &Cli,
    (gateway, far): (&Gateway, Option<u32>),
    listening: Instant,
) -> Result<PlantWindow, String> {
    let (pid, addr) = (gateway.pid(), gateway.metrics);
    let values = first_pass(addr).await?;
    let first_pass = listening.elapsed();
    let expected = usize::from(SLAVES) * PLANT_VALUES.len();
    if values != expected {
        return Err(format!("GET /values lists {values} values, not {expected}"));
    }
    let polls = |page: &str| sample(page, "modbus_gateway_polls_total", &[]);
    let before = polls(&scrape(addr).await?);
    let far_start = far.map(cpu_time);
    let (start, cpu_start) = (Instant::now(), cpu_time(pid));
    tokio::time::sleep(Duration::from_secs_f64(cli.seconds)).await;
    let (polling, polling_cpu) = (start.elapsed(), cpu_time(pid) - cpu_start);
    let far_polling_cpu = far.map(cpu_time).zip(far_start).map(|(e, s)| e - s);
    let after = polls(&scrape(addr).await?);
    let rss_polling_mb = rss_mb(pid);
    let (metrics, _) = gets(cli, pid, addr, "/metrics").await?;
    let (values_gets, _) = gets(cli, pid, addr, "/values").await?;
    let (history, last) = gets(cli, pid, addr, "/values?history=1").await?;
    let listed = listing(&last)?;
    let points: usize = listed
        .iter()
        .map(|v| v["history"].as_array().map_or(0, Vec::len))
        .sum();
    Ok(PlantWindow {
        values,
        first_pass,
        polling,
        polling_cpu,
        far_polling_cpu,
        polls: after - before,
        rss_polling_mb,
        rss_mb: rss_mb(pid),
        metrics,
        values_gets,
        history,
        history_points: points as f64 / listed.len().max(1) as f64,
    })
}

/// Wait (at most [`FIRST_PASS_LIMIT`]) until `GET /values` lists no value unread; how many it
/// lists.
pub(crate) async fn first_pass(addr: SocketAddr) -> Result<usize, String> {
    let started = Instant::now();
    loop {
        let listed = listing(&get(addr, "/values", Acks::Delayed).await?)?;
        let unread = listed.iter().filter(|v| v["value"].is_null()).count();
        if unread == 0 && !listed.is_empty() {
            return Ok(listed.len());
        }
        if started.elapsed() > FIRST_PASS_LIMIT {
            return Err(format!(
                "{unread} of {} plant values still unread after {FIRST_PASS_LIMIT:?}",
                listed.len()
            ));
        }
        tokio::time::sleep(FIRST_PASS_CHECK).await;
    }
}

/// The values of a `GET /values` answer.
fn listing(body: &str) -> Result<Vec<serde_json::Value>, String> {
    let mut page: serde_json::Value =
        serde_json::from_str(body).map_err(|e| format!("GET /values: {e}"))?;
    match page.get_mut("values").map(serde_json::Value::take) {
        Some(serde_json::Value::Array(values)) => Ok(values),
        _ => Err("GET /values: no list of values".into()),
    }
}

/// `path` fetched back to back by a client that acknowledges at once, for `--seconds` and at
/// least `--rounds` times, then `--rounds` times by one that delays its ACKs as Linux does by
/// default; and the last answer's body.
async fn gets(cli: &Cli, pid: u32, addr: SocketAddr, path: &str) -> Result<(Gets, String), String> {
    let least = Duration::from_secs_f64(cli.seconds);
    let (start, cpu_start) = (Instant::now(), cpu_time(pid));
    let mut count = 0;
    let last = loop {
        let body = get(addr, path, Acks::Quick).await?;
        count += 1;
        if start.elapsed() >= least && count >= u64::from(cli.rounds) {
            break body;
        }
    };
    let (wall, cpu) = (start.elapsed(), cpu_time(pid) - cpu_start);
    let plain = Instant::now();
    for _ in 0..cli.rounds {
        get(addr, path, Acks::Delayed).await?;
    }
    let gets = Gets {
        count,
        cpu,
        wall,
        plain: plain.elapsed() / cli.rounds.max(1),
        bytes: last.len(),
    };
    Ok((gets, last))
}

#[cfg(test)]
mod tests {
    use super::*;
    use test_support::{Bus, GatewayConfig};

    #[test]
    fn each_slaves_plant_values_are_a_block_of_their_own_the_gateway_accepts() {
        let config = GatewayConfig::new()
            .bus(Bus::sim("bench").text(&slaves()))
            .load();
        let slaves = &config.bus[0].slave;
        assert_eq!(slaves.len(), usize::from(SLAVES));
        for slave in slaves {
            assert_eq!(slave.value.len(), PLANT_VALUES.len());
            // Every register from the block's start to its 24th read by some value, no other:
            // one contiguous read.
            let base = u32::from(plant_base(slave.address));
            let mut read = [false; 24];
            for v in &slave.value {
                for r in v.register..v.register + u32::from(v.width()) {
                    let at = r.checked_sub(base).and_then(|at| usize::try_from(at).ok());
                    *at.and_then(|at| read.get_mut(at))
                        .expect("within the block") = true;
                }
            }
            assert!(read.iter().all(|&r| r), "slave {}", slave.address);
        }
    }
}
