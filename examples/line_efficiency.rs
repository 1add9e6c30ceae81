//! One Modbus TCP master polling back to back through an in-process gateway on a simulated line:
//! prints the bus efficiency against physics (DESIGN.md, "Performance model"), the added latency,
//! and the silence the gateway left before each request compared with t3.5. A first figure until
//! the benchmark harness arrives. The master runs on its own thread and runtime.
//!
//! Usage: cargo run --release --example line_efficiency -- [BAUD] [SECONDS]

use modbus_gateway::sim::Source;
use modbus_gateway::{Config, Gateway};
use std::net::SocketAddr;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Read 10 holding registers of unit 1: 8 RTU bytes out, 25 back.
const REQUEST: [u8; 12] = [0, 1, 0, 0, 0, 6, 1, 0x03, 0x00, 0x00, 0x00, 0x0A];
const REPLY_LEN: usize = 7 + 22;
const RTU_REQUEST: usize = 8;
const RTU_REPLY: usize = 25;

/// Poll until `seconds` have passed; the latency of each transaction.
fn poll(at: SocketAddr, seconds: u64) -> std::io::Result<(Vec<Duration>, Duration)> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let mut stream = TcpStream::connect(at).await?;
        stream.set_nodelay(true)?;
        let mut reply = [0u8; REPLY_LEN];
        let mut latencies = Vec::new();
        let started = Instant::now();
        while started.elapsed() < Duration::from_secs(seconds) {
            let sent = Instant::now();
            stream.write_all(&REQUEST).await?;
            stream.read_exact(&mut reply).await?;
            latencies.push(sent.elapsed());
        }
        Ok((latencies, started.elapsed()))
    })
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() as f64 * q) as usize).min(sorted.len() - 1)]
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let baud: u32 = args.next().map_or(Ok(9600), |a| a.parse())?;
    let seconds: u64 = args.next().map_or(Ok(10), |a| a.parse())?;
    let config = Config::from_toml_str(&format!(
        "[server]\nlisten = \"127.0.0.1:0\"\n[[bus]]\nname = \"sim\"\ndevice = \"sim\"\n\
         baud = {baud}\nparity = \"even\"\n[[bus.sim_slave]]\naddress = 1\n"
    ))?;
    let timing = config.bus[0].line_timing();
    let gateway = Gateway::start(&config).await?;
    let at = gateway.local_addrs()[0];
    let (latencies, wall) = tokio::task::spawn_blocking(move || poll(at, seconds)).await??;

    // The sim slave answers t3.5 after the request, with no processing time.
    let minimum = timing.transaction_minimum(RTU_REQUEST, RTU_REPLY, timing.t35);
    let n = latencies.len();
    let efficiency = (minimum * n as u32).as_secs_f64() / wall.as_secs_f64();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let mut added: Vec<f64> = latencies.iter().map(|l| ms(*l) - ms(minimum)).collect();
    added.sort_by(f64::total_cmp);
    let frames = gateway.sim_line("sim").ok_or("no sim line")?.frames();
    let mut gaps: Vec<f64> = frames
        .windows(2)
        .filter(|w| w[1].from == Source::Master)
        .map(|w| ms(w[1].start - w[0].end))
        .collect();
    gaps.sort_by(f64::total_cmp);
    println!(
        "baud {baud} 8E1: {n} transactions in {:.1} s ({:.1}/s), physical minimum {:.3} ms each, \
         efficiency {efficiency:.3}; added latency p50 {:.3} ms, p99 {:.3} ms; silence before a \
         request p50 {:.3} ms, max {:.3} ms (t3.5 {:.3} ms)",
        wall.as_secs_f64(),
        n as f64 / wall.as_secs_f64(),
        ms(minimum),
        quantile(&added, 0.5),
        quantile(&added, 0.99),
        quantile(&gaps, 0.5),
        quantile(&gaps, 1.0),
        ms(timing.t35),
    );
    gateway.shutdown().await;
    Ok(())
}
