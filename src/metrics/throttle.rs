//! Warn lines that a master's own doing causes (a protocol error, a refused write, a failed TLS
//! handshake), at most one per interval per source address and kind, the next one saying how
//! many were held back meanwhile, so that one client cannot flood the journal and make it drop
//! the gateway's own lines ("slave down", "port lost"). What is held back is still counted, and
//! logged at debug.

use crate::master::Host;
use crate::timer::RealInstant;
use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

/// At most one warn line per source address and kind of event per this interval.
pub(super) const INTERVAL: Duration = Duration::from_secs(60);
/// Source addresses remembered per kind; beyond that, events of new addresses are logged at
/// debug until the oldest are an interval old, so a scan of many addresses cannot grow the map.
const PEERS: usize = 1024;

struct Logged {
    at: RealInstant,
    /// Events held back since `at`.
    held_back: u64,
}

/// One kind of event's last warn line per source address.
pub(super) struct PeerThrottle {
    logged: Mutex<HashMap<Host, Logged>>,
}

impl PeerThrottle {
    pub(super) fn new() -> Self {
        PeerThrottle {
            logged: Mutex::new(HashMap::new()),
        }
    }

    /// Whether an event from `peer` now gets its warn line: `Some(n)`, `n` being how many of
    /// its events were held back since its last one; `None`: log it at debug.
    pub(super) fn due(&self, peer: impl Into<Host>) -> Option<u64> {
        let host = match peer.into() {
            Host::Ip(ip) => Host::Ip(ip.to_canonical()),
            port => port,
        };
        self.due_at(host, RealInstant::now())
    }

    fn due_at(&self, peer: Host, now: RealInstant) -> Option<u64> {
        let mut logged = self.logged.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(last) = logged.get_mut(&peer) {
            if now.duration_since(last.at) < INTERVAL {
                last.held_back += 1;
                return None;
            }
            let held_back = last.held_back;
            *last = Logged {
                at: now,
                held_back: 0,
            };
            return Some(held_back);
        }
        if logged.len() >= PEERS {
            logged.retain(|_, last| now.duration_since(last.at) < INTERVAL);
            if logged.len() >= PEERS {
                return None;
            }
        }
        logged.insert(
            peer,
            Logged {
                at: now,
                held_back: 0,
            },
        );
        Some(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::IpAddr;

    #[test]
    fn one_line_per_address_per_interval_and_the_next_says_how_many_were_held_back() {
        let throttle = PeerThrottle::new();
        let start = RealInstant::now();
        let a: IpAddr = "192.0.2.1".parse().unwrap();
        let b: IpAddr = "192.0.2.2".parse().unwrap();
        assert_eq!(throttle.due_at(a.into(), start), Some(0));
        for _ in 0..5 {
            assert_eq!(
                throttle.due_at(a.into(), start + Duration::from_secs(1)),
                None
            );
        }
        assert_eq!(throttle.due_at(b.into(), start), Some(0), "another address");
        assert_eq!(throttle.due_at(a.into(), start + INTERVAL), Some(5));
        assert_eq!(throttle.due_at(a.into(), start + INTERVAL), None);
    }

    #[test]
    fn a_scan_of_many_addresses_does_not_grow_the_map_past_its_bound() {
        let throttle = PeerThrottle::new();
        let start = RealInstant::now();
        for n in 0..(PEERS as u32 + 100) {
            let peer = IpAddr::from(std::net::Ipv4Addr::from(0x0A00_0000 + n));
            let due = throttle.due_at(peer.into(), start);
            assert_eq!(due.is_some(), (n as usize) < PEERS, "{n}");
        }
        let logged = throttle.logged.lock().unwrap();
        assert_eq!(logged.len(), PEERS);
        drop(logged);
        // An interval later the old ones make room.
        let late = IpAddr::from(std::net::Ipv4Addr::new(192, 0, 2, 9));
        assert_eq!(throttle.due_at(late.into(), start + INTERVAL), Some(0));
    }
}
