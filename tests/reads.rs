//! Many masters, one read: identical reads coalesced into one transaction (and never answered
//! with data older than the request), `coalesce_reads = false`, the opt-in cache, and priority
//! masters served first up to their share of the line.

use crate::support::{
    addr, settle, sim_bus_counted, sim_line, within, Bus, GatewayConfig, RawMaster, Scrape,
};
use modbus_gateway::testing::bus::BusHandle;
use modbus_gateway::testing::error::Answer;
use modbus_gateway::testing::master::{Origin, Protocol};
use modbus_gateway::testing::metrics::Metrics;
use modbus_gateway::testing::sim::{SimLine, Source};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::Barrier;
use tokio::time::Instant;

/// Read holding registers 0x0010-0x0019 (ten words).
const READ_BLOCK: [u8; 5] = [0x03, 0x00, 0x10, 0x00, 0x0A];

/// The 9600 8E1 sim line named "sim" with room for many readers in its queue, no slaves yet.
fn line_9600() -> Bus {
    sim_line().queue_depth(1024).queue_timeout("30s")
}

/// A gateway on `line` ([`line_9600`] and what the test adds) with register-bank slaves 1-4.
async fn gateway_9600(line: Bus) -> modbus_gateway::Gateway {
    GatewayConfig::new()
        .bus(line.sim_slaves("1-4"))
        .start()
        .await
}

fn master_frames(line: &SimLine) -> usize {
    line.frames()
        .iter()
        .filter(|f| f.from == Source::Master)
        .count()
}

/// The ten words 0x0010-0x0019 as a read answers them: `first`, `first + 1`, ...
fn block_answer(first: u16) -> Vec<u8> {
    let mut pdu = vec![0x03, 20];
    for n in 0..10 {
        pdu.extend_from_slice(&(first + n).to_be_bytes());
    }
    pdu
}

/// The ten words as the register bank holds them before any write: zeros.
fn zeros() -> Vec<u8> {
    let mut pdu = vec![0x03, 20];
    pdu.resize(22, 0);
    pdu
}

/// Write `first`, `first + 1`, ... into 0x0010-0x0019.
fn write_block(first: u16) -> Vec<u8> {
    let mut pdu = vec![0x10, 0x00, 0x10, 0x00, 0x0A, 20];
    for n in 0..10 {
        pdu.extend_from_slice(&(first + n).to_be_bytes());
    }
    pdu
}

/// A hundred masters polling the same registers are answered correctly, by at most two transactions
/// per hundred reads.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hundred_masters_polling_alike_cost_at_most_2_transactions_per_100_reads() {
    const MASTERS: usize = 100;
    const ROUNDS: usize = 5;
    let gateway = gateway_9600(line_9600()).await;
    let at = addr(&gateway);
    let line = gateway.sim_line("sim").expect("sim line");
    let mut writer = RawMaster::connect(at).await;
    assert_eq!(
        writer.call(1, 1, &write_block(100)).await[..5],
        [0x10, 0x00, 0x10, 0x00, 0x0A]
    );
    let before = master_frames(&line);
    let barrier = Arc::new(Barrier::new(MASTERS));
    let mut masters = Vec::new();
    for m in 0..MASTERS {
        let barrier = barrier.clone();
        masters.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(at).await;
            barrier.wait().await;
            for round in 0..ROUNDS {
                let tid = (m * ROUNDS + round) as u16;
                assert_eq!(
                    master.call(tid, 1, &READ_BLOCK).await,
                    block_answer(100),
                    "master {m}"
                );
            }
        }));
    }
    for master in masters {
        within("every master is answered", master)
            .await
            .expect("master");
    }
    let transactions = master_frames(&line) - before;
    let answered = MASTERS * ROUNDS;
    let per_read = transactions as f64 / answered as f64;
    eprintln!("{transactions} transactions for {answered} reads: {per_read:.3} per read");
    assert!(
        per_read <= 0.02,
        "{transactions} transactions for {answered} reads"
    );
    let scrape = Scrape::of(&gateway).await;
    let coalesced =
        scrape.value("modbus_gateway_coalesced_requests_total{bus=\"sim\",slave=\"1\"}");
    assert_eq!(coalesced as usize, answered - transactions);
}

/// While others coalesce; no read gets data from before it arrived.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_master_reads_back_its_write_amid_coalescing_and_no_read_gets_older_data() {
    const READERS: usize = 99;
    const WRITES: u16 = 15;
    let gateway = gateway_9600(line_9600()).await;
    let at = addr(&gateway);
    let line = gateway.sim_line("sim").expect("sim line");
    let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mut readers = Vec::new();
    for m in 0..READERS {
        let done = done.clone();
        readers.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(at).await;
            // (when the request was sent, the first word it got)
            let mut seen = Vec::new();
            let mut tid = 0u16;
            while !done.load(std::sync::atomic::Ordering::Relaxed) {
                tid += 1;
                let sent = Instant::now();
                let pdu = master.call(tid, 1, &READ_BLOCK).await;
                assert_eq!((pdu[0], pdu[1]), (0x03, 20), "reader {m}");
                seen.push((sent, u16::from_be_bytes([pdu[2], pdu[3]])));
            }
            seen
        }));
    }
    let mut writer = RawMaster::connect(at).await;
    for n in 1..=WRITES {
        let value = n * 100;
        writer.call(2 * n, 1, &write_block(value)).await;
        assert_eq!(
            writer.call(2 * n + 1, 1, &READ_BLOCK).await,
            block_answer(value),
            "the writer reads back its own write {n}"
        );
    }
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    let mut reads = Vec::new();
    for reader in readers {
        reads.extend(within("readers finish", reader).await.expect("reader"));
    }
    // Every read's answer came from a frame that started after the read was sent: some request
    // frame starting then or later was answered with the value the read got.
    let frames = line.frames();
    let answered: Vec<(Instant, u16)> = frames
        .windows(2)
        .filter(|pair| pair[0].from == Source::Master && pair[1].from == Source::Slave(1))
        .filter(|pair| pair[1].bytes.get(1..3) == Some(&[0x03, 20][..]))
        .map(|pair| {
            (
                pair[0].start,
                u16::from_be_bytes([pair[1].bytes[3], pair[1].bytes[4]]),
            )
        })
        .collect();
    assert!(
        frames.len() < 4000,
        "the line's record holds the whole test"
    );
    let stale = reads
        .iter()
        .filter(|(sent, value)| {
            !answered
                .iter()
                .any(|(start, v)| start >= sent && v == value)
        })
        .count();
    let transactions = answered.len();
    eprintln!(
        "{} reads, {transactions} read transactions, {stale} stale",
        reads.len()
    );
    assert_eq!(
        stale, 0,
        "reads answered with data from a frame older than the request"
    );
    assert!(reads.len() > 3 * transactions, "the readers coalesced");
}

#[tokio::test]
async fn with_coalesce_reads_off_on_a_slave_each_read_is_a_transaction_of_its_own() {
    let gateway = gateway_9600(line_9600().slave(2, &[("coalesce_reads", false.into())])).await;
    let at = addr(&gateway);
    let line = gateway.sim_line("sim").expect("sim line");
    for (slave, most) in [(2u8, 10usize), (1, 2)] {
        let before = master_frames(&line);
        let barrier = Arc::new(Barrier::new(10));
        let mut masters = Vec::new();
        for m in 0..10u16 {
            let barrier = barrier.clone();
            masters.push(tokio::spawn(async move {
                let mut master = RawMaster::connect(at).await;
                barrier.wait().await;
                master.call(m, slave, &READ_BLOCK).await
            }));
        }
        for master in masters {
            assert_eq!(within("answered", master).await.unwrap(), zeros());
        }
        let transactions = master_frames(&line) - before;
        if slave == 2 {
            assert_eq!(transactions, most, "read-to-clear registers: one read each");
        } else {
            assert!(transactions <= most, "slave 1 coalesces: {transactions}");
        }
    }
}

/// A 9600 8E1 sim line named "sim" whose queue neither fills nor times out, no slaves yet.
fn patient_line() -> Bus {
    sim_line()
        .queue_depth(4096)
        .queue_timeout("600s")
        .response_timeout("200ms")
}

/// The settings of `line` ([`patient_line`] and what the test adds) with register-bank slaves
/// 1-4.
fn bus_settings(line: Bus) -> modbus_gateway::config::Bus {
    GatewayConfig::new()
        .bus(line.sim_slaves("1-4"))
        .load()
        .bus
        .remove(0)
}

fn origin(master: u64, priority: bool) -> Origin {
    Origin {
        master,
        admission: master,
        protocol: Protocol::Tcp,
        class: modbus_gateway::testing::master::Class::of_master(priority),
    }
}

async fn read(bus: &BusHandle, master: u64, slave: u8, pdu: &[u8]) -> Answer {
    bus.submit_from(origin(master, false), slave, pdu.to_vec())
        .await
        .expect("answered")
        .expect("an answer")
}

/// A cached answer serves within its age without the line; a write drops it; exceptions are not
/// cached.
#[tokio::test(start_paused = true)]
async fn the_cache_answers_within_its_age_drops_on_a_write_and_keeps_no_exceptions() {
    let metrics = Metrics::new();
    let (line, bus) = sim_bus_counted(
        bus_settings(patient_line().slave(1, &[("cache", "500ms".into())])),
        &metrics,
    );
    settle(&bus).await;
    let frames = |line: &SimLine| master_frames(line);
    assert_eq!(read(&bus, 1, 1, &READ_BLOCK).await, Answer::Reply(zeros()));
    assert_eq!(frames(&line), 1);
    tokio::time::sleep(Duration::from_millis(400)).await;
    assert_eq!(read(&bus, 2, 1, &READ_BLOCK).await, Answer::Reply(zeros()));
    assert_eq!(frames(&line), 1, "within 500 ms: no frame on the wire");
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(read(&bus, 3, 1, &READ_BLOCK).await, Answer::Reply(zeros()));
    assert_eq!(frames(&line), 2, "older than 500 ms: read again");
    // A write drops it: the read after it sees the new values, from the line.
    let write = bus
        .submit_from(origin(4, false), 1, write_block(7))
        .await
        .unwrap();
    assert!(write.is_ok());
    assert_eq!(
        read(&bus, 5, 1, &READ_BLOCK).await,
        Answer::Reply(block_answer(7))
    );
    assert_eq!(frames(&line), 4);
    // Slave 2 has no cache: every read goes to the line.
    read(&bus, 6, 2, &READ_BLOCK).await;
    read(&bus, 7, 2, &READ_BLOCK).await;
    assert_eq!(frames(&line), 6);
    // An exception (past the register bank's end) is never cached.
    let beyond = [0x03, 0xFF, 0xFF, 0x00, 0x02];
    for master in [8, 9] {
        let answer = read(&bus, master, 1, &beyond).await;
        assert_eq!(answer, Answer::Reply(vec![0x83, 0x02]));
    }
    assert_eq!(frames(&line), 8);
    let text = metrics.render().unwrap();
    let hits =
        Scrape::parse(text).value("modbus_gateway_cache_hits_total{bus=\"sim\",slave=\"1\"}");
    assert_eq!(hits, 1.0);
}

/// One transaction's time on the 9600 8E1 line for a ten-word read.
fn transaction_time(line: &SimLine) -> Duration {
    let timing = line.timing();
    // Request 8 bytes, reply 25, then the gap.
    timing.char_time * (8 + 25) + timing.t35
}

#[tokio::test(start_paused = true)]
async fn a_priority_master_among_a_hundred_saturating_ones_waits_at_most_two_transactions() {
    let (line, bus) = sim_bus_counted(bus_settings(patient_line()), &Metrics::new());
    settle(&bus).await;
    // A hundred masters, each keeping five distinct reads queued, of slaves 1, 3 and 4: slave 2
    // is the priority master's.
    let mut pending = Vec::new();
    for master in 0..100u64 {
        for n in 0..5u16 {
            let register = (master as u16) * 8 + n;
            let pdu = vec![0x03, (register >> 8) as u8, register as u8, 0x00, 0x0A];
            let slave = [1, 3, 4][(master % 3) as usize];
            pending.push(bus.submit_from(origin(100 + master, false), slave, pdu));
        }
    }
    let tx = transaction_time(&line);
    let mut sent = Vec::new();
    for _ in 0..100 {
        sent.push(Instant::now());
        let answer = bus
            .submit_from(origin(1, true), 2, READ_BLOCK.to_vec())
            .await
            .unwrap();
        assert!(answer.is_ok());
    }
    // Its wait: from its request to the start of its frame on the wire.
    let started: Vec<Instant> = line
        .frames()
        .iter()
        .filter(|f| f.from == Source::Master && f.bytes[0] == 2)
        .map(|f| f.start)
        .collect();
    assert_eq!(started.len(), sent.len());
    let mut waits: Vec<Duration> = sent.iter().zip(&started).map(|(s, f)| *f - *s).collect();
    waits.sort();
    let p99 = waits[waits.len() * 99 / 100];
    let p50 = waits[waits.len() / 2];
    eprintln!("priority waits: p50 {p50:?}, p99 {p99:?}, transaction {tx:?}");
    assert!(
        p99 <= 2 * tx,
        "p99 {p99:?} against two transactions of {tx:?}"
    );
    let served = pending.iter().filter(|p| !p.is_empty()).count();
    assert!(
        served >= 5,
        "the others still got the line: {served} answered"
    );
    assert!(served < pending.len(), "and were still waiting");
}

#[tokio::test(start_paused = true)]
async fn a_saturating_priority_master_leaves_the_others_their_share_of_the_line() {
    let (line, bus) = sim_bus_counted(bus_settings(patient_line()), &Metrics::new());
    bus.set_priority_share(0.9);
    settle(&bus).await;
    let mut answers = Vec::new();
    // The priority master reads slave 1, the others slave 2: the line's record says whose.
    for n in 0..300u16 {
        let urgent = vec![0x03, (n >> 8) as u8, n as u8, 0x00, 0x01];
        answers.push(bus.submit_from(origin(1, true), 1, urgent));
        let other = vec![0x03, (n >> 8) as u8, n as u8, 0x00, 0x01];
        answers.push(bus.submit_from(origin(2 + u64::from(n % 10), false), 2, other));
    }
    // 200 transactions while both wait.
    tokio::time::sleep(transaction_time(&line) * 200).await;
    let frames = line.frames();
    let requests: Vec<u8> = frames
        .iter()
        .filter(|f| f.from == Source::Master)
        .map(|f| f.bytes[0])
        .take(200)
        .collect();
    let others = requests.iter().filter(|&&slave| slave == 2).count();
    let share = others as f64 / requests.len() as f64;
    eprintln!("{others} of {} transactions to the others", requests.len());
    assert!(requests.len() >= 150, "{} transactions", requests.len());
    assert!((0.09..=0.12).contains(&share), "the others' share {share}");
    drop(answers);
}
