//! How polls share the line, on tokio's paused clock over the simulated line (19200 8E1, slaves
//! that answer at once): ten masters saturating it are each held up by one transaction at most
//! by a poll list that is always due, and with nobody else on the line polling takes at most
//! `poll_share` of it, and nearly all of it when it has that much to read.

use super::plan::Read;
use super::poller::{self, Poll};
use super::store::{Store, ValueSpec};
use crate::bus::{BusHandle, BusTask, Device};
use crate::config::{self, Config, Table, Value};
use crate::error::Answer;
use crate::metrics::Metrics;
use crate::shutdown::Stopping;
use crate::sim::{RegisterBank, SimLine, Source};
use std::sync::Arc;
use std::time::Duration;
use tokio::time::{sleep, Instant};

const MASTERS: u8 = 10;
/// The poller's slave: the masters' are 1 to 10.
const POLLED: u8 = 11;
/// Read 10 registers: every master's read and every poll the same size on the wire.
const COUNT: u16 = 10;
const RUN: Duration = Duration::from_secs(20);

fn settings() -> config::Bus {
    let text = "[[bus]]\nname = \"line\"\ndevice = \"sim\"\nbaud = 19200\nqueue_timeout = \"1h\"\n";
    Config::from_toml_str(text)
        .expect("test config")
        .bus
        .remove(0)
}

/// A line with slaves 1 to 11 answering at once, and a bus task serving it.
async fn bus() -> (SimLine, BusHandle) {
    let settings = settings();
    let line = SimLine::new(settings.line_timing());
    for address in 1..=POLLED {
        line.add_slave(address, RegisterBank::new(Duration::ZERO));
    }
    let task = BusTask::new(settings, Device::Sim(line.clone()), &Metrics::new());
    let bus = task.handle();
    tokio::spawn(task.run(Stopping::never()));
    sleep(Duration::from_millis(10)).await;
    (line, bus)
}

/// `polls` reads of [`COUNT`] registers of slave [`POLLED`], due every 10 ms: more than any
/// share of the line can carry, so polling always has something due.
fn start_polling(bus: &BusHandle, polls: u16, share: f64) -> tokio::task::JoinHandle<()> {
    let store = Arc::new(Store::default());
    let value: Value = toml::from_str("name = \"v\"\nregister = 0\n").expect("a value");
    let mut specs = Vec::new();
    let mut list = Vec::new();
    for n in 0..polls {
        specs.push(ValueSpec {
            bus: "line".into(),
            slave: POLLED,
            name: format!("v{n}"),
            help: String::new(),
            unit: None,
            labels: Default::default(),
        });
        let read = Read {
            slave: POLLED,
            table: Table::Holding,
            first: 100 * n,
            count: COUNT,
            interval: Duration::from_millis(10),
            values: vec![(usize::from(n), 0)],
        };
        list.push(Poll {
            read,
            values: vec![(usize::from(n), 0, value.clone())],
        });
    }
    store.configure(specs);
    tokio::spawn(poller::run(bus.clone(), list, store, share))
}

/// Each master's latencies over [`RUN`], every master reading its own slave back to back.
async fn saturate(bus: &BusHandle) -> Vec<Vec<Duration>> {
    let end = Instant::now() + RUN;
    let masters: Vec<_> = (1..=MASTERS)
        .map(|slave| {
            let bus = bus.clone();
            tokio::spawn(async move {
                let mut latencies = Vec::new();
                let read = [0x03, 0x00, 0x00, 0x00, 0x0A];
                while Instant::now() < end {
                    let asked = Instant::now();
                    let outcome = bus.submit(u64::from(slave), slave, read.to_vec()).await;
                    assert!(matches!(outcome, Ok(Ok(Answer::Reply(_)))), "{outcome:?}");
                    latencies.push(asked.elapsed());
                }
                latencies
            })
        })
        .collect();
    let mut all = Vec::new();
    for master in masters {
        all.push(master.await.expect("a master"));
    }
    all
}

fn p99(latencies: &mut [Duration]) -> Duration {
    latencies.sort_unstable();
    latencies[latencies.len() * 99 / 100]
}

/// Polls hold each master up by one transaction at most.
#[tokio::test(start_paused = true)]
async fn ten_masters_saturating_the_line_wait_at_most_one_poll_transaction_each() {
    let (_, quiet) = bus().await;
    let mut alone = saturate(&quiet).await;
    let (line, busy) = bus().await;
    let polling = start_polling(&busy, 20, 0.2);
    let mut shared = saturate(&busy).await;
    polling.abort();
    let polls = line
        .frames()
        .iter()
        .filter(|f| f.from == Source::Master && f.bytes[0] == POLLED)
        .count();
    // One a round of the ten masters: about 20 s / (11 x 21 ms).
    assert!(polls > 60, "the polls got their turns: {polls}");
    for (m, (alone, shared)) in alone.iter_mut().zip(&mut shared).enumerate() {
        let (before, after) = (p99(alone), p99(shared));
        // Alone, a master's request waits for the ten masters' turns: one round, ten
        // transactions. Beside the polls, at most one transaction more.
        let one = before / u32::from(MASTERS);
        assert!(
            after <= before + one,
            "master {m}: p99 {before:?} alone, {after:?} beside the polls (one transaction: {one:?})"
        );
    }
}

/// With nobody else on the line.
#[tokio::test(start_paused = true)]
async fn on_an_idle_line_polling_takes_at_most_its_share_and_nearly_all_of_it() {
    for share in [0.2, 0.5] {
        let (line, bus) = bus().await;
        let started = Instant::now();
        let polling = start_polling(&bus, 20, share);
        sleep(RUN).await;
        polling.abort();
        let elapsed = started.elapsed().as_secs_f64();
        // Each poll's time on the line: from its request's first bit to its reply's last.
        let frames = line.frames();
        let used: f64 = frames
            .windows(2)
            .filter(|pair| pair[0].from == Source::Master && pair[1].from != Source::Master)
            .map(|pair| (pair[1].end - pair[0].start).as_secs_f64())
            .sum();
        let taken = used / elapsed;
        assert!(
            taken <= share,
            "share {share}: polling took {taken:.3} of the line"
        );
        assert!(
            taken >= 0.9 * share,
            "share {share}: polling took only {taken:.3}"
        );
    }
}
