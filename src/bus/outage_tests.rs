//! The bus task's back-off and outage log against device servers on loopback, on tokio's paused
//! clock: one that accepts and closes at once (ser2net with its serial port missing), one that
//! comes good after a few such connections, and an RFC 2217 converter whose option negotiation
//! would make the gateway owe it without bound.

use super::{BusHandle, BusTask, Device};
use crate::config::{self, Config, DeviceName};
use crate::error::Answer;
use crate::metrics::Metrics;
use crate::shutdown::Stopping;
use std::cell::RefCell;
use std::io::Write;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, Once, PoisonError};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::{sleep, timeout_at, Instant};

const FIRST: Duration = Duration::from_millis(100);
const MAX: Duration = Duration::from_millis(1_600);
/// How long the converters of these tests are watched.
const PERIOD: Duration = Duration::from_secs(20);
const MS: Duration = Duration::from_millis(1);
/// Read two holding registers from 0000H, and slave 1's answer.
const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x02];
const ANSWER: [u8; 6] = [0x03, 0x04, 0x00, 0x07, 0x00, 0x08];

/// What the gateway logs at info and above on this thread, one event a line, while captured.
#[derive(Clone, Default)]
struct Log(Arc<Mutex<Vec<u8>>>);

thread_local! {
    /// Where this thread's events go: a paused-clock test runs all its tasks on its own thread.
    static CAPTURE: RefCell<Option<Log>> = const { RefCell::new(None) };
}

/// The writer of the process's one subscriber: into the capture of the thread it writes on.
struct ThisThread;

impl Write for ThisThread {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        CAPTURE.with_borrow(|capture| {
            if let Some(Log(text)) = capture {
                let mut text = text.lock().unwrap_or_else(PoisonError::into_inner);
                text.extend_from_slice(bytes);
            }
        });
        Ok(bytes.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Ends a capture when dropped.
struct Capturing;

impl Drop for Capturing {
    fn drop(&mut self) {
        CAPTURE.set(None);
    }
}

impl Log {
    /// Capture this thread's events until the guard is dropped. The subscriber is the process's
    /// global one, set once: a subscriber of one thread's misses events whose call sites another
    /// test's thread met first.
    fn capture(&self) -> Capturing {
        static SUBSCRIBER: Once = Once::new();
        SUBSCRIBER.call_once(|| {
            let subscriber = tracing_subscriber::fmt()
                .with_writer(|| ThisThread)
                .with_max_level(tracing::Level::INFO)
                .with_ansi(false)
                .without_time()
                .finish();
            tracing::subscriber::set_global_default(subscriber).expect("the only subscriber");
        });
        tracing::callsite::rebuild_interest_cache();
        CAPTURE.set(Some(self.clone()));
        Capturing
    }

    fn lines(&self) -> Vec<String> {
        let text = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        String::from_utf8_lossy(&text)
            .lines()
            .map(str::to_owned)
            .collect()
    }
}

/// A 19200 8E1 bus named `line` on `device`, backing off from 100 ms to 1.6 s.
fn settings(device: &str) -> config::Bus {
    let text = format!(
        "[[bus]]\nname = \"line\"\ndevice = \"{device}\"\nbaud = 19200\n\
         response_timeout = \"200ms\"\nreopen_delay = \"{}ms\"\nreopen_delay_max = \"{}ms\"\n",
        FIRST.as_millis(),
        MAX.as_millis()
    );
    let mut config = Config::from_toml_str(&text).expect("test config");
    config.bus.remove(0)
}

/// The bus of `settings` running, counting into `metrics`.
fn running(settings: config::Bus, metrics: &Metrics) -> BusHandle {
    let DeviceName::Server(addr) = settings.device_name() else {
        panic!("a device server");
    };
    let format = settings.format();
    let task = BusTask::new(
        settings,
        Device::Server {
            addr,
            format,
            tls: None,
        },
        metrics,
    );
    let bus = task.handle();
    tokio::spawn(task.run(Stopping::never()));
    bus
}

/// A listener on loopback, and the bus `line` connecting to it at `scheme`.
async fn listener(scheme: &str) -> (TcpListener, config::Bus) {
    let listener = TcpListener::bind("127.0.0.1:0").await.expect("loopback");
    let addr: SocketAddr = listener.local_addr().expect("bound");
    (listener, settings(&format!("{scheme}://{addr}")))
}

/// The next connection within [`PERIOD`] of `start`, and when it came.
async fn next(listener: &TcpListener, start: Instant) -> Option<(TcpStream, Duration)> {
    let (socket, _) = timeout_at(start + PERIOD, listener.accept())
        .await
        .ok()?
        .ok()?;
    Some((socket, start.elapsed()))
}

/// What one wait between two connections must be at least, the `n`th: doubling from the first.
fn least_wait(n: u32) -> Duration {
    (FIRST * 2u32.saturating_pow(n)).min(MAX)
}

fn metric(metrics: &Metrics, series: &str) -> Option<f64> {
    crate::metrics::sample(&metrics.render().expect("metrics render"), series)
}

#[tokio::test(start_paused = true)]
async fn a_device_server_that_accepts_and_closes_at_once_is_connected_ever_less_often() {
    let log = Log::default();
    let _capture = log.capture();
    let (listener, settings) = listener("tcp").await;
    let metrics = Metrics::new();
    let _bus = running(settings, &metrics);
    let start = Instant::now();
    let mut connects = Vec::new();
    while let Some((socket, at)) = next(&listener, start).await {
        drop(socket);
        connects.push(at);
    }
    // 100, 200, 400 and 800 ms, then 1.6 s: 16 connections in 20 s, where a back-off reset by
    // every connection would make 200.
    let most = 5 + (PERIOD - least_wait(4)).as_millis() / MAX.as_millis();
    assert!(
        (5..=most as usize).contains(&connects.len()),
        "{connects:?}"
    );
    for (n, pair) in (0..).zip(connects.windows(2)) {
        assert!(pair[1] - pair[0] >= least_wait(n), "{connects:?}");
    }
    // One outage: the first connection's line, its loss's, and nothing more above debug.
    let lines = log.lines();
    assert_eq!(lines.len(), 2, "{lines:#?}");
    assert!(lines[0].contains("INFO") && lines[0].contains("device server connected"));
    assert!(lines[1].contains("WARN") && lines[1].contains("lost before it served a request"));
    let reopens = metric(&metrics, "modbus_gateway_port_reopens_total{bus=\"line\"}");
    assert_eq!(reopens, Some((connects.len() - 1) as f64));
}

/// Slave 1 behind the converter on `socket`: the next request, answered.
async fn answer_a_read(socket: &mut TcpStream) {
    let mut request = [0u8; 8];
    socket.read_exact(&mut request).await.expect("a request");
    assert_eq!(request[..], crate::line::rtu::encode(1, &READ)[..]);
    let reply = crate::line::rtu::encode(1, &ANSWER);
    socket.write_all(&reply).await.expect("the answer");
}

#[tokio::test(start_paused = true)]
async fn a_flapping_device_servers_outage_ends_in_one_line_that_counts_the_drops() {
    let log = Log::default();
    let _capture = log.capture();
    let (listener, settings) = listener("tcp").await;
    let metrics = Metrics::new();
    let bus = running(settings, &metrics);
    let start = Instant::now();
    for _ in 0..4 {
        drop(next(&listener, start).await.expect("a connection"));
    }
    // The fifth stays, and serves a read once the line has settled.
    let (mut socket, _) = next(&listener, start).await.expect("a connection");
    while !bus.is_up() {
        sleep(MS).await;
    }
    let device = tokio::spawn(async move {
        answer_a_read(&mut socket).await;
        socket
    });
    let outcome = bus.submit(1, 1, READ.to_vec()).await.expect("answered");
    assert_eq!(outcome, Ok(Answer::Reply(ANSWER.to_vec())));
    let lines = log.lines();
    assert_eq!(lines.len(), 3, "{lines:#?}");
    assert!(lines[2].contains("INFO") && lines[2].contains("device server reconnected"));
    assert!(lines[2].contains("lost_before_serving=4"), "{}", lines[2]);
    // It served, so its loss is an outage of its own, reconnected after the first wait again.
    drop(device.await.expect("the device"));
    let lost = Instant::now();
    let (_socket, _) = next(&listener, start).await.expect("a connection");
    assert!(lost.elapsed() <= FIRST + MS, "{:?}", lost.elapsed());
    let lines = log.lines();
    assert!(lines[3].contains("WARN") && lines[3].contains("device server connection lost;"));
}

const IAC: u8 = 255;
const SB: u8 = 250;
const SE: u8 = 240;

/// The RFC 2217 converter on `socket` takes the gateway's negotiation, acknowledges 19200 8E1,
/// then asks for every option there is on both sides, a refusal owed for each.
async fn negotiate_then_ask_everything(socket: &mut TcpStream) {
    let mut asked = Vec::new();
    let set_control = [IAC, SB, 44, 5, 1, IAC, SE]; // the negotiation's last subnegotiation
    while !asked.ends_with(&set_control) {
        let mut byte = [0u8; 1];
        if socket.read_exact(&mut byte).await.is_err() {
            return;
        }
        asked.push(byte[0]);
    }
    #[rustfmt::skip]
    let mut reply = vec![
        IAC, 253, 44, // DO COM-PORT-OPTION
        IAC, SB, 44, 101, 0x00, 0x00, 0x4B, 0x00, IAC, SE, // 19200 baud
        IAC, SB, 44, 102, 8, IAC, SE, // 8 data bits
        IAC, SB, 44, 103, 3, IAC, SE, // even parity
        IAC, SB, 44, 104, 1, IAC, SE, // 1 stop bit
    ];
    for option in (0..=u8::MAX).filter(|option| ![0, 3, 44].contains(option)) {
        reply.extend_from_slice(&[IAC, 253, option, IAC, 251, option]); // DO and WILL
    }
    let _ = socket.write_all(&reply).await;
}

#[tokio::test(start_paused = true)]
async fn a_converter_owed_past_the_cap_is_dropped_counted_and_reconnected_with_back_off() {
    let (listener, settings) = listener("rfc2217").await;
    let metrics = Metrics::new();
    let _bus = running(settings, &metrics);
    let dropped = "modbus_gateway_link_dropped_total{bus=\"line\",reason=\"telnet_answers\"}";
    assert_eq!(metric(&metrics, dropped), Some(0.0), "there from the start");
    let start = Instant::now();
    let mut connects = Vec::new();
    while let Some((mut socket, at)) = next(&listener, start).await {
        connects.push(at);
        negotiate_then_ask_everything(&mut socket).await;
        // Held open: the gateway is the one to close it.
        let mut rest = Vec::new();
        let _ = timeout_at(start + PERIOD, socket.read_to_end(&mut rest)).await;
        if connects.len() == 5 {
            break;
        }
    }
    assert_eq!(connects.len(), 5, "{connects:?}");
    for (n, pair) in (0..).zip(connects.windows(2)) {
        assert!(pair[1] - pair[0] >= least_wait(n), "{connects:?}");
    }
    sleep(MS).await;
    assert_eq!(metric(&metrics, dropped), Some(5.0));
}
