//! RTU over TCP: masters that send plain RTU frames on a TCP connection (`listen_rtu_over_tcp`),
//! served by the same dispatcher and buses as Modbus TCP masters; every answer, the gateway's own
//! exceptions included, comes back as an RTU frame with the master's unit id.

use crate::support::{Bus, GatewayConfig, Scrape, Value, PATIENCE};
use modbus_gateway::testing::line::rtu;
use modbus_gateway::Gateway;
use std::net::SocketAddr;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_modbus::client::{rtu as rtu_client, Reader, Writer};
use tokio_modbus::Slave;

/// The simulated line at 115200 named "sim", with no slaves yet.
fn sim_line() -> Bus {
    Bus::sim("sim").baud(115_200).response_timeout("200ms")
}

/// A gateway with a Modbus TCP and an RTU over TCP listener and `server` keys besides, in front
/// of a simulated line with register slaves at 1-4.
async fn gateway(server: Vec<(&str, Value)>) -> Gateway {
    let config = GatewayConfig::new()
        .listen_rtu_over_tcp("127.0.0.1:0")
        .bus(sim_line().sim_slaves("1-4"));
    let config = server
        .into_iter()
        .fold(config, |config, (key, value)| config.server(key, value));
    config.start().await
}

/// The RTU over TCP listener's address: it comes after the Modbus TCP one.
fn rtu_addr(gateway: &Gateway) -> SocketAddr {
    gateway.rtu_over_tcp_addrs()[0]
}

/// Send `request` (whole RTU frames) and read exactly `len` bytes back.
async fn exchange(stream: &mut TcpStream, request: &[u8], len: usize) -> Vec<u8> {
    stream.write_all(request).await.unwrap();
    read_exactly(stream, len).await
}

async fn read_exactly(stream: &mut TcpStream, len: usize) -> Vec<u8> {
    let mut reply = vec![0; len];
    tokio::time::timeout(PATIENCE, stream.read_exact(&mut reply))
        .await
        .expect("a reply within the patience")
        .expect("the connection stays open");
    reply
}

/// Nothing more arrives within `wait`.
async fn silent_for(stream: &mut TcpStream, wait: Duration) -> bool {
    let mut byte = [0u8; 1];
    tokio::time::timeout(wait, stream.read(&mut byte))
        .await
        .is_err()
}

#[tokio::test]
async fn an_rtu_over_tcp_master_writes_and_reads_the_line_and_gets_rtu_frames_back() {
    let gateway = gateway(vec![]).await;
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    let write = rtu::encode(2, &[0x06, 0x00, 0x04, 0x13, 0x88]);
    assert_eq!(exchange(&mut master, &write, 8).await, write, "the echo");
    let read = rtu::encode(2, &[0x03, 0x00, 0x04, 0x00, 0x02]);
    assert_eq!(
        exchange(&mut master, &read, 9).await,
        rtu::encode(2, &[0x03, 0x04, 0x13, 0x88, 0x00, 0x00])
    );
}

#[tokio::test]
async fn tokio_modbus_rtu_client_on_a_tcp_stream_reads_what_a_modbus_tcp_master_wrote() {
    let gateway = gateway(vec![]).await;
    // A third-party RTU client on the TCP stream, and a Modbus TCP master on the other listener:
    // a write from one kind is read back by the other.
    let stream = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    let mut rtu_master = rtu_client::attach_slave(stream, Slave(3));
    let mut tcp_master = crate::support::RawMaster::connect(gateway.tcp_addrs()[0]).await;
    assert_eq!(
        tcp_master
            .call(
                1,
                3,
                &[0x10, 0x00, 0x07, 0x00, 0x02, 0x04, 0xAB, 0xCD, 0x00, 0x2A]
            )
            .await,
        [0x10, 0x00, 0x07, 0x00, 0x02]
    );
    let words = rtu_master
        .read_holding_registers(7, 2)
        .await
        .expect("transport")
        .expect("no exception");
    assert_eq!(words, [0xABCD, 0x002A]);
    rtu_master
        .write_single_register(9, 77)
        .await
        .expect("transport")
        .expect("no exception");
    assert_eq!(
        tcp_master.call(2, 3, &[0x03, 0x00, 0x09, 0x00, 0x01]).await,
        [0x03, 0x02, 0x00, 77]
    );
}

/// A request with a bad CRC gets no answer and is counted.
#[tokio::test]
async fn a_request_with_a_bad_crc_is_counted_unanswered_and_the_next_is_answered() {
    let gateway = gateway(vec![]).await;
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    let mut bad = rtu::encode(1, &[0x03, 0x00, 0x00, 0x00, 0x01]);
    bad[6] ^= 0x01;
    master.write_all(&bad).await.unwrap();
    assert!(silent_for(&mut master, Duration::from_millis(300)).await);
    let read = rtu::encode(1, &[0x03, 0x00, 0x00, 0x00, 0x01]);
    assert_eq!(
        exchange(&mut master, &read, 7).await,
        rtu::encode(1, &[0x03, 0x02, 0x00, 0x00])
    );
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value("modbus_gateway_tcp_bad_crc_total"), 1.0);
    assert_eq!(
        gateway.sim_line("sim").unwrap().stats().master_frames,
        1,
        "the bad request never reached the line"
    );
}

#[tokio::test]
async fn a_request_split_across_segments_is_answered_once_whole() {
    let gateway = gateway(vec![]).await;
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    master.set_nodelay(true).unwrap();
    let read = rtu::encode(4, &[0x03, 0x00, 0x00, 0x00, 0x01]);
    master.write_all(&read[..3]).await.unwrap();
    assert!(silent_for(&mut master, Duration::from_millis(100)).await);
    master.write_all(&read[3..]).await.unwrap();
    assert_eq!(
        read_exactly(&mut master, 7).await,
        rtu::encode(4, &[0x03, 0x02, 0x00, 0x00])
    );
}

#[tokio::test]
async fn two_requests_in_one_segment_are_answered_in_order() {
    let gateway = gateway(vec![]).await;
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    let write = rtu::encode(1, &[0x06, 0x00, 0x01, 0x00, 0x05]);
    let read = rtu::encode(1, &[0x03, 0x00, 0x01, 0x00, 0x01]);
    let both = [write.clone(), read].concat();
    let replies = exchange(&mut master, &both, 8 + 7).await;
    assert_eq!(&replies[..8], write);
    assert_eq!(&replies[8..], rtu::encode(1, &[0x03, 0x02, 0x00, 0x05]));
}

#[tokio::test]
async fn an_unknown_function_code_reaches_the_slave_and_its_exception_comes_back() {
    let gateway = gateway(vec![]).await;
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    let request = rtu::encode(1, &[0x41, 0x01, 0x02]);
    assert_eq!(
        exchange(&mut master, &request, 5).await,
        rtu::encode(1, &[0xC1, 0x01])
    );
    assert_eq!(
        gateway.sim_line("sim").unwrap().stats().master_frames,
        1,
        "it went to the line"
    );
}

#[tokio::test]
async fn the_gateways_own_exceptions_come_back_as_rtu_frames_with_the_masters_unit() {
    let gateway = gateway(vec![("read_only", "127.0.0.1".into())]).await;
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    let read = [0x03, 0x00, 0x00, 0x00, 0x01];
    // No route for unit 250: 0x0A.
    assert_eq!(
        exchange(&mut master, &rtu::encode(250, &read), 5).await,
        rtu::encode(250, &[0x83, 0x0A])
    );
    // Nobody at 9: 0x0B after the response timeout.
    assert_eq!(
        exchange(&mut master, &rtu::encode(9, &read), 5).await,
        rtu::encode(9, &[0x83, 0x0B])
    );
    // A write from a read-only master: 0x01.
    let write = [0x06, 0x00, 0x00, 0x00, 0x01];
    assert_eq!(
        exchange(&mut master, &rtu::encode(1, &write), 5).await,
        rtu::encode(1, &[0x86, 0x01])
    );
}

#[tokio::test]
async fn bytes_that_cannot_be_an_rtu_request_close_the_connection() {
    let gateway = gateway(vec![]).await;
    // A header announcing more data than a frame holds: closed at once.
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    master
        .write_all(&[0x01, 0x10, 0x00, 0x00, 0x00, 0x7F, 0xFF])
        .await
        .unwrap();
    let mut byte = [0u8; 1];
    let read = tokio::time::timeout(PATIENCE, master.read(&mut byte)).await;
    assert!(matches!(read, Ok(Ok(0) | Err(_))), "{read:?}");
    // A flood of bytes that never frame: closed once more than a frame is held.
    let mut flood = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    let junk: Vec<u8> = std::iter::repeat_n([0x01, 0x41], 400).flatten().collect();
    let _ = flood.write_all(&junk).await;
    let read = tokio::time::timeout(PATIENCE, flood.read(&mut byte)).await;
    assert!(matches!(read, Ok(Ok(0) | Err(_))), "{read:?}");
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_tcp_connections_closed_total{protocol=\"rtu_over_tcp\",reason=\"protocol_error\"}"),
        2.0
    );
    assert_eq!(gateway.sim_line("sim").unwrap().stats().master_frames, 0);
}

#[tokio::test]
async fn a_full_queue_answers_0x06_as_an_rtu_frame_after_the_requests_before_it() {
    let gateway = GatewayConfig::new()
        .listen_rtu_over_tcp("127.0.0.1:0")
        .bus(sim_line().queue_depth(1).sim_slaves("1"))
        .start()
        .await;
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    // Three reads of silent unit 9 at once: the queue holds one, so at least one is refused
    // (which depends on whether the line has taken the first yet); all come back in order.
    let read = rtu::encode(9, &[0x03, 0x00, 0x00, 0x00, 0x01]);
    let replies = exchange(
        &mut master,
        &[read.clone(), read.clone(), read].concat(),
        15,
    )
    .await;
    let (timeout, full) = (rtu::encode(9, &[0x83, 0x0B]), rtu::encode(9, &[0x83, 0x06]));
    let replies: Vec<&[u8]> = replies.chunks(5).collect();
    assert!(
        replies.iter().all(|r| *r == timeout || *r == full),
        "{replies:02X?}"
    );
    assert!(replies.contains(&&full[..]), "{replies:02X?}");
    assert_eq!(replies[0], timeout, "the first went on the line");
}

#[tokio::test]
async fn two_user_defined_requests_sent_together_never_frame_and_close_at_frame_timeout() {
    let gateway = gateway(vec![("frame_timeout", "300ms".into())]).await;
    let mut master = TcpStream::connect(rtu_addr(&gateway)).await.unwrap();
    let request = rtu::encode(1, &[0x41, 0x01, 0x02]);
    master
        .write_all(&[request.clone(), request].concat())
        .await
        .unwrap();
    let mut byte = [0u8; 1];
    let read = tokio::time::timeout(PATIENCE, master.read(&mut byte)).await;
    assert!(matches!(read, Ok(Ok(0) | Err(_))), "{read:?}");
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value(
            "modbus_gateway_tcp_connections_closed_total{protocol=\"rtu_over_tcp\",reason=\"frame_timeout\"}"
        ),
        1.0
    );
    assert_eq!(gateway.sim_line("sim").unwrap().stats().master_frames, 0);
}
