//! A serial master port's serving loop on tokio's paused clock, its master an in-memory port and
//! its bus the simulated line: when a reply goes out, which frames get silence, and how each is
//! counted.

use super::{plan, serve, Planned};
use crate::bus::{BusTask, Device};
use crate::config::Config;
use crate::dispatch::{Client, Dispatcher};
use crate::line::{rtu, Framing, Transport};
use crate::master::Rights;
use crate::metrics::{Metrics, PortOutcome};
use crate::routing::Router;
use crate::shutdown::Stopping;
use crate::sim::{RegisterBank, SimLine, Source};
use std::io;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::time::{sleep, Instant};

type Sent = Arc<Mutex<Vec<(Instant, Vec<u8>)>>>;

/// The master's end of the port: what it sends arrives as one burst; what the gateway sends is
/// kept with its time.
struct MemPort {
    incoming: mpsc::UnboundedReceiver<Vec<u8>>,
    sent: Sent,
    /// A line that echoes (`[server.serial.rs485] echo`): each frame sent comes back in.
    echo: Option<mpsc::UnboundedSender<Vec<u8>>>,
}

impl Transport for MemPort {
    async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        self.sent
            .lock()
            .unwrap()
            .push((Instant::now(), frame.to_vec()));
        if let Some(echo) = &self.echo {
            let _ = echo.send(frame.to_vec());
        }
        Ok(())
    }

    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        match self.incoming.recv().await {
            Some(bytes) => {
                buf.extend_from_slice(&bytes);
                Ok(bytes.len())
            }
            None => std::future::pending().await,
        }
    }

    fn clear_input(&mut self, _stale: &mut Vec<u8>) -> io::Result<()> {
        Ok(())
    }
}

/// Read one holding register at 0 of `unit`.
fn read(unit: u8) -> Vec<u8> {
    rtu::encode(unit, &[0x03, 0x00, 0x00, 0x00, 0x01])
}

/// A port `p` with `port_keys` in front of bus `line` (19200 8E1, simulated), whose slave 1
/// answers after `delay`; units 0-8 are routed to it, the rest nowhere (bus `spare`, which
/// nothing routes to, only keeps a lone bus from taking every unit).
struct Rig {
    master: mpsc::UnboundedSender<Vec<u8>>,
    sent: Sent,
    line: SimLine,
    view: Arc<super::PortView>,
    dispatcher: Arc<Dispatcher>,
    timing: crate::line::LineTiming,
}

impl Rig {
    async fn new(port_keys: &str, delay: Duration) -> Rig {
        // A pty unless the keys name a device (a UART's, for `[server.serial.rs485]`).
        let device = if port_keys.contains("device =") {
            ""
        } else {
            "device = \"pty:/run/p\"\n"
        };
        let text = format!(
            "[[server.serial]]\nname = \"p\"\n{device}{port_keys}\n\
             [[bus]]\nname = \"line\"\ndevice = \"sim\"\nbaud = 19200\n\
             [[bus]]\nname = \"spare\"\ndevice = \"sim\"\n\
             [[route]]\nunits = \"0-8\"\nbus = \"line\"\n"
        );
        let config = Config::from_toml_str(&text).expect("test config");
        let metrics = Arc::new(Metrics::new());
        let line = SimLine::new(config.bus[0].line_timing());
        line.add_slave(1, RegisterBank::new(delay));
        let task = BusTask::new(config.bus[0].clone(), Device::Sim(line.clone()), &metrics);
        let bus = task.handle();
        tokio::spawn(task.run(Stopping::never()));
        sleep(Duration::from_millis(10)).await;
        let dispatcher = Arc::new(Dispatcher::new(
            Router::new(&config),
            vec![bus],
            metrics.clone(),
        ));
        let Planned {
            mut settings, view, ..
        } = plan(0, &config.server.serial[0], 1_000, &metrics);
        let (master, incoming) = mpsc::unbounded_channel();
        let sent = Sent::default();
        let mut port = MemPort {
            incoming,
            sent: sent.clone(),
            echo: settings.echo.then(|| master.clone()),
        };
        let trace = metrics.trace.register(Arc::from("serial:p"));
        let (serving, serving_view) = (dispatcher.clone(), view.clone());
        tokio::spawn(async move {
            serve::serve(&mut port, &mut settings, &serving, &serving_view, &trace).await
        });
        Rig {
            master,
            sent,
            line,
            view,
            dispatcher,
            timing: config.bus[0].line_timing(),
        }
    }

    /// The master sends `bytes` now; the time it did.
    fn send(&self, bytes: &[u8]) -> Instant {
        self.master.send(bytes.to_vec()).expect("port serving");
        Instant::now()
    }

    fn sent(&self) -> Vec<(Instant, Vec<u8>)> {
        self.sent.lock().unwrap().clone()
    }

    fn counted(&self, outcome: PortOutcome) -> u64 {
        self.view.metrics.counted(outcome)
    }

    /// The frames the gateway's bus put on the line.
    fn on_the_line(&self) -> Vec<Vec<u8>> {
        self.line
            .frames()
            .into_iter()
            .filter(|f| f.from == Source::Master)
            .map(|f| f.bytes)
            .collect()
    }
}

#[tokio::test(start_paused = true)]
async fn the_slaves_reply_goes_back_byte_for_byte_no_sooner_than_t35_after_the_request() {
    let rig = Rig::new("baud = 19200", Duration::from_millis(5)).await;
    let asked = rig.send(&read(1));
    sleep(Duration::from_millis(200)).await;
    let sent = rig.sent();
    assert_eq!(sent.len(), 1, "{sent:?}");
    assert_eq!(sent[0].1, rtu::encode(1, &[0x03, 0x02, 0x00, 0x00]));
    assert_eq!(rig.on_the_line(), [read(1)]);
    assert_eq!(rig.counted(PortOutcome::Answered), 1);
    // Unit 9 has no route: the gateway's 0x0A is ready at once, and still waits out t3.5 of
    // the port's 19200 8E1 (3.5 x 11 bits).
    let asked_again = rig.send(&read(9));
    sleep(Duration::from_millis(50)).await;
    let sent = rig.sent();
    assert_eq!(sent[1].1, rtu::encode(9, &[0x83, 0x0A]));
    let t35 = Duration::from_nanos(11 * 7 * 1_000_000_000 / (2 * 19_200));
    assert!(
        sent[1].0 - asked_again >= t35,
        "{:?}",
        sent[1].0 - asked_again
    );
    assert!(sent[0].0 - asked >= t35);
    assert_eq!(rig.counted(PortOutcome::Exception), 1);
}

#[tokio::test(start_paused = true)]
async fn a_reply_not_ready_within_answer_within_is_never_sent_and_is_counted() {
    let rig = Rig::new("answer_within = \"100ms\"", Duration::from_millis(300)).await;
    rig.send(&read(1));
    sleep(Duration::from_secs(1)).await;
    assert_eq!(rig.sent(), []);
    assert_eq!(rig.counted(PortOutcome::TooLate), 1);
    assert_eq!(rig.counted(PortOutcome::Answered), 0);
}

#[tokio::test(start_paused = true)]
async fn a_unit_outside_units_a_bad_crc_and_a_frame_cut_by_a_gap_get_silence_and_are_counted() {
    let rig = Rig::new("units = \"1-4\"", Duration::from_millis(5)).await;
    rig.send(&read(5));
    sleep(Duration::from_millis(50)).await;
    let mut bad = read(1);
    bad[7] ^= 0xFF;
    rig.send(&bad);
    sleep(Duration::from_millis(50)).await;
    // The first half, then more than t3.5 of silence: the frame is broken, and so is its rest.
    let whole = read(1);
    rig.send(&whole[..4]);
    sleep(Duration::from_millis(20)).await;
    rig.send(&whole[4..]);
    sleep(Duration::from_millis(100)).await;
    assert_eq!(rig.sent(), []);
    assert_eq!(rig.on_the_line(), Vec::<Vec<u8>>::new());
    assert_eq!(rig.counted(PortOutcome::NotAddressed), 1);
    assert_eq!(rig.counted(PortOutcome::BadFrame), 3);
    // The port still answers.
    rig.send(&read(1));
    sleep(Duration::from_millis(100)).await;
    assert_eq!(rig.sent().len(), 1);
}

#[tokio::test(start_paused = true)]
async fn a_broadcast_reaches_the_line_and_is_never_answered_whether_or_not_units_lists_0() {
    let rig = Rig::new("units = \"1\"", Duration::from_millis(5)).await;
    let write = rtu::encode(0, &[0x06, 0x00, 0x01, 0x00, 0x2A]);
    rig.send(&write);
    sleep(Duration::from_millis(500)).await;
    assert_eq!(rig.on_the_line(), [write]);
    assert_eq!(rig.sent(), []);
    assert_eq!(rig.counted(PortOutcome::Broadcast), 1);
}

#[tokio::test(start_paused = true)]
async fn the_masters_next_request_drops_the_reply_it_no_longer_waits_for() {
    let rig = Rig::new("", Duration::from_millis(100)).await;
    rig.send(&read(1));
    sleep(Duration::from_millis(20)).await;
    rig.send(&read(9));
    sleep(Duration::from_millis(400)).await;
    // Only the second request's answer; the first's reply, late for its master, is dropped.
    let sent: Vec<Vec<u8>> = rig.sent().into_iter().map(|(_, b)| b).collect();
    assert_eq!(sent, [rtu::encode(9, &[0x83, 0x0A])]);
    assert_eq!(rig.counted(PortOutcome::TooLate), 1);
}

#[tokio::test(start_paused = true)]
async fn on_a_line_that_echoes_each_replys_echo_is_dropped_not_taken_for_a_request() {
    let keys = "device = \"/dev/ttyS9\"\n[server.serial.rs485]\necho = true";
    let rig = Rig::new(keys, Duration::from_millis(5)).await;
    for n in 1..=3 {
        rig.send(&read(1));
        sleep(Duration::from_millis(100)).await;
        assert_eq!(rig.sent().len(), n);
    }
    // Each reply came back in and was dropped: had one been read, it would have been a frame
    // of the wrong length for its function (bad_frame) or a request from the master.
    assert_eq!(rig.counted(PortOutcome::Answered), 3);
    assert_eq!(rig.counted(PortOutcome::BadFrame), 0);
    assert_eq!(rig.on_the_line(), [read(1), read(1), read(1)]);
}

#[tokio::test(start_paused = true)]
async fn a_read_only_port_refuses_a_write_with_0x01_unsent() {
    let rig = Rig::new("read_only = true", Duration::from_millis(5)).await;
    rig.send(&rtu::encode(1, &[0x06, 0x00, 0x01, 0x00, 0x2A]));
    sleep(Duration::from_millis(50)).await;
    let sent: Vec<Vec<u8>> = rig.sent().into_iter().map(|(_, b)| b).collect();
    assert_eq!(sent, [rtu::encode(1, &[0x86, 0x01])]);
    assert_eq!(rig.on_the_line(), Vec::<Vec<u8>>::new());
}

/// The budget: the port's master, in `priority`, polling every 100 ms while 20 other
/// masters keep the line busy, waits at most its own transaction, one other (the one on the wire
/// when it asked) and 20 ms.
#[tokio::test(start_paused = true)]
async fn a_priority_port_master_waits_at_most_one_other_transaction_while_20_masters_saturate() {
    let delay = Duration::from_millis(5);
    let rig = Rig::new("priority = true\nbaud = 19200", delay).await;
    let pdu = [0x03, 0x00, 0x00, 0x00, 0x0A];
    for m in 0..20u64 {
        let (dispatcher, pdu) = (rig.dispatcher.clone(), pdu.to_vec());
        let peer = format!("127.0.0.1:{}", 40_000 + m).parse().unwrap();
        tokio::spawn(async move {
            let mut client = Client::new(m + 1, peer, Rights::ReadWrite);
            loop {
                let _ = dispatcher.submit(&mut client, 1, pdu.clone()).await;
            }
        });
    }
    sleep(Duration::from_millis(500)).await;
    let mut waits = Vec::new();
    for _ in 0..100 {
        let before = rig.sent().len();
        let asked = rig.send(&rtu::encode(1, &pdu));
        sleep(Duration::from_millis(100)).await;
        let sent = rig.sent();
        assert_eq!(sent.len(), before + 1, "answered within 100 ms");
        waits.push(sent[before].0 - asked);
    }
    waits.sort();
    let p99 = waits[98];
    let timing = rig.timing;
    let one = Framing::Rtu.transaction_minimum(&timing, 5, 22) + delay;
    let budget = one * 2 + Duration::from_millis(20);
    assert!(
        p99 <= budget,
        "p99 {p99:?} over {budget:?} ({one:?} a transaction)"
    );
    // The others kept the line busy: 10.5 s of transactions, less the port master's.
    let frames = u32::try_from(rig.on_the_line().len()).unwrap();
    assert!(
        one * frames > Duration::from_secs(9),
        "{frames} transactions of {one:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn an_ascii_master_reaches_an_rtu_line_and_gets_its_reply_in_ascii() {
    let rig = Rig::new("framing = \"ascii\"", Duration::from_millis(5)).await;
    let mut request = Vec::new();
    crate::line::ascii::encode_into(&mut request, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]);
    assert_eq!(request, b":010300000001FB\r\n");
    rig.send(&request);
    sleep(Duration::from_millis(200)).await;
    let sent: Vec<Vec<u8>> = rig.sent().into_iter().map(|(_, b)| b).collect();
    assert_eq!(sent, [b":0103020000FA\r\n".to_vec()]);
    // On the line, the same PDU in RTU.
    assert_eq!(rig.on_the_line(), [read(1)]);
}
