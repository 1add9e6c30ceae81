//! A Modbus TCP master that sees every byte: raw ADUs out, replies as received.

use crate::frames::mbap;
use crate::wait::{within, PATIENCE};
use std::net::SocketAddr;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// A TCP connection to `addr` from the loopback address `source` (127.0.0.x: Linux answers for
/// all of 127/8), as from a host of its own.
pub async fn connect_from(source: [u8; 4], addr: SocketAddr) -> TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().expect("a socket");
    socket
        .bind(SocketAddr::from((source, 0)))
        .expect("bind a loopback address");
    within("connect", socket.connect(addr))
        .await
        .expect("gateway accepts")
}

/// What a master talks over: a TCP connection, or a TLS session on one.
pub trait Duplex: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send {}
impl<S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send> Duplex for S {}

/// A Modbus TCP master that writes and reads raw ADUs.
pub struct RawMaster {
    stream: Box<dyn Duplex>,
}

/// A reply as the master received it.
#[derive(Debug, PartialEq, Eq)]
pub struct Reply {
    pub transaction: u16,
    pub unit: u8,
    pub pdu: Vec<u8>,
}

impl RawMaster {
    pub async fn connect(addr: SocketAddr) -> Self {
        let stream = within("connect", TcpStream::connect(addr))
            .await
            .expect("gateway accepts");
        Self::over(stream)
    }

    /// A master connecting from the loopback address `source` (127.0.0.x), as from a host of
    /// its own.
    pub async fn connect_from(source: [u8; 4], addr: SocketAddr) -> Self {
        Self::over(connect_from(source, addr).await)
    }

    /// A master on a stream already connected (a TLS session, say).
    pub fn over(stream: impl Duplex + 'static) -> Self {
        RawMaster {
            stream: Box::new(stream),
        }
    }

    /// The ADU of a request: [`mbap`].
    pub fn adu(transaction: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
        mbap(transaction, unit, pdu)
    }

    pub async fn send_raw(&mut self, bytes: &[u8]) {
        self.stream.write_all(bytes).await.expect("send");
    }

    /// One request and its reply PDU; `None` if the gateway closed the connection instead.
    pub async fn try_call(&mut self, transaction: u16, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
        self.stream
            .write_all(&Self::adu(transaction, unit, pdu))
            .await
            .ok()?;
        let reply = self.try_recv().await?;
        assert_eq!((reply.transaction, reply.unit), (transaction, unit));
        Some(reply.pdu)
    }

    pub async fn send(&mut self, transaction: u16, unit: u8, pdu: &[u8]) {
        self.send_raw(&Self::adu(transaction, unit, pdu)).await;
    }

    pub async fn recv(&mut self) -> Reply {
        self.try_recv()
            .await
            .expect("a reply, not a closed connection")
    }

    async fn try_recv(&mut self) -> Option<Reply> {
        let mut header = [0u8; 7];
        within("reply header", self.stream.read_exact(&mut header))
            .await
            .ok()?;
        assert_eq!(&header[2..4], &[0, 0], "protocol id");
        let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
        assert!((2..=254).contains(&length), "length field {length}");
        let mut pdu = vec![0u8; length - 1];
        within("reply body", self.stream.read_exact(&mut pdu))
            .await
            .ok()?;
        Some(Reply {
            transaction: u16::from_be_bytes([header[0], header[1]]),
            unit: header[6],
            pdu,
        })
    }

    /// One request, one reply with the same transaction and unit ids; the reply PDU.
    pub async fn call(&mut self, transaction: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
        self.send(transaction, unit, pdu).await;
        let reply = self.recv().await;
        assert_eq!((reply.transaction, reply.unit), (transaction, unit));
        reply.pdu
    }

    /// True once the gateway has closed the connection (EOF or reset).
    pub async fn is_closed(&mut self) -> bool {
        let mut byte = [0u8; 1];
        matches!(
            tokio::time::timeout(PATIENCE, self.stream.read(&mut byte)).await,
            Ok(Ok(0) | Err(_))
        )
    }
}

/// A raw master on a gateway process, once the process listens on `addr`.
pub async fn connect_when_listening(addr: SocketAddr) -> RawMaster {
    within("the gateway listens", async {
        loop {
            if let Ok(stream) = TcpStream::connect(addr).await {
                drop(stream);
                return RawMaster::connect(addr).await;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await
}
