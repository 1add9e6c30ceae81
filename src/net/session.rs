//! One master's connection. Every whole request read is handed to the dispatcher at once, so
//! pipelined requests queue (fairly) on the line right away; the answers go back in request
//! order, each in its own MBAP header. A malformed header closes the connection; so does a
//! request whose bytes trickle in slower than `frame_timeout`, a reply the master leaves unread
//! as long, a connection idle for `idle_timeout`, or the listener making room for a new master.
//! When the master goes, its queued requests go too.

use super::framing::{Decoded, FrameError, UpstreamFraming};
use crate::dispatch::{Client, Dispatcher};
use crate::error::{Outcome, RequestError};
use crate::mbap::{self, Header};
use crate::metrics::Closing;
use crate::pdu::exception_pdu;
use crate::shutdown::Stopping;
use crate::timer::coarse_sleep_until;
use bytes::BytesMut;
use std::collections::VecDeque;
use std::future::Future;
use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};
use std::task::Poll;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::{oneshot, Notify};
use tokio::time::Instant;

/// Longest a TLS session's close_notify may take to send.
const CLOSE_NOTIFY_WAIT: Duration = Duration::from_secs(1);
/// Room for a few whole requests before a read must wait.
const READ_BUFFER: usize = 1024;

#[derive(Clone, Copy, Debug)]
pub struct SessionLimits {
    pub pipeline_depth: usize,
    /// `None`: never close an idle connection.
    pub idle_timeout: Option<Duration>,
    /// Longest a request may take to arrive, from its first byte to its last.
    pub frame_timeout: Duration,
}

/// What the listener sees of a session ([`SessionView`]), how many requests it has had, and a
/// way to ask it to close: at once if it is waiting for its master to read a reply, else once it
/// has nothing in flight.
#[derive(Debug)]
pub struct Activity {
    seen: Mutex<SessionView>,
    requests: AtomicU64,
    close: Notify,
}

/// A session at one moment, for choosing which connection makes room for a new master.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct SessionView {
    /// When it last had a request or sent an answer; its accept, before either.
    pub last: Instant,
    /// Requests in flight.
    pub busy: bool,
    /// When it last completed a request (its answer written); `None`: never.
    pub answered: Option<Instant>,
    /// Since when a reply has been waiting for the master to read (the socket's buffer full).
    pub blocked: Option<Instant>,
}

impl Default for Activity {
    fn default() -> Self {
        Activity {
            seen: Mutex::new(SessionView {
                last: Instant::now(),
                busy: false,
                answered: None,
                blocked: None,
            }),
            requests: AtomicU64::new(0),
            close: Notify::new(),
        }
    }
}

impl Activity {
    fn update(&self, change: impl FnOnce(&mut SessionView)) {
        change(&mut self.seen.lock().unwrap_or_else(PoisonError::into_inner));
    }

    /// A request was read.
    fn requested(&self) {
        self.requests.fetch_add(1, Ordering::Relaxed);
        self.update(|seen| {
            seen.last = Instant::now();
            seen.busy = true;
        });
    }

    /// A request was answered (its reply written, if it has one); `busy`: others are in flight.
    fn answered(&self, busy: bool) {
        self.update(|seen| {
            let now = Instant::now();
            seen.last = now;
            seen.answered = Some(now);
            seen.busy = busy;
            seen.blocked = None;
        });
    }

    fn blocked(&self) {
        self.update(|seen| seen.blocked = Some(Instant::now()));
    }

    /// Requests read on the connection so far.
    pub fn requests(&self) -> u64 {
        self.requests.load(Ordering::Relaxed)
    }

    pub(crate) fn seen(&self) -> SessionView {
        *self.seen.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Ask the session to close: at once if it waits for its master to read a reply, else as
    /// soon as nothing is in flight.
    pub(crate) fn evict(&self) {
        self.close.notify_one();
    }
}

/// Why a session ended.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("master closed the connection")]
    Closed,
    #[error("not a Modbus request: {0}")]
    Frame(#[from] FrameError),
    #[error("idle for {0:?}")]
    Idle(Duration),
    #[error("a request did not arrive whole within {0:?} of its first byte")]
    FrameTimeout(Duration),
    #[error("closed to make room for a new master")]
    Evicted,
    #[error("a reply waited {0:?} for the master to read it")]
    WriteTimeout(Duration),
    #[error("the gateway is shutting down")]
    Shutdown,
    #[error("socket error: {0}")]
    Io(#[from] io::Error),
}

impl SessionError {
    pub fn closing(&self) -> Closing {
        match self {
            SessionError::Closed => Closing::ByMaster,
            SessionError::Frame(_) => Closing::ProtocolError,
            SessionError::Idle(_) => Closing::Idle,
            SessionError::FrameTimeout(_) => Closing::FrameTimeout,
            SessionError::Evicted => Closing::Evicted,
            SessionError::WriteTimeout(_) => Closing::WriteTimeout,
            SessionError::Io(_) => Closing::IoError,
            SessionError::Shutdown => Closing::Shutdown,
        }
    }
}

struct InFlight {
    header: Header,
    function: u8,
    outcome: oneshot::Receiver<Outcome>,
}

/// The PDU a master gets for an outcome: the slave's own bytes, or the gateway's exception.
pub(crate) fn reply_pdu(function: u8, outcome: Outcome) -> Option<Vec<u8>> {
    match outcome {
        Ok(answer) => answer.into_pdu(),
        Err(error) => Some(exception_pdu(function, error.exception_code()).to_vec()),
    }
}

async fn next_outcome(in_flight: &mut VecDeque<InFlight>) -> Outcome {
    match in_flight.front_mut() {
        // A bus that stopped without answering has no port to answer with.
        Some(front) => (&mut front.outcome)
            .await
            .unwrap_or(Err(RequestError::PortDown)),
        None => std::future::pending().await,
    }
}

/// Write one reply. It goes straight into the socket's buffer unless the master has left a
/// buffer's worth of replies unread: then the session waits for it, evictable at once, for at
/// most `limit` (the frame timeout: a master gets as long to take a reply as to send a request).
async fn send<S: AsyncWrite + Unpin>(
    stream: &mut S,
    bytes: &[u8],
    activity: &Activity,
    limit: Duration,
) -> Result<(), SessionError> {
    let mut write = std::pin::pin!(stream.write_all(bytes));
    let first = std::future::poll_fn(|cx| Poll::Ready(write.as_mut().poll(cx))).await;
    if let Poll::Ready(written) = first {
        return written.map_err(SessionError::from);
    }
    activity.blocked();
    tokio::select! {
        written = tokio::time::timeout(limit, write) => match written {
            Ok(written) => written.map_err(SessionError::from),
            Err(_) => Err(SessionError::WriteTimeout(limit)),
        },
        () = activity.close.notified() => Err(SessionError::Evicted),
    }
}

/// Serve one master on `stream` (a connection) until it leaves or breaks the protocol, or
/// until a stop: then read no more and answer what was read. Closing the stream (after a TLS
/// close_notify, when `close_notify_due`) is the caller's.
pub async fn run<S: AsyncRead + AsyncWrite + Unpin>(
    mut stream: S,
    framing: UpstreamFraming,
    mut client: Client,
    activity: &Activity,
    dispatcher: &Dispatcher,
    limits: SessionLimits,
    stopping: Stopping,
) -> SessionError {
    let error = serve(
        &mut stream,
        framing,
        &mut client,
        activity,
        dispatcher,
        limits,
        stopping,
    )
    .await;
    dispatcher.forget(client.master);
    error
}

/// Whether a TLS session that ended with `error` gets its close_notify, so the master can tell
/// a close from a cut: not when the master left or broke the connection, nor when it stopped
/// reading (it would hold the close up).
pub(crate) fn close_notify_due(error: &SessionError, activity: &Activity) -> bool {
    let unread = activity.seen().blocked.is_some();
    !unread
        && !matches!(
            error,
            SessionError::Closed | SessionError::Io(_) | SessionError::WriteTimeout(_)
        )
}

/// Send a TLS session's close_notify, within [`CLOSE_NOTIFY_WAIT`].
pub(crate) async fn close_notify<S: AsyncWrite + Unpin>(stream: &mut S) {
    let _ = tokio::time::timeout(CLOSE_NOTIFY_WAIT, stream.shutdown()).await;
}

/// What taking requests off a session's buffer found.
#[derive(Default)]
struct Taken {
    /// A whole frame came off the buffer (a request, or one dropped for its CRC).
    frame: bool,
    /// When the last request was handed to the dispatcher.
    request_at: Option<Instant>,
}

/// Where a session's requests come from and go to.
struct Requests<'a> {
    framing: UpstreamFraming,
    dispatcher: &'a Dispatcher,
    activity: &'a Activity,
}

impl Requests<'_> {
    /// Hand each whole request `inbound` holds to the dispatcher while fewer than `depth` are
    /// in flight. An error is a stream that is no request: it closes the session.
    fn take(
        &self,
        inbound: &mut BytesMut,
        in_flight: &mut VecDeque<InFlight>,
        depth: usize,
        client: &mut Client,
    ) -> Result<Taken, SessionError> {
        let mut taken = Taken::default();
        while in_flight.len() < depth {
            match self.framing.decode(inbound)? {
                Some(Decoded::BadCrc) => {
                    taken.frame = true;
                    self.dispatcher.bad_frame(client);
                }
                Some(Decoded::Request(request)) => {
                    taken.frame = true;
                    taken.request_at = Some(Instant::now());
                    let function = request.pdu[0];
                    let outcome = self
                        .dispatcher
                        .submit(client, request.header.unit, request.pdu);
                    in_flight.push_back(InFlight {
                        header: request.header,
                        function,
                        outcome,
                    });
                    self.activity.requested();
                }
                None => break,
            }
        }
        Ok(taken)
    }
}

async fn serve<S: AsyncRead + AsyncWrite + Unpin>(
    stream: &mut S,
    framing: UpstreamFraming,
    client: &mut Client,
    activity: &Activity,
    dispatcher: &Dispatcher,
    limits: SessionLimits,
    mut stopping: Stopping,
) -> SessionError {
    let mut inbound = BytesMut::with_capacity(READ_BUFFER);
    let mut outbound = Vec::with_capacity(mbap::MAX_FRAME_LEN);
    let mut in_flight: VecDeque<InFlight> = VecDeque::with_capacity(limits.pipeline_depth);
    let mut last_activity = Instant::now();
    // Since when the start of a request has been waiting for the rest of it.
    let mut partial_since: Option<Instant> = None;
    let mut stopped = stopping.deadline().is_some();
    let requests = Requests {
        framing,
        dispatcher,
        activity,
    };
    let depth = limits.pipeline_depth;
    loop {
        match requests.take(&mut inbound, &mut in_flight, depth, client) {
            Ok(taken) => {
                if taken.frame {
                    partial_since = None;
                }
                last_activity = taken.request_at.unwrap_or(last_activity);
            }
            Err(error) => return error,
        }
        if stopped && in_flight.is_empty() {
            return SessionError::Shutdown;
        }
        let can_read = !stopped && in_flight.len() < limits.pipeline_depth;
        // Only bytes the session is waiting to complete count against the frame timeout, not
        // whole requests held back while the pipeline is full.
        partial_since = if can_read && !inbound.is_empty() {
            Some(partial_since.unwrap_or_else(Instant::now))
        } else {
            None
        };
        let frame_due = partial_since.map(|since| since + limits.frame_timeout);
        let idle_at = limits
            .idle_timeout
            .filter(|_| in_flight.is_empty())
            .map(|timeout| last_activity + timeout);
        tokio::select! {
            outcome = next_outcome(&mut in_flight) => {
                let Some(done) = in_flight.pop_front() else { continue };
                if let Some(pdu) = reply_pdu(done.function, outcome) {
                    framing.encode(done.header, &pdu, &mut outbound);
                    if let Err(error) = send(stream, &outbound, activity, limits.frame_timeout).await {
                        return error;
                    }
                }
                last_activity = Instant::now();
                activity.answered(!in_flight.is_empty());
            }
            read = stream.read_buf(&mut inbound), if can_read => match read {
                Ok(0) => return SessionError::Closed,
                Ok(_) => {}
                Err(error) => return error.into(),
            },
            () = coarse_sleep_until(frame_due.unwrap_or(last_activity)), if frame_due.is_some() => {
                return SessionError::FrameTimeout(limits.frame_timeout);
            }
            () = coarse_sleep_until(idle_at.unwrap_or(last_activity)), if idle_at.is_some() => {
                return SessionError::Idle(limits.idle_timeout.unwrap_or_default());
            }
            () = activity.close.notified(), if in_flight.is_empty() => {
                return SessionError::Evicted;
            }
            _ = stopping.requested(), if !stopped => stopped = true,
        }
    }
}
