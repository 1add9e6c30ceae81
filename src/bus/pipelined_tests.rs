//! The pipelined loop (`max_in_flight` above 1) on tokio's paused clock, over an in-memory link
//! to a Modbus TCP device that answers every request a fixed time after it came: how many
//! requests it keeps outstanding, what that is worth in transactions, and that each master gets
//! its own answer. The clock is exact here, so the figures are the loop's own, with neither the
//! timer's rounding nor the CPU of a debug build in them (the bench measures those).

use super::device::net::{tests::Measured, NetPort};
use super::{BusTask, Device};
use crate::config::{self, Config};
use crate::error::Answer;
use crate::metrics::Metrics;
use crate::shutdown::Stopping;
use crate::sim::SimLine;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use test_support::device::{answer_each_after, answer_to, read};
use tokio::io::DuplexStream;
use tokio::time::Instant;

/// How long the device takes to answer each request.
const DEVICE_DELAY: Duration = Duration::from_millis(5);
const MASTERS: u16 = 8;
const READS_EACH: u16 = 25;

fn settings(in_flight: usize) -> config::Bus {
    let text = format!(
        "[[bus]]\nname = \"dev\"\ndevice = \"tcp://127.0.0.1:1502\"\nframing = \"tcp\"\n\
         response_timeout = \"200ms\"\nmax_in_flight = {in_flight}\n"
    );
    Config::from_toml_str(&text)
        .expect("test config")
        .bus
        .remove(0)
}

/// A device on `far` that answers every read [`DEVICE_DELAY`] after it came, several at once
/// if they come so, echoing the transaction and unit ids. Returns the most requests it ever
/// held unanswered at once.
fn device(far: DuplexStream) -> Arc<AtomicUsize> {
    let most = Arc::new(AtomicUsize::new(0));
    tokio::spawn(answer_each_after(far, DEVICE_DELAY, most.clone()));
    most
}

/// [`MASTERS`] masters each read [`READS_EACH`] registers of their own back to back through a
/// bus with `in_flight` requests outstanding at most, each checking it got its own register's
/// answer. Returns the reads a second, and the most requests the device held at once.
async fn reads_per_second(in_flight: usize) -> (f64, usize) {
    let settings = settings(in_flight);
    let line = SimLine::new(settings.line_timing());
    let mut task = BusTask::new(settings, Device::Sim(line), &Metrics::new());
    let bus = task.handle();
    let (near, far) = tokio::io::duplex(64 * 1024);
    let link = Measured {
        stream: near,
        round_trip: Some(Duration::from_micros(50)),
    };
    let most = device(far);
    task.handle.up.store(true, Ordering::Release);
    let serving = tokio::spawn(async move {
        let mut stopping = Stopping::never();
        task.serve_pipelined(NetPort::new(link, "device".into()), &mut stopping)
            .await;
    });
    let started = Instant::now();
    let mut masters = Vec::new();
    for m in 0..MASTERS {
        let bus = bus.clone();
        masters.push(tokio::spawn(async move {
            for n in 0..READS_EACH {
                let request = read(100 * m + n);
                let outcome = bus.submit(u64::from(m) + 1, 1, request.clone()).await;
                match outcome.expect("the bus answers every request") {
                    Ok(Answer::Reply(pdu)) => assert_eq!(pdu, answer_to(&request)),
                    other => panic!("master {m}, read {n}: {other:?}"),
                }
            }
        }));
    }
    for master in masters {
        master.await.expect("a master's reads");
    }
    let elapsed = started.elapsed();
    serving.abort();
    let reads = f64::from(MASTERS * READS_EACH);
    (reads / elapsed.as_secs_f64(), most.load(Ordering::SeqCst))
}

#[tokio::test(start_paused = true)]
async fn four_in_flight_carry_at_least_three_and_a_half_times_the_reads_of_one_each_to_its_master()
{
    let (one, most_one) = reads_per_second(1).await;
    let (four, most_four) = reads_per_second(4).await;
    assert_eq!(
        (most_one, most_four),
        (1, 4),
        "requests held by the device at once"
    );
    assert!(
        four >= 3.5 * one,
        "max_in_flight = 4: {four:.0} reads/s, 1: {one:.0} reads/s"
    );
}
