//! `simulate --listen`: a bus's simulated line on a TCP socket, as a serial device server in
//! transparent (raw TCP) mode serves its RS-485 port. One client at a time, as a serial line has
//! one master: a connection that comes while a client is served is accepted and closed at once
//! (refused, as a device server set to one connection does), so its master learns it at once
//! rather than by timeouts; once the client leaves, the next connection is served. The slaves
//! keep their state from one client to the next. Owns the socket and who is connected; how bytes
//! become frames on the line and when replies come back is [`crate::sim::device_server`]'s.

use crate::config::Bus;
use crate::sim::device_server::{ClientStats, DeviceServer};
use std::io;
use tokio::net::{TcpListener, TcpStream};
use tokio::time::sleep;
use tracing::{info, warn};

/// Serve `bus`'s simulated line on `listen` (`HOST:PORT`) until an error no retry can cure.
/// `ready` gets `tcp://ADDR` with the address bound, once clients can connect.
pub(super) async fn serve(
    bus: &Bus,
    listen: &str,
    ready: impl FnOnce(&str) -> io::Result<()>,
) -> io::Error {
    let line = match crate::gateway::power_on_line(bus) {
        Ok(line) => line,
        Err(e) => return io::Error::new(io::ErrorKind::InvalidInput, e.to_string()),
    };
    let listener = match TcpListener::bind(listen).await {
        Ok(listener) => listener,
        Err(e) => return io::Error::new(e.kind(), format!("cannot listen on {listen}: {e}")),
    };
    let addr = match listener.local_addr() {
        Ok(addr) => addr,
        Err(e) => return e,
    };
    info!(%addr, bus = bus.name, "serving the simulated line to one client at a time");
    if let Err(e) = ready(&format!("tcp://{addr}")) {
        return e;
    }
    let server = DeviceServer::new(line, bus.framing, bus.master_timing().silence);
    loop {
        let (mut stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(e) => {
                // Out of descriptors, say: the clients' problem or a passing one, not the line's.
                warn!(%addr, error = %e, "cannot accept a client");
                sleep(bus.reopen_delay).await;
                continue;
            }
        };
        // Each reply is one write, already whole: nothing to gain from waiting to coalesce.
        if let Err(e) = stream.set_nodelay(true) {
            warn!(%peer, error = %e, "cannot set TCP_NODELAY");
        }
        info!(%peer, "client connected");
        let (stats, result) = serve_one(&server, &listener, &mut stream).await;
        let (requests, replies) = (stats.requests, stats.replies);
        match result {
            Ok(()) => info!(%peer, requests, replies, "client disconnected"),
            Err(e) => info!(%peer, requests, replies, error = %e, "client lost"),
        }
    }
}

/// Serve `stream` until its client leaves, refusing every other connection meanwhile.
async fn serve_one(
    server: &DeviceServer,
    listener: &TcpListener,
    stream: &mut TcpStream,
) -> (ClientStats, io::Result<()>) {
    let served = server.serve(stream);
    tokio::pin!(served);
    loop {
        tokio::select! {
            // The client's own end first: when it has closed and another connects, the newcomer
            // is served, not refused.
            biased;
            done = &mut served => return done,
            accepted = listener.accept() => match accepted {
                Ok((other, peer)) => {
                    info!(%peer, "connection refused: the line has a master already");
                    drop(other);
                }
                // Accepting fails (out of descriptors): stop trying until this client is done.
                Err(_) => return (&mut served).await,
            },
        }
    }
}
