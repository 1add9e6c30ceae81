use super::*;
use tokio::io::DuplexStream;

/// One end of an in-memory link whose kernel would report `round_trip`.
pub(crate) struct Measured {
    pub(crate) stream: DuplexStream,
    pub(crate) round_trip: Option<Duration>,
}

impl AsyncRead for Measured {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_read(cx, buf)
    }
}

impl AsyncWrite for Measured {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

impl Link for Measured {
    fn round_trip(&self) -> Option<Duration> {
        self.round_trip
    }
}

fn port(round_trip: Option<Duration>) -> (NetPort<Measured>, DuplexStream) {
    let (near, far) = tokio::io::duplex(4096);
    let link = Measured {
        stream: near,
        round_trip,
    };
    (NetPort::new(link, "192.0.2.7:4001".into()), far)
}

const MS: Duration = Duration::from_millis(1);

#[test]
fn the_link_budget_is_twice_the_least_round_trip_within_bounds() {
    assert_eq!(link_budget(Some(20 * MS)), 40 * MS);
    // Loopback: a few microseconds, raised to the timer's resolution.
    assert_eq!(
        link_budget(Some(Duration::from_micros(40))),
        MIN_LINK_BUDGET
    );
    // A link gone bad, or nothing measured: the most, never more.
    assert_eq!(link_budget(Some(3000 * MS)), MAX_LINK_BUDGET);
    assert_eq!(link_budget(None), MAX_LINK_BUDGET);
}

#[tokio::test(start_paused = true)]
async fn a_frame_has_left_the_far_wire_once_its_time_and_the_link_budget_have_passed() {
    let (port, _far) = port(Some(20 * MS));
    let now = Instant::now();
    assert_eq!(port.end_of_transmission(now, 9 * MS), now + 49 * MS);
    assert_eq!(port.link(), ("192.0.2.7:4001", 40 * MS, Some(20 * MS)));
}

#[tokio::test]
async fn bytes_left_in_the_socket_before_a_frame_are_drained_and_handed_back() {
    let (mut port, mut far) = port(None);
    far.write_all(&[0x01, 0x83, 0x02]).await.unwrap();
    let mut stale = Vec::new();
    port.clear_input(&mut stale).unwrap();
    assert_eq!(stale, [0x01, 0x83, 0x02]);
    stale.clear();
    port.clear_input(&mut stale).unwrap();
    assert!(stale.is_empty(), "nothing more: {stale:?}");
    port.send(&[0x01, 0x03]).await.unwrap();
    let mut sent = [0u8; 2];
    far.read_exact(&mut sent).await.unwrap();
    assert_eq!(sent, [0x01, 0x03]);
}

#[tokio::test]
async fn a_device_server_that_closed_the_connection_is_a_lost_port() {
    let (mut port, far) = port(None);
    drop(far);
    let error = port.clear_input(&mut Vec::new()).unwrap_err();
    assert_eq!(error.kind(), io::ErrorKind::UnexpectedEof);
    let error = port.recv(&mut Vec::new()).await.unwrap_err();
    assert_eq!(error.kind(), io::ErrorKind::UnexpectedEof);
}

#[tokio::test]
async fn on_an_rfc2217_line_a_data_byte_0xff_crosses_escaped_and_commands_are_not_data() {
    let (mut port, mut far) = port(None);
    port.telnet = Some(Box::new(Telnet::new()));
    port.send(&[0x01, 0xFF, 0x02]).await.unwrap();
    let mut sent = [0u8; 4];
    far.read_exact(&mut sent).await.unwrap();
    assert_eq!(sent, [0x01, 0xFF, 0xFF, 0x02]);
    // A Telnet NOP alone is no data: the receive waits on for the reply's bytes.
    far.write_all(&[0xFF, 0xF1]).await.unwrap();
    far.write_all(&[0x03, 0xFF, 0xFF, 0x04]).await.unwrap();
    let mut got = Vec::new();
    while got.len() < 3 {
        assert!(port.recv(&mut got).await.unwrap() > 0);
    }
    assert_eq!(got, [0x03, 0xFF, 0x04]);
    // Stale bytes are decoded too.
    far.write_all(&[0xFF, 0xFF, 0xFF, 0xF1]).await.unwrap();
    let mut stale = Vec::new();
    port.clear_input(&mut stale).unwrap();
    assert_eq!(stale, [0xFF]);
}

/// An RTU line's master at 115200 8N2 on a port of an in-memory link, recording for the trace;
/// and the link's far end.
fn recording_master() -> (crate::line::LineMaster<NetPort<Measured>>, DuplexStream) {
    use crate::line::{Framing, LineMaster, LineTiming, MasterTiming, Parity, SerialFormat};
    let timing = LineTiming::new(&SerialFormat {
        baud: 115_200,
        data_bits: 8,
        parity: Parity::None,
        stop_bits: 2,
    });
    let (port, far) = port(None);
    let mut master = LineMaster::new(port, Framing::Rtu, MasterTiming::new(timing, MS, MS));
    master.record_frames(true);
    (master, far)
}

#[tokio::test]
async fn stale_bytes_are_counted_as_stray_and_recorded_for_the_trace_before_the_request_goes_out() {
    use crate::line::Seen;
    let (mut master, mut far) = recording_master();
    far.write_all(&[0xDE, 0xAD]).await.unwrap();
    let answering = tokio::spawn(async move {
        let mut request = [0u8; 8];
        far.read_exact(&mut request).await.unwrap();
        far.write_all(&crate::line::rtu::encode(1, &[0x03, 0x02, 0x00, 0x07]))
            .await
            .unwrap();
        far
    });
    let reply = master
        .transact(1, &[0x03, 0x00, 0x00, 0x00, 0x01], 100 * MS)
        .await;
    assert_eq!(
        reply.unwrap(),
        crate::line::Reply::Fits(vec![0x03, 0x02, 0x00, 0x07])
    );
    let recorded: Vec<_> = master.recorded().map(|f| (f.seen, f.bytes)).collect();
    assert_eq!(
        recorded[0],
        (Seen::Stale, vec![0xDE, 0xAD]),
        "{recorded:02X?}"
    );
    assert_eq!(recorded[1].0, Seen::Sent);
    assert_eq!(master.counters().stray_bytes, 2);
    drop(answering.await.unwrap());
}

#[tokio::test]
async fn a_line_that_babbles_while_nobody_asks_is_counted_but_recorded_only_so_far() {
    let (mut master, mut far) = recording_master();
    for _ in 0..100 {
        far.write_all(&[0x55]).await.unwrap();
        assert_eq!(master.watch_idle().await.unwrap(), 1);
    }
    assert_eq!(master.counters().stray_bytes, 100);
    assert_eq!(master.recorded().count(), 32);
}
