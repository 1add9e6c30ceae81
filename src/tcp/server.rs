//! The listeners: accept masters on every `server.listen` address, refuse those beyond
//! `max_connections` (accepted and closed at once, so they see the refusal instead of hanging in
//! the backlog), set TCP_NODELAY, and run one session task per master.

use super::session::{self, SessionLimits};
use crate::bus::MasterId;
use crate::dispatch::Dispatcher;
use crate::metrics::{Metrics, Rejection};
use crate::shutdown::Stopping;
use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tracing::{debug, warn};

/// Pause after an accept error such as running out of file descriptors, so the loop does not spin.
const ACCEPT_ERROR_PAUSE: Duration = Duration::from_millis(100);

pub struct Listener {
    pub addr: SocketAddr,
    listener: TcpListener,
}

/// Bind every address, or fail naming the one that could not be bound.
pub async fn bind(addrs: &[SocketAddr]) -> Result<Vec<Listener>, (SocketAddr, io::Error)> {
    let mut listeners = Vec::with_capacity(addrs.len());
    for &addr in addrs {
        let listener = TcpListener::bind(addr).await.map_err(|e| (addr, e))?;
        let addr = listener.local_addr().map_err(|e| (addr, e))?;
        listeners.push(Listener { addr, listener });
    }
    Ok(listeners)
}

/// What every accept loop shares.
pub struct Shared {
    pub dispatcher: Dispatcher,
    /// For sessions that start from now on.
    limits: Mutex<SessionLimits>,
    pub connections: Arc<Semaphore>,
    pub metrics: Arc<Metrics>,
    pub stopping: Stopping,
    max_connections: AtomicUsize,
    next_master: AtomicU64,
}

impl Shared {
    pub fn new(
        dispatcher: Dispatcher,
        limits: SessionLimits,
        max_connections: usize,
        metrics: Arc<Metrics>,
        stopping: Stopping,
    ) -> Self {
        Shared {
            dispatcher,
            limits: Mutex::new(limits),
            connections: Arc::new(Semaphore::new(max_connections)),
            metrics,
            stopping,
            max_connections: AtomicUsize::new(max_connections),
            next_master: AtomicU64::new(1),
        }
    }

    pub fn limits(&self) -> SessionLimits {
        *self.limits.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// New limits: sessions that start from now on get `limits`; connections beyond a lower
    /// `max_connections` stay open, and new ones are refused until enough have closed.
    pub fn set_limits(&self, limits: SessionLimits, max_connections: usize) {
        *self.limits.lock().unwrap_or_else(PoisonError::into_inner) = limits;
        let old = self
            .max_connections
            .swap(max_connections, Ordering::Relaxed);
        if max_connections > old {
            self.connections.add_permits(max_connections - old);
        } else {
            let mut owed = old - max_connections;
            owed -= self.connections.forget_permits(owed);
            // Permits still held by open sessions are taken back as those sessions end.
            if owed > 0 {
                let connections = self.connections.clone();
                let owed = u32::try_from(owed).unwrap_or(u32::MAX);
                tokio::spawn(async move {
                    if let Ok(permits) = connections.acquire_many(owed).await {
                        permits.forget();
                    }
                });
            }
        }
    }

    /// Sessions running now.
    pub fn connections_open(&self) -> usize {
        let max = self.max_connections.load(Ordering::Relaxed);
        max.saturating_sub(self.connections.available_permits())
    }

    /// Wait until every session has ended (each holds a connection permit while it runs).
    pub async fn sessions_ended(&self) {
        let all = self.max_connections.load(Ordering::Relaxed);
        let all = u32::try_from(all).unwrap_or(u32::MAX);
        let _ = self.connections.acquire_many(all).await;
    }
}

/// Accept masters on `listener` forever.
pub async fn serve(listener: Listener, shared: Arc<Shared>) {
    loop {
        let (stream, peer) = match listener.listener.accept().await {
            Ok(accepted) => accepted,
            Err(error) => {
                warn!(listen = %listener.addr, %error, "accept failed");
                tokio::time::sleep(ACCEPT_ERROR_PAUSE).await;
                continue;
            }
        };
        let tcp = &shared.metrics.tcp;
        let Ok(permit) = shared.connections.clone().try_acquire_owned() else {
            tcp.rejected(Rejection::MaxConnections, &listener.addr, &peer);
            drop(stream);
            continue;
        };
        if let Err(error) = stream.set_nodelay(true) {
            debug!(%peer, %error, "cannot set TCP_NODELAY");
        }
        let master: MasterId = shared.next_master.fetch_add(1, Ordering::Relaxed);
        tcp.accepted(master, &peer);
        let shared = shared.clone();
        tokio::spawn(async move {
            let stopping = shared.stopping.clone();
            let limits = shared.limits();
            let error = session::run(stream, master, &shared.dispatcher, limits, stopping).await;
            shared
                .metrics
                .tcp
                .closed(error.closing(), master, &peer, &error);
            drop(permit);
        });
    }
}
