//! Does scraping /metrics slow the bus? Runs a gateway on a simulated 19200 8E1 line with 247
//! register slaves, polled by 100 Modbus TCP masters (read 10 holding registers, round robin over
//! the slaves), first without scrapes, then with one scraper fetching /metrics back to back.
//! Prints, for each phase, the line's busy fraction (from the gateway's own
//! `modbus_gateway_line_busy_seconds_total`), transactions per second, and the scrape times.
//!
//! `cargo run --release --example scrape_under_load [SECONDS_PER_PHASE] [ROUNDS]`

// Test code may be long and cast freely; the lint table in Cargo.toml is for the product.
#![allow(
    unreachable_pub,
    clippy::too_many_lines,
    clippy::cast_possible_truncation
)]

use modbus_gateway::{Config, Gateway};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const MASTERS: usize = 100;
const SLAVES: u8 = 247;

const CONFIG: &str = "[server]\nlisten = \"127.0.0.1:0\"\n\
    [metrics]\nlisten = \"127.0.0.1:0\"\n\
    [log]\nlevel = \"warn\"\n\
    [[bus]]\nname = \"sim\"\ndevice = \"sim\"\nbaud = 19200\nparity = \"even\"\n\
    queue_depth = 1024\nqueue_timeout = \"10s\"\n\
    [[bus.sim_slave]]\naddress = \"1-247\"\n";

async fn master(addr: SocketAddr, first_slave: u8, stop: Arc<AtomicBool>, done: Arc<AtomicU64>) {
    let mut stream = TcpStream::connect(addr).await.expect("connect");
    stream.set_nodelay(true).expect("nodelay");
    let mut slave = first_slave;
    let mut tid: u16 = 0;
    let mut reply = [0u8; 9 + 20];
    while !stop.load(Ordering::Relaxed) {
        tid = tid.wrapping_add(1);
        let [th, tl] = tid.to_be_bytes();
        let adu = [th, tl, 0, 0, 0, 6, slave, 0x03, 0x00, 0x00, 0x00, 0x0A];
        stream.write_all(&adu).await.expect("send");
        stream.read_exact(&mut reply).await.expect("reply");
        assert_eq!(&reply[..2], &[th, tl], "transaction id");
        done.fetch_add(1, Ordering::Relaxed);
        slave = slave % SLAVES + 1;
    }
}

async fn get(addr: SocketAddr, path: &str) -> String {
    let mut stream = TcpStream::connect(addr).await.expect("connect");
    let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.expect("send");
    let mut response = String::new();
    stream.read_to_string(&mut response).await.expect("read");
    response
}

fn busy_seconds(scrape: &str) -> f64 {
    scrape
        .lines()
        .find_map(|l| l.strip_prefix("modbus_gateway_line_busy_seconds_total{bus=\"sim\"} "))
        .and_then(|v| v.parse().ok())
        .expect("busy seconds in the scrape")
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    let rank = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[rank]
}

struct Phase {
    busy_fraction: f64,
    tx_per_s: f64,
    scrapes: Vec<Duration>,
    scrape_bytes: usize,
}

async fn phase(gateway: &Gateway, seconds: f64, scraping: bool, done: &AtomicU64) -> Phase {
    let metrics = gateway.metrics_addr();
    let busy_before = busy_seconds(&get(metrics, "/metrics").await);
    let done_before = done.load(Ordering::Relaxed);
    let started = Instant::now();
    let length = Duration::from_secs_f64(seconds);
    let mut scrapes = Vec::new();
    let mut scrape_bytes = 0;
    if scraping {
        while started.elapsed() < length {
            let t = Instant::now();
            let body = get(metrics, "/metrics").await;
            scrapes.push(t.elapsed());
            scrape_bytes = body.len();
        }
    } else {
        tokio::time::sleep(length).await;
    }
    let wall = started.elapsed().as_secs_f64();
    let busy_after = busy_seconds(&get(metrics, "/metrics").await);
    scrapes.sort();
    Phase {
        busy_fraction: (busy_after - busy_before) / wall,
        tx_per_s: (done.load(Ordering::Relaxed) - done_before) as f64 / wall,
        scrapes,
        scrape_bytes,
    }
}

#[tokio::main]
async fn main() {
    let mut args = std::env::args().skip(1);
    let seconds: f64 = args.next().and_then(|a| a.parse().ok()).unwrap_or(10.0);
    let rounds: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(3);
    let config = Config::from_toml_str(CONFIG).expect("config");
    let gateway = Gateway::start(&config).await.expect("gateway starts");
    let addr = gateway.local_addrs()[0];
    let stop = Arc::new(AtomicBool::new(false));
    let done = Arc::new(AtomicU64::new(0));
    let masters: Vec<_> = (0..MASTERS)
        .map(|i| {
            let first = (i % usize::from(SLAVES)) as u8 + 1;
            tokio::spawn(master(addr, first, stop.clone(), done.clone()))
        })
        .collect();
    // Let every master connect and the queue fill.
    tokio::time::sleep(Duration::from_secs(1)).await;
    println!(
        "{MASTERS} masters, {SLAVES} slaves, 19200 8E1, read 10 registers; {seconds} s a phase"
    );
    println!("phase      busy    tx/s   scrapes  p50 ms  p99 ms  max ms  bytes");
    for _ in 0..rounds {
        for scraping in [false, true] {
            let p = phase(&gateway, seconds, scraping, &done).await;
            let ms = |d: Duration| d.as_secs_f64() * 1e3;
            println!(
                "{:<9} {:.4} {:7.1} {:8} {:7.2} {:7.2} {:7.2} {:6}",
                if scraping { "scraping" } else { "quiet" },
                p.busy_fraction,
                p.tx_per_s,
                p.scrapes.len(),
                ms(percentile(&p.scrapes, 0.5)),
                ms(percentile(&p.scrapes, 0.99)),
                ms(p.scrapes.last().copied().unwrap_or_default()),
                p.scrape_bytes,
            );
        }
    }
    stop.store(true, Ordering::Relaxed);
    for m in masters {
        let _ = m.await;
    }
}
