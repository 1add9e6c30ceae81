//! A serial device server's socket as a bus's transport: the line's bytes carried over TCP to a
//! converter's UART, as they are (`tcp://`, raw or "transparent" mode) or inside Telnet with the
//! far port's format set at every connect (`rfc2217://`, [`rfc2217`](super::rfc2217)). A Modbus
//! TCP device's connection is the same socket, plain (`tcp://` with `framing = "tcp"`) or in TLS
//! (`tls://`, [`tls`](super::tls)), carrying MBAP frames.
//! Connecting (bounded in time, keepalive on, Nagle off so a frame leaves at once), the link's
//! round trip budgeted on top of every frame's time on the wire, and bytes already in the socket
//! before a frame drained and handed back to be counted. What a peer can make a port hold is
//! bounded: one drain reads at most [`MAX_DRAIN`], and an `rfc2217://` line owing its server more
//! than [`MAX_OWED`] in Telnet answers is lost ([`Dropped`] says why). Knows nothing of framing,
//! transactions or what the bytes mean.
//!
//! The timing rule (docs/device-servers.md): the gateway cannot see the far wire, so a frame
//! "has left the wire" when it can have crossed the link and left the converter's UART: the
//! frame's time at the line's speed plus the link budget, twice the least round trip the kernel
//! has measured on the socket (`TCP_INFO`'s `min_rtt`: the link's own, where the smoothed RTT
//! would count the slaves' answering time, since the converter acknowledges a request with its
//! reply), between [`MIN_LINK_BUDGET`] and [`MAX_LINK_BUDGET`]. The response timeout counts from
//! there, so the reply's way back is inside the budget too, and as much again for queueing. The
//! gap before a frame counts from the last byte received, as on a local line (the request then
//! reaches the far wire at least the gap after the reply left it), and from the previous frame's
//! end there unless a reply to it showed it had left: junk that comes back sooner says nothing.

use super::rfc2217::{self, Telnet};
use super::{Port, TlsDevice};
use crate::config::{ServerAddr, ServerMode};
use crate::line::{SerialFormat, Transport};
use crate::metrics::LinkDrop;
use std::io;
use std::pin::Pin;
use std::task::{Context, Poll, Waker};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::TcpStream;
use tokio::time::Instant;
use tokio_rustls::client::TlsStream;

/// The least the link adds to a frame's time: the timer's resolution.
pub(crate) const MIN_LINK_BUDGET: Duration = Duration::from_millis(1);
/// The most: a link slower than this is broken, and a slave behind it needs a longer
/// `response_timeout` rather than the gateway waiting ever longer on its own.
pub(crate) const MAX_LINK_BUDGET: Duration = Duration::from_secs(1);
/// How long a connect (name lookup included) may take before it counts as failed.
pub(crate) const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// How long an RFC 2217 server may take to acknowledge the line's settings after connecting.
pub(crate) const NEGOTIATION_TIMEOUT: Duration = Duration::from_secs(5);
/// A converter that is silent this long is probed (TCP keepalive); it is given up once three
/// probes, or data sent to it, go unanswered for as long again.
pub(crate) const KEEPALIVE_IDLE: Duration = Duration::from_secs(10);
/// How often the budget is read again from the kernel's measurement.
const REMEASURE_EVERY: Duration = Duration::from_secs(1);
/// Largest read from the socket in one call.
const READ_CHUNK: usize = 512;
/// The most one drain of the socket before a frame reads: far more than a line delivers in the
/// moment between the end of the gap and the drain, at any baud. A peer sending faster leaves
/// the rest in the socket, read as the stray bytes they are by the next wait for the gap.
pub(crate) const MAX_DRAIN: usize = 8 * READ_CHUNK;
/// The most an `rfc2217://` line may owe its server in Telnet answers between two frames. A
/// server that asks for every option there is once, on both sides, makes it owe 1.5 KiB; real
/// converters ask for a handful. One past it is closed, and connected again with back-off.
pub(crate) const MAX_OWED: usize = 1024;

/// Why the gateway closed a device server's connection itself: an error's source, so that the
/// loss it causes is counted by its reason ([`Dropped::of`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub(crate) enum Dropped {
    #[error("the device server's Telnet negotiation asked for more than {MAX_OWED} bytes of answers between two frames; closing the connection")]
    TelnetAnswers,
}

impl Dropped {
    /// The reason a port was lost with `error`, if the gateway closed it itself.
    pub(crate) fn of(error: &io::Error) -> Option<LinkDrop> {
        match error.get_ref()?.downcast_ref::<Dropped>()? {
            Dropped::TelnetAnswers => Some(LinkDrop::TelnetAnswers),
        }
    }
}

/// A byte stream to a device server, with the round trip its kernel measures, if it does.
pub trait Link: AsyncRead + AsyncWrite + Unpin + Send {
    /// The least round trip measured on it.
    fn round_trip(&self) -> Option<Duration>;
}

impl Link for TcpStream {
    fn round_trip(&self) -> Option<Duration> {
        crate::socket::round_trip(self).ok()
    }
}

/// A `tls://` device: the round trip is its TCP connection's.
impl Link for TlsStream<TcpStream> {
    fn round_trip(&self) -> Option<Duration> {
        crate::socket::round_trip(self.get_ref().0).ok()
    }
}

/// What the link adds to every frame's time, from the least round trip measured: twice it (the
/// way there and back, and as much again for queueing on the way), kept within
/// [`MIN_LINK_BUDGET`]..=[`MAX_LINK_BUDGET`]; the most when nothing is measured.
pub(crate) fn link_budget(least_round_trip: Option<Duration>) -> Duration {
    least_round_trip.map_or(MAX_LINK_BUDGET, |rtt| {
        (rtt * 2).clamp(MIN_LINK_BUDGET, MAX_LINK_BUDGET)
    })
}

/// An open connection to a device server, as the line's master drives it.
pub struct NetPort<S = TcpStream> {
    stream: S,
    /// The peer's address as connected, for the logs and the status page.
    peer: String,
    budget: Duration,
    measured: Option<Duration>,
    measured_at: Instant,
    chunk: Box<[u8; READ_CHUNK]>,
    /// On an `rfc2217://` line: the Telnet state, what it owes the server (sent before the next
    /// frame), and the escaped frame.
    telnet: Option<Box<Telnet>>,
    owed: Vec<u8>,
    out: Vec<u8>,
}

/// Connect to the device server or device at `addr`, whose line runs in `format`.
/// On `rfc2217://`, the server must acknowledge `format` within [`NEGOTIATION_TIMEOUT`]; a
/// server that refuses COM-PORT-OPTION fails the open as `Unsupported` (retrying will not cure
/// it). On `tls://`, the TLS handshake must be over within [`CONNECT_TIMEOUT`] too.
pub(super) async fn open(
    addr: &ServerAddr,
    format: &SerialFormat,
    tls: Option<&TlsDevice>,
) -> io::Result<Port> {
    let stream = connect(&addr.host, addr.port).await?;
    let peer = stream.peer_addr()?.to_string();
    if let Some(tls) = tls {
        let handshake = tokio::time::timeout(CONNECT_TIMEOUT, tls.handshake(stream));
        let stream = handshake.await.map_err(|_| {
            io::Error::new(
                io::ErrorKind::TimedOut,
                format!("no TLS handshake within {CONNECT_TIMEOUT:?}"),
            )
        })??;
        return Ok(Port::Tls(Box::new(NetPort::new(stream, peer))));
    }
    let mut port = NetPort::new(stream, peer);
    if addr.mode == ServerMode::Rfc2217 {
        let mut telnet = Box::new(Telnet::new());
        let deadline = Instant::now() + NEGOTIATION_TIMEOUT;
        let stale = rfc2217::negotiate(&mut port.stream, &mut telnet, format, deadline).await?;
        if stale > 0 {
            tracing::debug!(device = %addr, stale, "bytes from the line during RFC 2217 negotiation, dropped");
        }
        port.telnet = Some(telnet);
    }
    Ok(Port::Net(port))
}

/// Connect to `host`:`port` (a name is looked up each time, as a converter's address may
/// change), by [`CONNECT_TIMEOUT`].
async fn connect(host: &str, port: u16) -> io::Result<TcpStream> {
    let connecting = TcpStream::connect((host, port));
    let stream = tokio::time::timeout(CONNECT_TIMEOUT, connecting)
        .await
        .map_err(|_| {
            io::Error::new(
                io::ErrorKind::TimedOut,
                format!("no connection within {CONNECT_TIMEOUT:?}"),
            )
        })??;
    // A frame goes out whole and at once: never held back to be joined with the next.
    stream.set_nodelay(true)?;
    crate::socket::set_keepalive(&stream, KEEPALIVE_IDLE)?;
    Ok(stream)
}

impl<S: Link> NetPort<S> {
    /// A port on the connected `stream` to `peer`.
    pub(crate) fn new(stream: S, peer: String) -> NetPort<S> {
        let measured = stream.round_trip();
        NetPort {
            stream,
            peer,
            budget: link_budget(measured),
            measured,
            measured_at: Instant::now(),
            chunk: Box::new([0; READ_CHUNK]),
            telnet: None,
            owed: Vec::new(),
            out: Vec::new(),
        }
    }

    /// The peer's address, what the link adds to each frame's time now, and the least round
    /// trip it is from, if measured.
    pub(crate) fn link(&self) -> (&str, Duration, Option<Duration>) {
        (&self.peer, self.budget, self.measured)
    }

    /// Read the kernel's measurement again if the last is older than [`REMEASURE_EVERY`].
    fn remeasure(&mut self) {
        if self.measured_at.elapsed() >= REMEASURE_EVERY {
            self.measured = self.stream.round_trip().or(self.measured);
            self.budget = link_budget(self.measured);
            self.measured_at = Instant::now();
        }
    }
}

/// Whatever `stream` holds now, without waiting, appended to `out`, up to [`MAX_DRAIN`] bytes
/// (the rest stays in it). `Ok(false)` when the peer has closed it.
fn drain_now<S: AsyncRead + Unpin>(stream: &mut S, out: &mut Vec<u8>) -> io::Result<bool> {
    let mut chunk = [0u8; READ_CHUNK];
    let mut context = Context::from_waker(Waker::noop());
    let mut left = MAX_DRAIN;
    while left > 0 {
        let mut buf = ReadBuf::new(&mut chunk[..left.min(READ_CHUNK)]);
        match Pin::new(&mut *stream).poll_read(&mut context, &mut buf) {
            Poll::Ready(Ok(())) if buf.filled().is_empty() => return Ok(false),
            Poll::Ready(Ok(())) => {
                left -= buf.filled().len();
                out.extend_from_slice(buf.filled());
            }
            Poll::Ready(Err(e)) => return Err(e),
            Poll::Pending => return Ok(true),
        }
    }
    Ok(true)
}

/// An `rfc2217://` line now owes `owed`: an error past [`MAX_OWED`], which loses the port.
fn within_owed(owed: &[u8]) -> io::Result<()> {
    if owed.len() > MAX_OWED {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            Dropped::TelnetAnswers,
        ));
    }
    Ok(())
}

/// The peer closed the connection: the port is lost.
fn closed() -> io::Error {
    io::Error::new(
        io::ErrorKind::UnexpectedEof,
        "the device server closed the connection",
    )
}

impl<S: Link> Transport for NetPort<S> {
    async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        self.remeasure();
        if self.telnet.is_none() {
            return self.stream.write_all(frame).await;
        }
        // What the protocol owes the server goes first; the frame's 0xFF bytes are doubled.
        self.out.clear();
        self.out.append(&mut self.owed);
        Telnet::escape_into(frame, &mut self.out);
        self.stream.write_all(&self.out).await
    }

    /// The frame has crossed the link and left the converter's UART: its time on the wire plus
    /// the link budget.
    fn end_of_transmission(&self, returned: Instant, frame_time: Duration) -> Instant {
        returned + self.budget + frame_time
    }

    /// Cancel-safe: a read that completes has its bytes taken in the same poll. Telnet commands
    /// alone are not data: the wait goes on.
    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        loop {
            let n = self.stream.read(&mut self.chunk[..]).await?;
            if n == 0 {
                return Err(closed());
            }
            let Some(telnet) = &mut self.telnet else {
                buf.extend_from_slice(&self.chunk[..n]);
                return Ok(n);
            };
            let data = telnet.receive(&self.chunk[..n], buf, &mut self.owed);
            within_owed(&self.owed)?;
            if data > 0 {
                return Ok(data);
            }
        }
    }

    fn clear_input(&mut self, stale: &mut Vec<u8>) -> io::Result<()> {
        let open = match &mut self.telnet {
            None => drain_now(&mut self.stream, stale)?,
            Some(telnet) => {
                let mut raw = Vec::new();
                let open = drain_now(&mut self.stream, &mut raw)?;
                telnet.receive(&raw, stale, &mut self.owed);
                within_owed(&self.owed)?;
                open
            }
        };
        if open {
            Ok(())
        } else {
            Err(closed())
        }
    }
}

#[cfg(test)]
mod limits_tests;
#[cfg(test)]
mod link_tests;
#[cfg(test)]
pub(crate) mod tests;
