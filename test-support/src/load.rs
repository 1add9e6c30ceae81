//! Load on a gateway: masters in rotation and their fairness, floods and polite masters.

use crate::master::RawMaster;
use crate::wait::within;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::task::JoinHandle;

/// The completions of many masters polling at once, counted in a window after a warm-up, for
/// judging whether the line was shared fairly.
pub struct Rotation {
    total: std::sync::atomic::AtomicUsize,
    over: std::sync::atomic::AtomicBool,
    /// Completions before counting starts, so that every master has joined the rotation.
    warm_up: usize,
    /// Completions counted.
    window: usize,
}

impl Rotation {
    /// For `masters` masters: a warm-up of two rounds, a window of five.
    pub fn new(masters: usize) -> Arc<Rotation> {
        Arc::new(Rotation {
            total: std::sync::atomic::AtomicUsize::new(0),
            over: std::sync::atomic::AtomicBool::new(false),
            warm_up: 2 * masters,
            window: 5 * masters,
        })
    }

    /// A master completed a request: whether it counts, or `None` once the window is over.
    pub fn completed(&self) -> Option<bool> {
        use std::sync::atomic::Ordering::Relaxed;
        let n = self.total.fetch_add(1, Relaxed) + 1;
        if self.over.load(Relaxed) {
            return None;
        }
        if n >= self.warm_up + self.window {
            self.over.store(true, Relaxed);
        }
        Some(n > self.warm_up)
    }
}

/// Wait for every master's count of completions in the window, and check that none got less
/// than half of what another got.
pub async fn assert_fair(masters: Vec<JoinHandle<usize>>, what: &str) {
    let mut counts = Vec::new();
    for master in masters {
        counts.push(
            within("every master finishes", master)
                .await
                .expect("master task"),
        );
    }
    let min = *counts.iter().min().unwrap();
    let max = *counts.iter().max().unwrap();
    eprintln!("completions per {what}: min {min}, max {max}");
    assert!(min >= 1, "a {what} got nothing: {counts:?}");
    assert!(max <= 2 * min, "unfair: min {min}, max {max}: {counts:?}");
}

/// A master reading 125 registers of slave 1 back to back until aborted, so that the trace has
/// about a kilobyte to send per read.
pub fn keep_line_busy(gateway: SocketAddr) -> JoinHandle<()> {
    tokio::spawn(async move {
        let mut master = RawMaster::connect(gateway).await;
        for transaction in (0..=u16::MAX).cycle() {
            if master
                .try_call(transaction, 1, &[0x03, 0x00, 0x00, 0x00, 0x7D])
                .await
                .is_none()
            {
                return;
            }
        }
    })
}

/// Masters flooding a gateway (an attack): when to stop, and how many of their requests it
/// refused with 0x06.
#[derive(Default)]
pub struct Flood {
    stopped: std::sync::atomic::AtomicBool,
    refused: std::sync::atomic::AtomicUsize,
}

impl Flood {
    pub fn new() -> Arc<Flood> {
        Arc::default()
    }

    pub fn stop(&self) {
        self.stopped
            .store(true, std::sync::atomic::Ordering::Relaxed);
    }

    pub fn is_stopped(&self) -> bool {
        self.stopped.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// One of the flood's requests got 0x06.
    pub fn refused(&self) {
        self.refused
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }

    /// Wait (bounded) until `n` of the flood's requests were refused: the queue is full.
    pub async fn until_refused(&self, n: usize) {
        within("the flood fills the queue", async {
            while self.refused.load(std::sync::atomic::Ordering::Relaxed) < n {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await;
    }
}

/// A polite master: `reads` reads of input register 1000 of `unit` (a register-bank slave), one
/// at a time. How many were answered; the others must have got 0x06.
pub async fn polite_reads(at: SocketAddr, unit: u8, reads: u16) -> u16 {
    let mut master = RawMaster::connect(at).await;
    let mut answered = 0;
    for transaction in 0..reads {
        // Input register N reads N.
        match &master
            .call(transaction, unit, &[0x04, 0x03, 0xE8, 0x00, 0x01])
            .await[..]
        {
            [0x04, 0x02, 0x03, 0xE8] => answered += 1,
            refused => assert_eq!(refused, [0x84, 0x06], "read {transaction}"),
        }
    }
    answered
}
