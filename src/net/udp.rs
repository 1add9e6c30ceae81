//! Modbus UDP (`server.listen_udp`): one MBAP request per datagram, its reply sent to the
//! datagram's source and nowhere else. A master is a source address and port; while it has
//! requests pending it is one master in the buses' fair queues, like a TCP connection, but all
//! the ports of one address share one turn on a line and count as one master for admission to a
//! full queue (ports cost a sender nothing). Datagrams from outside `server.allow` (the door
//! every listener shares, [`listener::admit`]), malformed ones, and those beyond
//! `pipeline_depth` pending for one source are dropped and counted, never queued without bound.

use super::listener;
use super::server::Shared;
use crate::dispatch::Client;
use crate::master::{MasterId, Protocol};
use crate::mbap;
use crate::metrics::{UdpDrop, UdpMetrics};
use bytes::BytesMut;
use std::collections::{hash_map, HashMap};
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::net::UdpSocket;
use tracing::warn;

/// A datagram holds one ADU: the MBAP header and at most a 253-byte PDU.
const MAX_DATAGRAM: usize = mbap::MAX_FRAME_LEN;
/// Pause after a receive error, so the loop does not spin.
const RECV_ERROR_PAUSE: Duration = Duration::from_millis(100);

/// The sources with requests pending, and their addresses.
#[derive(Default)]
struct Sources {
    /// By source: its client state (a master id of its own) and how many of its requests are
    /// pending.
    ports: HashMap<SocketAddr, (Client, usize)>,
    /// By address: the id all its sources' requests count against in a full bus queue and take
    /// their turns on a line under, and how many of its sources are in `ports`.
    addresses: HashMap<IpAddr, (MasterId, usize)>,
}

type Pending = Mutex<Sources>;

impl Sources {
    /// The client of `peer`; if it has nothing pending, a new one made by `make` from a new
    /// master id, counted against its address's admission id (new too, if no other source of
    /// the address has anything pending).
    fn client(
        &mut self,
        peer: SocketAddr,
        mut new_id: impl FnMut() -> MasterId,
        make: impl FnOnce(MasterId) -> Client,
    ) -> &mut (Client, usize) {
        match self.ports.entry(peer) {
            hash_map::Entry::Occupied(entry) => entry.into_mut(),
            hash_map::Entry::Vacant(entry) => {
                let (admission, ports) = self
                    .addresses
                    .entry(address_of(peer))
                    .or_insert_with(|| (new_id(), 0));
                *ports += 1;
                let mut client = make(new_id());
                client.admission = *admission;
                entry.insert((client, 0))
            }
        }
    }

    /// One of `peer`'s requests is answered; a source with none pending is forgotten, and an
    /// address with no source left, so the table holds only sources the buses are serving.
    fn done(&mut self, peer: SocketAddr) {
        let Some((_, count)) = self.ports.get_mut(&peer) else {
            return;
        };
        *count -= 1;
        if *count > 0 {
            return;
        }
        self.ports.remove(&peer);
        if let hash_map::Entry::Occupied(mut entry) = self.addresses.entry(address_of(peer)) {
            entry.get_mut().1 -= 1;
            if entry.get().1 == 0 {
                entry.remove();
            }
        }
    }
}

/// The address `peer` sends from, an IPv4 one however the socket reports it.
fn address_of(peer: SocketAddr) -> IpAddr {
    peer.ip().to_canonical()
}

/// Serve datagrams on `socket`, bound at `addr`, forever.
pub(crate) async fn serve(socket: UdpSocket, addr: SocketAddr, shared: Arc<Shared>) {
    let socket = Arc::new(socket);
    let pending: Arc<Pending> = Arc::default();
    let mut buf = vec![0u8; MAX_DATAGRAM + 1];
    loop {
        let (len, peer) = match socket.recv_from(&mut buf).await {
            Ok(received) => received,
            Err(error) => {
                warn!(target: UdpMetrics::EVENTS, listen = %addr, %error, "UDP receive failed");
                tokio::time::sleep(RECV_ERROR_PAUSE).await;
                continue;
            }
        };
        let udp = &shared.metrics.udp;
        let policy = shared.policy();
        let Some(admission) = listener::admit(&policy, &shared.metrics, Protocol::Udp, addr, peer)
        else {
            continue;
        };
        let Some(request) = request_of(&buf[..len]) else {
            udp.dropped(UdpDrop::Malformed, &peer);
            continue;
        };
        let depth = policy.limits.pipeline_depth;
        let (header, function) = (request.header, request.pdu[0]);
        let outcome = {
            let mut sources = pending.lock().unwrap_or_else(PoisonError::into_inner);
            let new_id = || shared.new_master();
            let (client, count) = sources.client(peer, new_id, |master| admission.client(master));
            if *count >= depth {
                None
            } else {
                *count += 1;
                Some(shared.dispatcher.submit(client, header.unit, request.pdu))
            }
        };
        let Some(outcome) = outcome else {
            udp.dropped(UdpDrop::Overloaded, &peer);
            continue;
        };
        let socket = socket.clone();
        let pending = pending.clone();
        tokio::spawn(async move {
            let outcome = outcome
                .await
                .unwrap_or(Err(crate::error::RequestError::PortDown));
            if let Some(pdu) = super::session::reply_pdu(function, outcome) {
                let mut reply = Vec::with_capacity(MAX_DATAGRAM);
                mbap::encode(header, &pdu, &mut reply);
                let _ = socket.send_to(&reply, peer).await;
            }
            done(&pending, peer);
        });
    }
}

/// The one whole request a datagram holds, if it is exactly one.
fn request_of(datagram: &[u8]) -> Option<mbap::Request> {
    let mut buf = BytesMut::from(datagram);
    let request = mbap::decode(&mut buf).ok()??;
    buf.is_empty().then_some(request)
}

/// One of `peer`'s requests is answered (see [`Sources::done`]).
fn done(pending: &Pending, peer: SocketAddr) {
    pending
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .done(peer);
}

/// The master id a source has while it has requests pending, and the id its requests count
/// against in a full bus queue (for tests of fairness).
#[cfg(test)]
fn ids_of(pending: &Pending, peer: SocketAddr) -> Option<(MasterId, MasterId)> {
    pending
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .ports
        .get(&peer)
        .map(|(client, _)| (client.master, client.admission))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_datagram_is_one_whole_request_or_nothing() {
        let read = [0, 1, 0, 0, 0, 6, 1, 0x03, 0, 0, 0, 1];
        let request = request_of(&read).expect("one request");
        assert_eq!(request.header.unit, 1);
        assert_eq!(request.pdu, [0x03, 0, 0, 0, 1]);
        assert!(request_of(&read[..10]).is_none(), "cut short");
        assert!(
            request_of(&[&read[..], &read[..]].concat()).is_none(),
            "two"
        );
        assert!(
            request_of(&[0, 1, 0, 9, 0, 6, 1, 0x03, 0, 0, 0, 1]).is_none(),
            "protocol"
        );
        assert!(request_of(&[]).is_none());
    }

    /// `peer` sends a request, its client made with ids counting from `next`.
    fn send(pending: &Pending, peer: SocketAddr, next: &mut MasterId) {
        let mut sources = pending.lock().unwrap();
        let new_id = || {
            *next += 1;
            *next
        };
        let (_, count) = sources.client(peer, new_id, |master| {
            Client::new(master, peer, crate::master::Rights::ReadWrite)
        });
        *count += 1;
    }

    #[test]
    fn a_source_is_forgotten_once_nothing_of_it_is_pending() {
        let pending = Pending::default();
        let mut next = 0;
        let peer: SocketAddr = ([127, 0, 0, 1], 5000).into();
        send(&pending, peer, &mut next);
        send(&pending, peer, &mut next);
        let ids = ids_of(&pending, peer).expect("pending");
        done(&pending, peer);
        assert_eq!(ids_of(&pending, peer), Some(ids));
        done(&pending, peer);
        assert_eq!(ids_of(&pending, peer), None);
        assert!(pending.lock().unwrap().addresses.is_empty());
    }

    #[test]
    fn ports_of_one_address_share_an_admission_id_while_any_has_requests_pending() {
        let pending = Pending::default();
        let mut next = 0;
        let port = |ip: &str, port: u16| SocketAddr::new(ip.parse().unwrap(), port);
        let (a, b) = (port("127.0.0.1", 5000), port("127.0.0.1", 5001));
        // The same address as a dual-stack socket reports it.
        let mapped = port("::ffff:127.0.0.1", 5002);
        let other = port("127.0.0.2", 5000);
        for peer in [a, b, mapped, other] {
            send(&pending, peer, &mut next);
        }
        let ids: Vec<(MasterId, MasterId)> = [a, b, mapped, other]
            .iter()
            .map(|&peer| ids_of(&pending, peer).expect("pending"))
            .collect();
        let masters: std::collections::HashSet<MasterId> = ids.iter().map(|&(m, _)| m).collect();
        assert_eq!(masters.len(), 4, "a master of its own each: {ids:?}");
        assert_eq!(ids[0].1, ids[1].1, "{ids:?}");
        assert_eq!(ids[0].1, ids[2].1, "{ids:?}");
        assert_ne!(ids[0].1, ids[3].1, "{ids:?}");
        assert!(!masters.contains(&ids[0].1) && !masters.contains(&ids[3].1));
        // The address keeps its id while one of its ports has a request pending.
        done(&pending, a);
        done(&pending, b);
        send(&pending, a, &mut next);
        assert_eq!(ids_of(&pending, a).expect("pending").1, ids[0].1);
        done(&pending, a);
        done(&pending, mapped);
        send(&pending, b, &mut next);
        assert_ne!(
            ids_of(&pending, b).expect("pending").1,
            ids[0].1,
            "a new one"
        );
    }
}
