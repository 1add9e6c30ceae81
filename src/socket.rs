//! What the gateway asks of its TCP sockets' kernel side, upstream (masters) and downstream
//! (device servers) alike: keepalive with a bound on unacknowledged data, and the round trip the
//! kernel measures. Knows nothing of what the sockets carry.

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

/// The round trip the kernel has measured on `stream` (`TCP_INFO`): its smoothed estimate and
/// the estimate's mean deviation.
pub(crate) fn round_trip(stream: &TcpStream) -> io::Result<(Duration, Duration)> {
    // SAFETY: tcp_info is plain integers; all zeroes is a valid value.
    let mut info: libc::tcp_info = unsafe { std::mem::zeroed() };
    let mut len = libc::socklen_t::try_from(std::mem::size_of::<libc::tcp_info>())
        .map_err(|_| io::Error::other("tcp_info is larger than a socklen_t"))?;
    // SAFETY: `info` is a tcp_info of `len` bytes, which the kernel fills up to `len`; the
    // descriptor is the stream's, open while it is borrowed.
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
    Ok((
        Duration::from_micros(u64::from(info.tcpi_rtt)),
        Duration::from_micros(u64::from(info.tcpi_rttvar)),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_kernel_reports_a_round_trip_for_a_connected_socket() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (client, _server) = tokio::join!(TcpStream::connect(addr), listener.accept());
        let (srtt, _rttvar) = round_trip(&client.unwrap()).unwrap();
        // The handshake gave it a first sample: on loopback well under a second, never zero.
        assert!(srtt > Duration::ZERO, "{srtt:?}");
        assert!(srtt < Duration::from_secs(1), "{srtt:?}");
    }
}
