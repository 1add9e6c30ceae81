//! What the gateway asks of its TCP sockets' kernel side, upstream (masters) and downstream
//! (device servers) alike: keepalive with a bound on unacknowledged data, and the least round
//! trip the kernel has measured. Knows nothing of what the sockets carry.

// Unsafe blocks, each with its SAFETY comment: getsockopt(TCP_INFO) on a connected socket.
#![allow(unsafe_code)]

use socket2::{SockRef, TcpKeepalive};
use std::io;
use std::os::fd::AsRawFd;
use std::time::Duration;
use tokio::net::TcpStream;

/// Keepalive probes a silent peer gets before its connection is dropped.
const KEEPALIVE_PROBES: u32 = 3;

/// Probe a silent peer after `idle`, then every third of that, and drop the connection when
/// `KEEPALIVE_PROBES` go unanswered, or when data sent to it stays unacknowledged as long: a
/// peer that lost power or its link no longer holds the connection.
pub fn set_keepalive(stream: &TcpStream, idle: Duration) -> io::Result<()> {
    let interval = (idle / 3).max(Duration::from_secs(1));
    let socket = SockRef::from(stream);
    socket.set_tcp_keepalive(
        &TcpKeepalive::new()
            .with_time(idle)
            .with_interval(interval)
            .with_retries(KEEPALIVE_PROBES),
    )?;
    socket.set_tcp_user_timeout(Some(idle + interval * KEEPALIVE_PROBES))
}

/// The least round trip the kernel has measured on `stream` (`TCP_INFO`'s `tcpi_min_rtt`, over
/// its window of minutes), or its smoothed estimate on a kernel too old to keep the minimum. The
/// minimum is the link's own: a peer that answers requests acknowledges them with its answer, so
/// every later sample (and the smoothed estimate) also counts how long the peer took to answer.
pub(crate) fn round_trip(stream: &TcpStream) -> io::Result<Duration> {
    // SAFETY: tcp_info is plain integers; all zeroes is a valid value.
    let mut info: libc::tcp_info = unsafe { std::mem::zeroed() };
    let mut len = libc::socklen_t::try_from(std::mem::size_of::<libc::tcp_info>())
        .map_err(|_| io::Error::other("tcp_info is larger than a socklen_t"))?;
    // SAFETY: `info` is a tcp_info of `len` bytes, which the kernel fills up to `len` (an older
    // kernel fills less, leaving the rest zero); the descriptor is the stream's, open while it
    // is borrowed.
    let done = unsafe {
        libc::getsockopt(
            stream.as_raw_fd(),
            libc::IPPROTO_TCP,
            libc::TCP_INFO,
            std::ptr::from_mut(&mut info).cast(),
            &mut len,
        )
    };
    if done != 0 {
        return Err(io::Error::last_os_error());
    }
    let least = match info.tcpi_min_rtt {
        0 => info.tcpi_rtt,
        least => least,
    };
    Ok(Duration::from_micros(u64::from(least)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_kernel_reports_a_round_trip_for_a_connected_socket() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (client, _server) = tokio::join!(TcpStream::connect(addr), listener.accept());
        let least = round_trip(&client.unwrap()).unwrap();
        // The handshake gave it a first sample: on loopback well under a second, never zero.
        assert!(least > Duration::ZERO, "{least:?}");
        assert!(least < Duration::from_secs(1), "{least:?}");
    }

    #[tokio::test]
    async fn a_peer_that_answers_slowly_does_not_lengthen_the_round_trip_reported() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        // The peer answers each request 30 ms later, its acknowledgement riding on the answer.
        let peer = tokio::spawn(async move {
            let (mut socket, _) = listener.accept().await.unwrap();
            let mut request = [0u8; 8];
            while socket.read_exact(&mut request).await.is_ok() {
                tokio::time::sleep(Duration::from_millis(30)).await;
                socket.write_all(&request).await.unwrap();
            }
        });
        let mut client = TcpStream::connect(addr).await.unwrap();
        client.set_nodelay(true).unwrap();
        for _ in 0..10 {
            client.write_all(&[1; 8]).await.unwrap();
            client.read_exact(&mut [0; 8]).await.unwrap();
        }
        let least = round_trip(&client).unwrap();
        assert!(least < Duration::from_millis(10), "{least:?}");
        peer.abort();
    }
}
