//! The bus task on tokio's paused clock over the simulated line: one transaction's result, the
//! reopen backoff, reconfiguration between transactions, the slave-state changes it renders,
//! and the answer of a request a full queue displaces.

use super::transaction::Ran;
use super::{longest_transaction, BusHandle, BusTask, Device, Job, Reconfigure, Waiter};
use crate::config::{self, Config};
use crate::error::NoReply;
use crate::error::{Answer, Outcome, RequestError};
use crate::line::{Framing, LineMaster};
use crate::metrics::Metrics;
use crate::shutdown::Stopping;
use crate::sim::{RegisterBank, Scripted, SimLine, Source, Transmission};
use std::time::Duration;
use tokio::sync::oneshot;
use tokio::time::{sleep, Instant};

const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x02];
const WRITE: [u8; 5] = [0x06, 0x00, 0x01, 0x00, 0x2A];

fn settings(keys: &str) -> config::Bus {
    let text = format!("[[bus]]\nname = \"line\"\ndevice = \"sim\"\nbaud = 19200\n{keys}\n");
    Config::from_toml_str(&text)
        .expect("test config")
        .bus
        .remove(0)
}

fn job(slave: u8, pdu: &[u8]) -> (Job, oneshot::Receiver<Outcome>) {
    let origin = super::Origin {
        master: 1,
        admission: 1,
        protocol: crate::master::Protocol::Tcp,
        class: crate::master::Class::Normal,
    };
    let deadline = Instant::now() + Duration::from_secs(60);
    let (waiter, outcome) = Waiter::new(origin, deadline);
    (Job::new(waiter, slave, pdu.to_vec()), outcome)
}

/// A task on `line`, and a master on a port of it, for driving one transaction by hand.
fn task_on(line: &SimLine, keys: &str) -> (BusTask, LineMaster<super::Port>) {
    let task = BusTask::new(settings(keys), Device::Sim(line.clone()), &Metrics::new());
    let port = super::Port::Sim(line.open().expect("sim port"));
    let mut master = LineMaster::new(
        port,
        task.current.derived.framing,
        task.current.derived.timing,
    );
    task.current.configure(&mut master);
    (task, master)
}

fn attempts(ran: &Ran) -> Option<u32> {
    match ran {
        Ran::Done(Err(RequestError::NoResponse { attempts, .. })) => Some(*attempts),
        _ => None,
    }
}

async fn call(bus: &BusHandle, slave: u8, pdu: &[u8]) -> Outcome {
    bus.submit(1, slave, pdu.to_vec())
        .await
        .expect("the bus answers every request")
}

#[tokio::test(start_paused = true)]
async fn a_silent_slave_gets_every_retry_for_a_read_and_one_try_for_a_write() {
    let line = SimLine::new(settings("").line_timing());
    let (mut task, mut master) = task_on(&line, "retries = 2\nresponse_timeout = \"50ms\"");
    let (read, _answer) = job(9, &READ);
    let ran = task
        .execute(&mut master, &task.clear(read, false), None)
        .await;
    assert_eq!(attempts(&ran), Some(3));
    let (write, _answer) = job(9, &WRITE);
    sleep(Duration::from_millis(200)).await;
    let ran = task
        .execute(&mut master, &task.clear(write, false), None)
        .await;
    assert_eq!(attempts(&ran), Some(1), "a write is not sent twice");
    let (probe, _answer) = job(9, &READ);
    sleep(Duration::from_millis(200)).await;
    let ran = task
        .execute(&mut master, &task.clear(probe, true), None)
        .await;
    assert_eq!(attempts(&ran), Some(1), "a probe is one try");
}

#[tokio::test(start_paused = true)]
async fn no_retry_starts_once_the_stop_deadline_has_passed() {
    let line = SimLine::new(settings("").line_timing());
    let (mut task, mut master) = task_on(&line, "retries = 5\nresponse_timeout = \"50ms\"");
    let (read, _answer) = job(9, &READ);
    let stop_at = Some(Instant::now() + Duration::from_millis(10));
    let ran = task
        .execute(&mut master, &task.clear(read, false), stop_at)
        .await;
    assert_eq!(attempts(&ran), Some(1));
}

#[tokio::test(start_paused = true)]
async fn a_port_lost_during_a_transaction_ends_it_as_port_lost_not_as_a_timeout() {
    let line = SimLine::new(settings("").line_timing());
    let (mut task, mut master) = task_on(&line, "response_timeout = \"1s\"");
    let (read, _answer) = job(9, &READ);
    let unplug = line.clone();
    tokio::spawn(async move {
        sleep(Duration::from_millis(100)).await;
        unplug.unplug();
    });
    let ran = task
        .execute(&mut master, &task.clear(read, false), None)
        .await;
    assert!(matches!(ran, Ran::PortLost(_)), "not a port loss");
}

#[tokio::test(start_paused = true)]
async fn a_broadcast_is_answered_by_the_gateway_and_a_slave_reply_is_passed_on() {
    let line = SimLine::new(settings("").line_timing());
    line.add_slave(3, RegisterBank::new(Duration::ZERO));
    let (mut task, mut master) = task_on(&line, "");
    let (broadcast, _answer) = job(0, &WRITE);
    match task
        .execute(&mut master, &task.clear(broadcast, false), None)
        .await
    {
        Ran::Done(Ok(Answer::Reply(pdu))) => assert_eq!(pdu, WRITE),
        _ => panic!("a broadcast write gets its echo from the gateway"),
    }
    let (read, _answer) = job(3, &READ);
    match task
        .execute(&mut master, &task.clear(read, false), None)
        .await
    {
        // The broadcast wrote 0x2A to register 1.
        Ran::Done(Ok(Answer::Reply(pdu))) => assert_eq!(pdu, [0x03, 0x04, 0, 0, 0, 0x2A]),
        _ => panic!("the slave's reply is the answer"),
    }
}

/// The task of `settings` on `line`, counting into `metrics`, running until `stopping`: its
/// handle, 10 ms after it started (its first open has been tried).
pub(super) async fn running(
    settings: config::Bus,
    line: &SimLine,
    metrics: &Metrics,
    stopping: Stopping,
) -> BusHandle {
    let task = BusTask::new(settings, Device::Sim(line.clone()), metrics);
    let bus = task.handle();
    tokio::spawn(task.run(stopping));
    sleep(Duration::from_millis(10)).await;
    bus
}

/// The value of `series` in what `metrics` exports.
fn metric(metrics: &Metrics, series: &str) -> Option<f64> {
    crate::metrics::sample(&metrics.render().expect("metrics render"), series)
}

const OPEN_ERRORS: &str = "modbus_gateway_port_open_errors_total{bus=\"line\"}";
const SLAVE_1_UP: &str = "modbus_gateway_slave_up{bus=\"line\",slave=\"1\"}";

#[tokio::test(start_paused = true)]
async fn a_lost_port_is_reopened_with_a_backoff_that_doubles_up_to_its_maximum() {
    let line = SimLine::new(settings("").line_timing());
    let metrics = Metrics::new();
    let keys = "reopen_delay = \"100ms\"\nreopen_delay_max = \"400ms\"";
    let bus = running(settings(keys), &line, &metrics, Stopping::never()).await;
    assert!(bus.is_up());
    line.unplug();
    // Lost at 10 ms; opens fail at 110, 310, 710, 1110, 1510 ms.
    sleep(Duration::from_millis(1_100)).await;
    assert_eq!(metric(&metrics, OPEN_ERRORS), Some(3.0));
    sleep(Duration::from_millis(450)).await;
    assert_eq!(metric(&metrics, OPEN_ERRORS), Some(5.0));
    line.plug();
    sleep(Duration::from_millis(400)).await;
    assert!(bus.is_up(), "reopened at the next attempt");
}

#[tokio::test(start_paused = true)]
async fn new_settings_apply_between_transactions_and_a_new_device_is_opened_at_once() {
    let first = SimLine::new(settings("").line_timing());
    first.add_slave(1, Scripted::new([None, None]));
    let mut task = BusTask::new(
        settings("response_timeout = \"1s\"\nretries = 0"),
        Device::Sim(first.clone()),
        &Metrics::new(),
    );
    let updates = task.updates();
    let bus = task.handle();
    tokio::spawn(task.run(Stopping::never()));
    sleep(Duration::from_millis(10)).await;
    let started = Instant::now();
    assert!(call(&bus, 1, &READ).await.is_err());
    assert!(started.elapsed() >= Duration::from_secs(1));
    // A shorter timeout on the same line: no reopen, the next request waits less.
    let reopen = updates.send(Reconfigure {
        settings: settings("response_timeout = \"100ms\"\nretries = 0"),
        device: Device::Sim(first.clone()),
    });
    assert!(!reopen);
    sleep(Duration::from_secs(2)).await;
    let started = Instant::now();
    assert!(call(&bus, 1, &READ).await.is_err());
    assert!(started.elapsed() < Duration::from_millis(200));
    // Another line: the bus moves to it, where slave 1 answers.
    let second = SimLine::new(settings("").line_timing());
    second.add_slave(
        1,
        Scripted::new([Some(Transmission::frame(
            1,
            &[0x03, 0x04, 0, 7, 0, 8],
            Duration::ZERO,
        ))]),
    );
    let reopen = updates.send(Reconfigure {
        settings: settings("response_timeout = \"100ms\""),
        device: Device::Sim(second.clone()),
    });
    assert!(reopen);
    sleep(Duration::from_millis(10)).await;
    let answer = call(&bus, 1, &READ)
        .await
        .expect("answered on the new line");
    assert_eq!(answer.into_pdu(), Some(vec![0x03, 0x04, 0, 7, 0, 8]));
    assert!(
        first.frames().len() == 2,
        "nothing more went to the old line"
    );
}

/// A bus of `framing` whose slave 1 answers, is silent twice, then answers its probe: what the
/// task makes of it, and what `slave_up` says.
async fn health_through_failing_down_and_back(framing: Framing) {
    let keys = format!(
        "framing = \"{}\"\nresponse_timeout = \"50ms\"\nretries = 0\nslave_down_after = 2\n\
         slave_probe_interval = \"1s\"",
        framing.name()
    );
    let line = SimLine::with_framing(settings(&keys).line_timing(), framing);
    let reply = || {
        let mut frame = Vec::new();
        framing.encode_into(&mut frame, 0, 1, &[0x03, 0x04, 0, 1, 0, 2]);
        Some(Transmission {
            bytes: frame,
            delay: Duration::ZERO,
            pause: None,
        })
    };
    line.add_slave(1, Scripted::new([reply(), None, None, reply()]));
    let metrics = Metrics::new();
    let bus = running(settings(&keys), &line, &metrics, Stopping::never()).await;
    assert!(call(&bus, 1, &READ).await.is_ok());
    assert_eq!(metric(&metrics, SLAVE_1_UP), Some(1.0));
    let timed_out = |o: &Outcome| {
        matches!(
            o,
            Err(RequestError::NoResponse {
                last: NoReply::Timeout,
                ..
            })
        )
    };
    assert!(timed_out(&call(&bus, 1, &READ).await));
    assert_eq!(metric(&metrics, SLAVE_1_UP), Some(0.0), "failing");
    assert!(timed_out(&call(&bus, 1, &READ).await));
    let sent = line.frames().len();
    assert!(matches!(
        call(&bus, 1, &READ).await,
        Err(RequestError::SlaveDown { timeouts: 2 })
    ));
    assert_eq!(line.frames().len(), sent, "down: answered without the line");
    sleep(Duration::from_secs(1)).await;
    assert!(call(&bus, 1, &READ).await.is_ok(), "the probe is answered");
    assert_eq!(metric(&metrics, SLAVE_1_UP), Some(1.0));
}

#[tokio::test(start_paused = true)]
async fn slave_up_follows_the_slaves_health_through_failing_down_and_back() {
    health_through_failing_down_and_back(Framing::Rtu).await;
}

#[tokio::test(start_paused = true)]
async fn an_ascii_bus_keeps_the_same_down_policy_probes_and_slave_up() {
    health_through_failing_down_and_back(Framing::Ascii).await;
}

#[test]
fn behind_a_device_server_the_longest_transaction_allows_for_the_link_both_ways_and_the_packing() {
    let on = |device: &str, keys: &str| {
        let text = format!("[[bus]]\nname = \"line\"\ndevice = \"{device}\"\n{keys}\n");
        Config::from_toml_str(&text)
            .expect("test config")
            .bus
            .remove(0)
    };
    let local = longest_transaction(&on("/dev/ttyS1", ""));
    let remote = longest_transaction(&on("tcp://nport:4001", "byte_timeout = \"1.75ms\""));
    let budget = crate::bus::device::net::MAX_LINK_BUDGET;
    assert_eq!(remote, local + budget * 2);
    let packed = on(
        "tcp://nport:4001",
        "byte_timeout = \"1.75ms\"\npacking_delay = \"50ms\"",
    );
    // Twice on the way (request, reply), and once more as silence a reply may hold.
    let packing = Duration::from_millis(50);
    assert_eq!(longest_transaction(&packed), remote + packing * 3);
}

#[tokio::test(start_paused = true)]
async fn a_newcomer_to_a_full_queue_of_ones_gets_in_and_the_newest_job_gets_0x06_once() {
    let line = SimLine::new(settings("").line_timing());
    line.add_slave(1, RegisterBank::new(Duration::ZERO));
    let bus = running(
        settings("queue_depth = 2"),
        &line,
        &Metrics::new(),
        Stopping::never(),
    )
    .await;
    let read = |bus: &BusHandle, master: u64| {
        let origin = super::Origin {
            master,
            admission: master,
            protocol: crate::master::Protocol::Tcp,
            class: crate::master::Class::Normal,
        };
        // Input register N reads N; each master a register of its own: none joins another.
        bus.submit_from(origin, 1, vec![0x04, 0x00, master as u8, 0x00, 0x01])
    };
    // Master 1's read takes the line; masters 2 and 3 fill the queue, one each.
    let first = read(&bus, 1);
    sleep(Duration::from_millis(1)).await;
    let (second, mut third) = (read(&bus, 2), read(&bus, 3));
    assert!(third.try_recv().is_err(), "queued");
    // Master 4 holds nothing: it gets in, and master 3's read, the newest, is refused at once.
    let fourth = read(&bus, 4);
    assert_eq!(
        third.try_recv().expect("answered at once"),
        Err(RequestError::QueueFull)
    );
    for (master, outcome) in [(1, first), (2, second), (4, fourth)] {
        let answer = outcome.await.expect("answered");
        let own = vec![0x04, 0x02, 0x00, master];
        assert_eq!(
            answer,
            Ok(crate::error::Answer::Reply(own)),
            "master {master}"
        );
    }
    let sent = line
        .frames()
        .iter()
        .filter(|f| f.from == Source::Master)
        .count();
    assert_eq!(sent, 3, "master 3's read never reached the line");
}
