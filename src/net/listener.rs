//! What every listener shares, whatever its transport: binding the `server.listen*` addresses
//! (a TCP socket for a stream transport, a UDP one for datagrams), the [`Policy`] connections
//! and datagrams are admitted under, and the door itself ([`admit`]): `server.allow`, then the
//! rights (`server.read_only`) and priority (`server.priority`) the master's address gives. What
//! comes after the door is the transport's: [`server`] for streams, [`udp`] for datagrams.
//! Knows nothing of framing or sessions.

use super::access::NetworkRights;
use super::server::{self, Shared};
use super::session::SessionLimits;
use super::tls::TlsServer;
use super::udp;
use crate::config::{self, WhenFull};
use crate::dispatch::Client;
use crate::master::{MasterId, Protocol, Rights};
use crate::metrics::{Metrics, Rejection, UdpDrop};
use std::collections::HashMap;
use std::io;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::{TcpListener, UdpSocket};

/// A bound listen address and the protocol its masters speak.
pub(crate) struct Listener {
    pub addr: SocketAddr,
    pub protocol: Protocol,
    socket: Socket,
}

enum Socket {
    Stream(TcpListener),
    Datagram(UdpSocket),
}

/// Bind every address for masters of `protocol`, or fail naming the one that could not be bound.
async fn bind(
    addrs: &[SocketAddr],
    protocol: Protocol,
) -> Result<Vec<Listener>, (SocketAddr, io::Error)> {
    let mut listeners = Vec::with_capacity(addrs.len());
    for &addr in addrs {
        let failed = |e| (addr, e);
        let (socket, bound) = if protocol.transport().is_stream() {
            let socket = TcpListener::bind(addr).await.map_err(failed)?;
            let bound = socket.local_addr().map_err(failed)?;
            (Socket::Stream(socket), bound)
        } else {
            let socket = UdpSocket::bind(addr).await.map_err(failed)?;
            let bound = socket.local_addr().map_err(failed)?;
            (Socket::Datagram(socket), bound)
        };
        listeners.push(Listener {
            addr: bound,
            protocol,
            socket,
        });
    }
    Ok(listeners)
}

/// A listen address that could not be bound: the key that has it, the address, why.
pub(crate) type Unbound = (&'static str, SocketAddr, io::Error);

/// Every listener of `server`, in the order of its keys: `listen` (Modbus TCP),
/// `listen_rtu_over_tcp`, `listen_tls`, `listen_udp`; or the address that could not be bound.
pub(crate) async fn bind_all(server: &config::Server) -> Result<Vec<Listener>, Unbound> {
    let mut listeners = Vec::new();
    for (key, addrs, protocol) in [
        ("server.listen", &server.listen, Protocol::Tcp),
        (
            "server.listen_rtu_over_tcp",
            &server.listen_rtu_over_tcp,
            Protocol::RtuOverTcp,
        ),
        ("server.listen_tls", &server.listen_tls, Protocol::Tls),
        ("server.listen_udp", &server.listen_udp, Protocol::Udp),
    ] {
        let bound = bind(addrs, protocol).await;
        listeners.extend(bound.map_err(|(addr, e)| (key, addr, e))?);
    }
    Ok(listeners)
}

/// Serve the masters of `listener` forever, as its transport does.
pub(crate) async fn serve(listener: Listener, shared: Arc<Shared>) {
    let Listener {
        addr,
        protocol,
        socket,
    } = listener;
    match socket {
        Socket::Stream(socket) => server::serve(socket, addr, protocol, shared).await,
        Socket::Datagram(socket) => udp::serve(socket, addr, shared).await,
    }
}

/// The bound addresses of the listeners by protocol (port 0 in the configuration becomes the
/// real port here).
#[derive(Clone, Debug, Default)]
pub(crate) struct ListenAddrs {
    by_protocol: HashMap<Protocol, Vec<SocketAddr>>,
}

impl ListenAddrs {
    pub(crate) fn of(listeners: &[Listener]) -> Self {
        let mut addrs = ListenAddrs::default();
        for listener in listeners {
            let of_protocol = addrs.by_protocol.entry(listener.protocol).or_default();
            of_protocol.push(listener.addr);
        }
        addrs
    }

    pub(crate) fn of_protocol(&self, protocol: Protocol) -> &[SocketAddr] {
        self.by_protocol.get(&protocol).map_or(&[], Vec::as_slice)
    }
}

/// How masters are admitted and served: `[server]` minus the listen addresses, and the TLS
/// server that the `[server.tls]` files made.
#[derive(Clone, Debug)]
pub(crate) struct Policy {
    pub limits: SessionLimits,
    pub access: NetworkRights,
    pub when_full: WhenFull,
    /// Connections one address may hold; `None`: no limit.
    pub per_address: Option<usize>,
    /// `None`: no keepalive probes.
    pub keepalive: Option<Duration>,
    /// For the TLS listeners.
    pub tls: Option<Arc<TlsServer>>,
}

impl Policy {
    /// The policy of `server`, with `tls` for its TLS listeners.
    pub(crate) fn of(server: &config::Server, tls: Option<Arc<TlsServer>>) -> Policy {
        Policy {
            limits: SessionLimits {
                pipeline_depth: server.pipeline_depth,
                idle_timeout: Some(server.idle_timeout).filter(|t| !t.is_zero()),
                frame_timeout: server.frame_timeout,
            },
            access: NetworkRights::new(server.allow.clone(), server.read_only.clone())
                .with_priority(server.priority.clone()),
            when_full: server.when_full,
            per_address: server.connections_per_address(),
            keepalive: Some(server.keepalive).filter(|t| !t.is_zero()),
            tls,
        }
    }
}

/// A master let in at a listener's door, with what its address gives it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Admitted {
    pub protocol: Protocol,
    pub peer: SocketAddr,
    /// What its address allows (a TLS master's role may narrow it).
    pub rights: Rights,
    /// Served before the others (`server.priority`).
    pub priority: bool,
}

impl Admitted {
    /// The client of the master so admitted, under the id `master`.
    pub(crate) fn client(&self, master: MasterId) -> Client {
        Client::new(master, self.peer, self.rights)
            .speaking(self.protocol)
            .prioritised(self.priority)
    }
}

/// Every listener's door: a master of `protocol` from `peer`, reaching the listener at `listen`,
/// as `policy` admits it; one outside `server.allow` is counted and logged as its transport
/// does (a refused connection, a dropped datagram), and gets `None`.
pub(crate) fn admit(
    policy: &Policy,
    metrics: &Metrics,
    protocol: Protocol,
    listen: SocketAddr,
    peer: SocketAddr,
) -> Option<Admitted> {
    let Some(rights) = policy.access.admit(peer.ip()) else {
        if protocol.transport().is_stream() {
            metrics
                .tcp
                .rejected(Rejection::NotAllowed, protocol, &listen, &peer);
        } else {
            metrics.udp.dropped(UdpDrop::NotAllowed, &peer);
        }
        return None;
    };
    Some(Admitted {
        protocol,
        peer,
        rights,
        priority: policy.access.is_priority(peer.ip()),
    })
}
