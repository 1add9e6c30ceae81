//! One task per bus that polls its slaves' plant values: each read when it is due, through the
//! bus's queue in the polls' ring (after every master, coalesced with their identical reads,
//! answered from a slave's cache), one at a time, and no more of the line's time than
//! `poll_share`: after a poll that took the line *t*, the next waits *t* x (1 - share) / share.
//! What a reply holds goes to the store, what a poll came to to the bus's metrics.

use super::decode::{self, BadBlock};
use super::plan::Read;
use super::store::Store;
use crate::bus::BusHandle;
use crate::config::Value;
use crate::error::{Answer, NoReply, Outcome, RequestError};
use crate::master::{Class, MasterId, Origin, Protocol};
use crate::timer::coarse_sleep_until;
use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::sync::Arc;
use std::time::{Duration, SystemTime};
use tokio::time::Instant;

/// The poller's id among a bus's masters: no connection ever has it.
const POLLER: MasterId = MasterId::MAX;

/// One read and the values it holds: each value's entry in the store, its first register's
/// distance from the read's first, and how to decode it.
pub(crate) struct Poll {
    pub(crate) read: Read,
    pub(crate) values: Vec<(usize, u16, Value)>,
}

/// Poll `polls` on `bus` for ever, into `store`, within `share` of the line's time.
pub(crate) async fn run(bus: BusHandle, polls: Vec<Poll>, store: Arc<Store>, share: f64) {
    if polls.is_empty() {
        return;
    }
    let origin = Origin {
        master: POLLER,
        admission: POLLER,
        protocol: Protocol::Tcp,
        class: Class::Poll,
    };
    let start = Instant::now();
    let mut due: BinaryHeap<Reverse<(Instant, usize)>> =
        (0..polls.len()).map(|i| Reverse((start, i))).collect();
    let mut not_before = start;
    while let Some(Reverse((at, i))) = due.pop() {
        coarse_sleep_until(at.max(not_before)).await;
        let poll = &polls[i];
        let read = &poll.read;
        let pdu = decode::request(read.table, read.first, read.count);
        let used_before = bus.poll_time();
        let outcome = bus.submit_from(origin, read.slave, pdu).await;
        let line_time = bus.poll_time().saturating_sub(used_before);
        let failed = take(poll, outcome, &store);
        bus.metrics().polled(read.slave, failed);
        let now = Instant::now();
        not_before = now + pause_after(line_time, share);
        // A poll that fell behind its interval is due at once, not as often as it missed.
        due.push(Reverse(((at + read.interval).max(now), i)));
    }
}

/// How long polling leaves the line to others after a poll that took it `line_time`, so that
/// polling takes at most `share` of it.
fn pause_after(line_time: Duration, share: f64) -> Duration {
    line_time.mul_f64((1.0 - share) / share)
}

/// What `outcome` of `poll` says of its values, into `store`; the outcome's label if it failed.
fn take(poll: &Poll, outcome: Result<Outcome, impl Sized>, store: &Store) -> Option<&'static str> {
    let read = &poll.read;
    let words = match outcome {
        Ok(Ok(Answer::Reply(pdu))) => decode::words(read.table, read.count, &pdu),
        Ok(Ok(Answer::Malformed(_) | Answer::Nothing | Answer::Acknowledged(_))) | Err(_) => {
            Err(BadBlock::BadReply)
        }
        Ok(Err(error)) => {
            let outcome = failure(&error);
            for &(entry, _, _) in &poll.values {
                store.failed(entry, outcome);
            }
            return Some(outcome);
        }
    };
    let words = match words {
        Ok(words) => words,
        Err(unreadable) => {
            let outcome = match unreadable {
                BadBlock::Exception(_) => "exception",
                BadBlock::BadReply => "bad_reply",
            };
            for &(entry, _, _) in &poll.values {
                store.failed(entry, outcome);
            }
            return Some(outcome);
        }
    };
    let now = SystemTime::now();
    for (entry, offset, value) in &poll.values {
        match decode::decode(value, words.get(usize::from(*offset)..).unwrap_or_default()) {
            Some(number) => store.read(*entry, number, now),
            None => store.failed(*entry, "bad_reply"),
        }
    }
    None
}

/// The `outcome` label of a poll the gateway could not have answered.
fn failure(error: &RequestError) -> &'static str {
    match error {
        RequestError::NoResponse {
            last: NoReply::Timeout,
            ..
        } => "timeout",
        RequestError::NoResponse { .. } => "bad_reply",
        RequestError::SlaveDown { .. } => "slave_down",
        RequestError::QueueFull => "queue_full",
        RequestError::Expired => "expired",
        _ => "port_down",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polling_leaves_the_line_to_others_for_the_rest_of_its_share() {
        let ms = Duration::from_millis;
        assert_eq!(pause_after(ms(50), 0.2), ms(200));
        assert_eq!(pause_after(ms(50), 0.5), ms(50));
        assert_eq!(pause_after(ms(50), 1.0), Duration::ZERO);
        assert_eq!(pause_after(Duration::ZERO, 0.2), Duration::ZERO);
    }
}
