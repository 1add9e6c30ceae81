//! The live trace: `GET /trace` read over real HTTP from a gateway on the simulated line (frames,
//! filters, timeouts, refusals, a stream that outlives the endpoint's connection lifetime, a
//! stalled reader dropped), a reader that stops reading on the paused clock, the trace's gate
//! with no reader, and the `trace` subcommand run as the real binary.

// Unsafe blocks, each with its SAFETY comment: signalling the daemon under test.
#![allow(unsafe_code)]

use crate::support::{
    http_get, mbap, rtu, sim_bus_counted, sim_line, start, start_sim, within, Bus, GatewayConfig,
    RawMaster,
};
use bytes::Bytes;
use http_body_util::{BodyExt, Empty};
use hyper::body::Incoming;
use modbus_gateway::testing::metrics::Metrics;
use modbus_gateway::testing::sim::Source;
use modbus_gateway::testing::trace::Traced;
use serde_json::Value;
use std::io::BufRead;
use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// A reader of `GET /trace` on a real HTTP connection.
struct Trace {
    response: hyper::Response<Incoming>,
    pending: String,
}

/// One SSE event: its name and its data as JSON, or a comment's text.
#[derive(Debug)]
enum Event {
    Frame(Value),
    Lost(u64),
    Comment(String),
}

impl Trace {
    async fn open(addr: SocketAddr, query: &str) -> Trace {
        let stream = within("connect", TcpStream::connect(addr)).await.unwrap();
        let (mut sender, connection) =
            hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream))
                .await
                .unwrap();
        tokio::spawn(connection);
        let request = hyper::Request::get(format!("/trace{query}"))
            .header(hyper::header::HOST, addr.to_string())
            .body(Empty::<Bytes>::new())
            .unwrap();
        let response = within("trace response", sender.send_request(request))
            .await
            .unwrap();
        assert_eq!(response.status(), 200);
        let headers = response.headers();
        assert_eq!(headers["content-type"], "text/event-stream");
        assert_eq!(headers["cache-control"], "no-cache");
        let mut trace = Trace {
            response,
            pending: String::new(),
        };
        assert!(
            matches!(trace.next().await, Some(Event::Comment(c)) if c == "modbus-gateway trace"),
            "the stream opens with its comment"
        );
        trace
    }

    /// The next event, comments included; `None` once the stream has ended.
    async fn next(&mut self) -> Option<Event> {
        loop {
            if let Some(end) = self.pending.find("\n\n") {
                let text: String = self.pending.drain(..end + 2).collect();
                let text = text.trim_end();
                if let Some(comment) = text.strip_prefix(": ") {
                    return Some(Event::Comment(comment.to_owned()));
                }
                let (name, data) = text.split_once('\n').expect("event and data lines");
                let data: Value = serde_json::from_str(data.strip_prefix("data: ").unwrap())
                    .unwrap_or_else(|e| panic!("{e}: {text}"));
                return Some(match name {
                    "event: frame" => Event::Frame(data),
                    "event: lost" => Event::Lost(data["lost"].as_u64().unwrap()),
                    _ => panic!("unknown event {text}"),
                });
            }
            let frame = within("a trace event", self.response.body_mut().frame()).await?;
            let data = frame.unwrap().into_data().unwrap();
            self.pending.push_str(std::str::from_utf8(&data).unwrap());
        }
    }

    /// The next frame event, skipping keepalives; a lost event fails.
    async fn frame(&mut self) -> Value {
        loop {
            match self.next().await.expect("the stream goes on") {
                Event::Frame(frame) => return frame,
                Event::Comment(_) => {}
                Event::Lost(n) => panic!("lost {n} events"),
            }
        }
    }

    /// The [`fields`] of the next `n` frame events.
    async fn fields_of_next(&mut self, n: usize) -> Vec<Fields> {
        let mut got = Vec::with_capacity(n);
        for _ in 0..n {
            got.push(fields(&self.frame().await));
        }
        got
    }
}

/// Bus, direction, slave, function, hex, outcome.
type Fields = (String, String, u64, u64, String, String);

/// A frame event's fields that the line decides: bus, direction, slave, function, hex, outcome.
fn fields(frame: &Value) -> Fields {
    let text = |key: &str| frame[key].as_str().unwrap().to_owned();
    (
        text("bus"),
        text("direction"),
        frame["slave"].as_u64().unwrap(),
        frame["function"].as_u64().unwrap(),
        text("hex"),
        text("outcome"),
    )
}

fn expect(
    bus: &str,
    direction: &str,
    slave: u64,
    function: u64,
    hex: &str,
    outcome: &str,
) -> Fields {
    (
        bus.into(),
        direction.into(),
        slave,
        function,
        hex.into(),
        outcome.into(),
    )
}

/// `01 03 00 00`: the trace's hex.
fn hex(bytes: &[u8]) -> String {
    let pairs: Vec<String> = bytes.iter().map(|b| format!("{b:02x}")).collect();
    pairs.join(" ")
}

/// Each frame with its hex, direction and outcome.
#[tokio::test]
async fn a_trace_reader_gets_six_frames_for_three_requests_with_hex_and_outcome() {
    let gateway = start_sim("").await;
    let mut trace = Trace::open(gateway.metrics_addr(), "").await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    // Slave 1: two holding registers from 0000H; slave 2: two input registers from 0001H (a
    // register slave's input register n holds n); slave 3: 126 registers, one too many.
    master.call(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x02]).await;
    master.call(2, 2, &[0x04, 0x00, 0x01, 0x00, 0x02]).await;
    master.call(3, 3, &[0x03, 0x00, 0x00, 0x00, 0x7E]).await;
    let mut frames = Vec::new();
    for _ in 0..6 {
        frames.push(trace.frame().await);
    }
    let got: Vec<_> = frames.iter().map(fields).collect();
    // CRCs computed apart from the gateway's (CRC-16/MODBUS, low byte first).
    assert_eq!(
        got,
        [
            expect("sim", "tx", 1, 3, "01 03 00 00 00 02 c4 0b", "ok"),
            expect("sim", "rx", 1, 3, "01 03 04 00 00 00 00 fa 33", "ok"),
            expect("sim", "tx", 2, 4, "02 04 00 01 00 02 20 38", "ok"),
            expect("sim", "rx", 2, 4, "02 04 04 00 01 00 02 18 85", "ok"),
            expect("sim", "tx", 3, 3, "03 03 00 00 00 7e c4 08", "exception"),
            expect("sim", "rx", 3, 0x83, "03 83 03 a0 f1", "exception"),
        ]
    );
    // The same frames, in the same order, as the simulated line carried them.
    let line = gateway.sim_line("sim").unwrap();
    let wire: Vec<String> = line.frames().iter().map(|f| hex(&f.bytes)).collect();
    let traced: Vec<String> = got.iter().map(|f| f.4.clone()).collect();
    assert_eq!(wire, traced);
    assert_eq!(line.frames()[1].from, Source::Slave(1));
    // RFC 3339 UTC times with microseconds, the request before its reply.
    let times: Vec<&str> = frames.iter().map(|f| f["time"].as_str().unwrap()).collect();
    for time in &times {
        assert_eq!(time.len(), "2026-11-23T14:00:00.123456Z".len(), "{time}");
        assert!(humantime::parse_rfc3339(time).is_ok(), "{time}");
    }
    assert!(times[0] < times[1] && times[1] < times[2], "{times:?}");
    gateway.shutdown().await;
}

#[tokio::test]
async fn on_an_ascii_line_the_trace_shows_the_ascii_frames_characters() {
    let gateway = GatewayConfig::new()
        .bus(
            Bus::sim("sim")
                .framing("ascii")
                .baud(9600)
                .sim_slaves("1-4"),
        )
        .start()
        .await;
    let mut trace = Trace::open(gateway.metrics_addr(), "").await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    master.call(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x02]).await;
    let got = trace.fields_of_next(2).await;
    // `:`, address 01, the PDU and the LRC (the two's complement of the bytes' sum) as hex
    // pairs, CR LF.
    assert_eq!(
        got,
        [
            expect("sim", "tx", 1, 3, &hex(b":010300000002FA\r\n"), "ok"),
            expect("sim", "rx", 1, 3, &hex(b":01030400000000F8\r\n"), "ok"),
        ]
    );
    gateway.shutdown().await;
}

/// Buses `a` and `b` with register slaves 1 and 2 each: units 1-2 on `a`, 11-12 on `b`.
fn two_buses() -> GatewayConfig {
    let line = |name: &str| Bus::sim(name).baud(19_200).parity("even").sim_slaves("1-2");
    GatewayConfig::new()
        .bus(line("a"))
        .bus(line("b"))
        .route("1-2", "a", None)
        .route_offset("11-12", "b", -10)
}

/// A virtual unit's requests are on the trace as bus `virtual:NAME`, the master's request `rx`
/// and the unit's answer `tx`, as on a serial master port: no frame of them on a line.
#[tokio::test]
async fn a_virtual_units_requests_and_answers_are_on_the_trace_as_its_own_bus() {
    let gateway = GatewayConfig::new()
        .bus(
            Bus::sim("a")
                .baud(19_200)
                .sim_slave("1", &[("offline", true.into())])
                .text("[[bus.slave]]\naddress = 1\n[[bus.slave.value]]\nname = \"v\"\nregister = 0\n"),
        )
        .tables("[[virtual]]\nunit = 100\nname = \"copy\"\n[[virtual.register]]\nregister = 0\nvalue = \"a/1/v\"\n")
        .start()
        .await;
    let mut trace = Trace::open(gateway.metrics_addr(), "?bus=virtual:copy").await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    // Never read (its slave is offline): stale. Register 5 is not laid out.
    let stale = [0x03, 0x00, 0x00, 0x00, 0x01];
    assert_eq!(master.call(1, 100, &stale).await, [0x83, 0x0B]);
    let unmapped = [0x03, 0x00, 0x05, 0x00, 0x01];
    assert_eq!(master.call(2, 100, &unmapped).await, [0x83, 0x02]);
    let got = trace.fields_of_next(4).await;
    let bus = "virtual:copy";
    assert_eq!(
        got,
        [
            expect(bus, "rx", 100, 3, &hex(&rtu(100, &stale)), "stale"),
            expect(
                bus,
                "tx",
                100,
                0x83,
                &hex(&rtu(100, &[0x83, 0x0B])),
                "stale"
            ),
            expect(bus, "rx", 100, 3, &hex(&rtu(100, &unmapped)), "not_mapped"),
            expect(
                bus,
                "tx",
                100,
                0x83,
                &hex(&rtu(100, &[0x83, 0x02])),
                "not_mapped"
            ),
        ]
    );
}

#[tokio::test]
async fn a_trace_filtered_by_bus_and_slave_gets_only_their_frames() {
    let gateway = two_buses().start().await;
    let metrics = gateway.metrics_addr();
    let mut trace = Trace::open(metrics, "?bus=b&slave=2").await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    let read = [0x03, 0x00, 0x00, 0x00, 0x01];
    for (transaction, unit) in [(1, 1), (2, 2), (3, 11), (4, 12)] {
        master.call(transaction, unit, &read).await;
    }
    // A second read of b's slave 2, of another register: had any other frame passed the
    // filter, it would have come before.
    master.call(5, 12, &[0x03, 0x00, 0x01, 0x00, 0x01]).await;
    let got = trace.fields_of_next(3).await;
    assert_eq!(
        got,
        [
            expect("b", "tx", 2, 3, "02 03 00 00 00 01 84 39", "ok"),
            expect("b", "rx", 2, 3, "02 03 02 00 00 fc 44", "ok"),
            expect(
                "b",
                "tx",
                2,
                3,
                &hex(&rtu(2, &[0x03, 0x00, 0x01, 0x00, 0x01])),
                "ok"
            ),
        ]
    );
    let (status, body) = http_get(metrics, "/trace?bus=c").await;
    assert_eq!(status, 404);
    assert!(body.contains("a, b"), "names the known buses: {body}");
    let (status, _) = http_get(metrics, "/trace?slave=256").await;
    assert_eq!(status, 400);
    gateway.shutdown().await;
}

/// A Modbus TCP device on a free loopback port, every unit id 0-255 its own: each request is
/// answered as a read of one register holding the unit id.
async fn every_unit_device() -> u16 {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    tokio::spawn(async move {
        while let Ok((mut socket, _)) = server.accept().await {
            tokio::spawn(async move {
                // Transaction id, protocol id, length, unit id.
                let mut header = [0u8; 7];
                while socket.read_exact(&mut header).await.is_ok() {
                    let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
                    let mut pdu = vec![0u8; length.saturating_sub(1)];
                    if socket.read_exact(&mut pdu).await.is_err() {
                        return;
                    }
                    let transaction = u16::from_be_bytes([header[0], header[1]]);
                    let reply = mbap(transaction, header[6], &[0x03, 0x02, 0x00, header[6]]);
                    if socket.write_all(&reply).await.is_err() {
                        return;
                    }
                }
            });
        }
    });
    port
}

/// A gateway whose one bus `dev` is [`every_unit_device`]: units 0-255 reach it as they are.
async fn gateway_on_a_modbus_tcp_device() -> modbus_gateway::Gateway {
    let port = every_unit_device().await;
    GatewayConfig::new()
        .bus(
            Bus::on("dev", &format!("tcp://127.0.0.1:{port}"))
                .framing("tcp")
                .response_timeout("1s"),
        )
        .start()
        .await
}

const READ_ONE: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];

#[tokio::test]
async fn a_trace_of_slave_255_gets_unit_255_of_a_modbus_tcp_device() {
    let gateway = gateway_on_a_modbus_tcp_device().await;
    let mut trace = Trace::open(gateway.metrics_addr(), "?slave=255").await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    for (transaction, unit) in [(1, 1), (2, 255), (3, 248), (4, 255)] {
        assert_eq!(
            master.call(transaction, unit, &READ_ONE).await,
            [0x03, 0x02, 0x00, unit]
        );
    }
    // Unit 255's two reads and their answers; had unit 1's or 248's passed the filter, they
    // would have come first.
    for _ in 0..2 {
        for (direction, pdu) in [("tx", &READ_ONE[..]), ("rx", &[0x03, 0x02, 0x00, 0xFF][..])] {
            let frame = trace.frame().await;
            assert_eq!(frame["slave"], 255, "{frame}");
            assert_eq!(frame["direction"], direction, "{frame}");
            assert_eq!(frame["framing"], "tcp", "{frame}");
            let shown = frame["hex"].as_str().unwrap();
            assert!(shown.ends_with(&format!("ff {}", hex(pdu))), "{frame}");
        }
    }
    gateway.shutdown().await;
}

#[tokio::test]
async fn a_request_that_gets_no_reply_is_one_tx_frame_with_outcome_timeout() {
    let gateway = start_sim("[[bus.slave]]\naddress = 5\nresponse_timeout = \"50ms\"\n").await;
    let mut trace = Trace::open(gateway.metrics_addr(), "").await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    let read = [0x03, 0x00, 0x00, 0x00, 0x01];
    master.call(1, 5, &read).await;
    master.call(2, 1, &read).await;
    let got = trace.fields_of_next(3).await;
    assert_eq!(
        got,
        [
            expect("sim", "tx", 5, 3, "05 03 00 00 00 01 85 8e", "timeout"),
            expect("sim", "tx", 1, 3, &hex(&rtu(1, &read)), "ok"),
            expect("sim", "rx", 1, 3, &hex(&rtu(1, &[0x03, 0x02, 0, 0])), "ok"),
        ]
    );
    gateway.shutdown().await;
}

#[tokio::test]
async fn more_trace_readers_than_eight_are_refused_and_metrics_are_still_served() {
    let gateway = start_sim("").await;
    let metrics = gateway.metrics_addr();
    let mut readers = Vec::new();
    for _ in 0..modbus_gateway::testing::trace::MAX_READERS {
        readers.push(Trace::open(metrics, "").await);
    }
    let (status, body) = http_get(metrics, "/trace").await;
    assert_eq!(status, 503, "{body}");
    assert_eq!(http_get(metrics, "/metrics").await.0, 200);
    // A reader that leaves frees its place, once a write to it fails: at the next frames or
    // keepalive.
    drop(readers.pop());
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    within("a place frees", async {
        loop {
            master.call(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]).await;
            let stream = TcpStream::connect(metrics).await.unwrap();
            let (mut sender, connection) =
                hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream))
                    .await
                    .unwrap();
            tokio::spawn(connection);
            let request = hyper::Request::get("/trace")
                .header(hyper::header::HOST, metrics.to_string())
                .body(Empty::<Bytes>::new())
                .unwrap();
            if sender.send_request(request).await.unwrap().status() == 200 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    gateway.shutdown().await;
}

/// A trace reader whose stream stays blocked.
#[tokio::test]
async fn a_blocked_trace_reader_is_dropped_and_its_place_goes_to_a_new_reader() {
    use crate::support::{
        fast_sim_config, fill_trace_with_stalled_readers, keep_line_busy, status_line, PATIENCE,
    };
    use tokio::io::AsyncReadExt;
    let gateway = start(&fast_sim_config()).await;
    let metrics = gateway.metrics_addr();
    let traffic = keep_line_busy(gateway.tcp_addrs()[0]);
    let stalled = fill_trace_with_stalled_readers(metrics).await;
    // Their streams block within a second or two; ten seconds later they are dropped.
    tokio::time::timeout(2 * PATIENCE, async {
        while status_line(metrics, "/trace").await != Some(200) {
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    })
    .await
    .expect("a new reader gets a place once the stalled ones are dropped");
    traffic.abort();
    // Each stalled reader's connection was closed: what it had not read, then the end.
    for mut reader in stalled {
        let mut rest = Vec::new();
        let end = within("the stalled reader's end", reader.read_to_end(&mut rest)).await;
        assert!(
            end.is_err() || String::from_utf8_lossy(&rest).contains("event: frame"),
            "a stream of frames that ended"
        );
    }
    gateway.shutdown().await;
}

#[tokio::test(start_paused = true)]
async fn a_trace_stream_outlives_the_endpoints_connection_lifetime_with_keepalives() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let metrics = Arc::new(Metrics::new());
    tokio::spawn(modbus_gateway::testing::serve_web(listener, metrics));
    let mut trace = Trace::open(addr, "").await;
    // Other connections are closed after 120 s; a keepalive comes every 5 s.
    for _ in 0..30 {
        match trace.next().await {
            Some(Event::Comment(comment)) => assert_eq!(comment, "keepalive"),
            other => panic!("{other:?} instead of a keepalive"),
        }
    }
}

/// A bus on the simulated line at 9600 8E1, slaves 1-4, its task running, counting into
/// `metrics` (whose trace hub it publishes to).
fn sim_bus(metrics: &Metrics) -> modbus_gateway::testing::bus::BusHandle {
    let settings = GatewayConfig::new()
        .bus(sim_line().sim_slaves("1-4"))
        .load()
        .bus
        .remove(0);
    sim_bus_counted(settings, metrics).1
}

/// `n` reads one after the other; how long they took on the paused clock.
async fn reads(bus: &modbus_gateway::testing::bus::BusHandle, n: usize) -> Duration {
    let started = tokio::time::Instant::now();
    for _ in 0..n {
        let (outcome, _) = crate::support::bus_call(bus, 1, &[0x03, 0x00, 0x00, 0x00, 0x02]).await;
        assert!(outcome.is_ok());
    }
    started.elapsed()
}

#[tokio::test(start_paused = true)]
async fn a_reader_that_stops_reading_loses_events_and_never_slows_the_line() {
    let metrics = Metrics::new();
    let bus = sim_bus(&metrics);
    crate::support::settle(&bus).await;
    reads(&bus, 10).await;
    let unwatched = reads(&bus, 600).await;
    let mut reader = metrics.trace.subscribe().unwrap();
    // Two frames a read: more than the reader may fall behind by.
    let watched = reads(&bus, 600).await;
    assert_eq!(watched, unwatched, "the line is exactly as fast");
    assert_eq!(metrics.trace.published(), 1200);
    let Traced::Lost(lost) = reader.next().await else {
        panic!("the reader is told first that it lost events");
    };
    assert!(lost > 0);
    let mut kept = 0;
    while tokio::time::timeout(Duration::from_millis(1), reader.next())
        .await
        .is_ok()
    {
        kept += 1;
    }
    assert_eq!(lost + kept, 1200, "every event is either lost or read");
}

#[tokio::test(start_paused = true)]
async fn with_no_trace_reader_the_bus_publishes_nothing() {
    let metrics = Metrics::new();
    let bus = sim_bus(&metrics);
    crate::support::settle(&bus).await;
    reads(&bus, 3).await;
    assert_eq!(metrics.trace.published(), 0);
    let _reader = metrics.trace.subscribe().unwrap();
    reads(&bus, 3).await;
    assert_eq!(metrics.trace.published(), 6);
}

/// The `trace` subcommand as the real binary, and the lines it prints as they come.
struct Subcommand {
    child: std::process::Child,
    printed: tokio::sync::mpsc::UnboundedReceiver<String>,
}

impl Subcommand {
    fn spawn(args: &[&str]) -> Subcommand {
        let mut child = Command::new(BINARY)
            .arg("trace")
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let (lines, printed) = tokio::sync::mpsc::unbounded_channel();
        let stdout = child.stdout.take().unwrap();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout).lines() {
                if lines.send(line.unwrap()).is_err() {
                    return;
                }
            }
        });
        Subcommand { child, printed }
    }

    /// The first line it prints while `master` sends `pdu` to `unit` again and again (the trace
    /// is connected once a frame shows), and the line after it.
    async fn first_two(&mut self, master: &mut RawMaster, unit: u8, pdu: &[u8]) -> [String; 2] {
        let printed = &mut self.printed;
        let first = within("the trace prints", async {
            loop {
                master.call(1, unit, pdu).await;
                if let Ok(Some(line)) =
                    tokio::time::timeout(Duration::from_millis(200), printed.recv()).await
                {
                    return line;
                }
            }
        })
        .await;
        let second = within("the reply", printed.recv()).await.unwrap();
        [first, second]
    }

    /// Ctrl-C ends it, successfully.
    async fn interrupt(mut self) {
        let pid = libc::pid_t::try_from(self.child.id()).unwrap();
        // SAFETY: kill(2) on our own child's pid.
        assert_eq!(unsafe { libc::kill(pid, libc::SIGINT) }, 0);
        let status = within("the trace stops", async {
            loop {
                if let Some(status) = self.child.try_wait().unwrap() {
                    return status;
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        })
        .await;
        assert!(status.success(), "{status}");
    }
}

/// A line of the subcommand without its time of day, UTC: `14:00:00.123456 `.
fn untimed(line: &str) -> &str {
    line.split_once(' ').unwrap().1
}

#[tokio::test]
async fn the_trace_subcommand_prints_each_frame_decoded() {
    let gateway = start_sim("").await;
    let url = format!("http://{}", gateway.metrics_addr());
    let mut trace = Subcommand::spawn(&["--url", &url, "--slave", "2"]);
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    let read = [0x04, 0x00, 0x01, 0x00, 0x02];
    let [first, second] = trace.first_two(&mut master, 2, &read).await;
    assert_eq!(
        untimed(&first),
        "sim tx  slave 2    read input registers 0x04  addr 0x0001 (1) count 2   02 04 00 01 00 02 20 38"
    );
    assert_eq!(
        untimed(&second),
        "sim rx  slave 2    0x04 ok  2 registers: 0x0001 0x0002   02 04 04 00 01 00 02 18 85"
    );
    assert_eq!(
        first.split(' ').next().unwrap().len(),
        "14:00:00.123456".len()
    );
    trace.interrupt().await;
    gateway.shutdown().await;
}

#[tokio::test]
async fn the_trace_subcommand_takes_slave_255_and_refuses_256() {
    let gateway = gateway_on_a_modbus_tcp_device().await;
    let url = format!("http://{}", gateway.metrics_addr());
    let refused = Command::new(BINARY)
        .args(["trace", "--url", &url, "--slave", "256"])
        .output()
        .unwrap();
    assert_eq!(refused.status.code(), Some(2), "{refused:?}");
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("--slave"), "{stderr}");

    let mut trace = Subcommand::spawn(&["--url", &url, "--slave", "255"]);
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    trace.first_two(&mut master, 255, &READ_ONE).await;
    // Connected: unit 1's frames are not printed, the next unit 255's are.
    assert_eq!(master.call(2, 1, &READ_ONE).await, [0x03, 0x02, 0x00, 0x01]);
    assert_eq!(
        master.call(3, 255, &READ_ONE).await,
        [0x03, 0x02, 0x00, 0xFF]
    );
    let tx = within("unit 255's request", trace.printed.recv())
        .await
        .unwrap();
    let rx = within("unit 255's answer", trace.printed.recv())
        .await
        .unwrap();
    assert!(
        untimed(&tx).starts_with("dev tx  slave 255  read holding registers 0x03  addr 0x0000"),
        "{tx}"
    );
    assert!(
        untimed(&rx).starts_with("dev rx  slave 255  0x03 ok  1 register: 0x00ff"),
        "{rx}"
    );
    trace.interrupt().await;
    gateway.shutdown().await;
}

#[test]
fn the_trace_subcommand_exits_non_zero_saying_why_on_an_unreachable_endpoint() {
    // A port that was free a moment ago: nothing listens on it.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let output = Command::new(BINARY)
        .args(["trace", "--url", &format!("http://127.0.0.1:{port}")])
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("cannot reach the gateway's metrics endpoint"),
        "{stderr}"
    );
}

/// A serial master port's frames: the master's request (`rx`) and the gateway's reply (`tx`),
/// under bus `serial:NAME`, each with how the request ended.
#[tokio::test]
async fn a_serial_master_ports_request_and_reply_are_on_the_trace_as_its_bus() {
    let link = std::env::temp_dir().join(format!("mbgw-trace-port-{}", std::process::id()));
    let port = format!(
        "[[server.serial]]\nname = \"scada\"\ndevice = \"pty:{}\"\nparity = \"none\"\n",
        link.display()
    );
    let gateway = start(
        &GatewayConfig::new()
            .listen("127.0.0.1:0")
            .server_table(&port)
            .bus(sim_line().sim_slaves("1-4"))
            .to_toml(),
    )
    .await;
    let mut trace = Trace::open(gateway.metrics_addr(), "?bus=serial:scada").await;
    let mut master = within("the port's pty", async {
        loop {
            if let Ok(port) = tokio_serial::SerialPortBuilderExt::open_native_async(
                tokio_serial::new(link.to_str().unwrap(), 19_200),
            ) {
                return port;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    master
        .write_all(&[0x01, 0x03, 0x00, 0x00, 0x00, 0x02, 0xc4, 0x0b])
        .await
        .unwrap();
    assert_eq!(
        trace.fields_of_next(2).await,
        [
            expect(
                "serial:scada",
                "rx",
                1,
                3,
                "01 03 00 00 00 02 c4 0b",
                "answered"
            ),
            expect(
                "serial:scada",
                "tx",
                1,
                3,
                "01 03 04 00 00 00 00 fa 33",
                "answered"
            ),
        ]
    );
    gateway.shutdown().await;
}
