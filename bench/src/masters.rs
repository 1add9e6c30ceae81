//! The load: the bench's masters, each on a connection of its own kind, requesting back to back
//! (or at a period) until told to stop, and how each request was answered; and the untimed RTU
//! slaves of the pty scenarios.

use crate::gateway::{tls_connect, Gateway};
use crate::scenarios::{Kind, Load, PRIORITY_IP, READ_10, SLAVES, WRITE_1};
use crate::virtual_unit;
use mio_serial::SerialPort;
use modbus_gateway::testing::bus::Port;
use modbus_gateway::testing::line::{rtu, LineTiming, SerialFormat};
use modbus_gateway::testing::sim::responder::Responder;
use modbus_gateway::testing::sim::RegisterBank;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use test_support::mbap;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream, UdpSocket};
use tokio_rustls::client::TlsStream;

/// One completed request: when its reply came, how long it took, whether it was a write.
pub(crate) type Done = (Instant, Duration, bool);

/// A line that takes no time: no character time, and no t3.5 before a reply.
const UNTIMED: LineTiming = LineTiming {
    char_time: Duration::ZERO,
    t15: Duration::ZERO,
    t35: Duration::ZERO,
};

/// RTU slaves on the far end of a pty that answer every request at once: the library's
/// responder (as `simulate` serves) with a register slave at every address, on an untimed line.
/// A frame cut short still ends after the real line's t3.5 of silence.
pub(crate) fn untimed_slave(
    format: &SerialFormat,
) -> Result<(String, tokio::task::JoinHandle<()>), String> {
    let (far, tty) = mio_serial::SerialStream::pair().map_err(|e| e.to_string())?;
    let path = tty.name().ok_or("the pty has no path")?;
    let mut port = Port::serial(far).map_err(|e| e.to_string())?;
    let mut responder = Responder::new(UNTIMED, LineTiming::new(format).t35);
    for address in 1..=SLAVES {
        responder.add_slave(address, Box::new(RegisterBank::new(Duration::ZERO)));
    }
    let task = tokio::spawn(async move {
        let _tty = tty;
        responder.serve(&mut port).await;
    });
    Ok((path, task))
}

/// One master's way to the gateway.
pub(crate) enum Conn {
    Tcp(TcpStream),
    RtuOverTcp(TcpStream),
    Udp(UdpSocket),
    Tls(Box<TlsStream<TcpStream>>),
    /// RTU frames on the pty of a serial master port: a master on a serial line.
    Port(tokio_serial::SerialStream),
}

/// One RTU transaction on `stream`: the frame, then the reply by its own length.
async fn rtu_exchange<S: AsyncRead + AsyncWrite + Unpin>(
    stream: &mut S,
    slave: u8,
    pdu: &[u8],
    reply: &mut [u8],
) -> std::io::Result<Answer> {
    stream.write_all(&rtu::encode(slave, pdu)).await?;
    // Address and function, then the rest by the reply's own length.
    stream.read_exact(&mut reply[..3]).await?;
    let len = match rtu::reply_len(&reply[..3], slave, pdu) {
        rtu::FrameLen::Exact(n) => n,
        _ => return Ok(Answer::Unexpected),
    };
    stream.read_exact(&mut reply[3..len]).await?;
    Ok(if rtu::crc_ok(&reply[..len]) {
        Answer::of_function(reply[1])
    } else {
        Answer::Unexpected
    })
}

/// One Modbus TCP transaction on `stream`: the MBAP request, then the reply by its own length.
async fn mbap_exchange<S: AsyncRead + AsyncWrite + Unpin>(
    stream: &mut S,
    tid: u16,
    slave: u8,
    pdu: &[u8],
    reply: &mut [u8],
) -> std::io::Result<Answer> {
    stream.write_all(&mbap(tid, slave, pdu)).await?;
    stream.read_exact(&mut reply[..7]).await?;
    let len = usize::from(u16::from_be_bytes([reply[4], reply[5]]));
    stream.read_exact(&mut reply[7..6 + len]).await?;
    Ok(Answer::of_mbap(reply, 7 + len, tid))
}

/// How a request was answered.
#[derive(Clone, Copy, PartialEq, Debug)]
pub(crate) enum Answer {
    /// Its normal reply.
    Normal,
    /// An exception reply to it (the function code's high bit set).
    Exception,
    /// Not a reply to it: a wrong transaction id, a bad CRC, a length that does not fit.
    Unexpected,
}

impl Answer {
    /// The answer whose function code is `function`.
    fn of_function(function: u8) -> Answer {
        if function & 0x80 == 0 {
            Answer::Normal
        } else {
            Answer::Exception
        }
    }

    /// The answer in the MBAP frame of `len` bytes at the start of `reply`, to request `tid`.
    fn of_mbap(reply: &[u8], len: usize, tid: u16) -> Answer {
        if len > 7 && reply[..2] == tid.to_be_bytes() {
            Answer::of_function(reply[7])
        } else {
            Answer::Unexpected
        }
    }
}

impl Conn {
    /// Send `pdu` to `slave` and wait for its answer.
    pub(crate) async fn exchange(
        &mut self,
        tid: u16,
        slave: u8,
        pdu: &[u8],
        reply: &mut [u8],
    ) -> std::io::Result<Answer> {
        match self {
            Conn::Tcp(stream) => mbap_exchange(stream, tid, slave, pdu, reply).await,
            Conn::Tls(stream) => mbap_exchange(stream.as_mut(), tid, slave, pdu, reply).await,
            Conn::RtuOverTcp(stream) => rtu_exchange(stream, slave, pdu, reply).await,
            Conn::Port(stream) => rtu_exchange(stream, slave, pdu, reply).await,
            Conn::Udp(socket) => {
                socket.send(&mbap(tid, slave, pdu)).await?;
                let len = socket.recv(reply).await?;
                Ok(Answer::of_mbap(reply, len, tid))
            }
        }
    }
}

/// What one master saw: its completed requests, and when each request that was answered with
/// an exception came back (the virtual load only: there an exception is an error the report
/// counts; in any other load it ends the run).
pub(crate) struct Served {
    pub(crate) done: Vec<Done>,
    pub(crate) exceptions: Vec<Instant>,
}

/// One master's loop: request, reply, again (after `period` from the last request, if not
/// zero), until `stop`.
pub(crate) async fn master(
    mut conn: Conn,
    index: usize,
    load: Load,
    period: Duration,
    stop: Arc<AtomicBool>,
) -> std::io::Result<Served> {
    let mut served = Served {
        done: Vec::new(),
        exceptions: Vec::new(),
    };
    let mut slave = match load {
        Load::Same | Load::Own => 1,
        Load::Virtual => virtual_unit::UNIT,
        _ => u8::try_from(index % usize::from(SLAVES)).unwrap_or(0) + 1,
    };
    // Its own block, 10 registers from 10 x index, so that no two masters' reads are identical
    // and none is coalesced (but in `Same`): the same length as READ_10, the same time on the
    // line.
    let [hi, lo] = u16::try_from(index * 10).unwrap_or(0).to_be_bytes();
    let own = [0x03, hi, lo, 0x00, 0x0A];
    let mut tid: u16 = 0;
    let mut reply = vec![0u8; 512];
    let mut next = tokio::time::Instant::now();
    while !stop.load(Ordering::Relaxed) {
        if !period.is_zero() {
            tokio::time::sleep_until(next).await;
            next += period;
        }
        tid = tid.wrapping_add(1);
        let write = load == Load::Mix && tid.is_multiple_of(4);
        let pdu: &[u8] = match load {
            _ if write => &WRITE_1,
            Load::Same => &READ_10,
            Load::Virtual => &virtual_unit::READ,
            _ => &own,
        };
        let sent = Instant::now();
        let answer = conn.exchange(tid, slave, pdu, &mut reply).await?;
        let now = Instant::now();
        match answer {
            Answer::Normal => served.done.push((now, now - sent, write)),
            Answer::Exception if load == Load::Virtual => served.exceptions.push(now),
            Answer::Exception | Answer::Unexpected => {
                return Err(std::io::Error::other(format!(
                    "master {index}: unexpected reply {:02X?}",
                    &reply[..16]
                )))
            }
        }
        if !matches!(load, Load::Same | Load::Own | Load::Virtual) {
            slave = slave % SLAVES + 1;
        }
    }
    Ok(served)
}

/// One master of `kind` (not `Mixed`), master `i` of the run.
async fn connect(gateway: &Gateway, kind: Kind, i: usize) -> Result<Conn, String> {
    let failed = |e: std::io::Error| format!("connect: {e} (raise `ulimit -n` for many masters)");
    Ok(match kind {
        Kind::Udp => {
            let socket = UdpSocket::bind("127.0.0.1:0").await.map_err(failed)?;
            socket.connect(gateway.listen_udp).await.map_err(failed)?;
            Conn::Udp(socket)
        }
        Kind::RtuOverTcp => {
            let stream = TcpStream::connect(gateway.listen_rtu_over_tcp)
                .await
                .map_err(failed)?;
            stream.set_nodelay(true).map_err(|e| e.to_string())?;
            Conn::RtuOverTcp(stream)
        }
        Kind::Tcp | Kind::Mixed => {
            let stream = TcpStream::connect(gateway.listen).await.map_err(failed)?;
            stream.set_nodelay(true).map_err(|e| e.to_string())?;
            Conn::Tcp(stream)
        }
        Kind::Tls => {
            let tls = gateway.tls.as_ref().ok_or("no TLS listener")?;
            let stream = tls_connect(tls)
                .await
                .map_err(|e| format!("master {i}: TLS: {e}"))?;
            Conn::Tls(Box::new(stream))
        }
    })
}

/// `n` masters of `kind` (the three kinds in turn for `Kind::Mixed`), connected one after
/// another, and how long each connection took to set up (TCP connect to connected, or to the TLS
/// handshake complete; none for UDP).
pub(crate) async fn connect_all(
    gateway: &Gateway,
    kind: Kind,
    n: usize,
) -> Result<(Vec<Conn>, Vec<Duration>), String> {
    let kinds = [Kind::Tcp, Kind::RtuOverTcp, Kind::Udp];
    let mut conns = Vec::with_capacity(n);
    let mut setup = Vec::with_capacity(n);
    for i in 0..n {
        let kind = if kind == Kind::Mixed {
            kinds[i % 3]
        } else {
            kind
        };
        let began = Instant::now();
        conns.push(connect(gateway, kind, i).await?);
        if kind != Kind::Udp {
            setup.push(began.elapsed());
        }
    }
    Ok((conns, setup))
}

/// The priority master: a Modbus TCP connection from 127.0.0.2, which `server.priority` names;
/// or, if the gateway has a serial master port, the port's pty, opened as a serial master would.
pub(crate) async fn priority_connect(gateway: &Gateway) -> Result<Conn, String> {
    let failed = |e: std::io::Error| format!("priority master: {e}");
    if let Some(link) = &gateway.port {
        let path = link.0.to_string_lossy();
        // A pty carries bytes at once whatever its baud rate: the port's own format is the
        // gateway's side of it.
        let stream = tokio_serial::SerialPortBuilderExt::open_native_async(tokio_serial::new(
            path.as_ref(),
            9600,
        ))
        .map_err(|e| format!("priority master: {path}: {e}"))?;
        return Ok(Conn::Port(stream));
    }
    let socket = TcpSocket::new_v4().map_err(failed)?;
    socket
        .bind(SocketAddr::new(PRIORITY_IP.into(), 0))
        .map_err(failed)?;
    let stream = socket.connect(gateway.listen).await.map_err(failed)?;
    stream.set_nodelay(true).map_err(failed)?;
    Ok(Conn::Tcp(stream))
}
