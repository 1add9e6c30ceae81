//! Hundreds of masters at once on one line: every reply correct and to the right master, the
//! line shared fairly even when some masters pipeline and others do not, and its queue too: a
//! master that asks politely gets in however many others flood it.

use crate::support::{
    addr, assert_fair, crowded_line, flood_target, polite_reads, start, within, Flood,
    GatewayConfig, RawMaster, Rotation,
};
use std::net::SocketAddr;
use std::sync::Arc;
use tokio::sync::Barrier;

const MASTERS: usize = 200;
/// Half the masters keep this many requests in flight; the other half one at a time.
const GREEDY_PIPELINE: usize = 8;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_hundred_masters_are_all_served_correctly_and_fairly() {
    let gateway = GatewayConfig::new().bus(crowded_line()).start().await;
    let at = addr(&gateway);
    let barrier = Arc::new(Barrier::new(MASTERS));
    let rotation = Rotation::new(MASTERS);
    let mut masters = Vec::new();
    for m in 0..MASTERS {
        let (barrier, rotation) = (barrier.clone(), rotation.clone());
        masters.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(at).await;
            let unit = 1 + (m % 4) as u8;
            // Input register N reads N: each master asks for its own and checks the answer.
            let register = m as u16;
            let request = [0x04, (register >> 8) as u8, register as u8, 0x00, 0x01];
            let in_flight = if m % 2 == 0 { GREEDY_PIPELINE } else { 1 };
            barrier.wait().await;
            let mut tid = 0u16;
            for _ in 0..in_flight {
                tid += 1;
                master.send(tid, unit, &request).await;
            }
            let mut counted = 0usize;
            let mut expected_tid = 1u16;
            loop {
                let reply = master.recv().await;
                assert_eq!(
                    reply.transaction, expected_tid,
                    "master {m}: in order, its own ids"
                );
                assert_eq!(reply.unit, unit);
                assert_eq!(
                    reply.pdu,
                    [0x04, 0x02, request[1], request[2]],
                    "master {m}"
                );
                expected_tid += 1;
                match rotation.completed() {
                    None => return counted,
                    Some(counts) => counted += usize::from(counts),
                }
                tid += 1;
                master.send(tid, unit, &request).await;
            }
        }));
    }
    assert_fair(masters, "master").await;
}

/// Attacking connections, each keeping `PIPELINE` reads in flight back to back.
const ATTACKERS: u16 = 40;
const PIPELINE: u16 = 16;
/// The polite master's reads, one at a time.
const POLITE_READS: u16 = 20;

/// Forty connections each pipelining sixteen reads.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forty_pipelining_connections_leave_a_polite_master_95_percent_answered() {
    // Room for more requests than there are masters, for far fewer than the attackers send.
    let gateway = start(&flood_target(115200, 64)).await;
    let at = addr(&gateway);
    let flood = Flood::new();
    let attackers: Vec<_> = (0..ATTACKERS)
        .map(|a| tokio::spawn(pipeline(at, a, flood.clone())))
        .collect();
    flood.until_refused(usize::from(ATTACKERS)).await;
    let answered = polite_reads(at, 2, POLITE_READS).await;
    flood.stop();
    for attacker in attackers {
        within("an attacker stops", attacker)
            .await
            .expect("attacker task");
    }
    eprintln!("polite master: {answered} of {POLITE_READS} answered");
    assert!(
        answered * 100 >= 95 * POLITE_READS,
        "polite master: {answered} of {POLITE_READS} answered"
    );
}

/// An attacker: `PIPELINE` reads of its own input register in flight until the flood stops.
/// Every reply in order, to its own request: the answer, or 0x06.
async fn pipeline(at: SocketAddr, index: u16, flood: Arc<Flood>) {
    let mut master = RawMaster::connect(at).await;
    let [hi, lo] = index.to_be_bytes();
    let request = [0x04, hi, lo, 0x00, 0x01];
    let mut sent = 0u16;
    for _ in 0..PIPELINE {
        master.send(sent, 1, &request).await;
        sent += 1;
    }
    let mut expected = 0u16;
    while !flood.is_stopped() {
        let reply = master.recv().await;
        assert_eq!((reply.transaction, reply.unit), (expected, 1), "in order");
        if reply.pdu == [0x84, 0x06] {
            flood.refused();
        } else {
            assert_eq!(reply.pdu, [0x04, 0x02, hi, lo], "attacker {index}: its own");
        }
        expected = expected.wrapping_add(1);
        master.send(sent, 1, &request).await;
        sent = sent.wrapping_add(1);
    }
}
