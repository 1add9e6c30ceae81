//! Every way a request ends, driven on tokio's paused clock over the simulated line: each gets
//! its master exactly one answer and the requests counter exactly one count, under the label of
//! how it ended ([`super::Waiter`] is the one place that does both).

use super::{BusHandle, BusTask, Device};
use crate::config::{self, Config};
use crate::dispatch::{Client, Dispatcher};
use crate::error::{Answer, Outcome, RequestError};
use crate::master::Rights;
use crate::metrics::Metrics;
use crate::routing::Router;
use crate::shutdown::{self, Stopping};
use crate::sim::{RegisterBank, SimLine};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::oneshot;
use tokio::time::sleep;

const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];
const WRITE: [u8; 5] = [0x06, 0x00, 0x01, 0x00, 0x2A];
/// Slave 1's answer to `READ`: one register, zero.
const ANSWER: [u8; 4] = [0x03, 0x02, 0x00, 0x00];
/// How long slave 1 takes to answer: the line stays busy that long.
const SLOW: Duration = Duration::from_millis(500);

/// A gateway of one bus, `line`, with `keys`, and slave 1 (known to the metrics) with
/// `slave_keys`.
fn config(keys: &str, slave_keys: &str) -> Config {
    let text = format!(
        "[[bus]]\nname = \"line\"\ndevice = \"sim\"\nbaud = 19200\nresponse_timeout = \"1s\"\n\
         {keys}\n[[bus.slave]]\naddress = 1\n{slave_keys}\n"
    );
    Config::from_toml_str(&text).expect("test config")
}

/// The running bus of `settings` with slave 1 answering after `SLOW`.
async fn bus(settings: &config::Bus, metrics: &Metrics, stopping: Stopping) -> BusHandle {
    let line = SimLine::new(settings.line_timing());
    line.add_slave(1, RegisterBank::new(SLOW));
    let bus = super::tests::running(settings.clone(), &line, metrics, stopping).await;
    assert!(bus.is_up());
    bus
}

/// Every series of the requests counter, labels as exported, with its value.
fn requests(metrics: &Metrics) -> Vec<(String, f64)> {
    let text = metrics.render().expect("metrics render");
    let mut series: Vec<(String, f64)> = text
        .lines()
        .filter_map(|l| l.strip_prefix("modbus_gateway_requests_total{"))
        .filter_map(|rest| rest.split_once("} "))
        .map(|(labels, value)| (labels.to_owned(), value.parse().expect("a count")))
        .collect();
    series.sort_by(|a, b| a.0.cmp(&b.0));
    series
}

/// The labels of a request of `function` to slave 1 of `line` over Modbus TCP that ended as
/// `outcome`.
fn counted(function: &str, outcome: &str) -> String {
    format!(
        "bus=\"line\",function=\"{function}\",outcome=\"{outcome}\",protocol=\"tcp\",slave=\"1\""
    )
}

/// The one answer waiting in `receiver`: there now, and the only one.
fn answer(mut receiver: oneshot::Receiver<Outcome>) -> Outcome {
    receiver.try_recv().expect("answered once")
}

async fn answered(receiver: oneshot::Receiver<Outcome>) -> Outcome {
    receiver.await.expect("answered, not dropped")
}

#[tokio::test(start_paused = true)]
async fn a_reply_from_the_line_is_answered_and_counted_once() {
    let metrics = Metrics::new();
    let bus = bus(&config("", "").bus[0], &metrics, Stopping::never()).await;
    let outcome = answered(bus.submit(1, 1, READ.to_vec())).await;
    assert_eq!(outcome, Ok(Answer::Reply(ANSWER.to_vec())));
    assert_eq!(requests(&metrics), [(counted("0x03", "ok"), 1.0)]);
}

#[tokio::test(start_paused = true)]
async fn a_read_that_followed_another_is_answered_and_counted_once_as_its_own() {
    let metrics = Metrics::new();
    let settings = &config("coalesce_reads = true", "").bus[0];
    let bus = bus(settings, &metrics, Stopping::never()).await;
    let leader = bus.submit(1, 1, READ.to_vec());
    let follower = bus.submit(2, 1, READ.to_vec());
    assert_eq!(bus.queue_depth(), 2, "the follower waits with its leader");
    for outcome in [answered(leader).await, answered(follower).await] {
        assert_eq!(outcome, Ok(Answer::Reply(ANSWER.to_vec())));
    }
    assert_eq!(requests(&metrics), [(counted("0x03", "ok"), 2.0)]);
    let coalesced = "modbus_gateway_coalesced_requests_total{bus=\"line\",slave=\"1\"} 1";
    assert!(metrics.render().unwrap().contains(coalesced));
}

#[tokio::test(start_paused = true)]
async fn a_read_answered_from_the_cache_is_answered_and_counted_once() {
    let metrics = Metrics::new();
    let settings = &config("", "cache = \"10s\"").bus[0];
    let bus = bus(settings, &metrics, Stopping::never()).await;
    answered(bus.submit(1, 1, READ.to_vec())).await.unwrap();
    let cached = answer(bus.submit(2, 1, READ.to_vec()));
    assert_eq!(cached, Ok(Answer::Reply(ANSWER.to_vec())), "at once");
    assert_eq!(requests(&metrics), [(counted("0x03", "ok"), 2.0)]);
    let hits = "modbus_gateway_cache_hits_total{bus=\"line\",slave=\"1\"} 1";
    assert!(metrics.render().unwrap().contains(hits));
}

#[tokio::test(start_paused = true)]
async fn a_request_that_waited_past_the_queue_timeout_is_answered_and_counted_once() {
    let metrics = Metrics::new();
    let settings = &config("queue_timeout = \"100ms\"", "").bus[0];
    let bus = bus(settings, &metrics, Stopping::never()).await;
    let first = bus.submit(1, 1, READ.to_vec());
    let late = bus.submit(2, 1, WRITE.to_vec());
    assert_eq!(answered(late).await, Err(RequestError::Expired));
    answered(first).await.unwrap();
    assert_eq!(
        requests(&metrics),
        [
            (counted("0x03", "ok"), 1.0),
            (counted("0x06", "expired"), 1.0)
        ]
    );
}

#[tokio::test(start_paused = true)]
async fn a_request_to_a_full_queue_is_answered_and_counted_once() {
    let metrics = Metrics::new();
    let settings = &config("queue_depth = 1", "").bus[0];
    let bus = bus(settings, &metrics, Stopping::never()).await;
    let on_the_line = bus.submit(1, 1, READ.to_vec());
    sleep(Duration::from_millis(10)).await;
    let queued = bus.submit(1, 1, WRITE.to_vec());
    let refused = answer(bus.submit(1, 1, WRITE.to_vec()));
    assert_eq!(refused, Err(RequestError::QueueFull));
    answered(on_the_line).await.unwrap();
    answered(queued).await.unwrap();
    assert_eq!(
        requests(&metrics),
        [
            (counted("0x03", "ok"), 1.0),
            (counted("0x06", "ok"), 1.0),
            (counted("0x06", "queue_full"), 1.0)
        ]
    );
}

#[tokio::test(start_paused = true)]
async fn a_request_whose_master_left_is_counted_once_and_never_sent() {
    let metrics = Metrics::new();
    let bus = bus(&config("", "").bus[0], &metrics, Stopping::never()).await;
    let on_the_line = bus.submit(1, 1, READ.to_vec());
    sleep(Duration::from_millis(10)).await;
    // One forgotten by the dispatcher, one found abandoned when its turn comes.
    drop(bus.submit(2, 1, WRITE.to_vec()));
    bus.forget(2);
    drop(bus.submit(3, 1, WRITE.to_vec()));
    answered(on_the_line).await.unwrap();
    sleep(SLOW * 2).await;
    assert!(bus.queue_depth() == 0);
    assert_eq!(
        requests(&metrics),
        [
            (counted("0x03", "ok"), 1.0),
            (counted("0x06", "dropped"), 2.0)
        ]
    );
}

#[tokio::test(start_paused = true)]
async fn a_request_to_a_bus_whose_port_is_down_is_answered_and_counted_once() {
    let metrics = Metrics::new();
    let settings = &config("", "").bus[0];
    let task = BusTask::new(
        settings.clone(),
        Device::Sim(SimLine::new(settings.line_timing())),
        &metrics,
    );
    let refused = answer(task.handle().submit(1, 1, READ.to_vec()));
    assert_eq!(refused, Err(RequestError::PortDown));
    assert_eq!(requests(&metrics), [(counted("0x03", "port_down"), 1.0)]);
}

#[tokio::test(start_paused = true)]
async fn requests_left_at_shutdown_are_answered_and_counted_once() {
    let metrics = Metrics::new();
    let (stop, stopping) = shutdown::channel();
    let bus = bus(&config("", "").bus[0], &metrics, stopping).await;
    let on_the_line = bus.submit(1, 1, READ.to_vec());
    sleep(Duration::from_millis(10)).await;
    let queued = bus.submit(2, 1, WRITE.to_vec());
    stop.stop(tokio::time::Instant::now());
    answered(on_the_line).await.unwrap();
    assert_eq!(answered(queued).await, Err(RequestError::ShuttingDown));
    // The bus is down for good: later requests meet a closed port.
    let after = answer(bus.submit(3, 1, WRITE.to_vec()));
    assert_eq!(after, Err(RequestError::PortDown));
    assert_eq!(
        requests(&metrics),
        [
            (counted("0x03", "ok"), 1.0),
            (counted("0x06", "port_down"), 1.0),
            (counted("0x06", "shutdown"), 1.0)
        ]
    );
}

#[tokio::test(start_paused = true)]
async fn a_request_the_dispatcher_refuses_is_answered_and_counted_once() {
    let metrics = Arc::new(Metrics::new());
    let config = config("", "");
    let bus = bus(&config.bus[0], &metrics, Stopping::never()).await;
    let dispatcher = Dispatcher::new(Router::new(&config), vec![bus], metrics.clone());
    let peer = "127.0.0.1:1502".parse().unwrap();
    let mut client = Client::new(1, peer, Rights::ReadOnly);
    // Units above 247 are no slave's: no route.
    let unrouted = answer(dispatcher.submit(&mut client, 250, READ.to_vec()));
    assert_eq!(unrouted, Err(RequestError::NoRoute(250)));
    let read_only = answer(dispatcher.submit(&mut client, 1, WRITE.to_vec()));
    assert_eq!(read_only, Err(RequestError::ReadOnly(0x06)));
    assert_eq!(
        requests(&metrics),
        [
            (
                "bus=\"\",function=\"0x03\",outcome=\"no_route\",protocol=\"tcp\",slave=\"other\""
                    .to_owned(),
                1.0
            ),
            (counted("0x06", "read_only"), 1.0)
        ]
    );
}
