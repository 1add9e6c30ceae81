//! The gateway's HTTP endpoint as the bench uses it: its metrics scraped at the window's ends, a
//! reader on `GET /trace`, a scraper fetching `/metrics` back to back (`--scrape`), and any other
//! page's body (`GET /values`).

use clap::ValueEnum;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// How the `--trace` reader reads.
#[derive(Clone, Copy, PartialEq, ValueEnum)]
pub(crate) enum TraceReader {
    Reading,
    Stalled,
}

/// A trace reader while it lives.
pub(crate) enum Watching {
    Reading(tokio::task::JoinHandle<()>),
    Stalled(#[allow(dead_code)] TcpStream),
}

impl Drop for Watching {
    fn drop(&mut self) {
        if let Watching::Reading(task) = self {
            task.abort();
        }
    }
}

/// Open `GET /trace` on the metrics endpoint at `addr` and read it as `how` says.
pub(crate) async fn watch_trace(addr: SocketAddr, how: TraceReader) -> Result<Watching, String> {
    let mut stream = http_get(addr, "/trace", "opening the trace").await?;
    Ok(match how {
        TraceReader::Stalled => Watching::Stalled(stream),
        TraceReader::Reading => Watching::Reading(tokio::spawn(async move {
            let mut buf = vec![0; 64 * 1024];
            while matches!(stream.read(&mut buf).await, Ok(n) if n > 0) {}
        })),
    })
}

/// A connection to the gateway's metrics endpoint at `addr` that has asked for `path` (the
/// server closes it after the answer, or keeps streaming); errors say they happened `doing`.
async fn http_get(addr: SocketAddr, path: &str, doing: &str) -> Result<TcpStream, String> {
    let failed = |e: std::io::Error| format!("{doing}: {e}");
    let mut stream = TcpStream::connect(addr).await.map_err(failed)?;
    let request = format!("GET {path} HTTP/1.1\r\nHost: bench\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.map_err(failed)?;
    Ok(stream)
}

/// The gateway's metrics page.
pub(crate) async fn scrape(addr: SocketAddr) -> Result<String, String> {
    let failed = |e: std::io::Error| format!("scraping the metrics: {e}");
    let mut stream = http_get(addr, "/metrics", "scraping the metrics").await?;
    let mut page = String::new();
    stream.read_to_string(&mut page).await.map_err(failed)?;
    Ok(page)
}

/// How a client acknowledges what it receives.
#[derive(Clone, Copy, PartialEq)]
pub(crate) enum Acks {
    /// As Linux does by default (curl, Prometheus): a lone segment's ACK waits for the next
    /// segment or the delayed-ACK timer.
    Delayed,
    /// At once (TCP_QUICKACK, set again before every read): a sender whose send buffer holds
    /// about one segment, as the gateway's endpoint's does on loopback, never waits for the
    /// timer, so the time is the gateway's.
    Quick,
}

/// The body of the gateway's answer to `GET path`, which must be 200 OK, read acknowledging
/// as `acks` says.
pub(crate) async fn get(addr: SocketAddr, path: &str, acks: Acks) -> Result<String, String> {
    let doing = format!("GET {path}");
    let failed = |e: std::io::Error| format!("{doing}: {e}");
    let mut stream = http_get(addr, path, &doing).await?;
    let mut answer = Vec::new();
    let mut chunk = vec![0; 256 * 1024];
    loop {
        if acks == Acks::Quick {
            socket2::SockRef::from(&stream)
                .set_tcp_quickack(true)
                .map_err(failed)?;
        }
        match stream.read(&mut chunk).await.map_err(failed)? {
            0 => break,
            n => answer.extend_from_slice(&chunk[..n]),
        }
    }
    let mut answer = String::from_utf8(answer).map_err(|e| format!("{doing}: {e}"))?;
    let Some(head) = answer.find("\r\n\r\n") else {
        return Err(format!("{doing}: no end to the answer's head"));
    };
    if !answer.starts_with("HTTP/1.1 200 ") {
        let status = answer.lines().next().unwrap_or_default();
        return Err(format!("{doing}: {status}"));
    }
    answer.drain(..head + 4);
    Ok(answer)
}

/// The sum of the samples of `name` on the bench's bus with every one of `labels`.
pub(crate) fn sample(page: &str, name: &str, labels: &[&str]) -> f64 {
    let mut on_bus = labels.to_vec();
    on_bus.push("bus=\"bench\"");
    sample_any(page, name, &on_bus)
}

/// The sum of the samples of `name` with every one of `labels`, whatever their bus, if any (the
/// MQTT metrics have none).
pub(crate) fn sample_any(page: &str, name: &str, labels: &[&str]) -> f64 {
    page.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let (series, value) = l.rsplit_once(' ')?;
            let (metric, set) = series.split_once('{').unwrap_or((series, ""));
            (metric == name && labels.iter().all(|x| set.contains(x)))
                .then(|| value.parse::<f64>().ok())?
        })
        .sum()
}

/// What the window's metrics say: line transactions, the gateway's own polls among them,
/// coalesced requests, and the queue wait's sum and count by class.
#[derive(Default)]
pub(crate) struct Counters {
    pub(crate) line_tx: f64,
    pub(crate) polls: f64,
    pub(crate) coalesced: f64,
    pub(crate) wait: [(f64, f64); 2],
}

impl Counters {
    pub(crate) fn of(page: &str) -> Counters {
        let wait = |class| {
            let class = format!("class=\"{class}\"");
            (
                sample(page, "modbus_gateway_queue_wait_seconds_sum", &[&class]),
                sample(page, "modbus_gateway_queue_wait_seconds_count", &[&class]),
            )
        };
        Counters {
            line_tx: sample(page, "modbus_gateway_round_trip_seconds_count", &[]),
            polls: sample(page, "modbus_gateway_polls_total", &[]),
            coalesced: sample(page, "modbus_gateway_coalesced_requests_total", &[]),
            wait: [wait("normal"), wait("priority")],
        }
    }
}

/// One scrape by the `--scrape` scraper: when it ended, how long it took, how many bytes.
pub(crate) type Scraped = (Instant, Duration, usize);

/// A scraper fetching `/metrics` back to back, as often as the gateway answers, until dropped:
/// does scraping slow the line?
pub(crate) struct Scraper {
    task: tokio::task::JoinHandle<()>,
    scrapes: Arc<Mutex<Vec<Scraped>>>,
}

impl Scraper {
    pub(crate) fn start(addr: SocketAddr) -> Scraper {
        let scrapes = Arc::new(Mutex::new(Vec::new()));
        let record = scrapes.clone();
        let task = tokio::spawn(async move {
            loop {
                let began = Instant::now();
                let Ok(page) = scrape(addr).await else {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                    continue;
                };
                let now = Instant::now();
                let mut record = record.lock().unwrap_or_else(PoisonError::into_inner);
                record.push((now, now - began, page.len()));
            }
        });
        Scraper { task, scrapes }
    }

    /// The scrapes that ended in `from..=to`.
    pub(crate) fn within(&self, from: Instant, to: Instant) -> Vec<Scraped> {
        let scrapes = self.scrapes.lock().unwrap_or_else(PoisonError::into_inner);
        scrapes
            .iter()
            .filter(|(at, _, _)| *at >= from && *at <= to)
            .copied()
            .collect()
    }
}

impl Drop for Scraper {
    fn drop(&mut self) {
        self.task.abort();
    }
}
