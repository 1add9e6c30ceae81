//! HTTP on the metrics endpoint: plain GETs, `/metrics` parsed, `/trace` readers that stall.

use crate::wait::within;
use modbus_gateway::Gateway;
use std::net::SocketAddr;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::task::JoinHandle;

/// One HTTP/1.1 GET over a fresh connection: the status code and the body.
pub async fn http_get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut stream = within("connect to the metrics endpoint", TcpStream::connect(addr))
        .await
        .expect("metrics endpoint accepts");
    let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.expect("send");
    let mut response = String::new();
    within("HTTP response", stream.read_to_string(&mut response))
        .await
        .expect("read the response");
    let (head, body) = response
        .split_once("\r\n\r\n")
        .unwrap_or_else(|| panic!("not an HTTP response: {response:?}"));
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|code| code.parse().ok())
        .unwrap_or_else(|| panic!("no status in {head:?}"));
    (status, body.to_owned())
}

/// One scrape of `/metrics`, parsed: every sample by its series, `name{label="value",...}`, with
/// labels sorted as the gateway writes them.
pub struct Scrape {
    pub text: String,
    samples: std::collections::BTreeMap<String, f64>,
}

impl Scrape {
    pub async fn of(gateway: &Gateway) -> Scrape {
        let (status, text) = http_get(gateway.metrics_addr(), "/metrics").await;
        assert_eq!(status, 200, "{text}");
        Scrape::parse(text)
    }

    pub fn parse(text: String) -> Scrape {
        let samples = text
            .lines()
            .filter(|line| !line.starts_with('#') && !line.is_empty())
            .map(|line| {
                let (series, value) = line
                    .rsplit_once(' ')
                    .unwrap_or_else(|| panic!("not a sample: {line}"));
                let value = value
                    .parse()
                    .unwrap_or_else(|_| panic!("not a number: {line}"));
                (series.to_owned(), value)
            })
            .collect();
        Scrape { text, samples }
    }

    /// The value of `series`, if the gateway exports it.
    pub fn get(&self, series: &str) -> Option<f64> {
        self.samples.get(series).copied()
    }

    /// The value of `series`, which must be exported.
    pub fn value(&self, series: &str) -> f64 {
        self.get(series)
            .unwrap_or_else(|| panic!("no series {series} in\n{}", self.text))
    }

    /// How much `series` grew since `before` (absent counts as 0).
    pub fn delta(&self, before: &Scrape, series: &str) -> f64 {
        self.get(series).unwrap_or(0.0) - before.get(series).unwrap_or(0.0)
    }

    /// Every series of metric `name` (any labels).
    pub fn series_of(&self, name: &str) -> Vec<(&str, f64)> {
        self.samples
            .iter()
            .filter(|(series, _)| series.split('{').next() == Some(name))
            .map(|(series, value)| (series.as_str(), *value))
            .collect()
    }
}

/// `GET /trace` from a client that never reads: its receive buffer made small before it
/// connects, so that its stream blocks after a few events. Keep it to keep it connected.
pub async fn stalled_trace_reader(metrics: SocketAddr) -> TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().expect("a socket");
    socket.set_recv_buffer_size(1024).expect("SO_RCVBUF");
    let mut stream = within("connect to the metrics endpoint", socket.connect(metrics))
        .await
        .expect("metrics endpoint accepts");
    let request = format!("GET /trace HTTP/1.1\r\nHost: {metrics}\r\n\r\n");
    stream.write_all(request.as_bytes()).await.expect("send");
    stream
}

/// As many stalled trace readers as the endpoint takes ([`stalled_trace_reader`]), once a
/// further reader is refused (503). Keep them to keep them connected.
pub async fn fill_trace_with_stalled_readers(metrics: SocketAddr) -> Vec<TcpStream> {
    let mut stalled = Vec::new();
    for _ in 0..modbus_gateway::testing::trace::MAX_READERS {
        stalled.push(stalled_trace_reader(metrics).await);
    }
    within("the stalled readers hold every place of the trace", async {
        while status_line(metrics, "/trace").await != Some(503) {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    stalled
}

/// The status code of a GET of `path` on a fresh connection, read from the status line alone
/// (a trace stream's body never ends); `None` if the endpoint closed the connection instead.
pub async fn status_line(addr: SocketAddr, path: &str) -> Option<u16> {
    let mut stream = TcpStream::connect(addr).await.ok()?;
    let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n");
    stream.write_all(request.as_bytes()).await.ok()?;
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n") {
        match within("a status line", stream.read(&mut byte)).await {
            Ok(1) => head.push(byte[0]),
            _ => return None,
        }
    }
    let head = String::from_utf8_lossy(&head).into_owned();
    head.split(' ').nth(1)?.parse().ok()
}

/// [`http_get`], bounded by `limit`, that says what went wrong instead of failing the test.
pub async fn try_http_get(
    addr: SocketAddr,
    path: &str,
    limit: Duration,
) -> Result<(u16, String), String> {
    let get = async {
        let mut stream = TcpStream::connect(addr)
            .await
            .map_err(|e| format!("connect: {e}"))?;
        let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
        stream
            .write_all(request.as_bytes())
            .await
            .map_err(|e| format!("send: {e}"))?;
        let mut response = String::new();
        stream
            .read_to_string(&mut response)
            .await
            .map_err(|e| format!("receive: {e}"))?;
        let (head, body) = response
            .split_once("\r\n\r\n")
            .ok_or_else(|| format!("not an HTTP response: {response:?}"))?;
        let status = head
            .split(' ')
            .nth(1)
            .and_then(|code| code.parse().ok())
            .ok_or_else(|| format!("no status in {head:?}"))?;
        Ok((status, body.to_owned()))
    };
    tokio::time::timeout(limit, get)
        .await
        .unwrap_or_else(|_| Err(format!("no answer within {limit:?}")))
}

/// A client that connects to `addr` and sends nothing, connecting again whenever it is closed
/// (after `pause`) and at least every 9 s, until aborted.
pub fn silent_socket(addr: SocketAddr, pause: Duration) -> JoinHandle<()> {
    tokio::spawn(async move {
        loop {
            if let Ok(mut stream) = TcpStream::connect(addr).await {
                let mut byte = [0u8; 1];
                let _ = tokio::time::timeout(Duration::from_secs(9), stream.read(&mut byte)).await;
            }
            tokio::time::sleep(pause).await;
        }
    })
}
