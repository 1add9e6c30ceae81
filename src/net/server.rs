//! The stream listeners' accept loop (TCP, and TLS on TCP): accept masters; refuse those the
//! door every listener shares refuses ([`listener::admit`]: outside `server.allow`) and those
//! beyond `max_connections_per_address` from one address; at `max_connections`, make room by
//! closing a connection that is not working (or refuse, with `when_full = "refuse"`, or when
//! every connection is working). Refused masters are accepted
//! and closed at once, so they see the refusal instead of hanging in the backlog. Each accepted
//! connection gets TCP_NODELAY, keepalive probes, and one session task. On a TLS listener the
//! handshake comes first (after `allow`, before a connection slot: a peer that has not proved
//! who it is never closes an authenticated master's connection), and the certificate's role
//! narrows the rights.

use super::listener::{self, Admitted, Policy};
use super::session::{self, Activity, SessionView};
use super::tls::Certified;
use crate::config::{WhenFull, OTHER_ROLE};
use crate::dispatch::{Client, Dispatcher};
use crate::master::{MasterId, Peer, Protocol, Rights, UpstreamTransport};
use crate::metrics::{Metrics, Rejection, TcpMetrics, TlsMaster};
use crate::shutdown::Stopping;
use crate::socket::set_keepalive;
use std::collections::HashMap;
use std::io;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, SystemTime};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;
use tracing::{debug, error, warn};

/// Pause after an accept error such as running out of file descriptors, so the loop does not spin.
const ACCEPT_ERROR_PAUSE: Duration = Duration::from_millis(100);
/// How long a new master waits for the connection closed to make room for it.
const EVICTION_WAIT: Duration = Duration::from_secs(1);
/// TLS handshakes worked on at once; more wait their turn (within the handshake timeout), so a
/// crowd of masters reconnecting together cannot take every core.
const HANDSHAKES_AT_ONCE: usize = 32;
/// Of those, the most one source address may have at once; its others wait their turn, so a
/// host whose peers stall mid-handshake keeps three quarters of the turns for the others.
const HANDSHAKES_PER_ADDRESS: usize = HANDSHAKES_AT_ONCE / 4;
/// How long a TLS peer may stay silent after its accept; it takes a handshake turn only once
/// its first bytes (its ClientHello) arrive, so silent connections never keep a master's
/// handshake waiting. A TLS master sends at once; this leaves room for a lost segment's
/// retransmission and a slow client's key generation. Within the handshake timeout.
const FIRST_BYTES_WAIT: Duration = Duration::from_secs(3);
/// A master that completed a request this recently is working: it is never closed to make room
/// for a new master (the newcomer is refused instead). Longer than any poll cycle a PLC, HMI or
/// SCADA uses; a master quiet this long may be closed for a newcomer.
pub const RECENTLY_ANSWERED: Duration = Duration::from_secs(60);

/// What every accept loop shares.
pub(crate) struct Shared {
    pub dispatcher: Dispatcher,
    /// For connections accepted from now on.
    policy: Mutex<Arc<Policy>>,
    pub connections: Arc<Semaphore>,
    pub metrics: Arc<Metrics>,
    pub stopping: Stopping,
    max_connections: AtomicUsize,
    next_master: AtomicU64,
    handshakes: Semaphore,
    /// The running sessions, for making room at `max_connections` and for the status page.
    sessions: Mutex<HashMap<MasterId, Session>>,
    addresses: Addresses,
}

/// A running session as the listener knows it.
struct Session {
    activity: Arc<Activity>,
    peer: SocketAddr,
    protocol: Protocol,
    rights: Rights,
    role: Option<String>,
    priority: bool,
    since: SystemTime,
}

/// A master connected now, as the operator's pages list it.
#[derive(Clone, Debug)]
pub(crate) struct Connected {
    pub(crate) peer: Peer,
    pub(crate) protocol: Protocol,
    pub(crate) rights: Rights,
    /// The role of its certificate, on a TLS connection that has one.
    pub(crate) role: Option<String>,
    pub(crate) priority: bool,
    pub(crate) since: SystemTime,
    /// Requests it has sent on this connection.
    pub(crate) requests: u64,
}

impl Shared {
    pub(crate) fn new(
        dispatcher: Dispatcher,
        policy: Policy,
        max_connections: usize,
        metrics: Arc<Metrics>,
        stopping: Stopping,
    ) -> Self {
        Shared {
            dispatcher,
            policy: Mutex::new(Arc::new(policy)),
            connections: Arc::new(Semaphore::new(max_connections)),
            metrics,
            stopping,
            max_connections: AtomicUsize::new(max_connections),
            next_master: AtomicU64::new(1),
            handshakes: Semaphore::new(HANDSHAKES_AT_ONCE),
            sessions: Mutex::new(HashMap::new()),
            addresses: Addresses::default(),
        }
    }

    /// A master id no other master has had.
    pub(crate) fn new_master(&self) -> MasterId {
        self.next_master.fetch_add(1, Ordering::Relaxed)
    }

    pub(crate) fn policy(&self) -> Arc<Policy> {
        self.policy
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// A new policy for connections accepted from now on; connections beyond a lower
    /// `max_connections` stay open, and new ones are refused (or make room) until enough have
    /// closed.
    pub(crate) fn set_policy(&self, policy: Policy, max_connections: usize) {
        *self.policy.lock().unwrap_or_else(PoisonError::into_inner) = Arc::new(policy);
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
    pub(crate) fn connections_open(&self) -> usize {
        let max = self.max_connections.load(Ordering::Relaxed);
        max.saturating_sub(self.connections.available_permits())
    }

    /// Wait until every session has ended (each holds a connection permit while it runs).
    pub(crate) async fn sessions_ended(&self) {
        let all = self.max_connections.load(Ordering::Relaxed);
        let all = u32::try_from(all).unwrap_or(u32::MAX);
        let _ = self.connections.acquire_many(all).await;
    }

    fn sessions(&self) -> std::sync::MutexGuard<'_, HashMap<MasterId, Session>> {
        self.sessions.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The masters connected now, longest connected first.
    pub(crate) fn masters(&self) -> Vec<Connected> {
        let sessions = self.sessions();
        let mut masters: Vec<(&MasterId, &Session)> = sessions.iter().collect();
        masters.sort_unstable_by_key(|(id, _)| **id);
        masters
            .into_iter()
            .map(|(_, session)| Connected {
                peer: Peer::Net(session.peer),
                protocol: session.protocol,
                rights: session.rights,
                role: session.role.clone(),
                priority: session.priority,
                since: session.since,
                requests: session.activity.requests(),
            })
            .collect()
    }

    /// A connection slot: a free one, or, with `close_oldest_idle`, that of the session first in
    /// line to make room ([`room_order`]), once it has closed. `None` if every session is
    /// working.
    async fn slot(&self, when_full: WhenFull) -> Option<OwnedSemaphorePermit> {
        if let Ok(permit) = self.connections.clone().try_acquire_owned() {
            return Some(permit);
        }
        if when_full == WhenFull::Refuse {
            return None;
        }
        let now = Instant::now();
        let first = self
            .sessions()
            .values()
            .map(|session| &session.activity)
            .filter_map(|activity| Some((room_order(&activity.seen(), now)?, activity.clone())))
            .min_by_key(|(order, _)| *order)
            .map(|(_, activity)| activity)?;
        first.evict();
        tokio::time::timeout(EVICTION_WAIT, self.connections.clone().acquire_owned())
            .await
            .ok()?
            .ok()
    }
}

/// Why a session may be closed to make room for a new master, in the order they go.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum NotWorking {
    /// Its master leaves its replies unread.
    Unread,
    /// It never completed a request: a newcomer itself, or a leaked connection.
    Unproven,
    /// It completed none within [`RECENTLY_ANSWERED`].
    Quiet,
}

/// Where a session stands in the line to make room for a new master at `now`: why it may go,
/// and since when (the longest first); `None`: it is working and stays (a request in flight, or
/// one answered within [`RECENTLY_ANSWERED`]).
fn room_order(seen: &SessionView, now: Instant) -> Option<(NotWorking, Instant)> {
    if let Some(since) = seen.blocked {
        return Some((NotWorking::Unread, since));
    }
    if seen.busy {
        return None;
    }
    match seen.answered {
        None => Some((NotWorking::Unproven, seen.last)),
        Some(at) if now.saturating_duration_since(at) >= RECENTLY_ANSWERED => {
            Some((NotWorking::Quiet, seen.last))
        }
        Some(_) => None,
    }
}

/// What the connections of one source address hold now.
#[derive(Debug)]
struct Held {
    connections: usize,
    /// Its share of the TLS handshake turns.
    turns: Arc<Semaphore>,
}

/// The connections by source address, for `max_connections_per_address` and
/// [`HANDSHAKES_PER_ADDRESS`]. An address is in the map while it has a connection open.
#[derive(Clone, Debug, Default)]
struct Addresses(Arc<Mutex<HashMap<IpAddr, Held>>>);

impl Addresses {
    fn held(&self) -> std::sync::MutexGuard<'_, HashMap<IpAddr, Held>> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A place for a new connection from `ip`, unless that address already holds `limit`.
    fn claim(&self, ip: IpAddr, limit: Option<usize>) -> Option<Ticket> {
        let ip = ip.to_canonical();
        let mut held = self.held();
        let here = held.entry(ip).or_insert_with(|| Held {
            connections: 0,
            turns: Arc::new(Semaphore::new(HANDSHAKES_PER_ADDRESS)),
        });
        if limit.is_some_and(|limit| here.connections >= limit) {
            return None;
        }
        here.connections += 1;
        Some(Ticket {
            addresses: self.clone(),
            turns: here.turns.clone(),
            ip,
        })
    }
}

/// A connection's place in its address's count, given back when it is dropped.
#[derive(Debug)]
struct Ticket {
    addresses: Addresses,
    ip: IpAddr,
    /// Its address's handshake turns.
    turns: Arc<Semaphore>,
}

impl Drop for Ticket {
    fn drop(&mut self) {
        let mut held = self.addresses.held();
        if let Some(here) = held.get_mut(&self.ip) {
            here.connections = here.connections.saturating_sub(1);
            if here.connections == 0 {
                held.remove(&self.ip);
            }
        }
    }
}

/// Accept masters of `protocol` (on a stream transport) on `listener`, bound at `addr`,
/// forever.
pub(crate) async fn serve(
    listener: TcpListener,
    addr: SocketAddr,
    protocol: Protocol,
    shared: Arc<Shared>,
) {
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(error) => {
                warn!(target: TcpMetrics::EVENTS, listen = %addr, %error, "accept failed");
                tokio::time::sleep(ACCEPT_ERROR_PAUSE).await;
                continue;
            }
        };
        let policy = shared.policy();
        let Some(admission) = listener::admit(&policy, &shared.metrics, protocol, addr, peer)
        else {
            continue;
        };
        let Some(ticket) = shared.addresses.claim(peer.ip(), policy.per_address) else {
            let reason = Rejection::MaxConnectionsPerAddress;
            shared.metrics.tcp.rejected(reason, protocol, &addr, &peer);
            continue;
        };
        prepare(&stream, &policy, peer);
        // A handshake, or making room, may wait: not in the accept loop.
        let master = Master {
            listen: addr,
            admission,
            ticket,
        };
        let shared = shared.clone();
        tokio::spawn(async move {
            if protocol.transport() == UpstreamTransport::Tls {
                accept_tls(stream, master, &policy, &shared).await;
            } else {
                admit(stream, master, None, &policy, &shared).await;
            }
        });
    }
}

/// A connection accepted on a listener, not yet served.
struct Master {
    listen: SocketAddr,
    admission: Admitted,
    /// Its place in its address's count, held until the connection ends.
    ticket: Ticket,
}

fn prepare(stream: &TcpStream, policy: &Policy, peer: SocketAddr) {
    if let Err(error) = stream.set_nodelay(true) {
        debug!(target: TcpMetrics::EVENTS, %peer, %error, "cannot set TCP_NODELAY");
    }
    if let Some(idle) = policy.keepalive {
        if let Err(error) = set_keepalive(stream, idle) {
            debug!(target: TcpMetrics::EVENTS, %peer, %error, "cannot set TCP keepalive");
        }
    }
}

/// The TLS handshake, within the handshake timeout; then the master is admitted with the rights
/// both its address and its certificate's role allow. A handshake turn (one of its address's
/// share, then one of all) is taken once the peer has sent something, within
/// [`FIRST_BYTES_WAIT`].
async fn accept_tls(stream: TcpStream, master: Master, policy: &Policy, shared: &Shared) {
    let Some(tls) = policy.tls.clone() else {
        error!(target: TcpMetrics::EVENTS, listen = %master.listen, "a TLS listener without [server.tls]; connection closed");
        return;
    };
    let turns = master.ticket.turns.clone();
    let handshake = async {
        first_bytes(&stream).await?;
        let _address_turn = turns.acquire().await;
        let _turn = shared.handshakes.acquire().await;
        tls.acceptor.accept(stream).await
    };
    let failed = |error: &dyn std::fmt::Display| {
        let metrics = &shared.metrics;
        metrics
            .tls
            .handshake_failed(&metrics.tcp, &master.listen, master.admission.peer, error);
    };
    let stream = match tokio::time::timeout(tls.handshake_timeout, handshake).await {
        Ok(Ok(stream)) => stream,
        Ok(Err(error)) => return failed(&error),
        Err(_) => {
            let timeout = humantime::format_duration(tls.handshake_timeout);
            return failed(&format_args!("not finished within {timeout}"));
        }
    };
    let identity = tls.identify(stream.get_ref().1.peer_certificates());
    admit(stream, master, Some(identity), policy, shared).await;
}

/// Wait for a new connection's first bytes, for at most [`FIRST_BYTES_WAIT`]; an error if none
/// come.
async fn first_bytes(stream: &TcpStream) -> io::Result<()> {
    match tokio::time::timeout(FIRST_BYTES_WAIT, stream.peek(&mut [0u8; 1])).await {
        Ok(Ok(0)) => Err(io::Error::new(
            io::ErrorKind::UnexpectedEof,
            "closed before sending anything",
        )),
        Ok(Ok(_)) => Ok(()),
        Ok(Err(error)) => Err(error),
        Err(_) => {
            let wait = humantime::format_duration(FIRST_BYTES_WAIT);
            Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("sent nothing within {wait}"),
            ))
        }
    }
}

/// Serve `master` once it has a connection slot; refused if none comes.
async fn admit<S: AsyncRead + AsyncWrite + Unpin>(
    stream: S,
    master: Master,
    identity: Option<Certified>,
    policy: &Policy,
    shared: &Shared,
) {
    let Some(permit) = shared.slot(policy.when_full).await else {
        let Admitted { protocol, peer, .. } = master.admission;
        shared
            .metrics
            .tcp
            .rejected(Rejection::MaxConnections, protocol, &master.listen, &peer);
        return;
    };
    run_session(stream, master, identity, policy, shared).await;
    drop(permit);
}

/// `client` as its TLS certificate identifies it: the role's rights and units, and the key that
/// granted them.
fn identified(client: Client, identity: &Certified) -> Client {
    let role_key = if identity.role_label == OTHER_ROLE {
        "server.tls.default_role_access".to_owned()
    } else {
        format!("server.tls.roles.{}", identity.role_label)
    };
    let who = crate::dispatch::Identity {
        subject: identity.subject.clone(),
        role: identity.role.clone(),
    };
    client.identified(who, identity.rights, role_key, identity.units.is_some())
}

/// A TLS master's certificate and role, counted and logged as it is accepted.
fn tls_accepted(
    metrics: &Metrics,
    master: MasterId,
    peer: SocketAddr,
    rights: Rights,
    identity: &Certified,
) {
    metrics.tls.accepted(&TlsMaster {
        master,
        peer,
        role_label: &identity.role_label,
        role: identity.role.as_deref(),
        access: rights.name(),
        role_problem: identity.role_problem,
        subject: &identity.subject,
    });
}

async fn run_session<S: AsyncRead + AsyncWrite + Unpin>(
    mut stream: S,
    master: Master,
    identity: Option<Certified>,
    policy: &Policy,
    shared: &Shared,
) {
    let Master {
        admission,
        ticket: _ticket,
        ..
    } = master;
    let Admitted {
        protocol,
        peer,
        priority,
        ..
    } = admission;
    let id = shared.new_master();
    let units = identity.as_ref().and_then(|identity| identity.units);
    let mut client = admission.client(id).addressing(units);
    if let Some(identity) = &identity {
        client = identified(client, identity);
    }
    // Its address's rights, narrowed by its certificate's role.
    let rights = client.rights;
    let tcp = &shared.metrics.tcp;
    tcp.accepted(protocol, id, &peer, rights == Rights::ReadOnly);
    if let Some(identity) = &identity {
        tls_accepted(&shared.metrics, id, peer, rights, identity);
    }
    let activity = Arc::new(Activity::default());
    shared.sessions().insert(
        id,
        Session {
            activity: activity.clone(),
            peer,
            protocol,
            rights,
            role: identity.as_ref().and_then(|identity| identity.role.clone()),
            priority,
            since: SystemTime::now(),
        },
    );
    let error = session::run(
        &mut stream,
        protocol.framing(),
        client,
        &activity,
        &shared.dispatcher,
        policy.limits,
        shared.stopping.clone(),
    )
    .await;
    let tls = protocol.transport() == UpstreamTransport::Tls;
    if tls && session::close_notify_due(&error, &activity) {
        session::close_notify(&mut stream).await;
    }
    drop(stream);
    shared.sessions().remove(&id);
    tcp.closed(protocol, error.closing(), id, &peer, &error);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seen(last: Instant) -> SessionView {
        SessionView {
            last,
            busy: false,
            answered: None,
            blocked: None,
        }
    }

    #[test]
    fn unread_then_unproven_then_quiet_make_room_and_working_sessions_never_do() {
        let start = Instant::now();
        let now = start + RECENTLY_ANSWERED * 3;
        let at = |secs| start + Duration::from_secs(secs);
        let unread = SessionView {
            busy: true,
            answered: Some(now),
            blocked: Some(at(150)),
            ..seen(now)
        };
        let unproven = seen(at(170));
        let quiet = SessionView {
            answered: Some(at(10)),
            ..seen(at(10))
        };
        let polling = SessionView {
            answered: Some(now - RECENTLY_ANSWERED + Duration::from_millis(1)),
            ..seen(at(0))
        };
        let in_flight = SessionView {
            busy: true,
            ..seen(at(0))
        };
        assert_eq!(
            room_order(&unread, now),
            Some((NotWorking::Unread, at(150)))
        );
        assert_eq!(
            room_order(&unproven, now),
            Some((NotWorking::Unproven, at(170)))
        );
        assert_eq!(room_order(&quiet, now), Some((NotWorking::Quiet, at(10))));
        assert!(room_order(&unread, now) < room_order(&unproven, now));
        assert!(room_order(&unproven, now) < room_order(&quiet, now));
        assert_eq!(
            room_order(&polling, now),
            None,
            "answered within the window"
        );
        assert_eq!(room_order(&in_flight, now), None, "a request in flight");
    }

    #[test]
    fn an_address_holds_at_most_its_limit_and_a_closed_connection_gives_its_place_back() {
        let addresses = Addresses::default();
        let ip: IpAddr = "127.0.0.9".parse().unwrap();
        let first = addresses.claim(ip, Some(2)).unwrap();
        let mapped: IpAddr = "::ffff:127.0.0.9".parse().unwrap();
        let second = addresses.claim(mapped, Some(2)).unwrap();
        assert!(addresses.claim(ip, Some(2)).is_none());
        assert!(
            Arc::ptr_eq(&first.turns, &second.turns),
            "one share of turns"
        );
        let other: IpAddr = "127.0.0.10".parse().unwrap();
        assert!(addresses.claim(other, Some(2)).is_some());
        drop(first);
        let third = addresses.claim(ip, Some(2)).unwrap();
        assert!(addresses.claim(ip, None).is_some(), "no limit");
        drop((second, third));
        assert!(addresses.held().is_empty(), "nothing left behind");
    }
}
