//! Modbus UDP (`server.listen_udp`): one MBAP request per datagram, its reply sent to the
//! datagram's source and nowhere else. A master is a source address and port; while it has
//! requests pending it is one master in the buses' fair queues, like a TCP connection. Datagrams
//! from outside `server.allow`, malformed ones, and those beyond `pipeline_depth` pending for one
//! source are dropped and counted, never queued without bound.

use super::mbap;
use super::server::Shared;
use crate::dispatch::Client;
use crate::metrics::{Protocol, UdpDrop};
use bytes::BytesMut;
use std::collections::HashMap;
use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::net::UdpSocket;
use tracing::warn;

/// A datagram holds one ADU: the MBAP header and at most a 253-byte PDU.
const MAX_DATAGRAM: usize = mbap::HEADER_LEN + crate::pdu::MAX_PDU_LEN;
/// Pause after a receive error, so the loop does not spin.
const RECV_ERROR_PAUSE: Duration = Duration::from_millis(100);

pub(crate) struct UdpListener {
    pub addr: SocketAddr,
    socket: Arc<UdpSocket>,
}

/// Bind every address, or fail naming the one that could not be bound.
pub(crate) async fn bind(
    addrs: &[SocketAddr],
) -> Result<Vec<UdpListener>, (SocketAddr, io::Error)> {
    let mut listeners = Vec::with_capacity(addrs.len());
    for &addr in addrs {
        let socket = UdpSocket::bind(addr).await.map_err(|e| (addr, e))?;
        let addr = socket.local_addr().map_err(|e| (addr, e))?;
        listeners.push(UdpListener {
            addr,
            socket: Arc::new(socket),
        });
    }
    Ok(listeners)
}

/// The sources with requests pending: their master id, client state and how many are pending.
type Pending = Mutex<HashMap<SocketAddr, (Client, usize)>>;

/// Serve datagrams on `listener` forever.
pub(crate) async fn serve(listener: UdpListener, shared: Arc<Shared>) {
    let pending: Arc<Pending> = Arc::default();
    let mut buf = vec![0u8; MAX_DATAGRAM + 1];
    loop {
        let (len, peer) = match listener.socket.recv_from(&mut buf).await {
            Ok(received) => received,
            Err(error) => {
                warn!(listen = %listener.addr, %error, "UDP receive failed");
                tokio::time::sleep(RECV_ERROR_PAUSE).await;
                continue;
            }
        };
        let udp = &shared.metrics.udp;
        let policy = shared.policy();
        let Some(rights) = policy.access.admit(peer.ip()) else {
            udp.dropped(UdpDrop::NotAllowed, &peer);
            continue;
        };
        let Some(request) = request_of(&buf[..len]) else {
            udp.dropped(UdpDrop::Malformed, &peer);
            continue;
        };
        let depth = policy.limits.pipeline_depth;
        let priority = policy.access.is_priority(peer.ip());
        let (header, function) = (request.header, request.pdu[0]);
        let outcome = {
            let mut sources = pending.lock().unwrap_or_else(PoisonError::into_inner);
            let (client, count) = sources.entry(peer).or_insert_with(|| {
                let client = Client::new(shared.new_master(), peer, rights);
                (client.speaking(Protocol::Udp).prioritised(priority), 0)
            });
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
        let socket = listener.socket.clone();
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

/// One of `peer`'s requests is answered; a source with none pending is forgotten, so the table
/// holds only sources the buses are serving.
fn done(pending: &Pending, peer: SocketAddr) {
    let mut sources = pending.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some((_, count)) = sources.get_mut(&peer) {
        *count -= 1;
        if *count == 0 {
            sources.remove(&peer);
        }
    }
}

/// The master id a source has while it has requests pending (for tests of fairness).
#[cfg(test)]
pub(crate) fn master_of(pending: &Pending, peer: SocketAddr) -> Option<crate::bus::MasterId> {
    pending
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .get(&peer)
        .map(|(client, _)| client.master)
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

    #[test]
    fn a_source_is_forgotten_once_nothing_of_it_is_pending() {
        let pending = Pending::default();
        let peer: SocketAddr = ([127, 0, 0, 1], 5000).into();
        let client = Client::new(7, peer, crate::dispatch::Rights::ReadWrite);
        pending.lock().unwrap().insert(peer, (client, 2));
        done(&pending, peer);
        assert_eq!(master_of(&pending, peer), Some(7));
        done(&pending, peer);
        assert_eq!(master_of(&pending, peer), None);
    }
}
