//! Modbus UDP masters (`listen_udp`): one MBAP request per datagram, the reply to the source it
//! came from; the buses, routes and access lists they share with TCP masters; what is dropped;
//! floods from many ports of one address and from thousands of addresses.

use crate::support::{
    flood_target, frames_from, mbap, polite_reads, start, within, Bus, Flood, GatewayConfig,
    Scrape, Value, PATIENCE,
};
use modbus_gateway::testing::sim::Source;
use modbus_gateway::Gateway;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::UdpSocket;

/// A gateway with Modbus TCP and UDP listeners, `server` keys besides, and a simulated line at
/// 115200 with slaves 1-4.
async fn gateway(server: Vec<(&str, Value)>) -> Gateway {
    let sim = Bus::sim("sim")
        .baud(115_200)
        .response_timeout("200ms")
        .sim_slaves("1-4");
    let config = GatewayConfig::new().listen_udp("127.0.0.1:0").bus(sim);
    let config = server
        .into_iter()
        .fold(config, |config, (key, value)| config.server(key, value));
    config.start().await
}

fn udp_addr(gateway: &Gateway) -> SocketAddr {
    gateway.udp_addrs()[0]
}

async fn master() -> UdpSocket {
    UdpSocket::bind("127.0.0.1:0").await.unwrap()
}

/// The next datagram, if one comes within `wait`.
async fn receive(socket: &UdpSocket, wait: Duration) -> Option<Vec<u8>> {
    let mut buf = vec![0u8; 512];
    let (len, _) = tokio::time::timeout(wait, socket.recv_from(&mut buf))
        .await
        .ok()?
        .ok()?;
    buf.truncate(len);
    Some(buf)
}

#[tokio::test]
async fn a_udp_master_writes_and_reads_the_line_and_its_replies_come_to_its_own_address() {
    let gateway = gateway(vec![]).await;
    let socket = master().await;
    let write = [0x06, 0x00, 0x02, 0x12, 0x34];
    socket
        .send_to(&mbap(7, 1, &write), udp_addr(&gateway))
        .await
        .unwrap();
    assert_eq!(
        receive(&socket, PATIENCE).await.unwrap(),
        mbap(7, 1, &write)
    );
    socket
        .send_to(
            &mbap(8, 1, &[0x03, 0x00, 0x02, 0x00, 0x01]),
            udp_addr(&gateway),
        )
        .await
        .unwrap();
    assert_eq!(
        receive(&socket, PATIENCE).await.unwrap(),
        mbap(8, 1, &[0x03, 0x02, 0x12, 0x34])
    );
    // The gateway's own answers too: no route for unit 250.
    socket
        .send_to(&mbap(9, 250, &[0x03, 0, 0, 0, 1]), udp_addr(&gateway))
        .await
        .unwrap();
    assert_eq!(
        receive(&socket, PATIENCE).await.unwrap(),
        mbap(9, 250, &[0x83, 0x0A])
    );
}

#[tokio::test]
async fn a_write_by_udp_is_read_back_by_a_modbus_tcp_master() {
    let gateway = gateway(vec![]).await;
    let socket = master().await;
    let write = [0x06, 0x00, 0x05, 0x00, 0x2A];
    socket
        .send_to(&mbap(1, 2, &write), udp_addr(&gateway))
        .await
        .unwrap();
    assert_eq!(
        receive(&socket, PATIENCE).await.unwrap(),
        mbap(1, 2, &write)
    );
    let mut tcp = crate::support::RawMaster::connect(gateway.tcp_addrs()[0]).await;
    assert_eq!(
        tcp.call(1, 2, &[0x03, 0x00, 0x05, 0x00, 0x01]).await,
        [0x03, 0x02, 0x00, 0x2A]
    );
}

#[tokio::test]
async fn a_datagram_from_a_source_outside_allow_is_dropped_and_never_reaches_the_line() {
    let gateway = gateway(vec![("allow", ["10.0.0.0/8"].into())]).await;
    let socket = master().await;
    socket
        .send_to(&mbap(1, 1, &[0x03, 0, 0, 0, 1]), udp_addr(&gateway))
        .await
        .unwrap();
    assert_eq!(receive(&socket, Duration::from_millis(300)).await, None);
    assert_eq!(gateway.sim_line("sim").unwrap().stats().master_frames, 0);
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_udp_dropped_total{reason=\"not_allowed\"}"),
        1.0
    );
}

#[tokio::test]
async fn a_malformed_datagram_is_dropped_and_counted_and_the_next_one_is_answered() {
    let gateway = gateway(vec![]).await;
    let socket = master().await;
    let read = mbap(3, 1, &[0x03, 0, 0, 0, 1]);
    // Cut short, two requests in one datagram, a wrong protocol id.
    let two = [read.clone(), read.clone()].concat();
    let mut wrong_protocol = read.clone();
    wrong_protocol[3] = 1;
    for bad in [&read[..9], &two[..], &wrong_protocol[..]] {
        socket.send_to(bad, udp_addr(&gateway)).await.unwrap();
    }
    socket.send_to(&read, udp_addr(&gateway)).await.unwrap();
    assert_eq!(
        receive(&socket, PATIENCE).await.unwrap(),
        mbap(3, 1, &[0x03, 0x02, 0, 0])
    );
    assert_eq!(receive(&socket, Duration::from_millis(200)).await, None);
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_udp_dropped_total{reason=\"malformed\"}"),
        3.0
    );
}

#[tokio::test]
async fn a_flood_from_one_source_is_cut_at_pipeline_depth_and_others_are_served() {
    let gateway = gateway(vec![("pipeline_depth", 4.into())]).await;
    let flooder = master().await;
    for id in 0..200u16 {
        flooder
            .send_to(&mbap(id, 1, &[0x03, 0, 0, 0, 10]), udp_addr(&gateway))
            .await
            .unwrap();
    }
    let polite = master().await;
    polite
        .send_to(&mbap(1, 2, &[0x03, 0, 0, 0, 1]), udp_addr(&gateway))
        .await
        .unwrap();
    assert_eq!(
        receive(&polite, PATIENCE).await.unwrap(),
        mbap(1, 2, &[0x03, 0x02, 0, 0])
    );
    let mut answered = 0;
    while receive(&flooder, Duration::from_millis(300))
        .await
        .is_some()
    {
        answered += 1;
    }
    assert!(answered <= 4 * 2, "{answered} answered");
    let scrape = Scrape::of(&gateway).await;
    let dropped = scrape.value("modbus_gateway_udp_dropped_total{reason=\"overloaded\"}");
    assert_eq!(
        dropped + f64::from(answered),
        200.0,
        "each dropped or answered"
    );
}

#[tokio::test]
async fn two_thousand_random_datagrams_leave_the_gateway_serving_and_the_line_untouched() {
    let gateway = gateway(vec![]).await;
    let socket = master().await;
    let mut rng = fastrand::Rng::with_seed(16);
    for _ in 0..2000 {
        let len = rng.usize(0..300);
        let datagram: Vec<u8> = (0..len).map(|_| rng.u8(..)).collect();
        let _ = socket.send_to(&datagram, udp_addr(&gateway)).await;
    }
    // The request after them is answered once they have all been read: then the line has
    // carried that request alone.
    socket
        .send_to(&mbap(1, 1, &[0x03, 0, 0, 0, 1]), udp_addr(&gateway))
        .await
        .unwrap();
    let mut reply = None;
    // Replies to random datagrams that happened to be requests may come first.
    for _ in 0..10 {
        match receive(&socket, PATIENCE).await {
            Some(r) if r == mbap(1, 1, &[0x03, 0x02, 0, 0]) => {
                reply = Some(r);
                break;
            }
            Some(_) => continue,
            None => break,
        }
    }
    assert!(reply.is_some(), "still serving");
    let on_the_line = frames_from(&gateway.sim_line("sim").unwrap(), Source::Master);
    let request = crate::support::rtu(1, &[0x03, 0, 0, 0, 1]);
    assert_eq!(on_the_line, [request], "the random datagrams sent none");
}

#[tokio::test]
async fn masters_of_all_three_kinds_polling_one_bus_are_all_answered_and_share_it_fairly() {
    use modbus_gateway::testing::line::rtu;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let gateway = GatewayConfig::new()
        .listen_rtu_over_tcp("127.0.0.1:0")
        .listen_udp("127.0.0.1:0")
        .bus(Bus::sim("sim").baud(115_200).sim_slaves("1-3"))
        .start()
        .await;
    let run_for = Duration::from_secs(2);
    let read = [0x03, 0x00, 0x00, 0x00, 0x0A];
    let answer_len = 2 + 20;
    let tcp_addr = gateway.tcp_addrs()[0];
    let rtu_addr = gateway.rtu_over_tcp_addrs()[0];
    let udp = udp_addr(&gateway);
    let tcp = tokio::spawn(async move {
        let mut master = crate::support::RawMaster::connect(tcp_addr).await;
        let (mut done, start) = (0u32, tokio::time::Instant::now());
        while start.elapsed() < run_for {
            let id = u16::try_from(done % 60_000).unwrap();
            assert_eq!(master.call(id, 1, &read).await.len(), answer_len);
            done += 1;
        }
        done
    });
    let rtu_master = tokio::spawn(async move {
        let mut stream = tokio::net::TcpStream::connect(rtu_addr).await.unwrap();
        let request = rtu::encode(2, &read);
        let mut reply = vec![0u8; 1 + answer_len + 2];
        let (mut done, start) = (0u32, tokio::time::Instant::now());
        while start.elapsed() < run_for {
            stream.write_all(&request).await.unwrap();
            tokio::time::timeout(PATIENCE, stream.read_exact(&mut reply))
                .await
                .unwrap()
                .unwrap();
            assert!(rtu::crc_ok(&reply));
            done += 1;
        }
        done
    });
    let udp_master = tokio::spawn(async move {
        let socket = master().await;
        let (mut done, start) = (0u32, tokio::time::Instant::now());
        while start.elapsed() < run_for {
            let id = u16::try_from(done % 60_000).unwrap();
            socket.send_to(&mbap(id, 3, &read), udp).await.unwrap();
            let reply = receive(&socket, PATIENCE).await.expect("a reply");
            assert_eq!(&reply[..2], &id.to_be_bytes());
            assert_eq!(reply.len(), 7 + answer_len);
            done += 1;
        }
        done
    });
    let counts = [
        tcp.await.unwrap(),
        rtu_master.await.unwrap(),
        udp_master.await.unwrap(),
    ];
    let (least, most) = (*counts.iter().min().unwrap(), *counts.iter().max().unwrap());
    assert!(least > 10, "{counts:?}");
    assert!(
        most <= 2 * least,
        "unfair: {counts:?} (Modbus TCP, RTU over TCP, UDP)"
    );
    // Each kind's requests are counted under its own protocol label.
    let scrape = Scrape::of(&gateway).await;
    for (protocol, count) in ["tcp", "rtu_over_tcp", "udp"].iter().zip(counts) {
        let counted: f64 = scrape
            .series_of("modbus_gateway_requests_total")
            .iter()
            .filter(|(series, _)| series.contains(&format!("protocol=\"{protocol}\"")))
            .map(|(_, value)| value)
            .sum();
        assert_eq!(counted, f64::from(count), "{protocol}");
    }
    assert_eq!(
        scrape.value("modbus_gateway_tcp_connections_accepted_total{protocol=\"rtu_over_tcp\"}"),
        1.0
    );
}

/// Forty UDP ports of one address.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forty_udp_ports_flooding_leave_a_polite_master_95_percent_answered() {
    // Fewer places than ports: were each port a master of its own, they would hold one place
    // each and a newcomer would wait for room.
    let gateway = start(&flood_target(115200, 32)).await;
    let udp = udp_addr(&gateway);
    let flood = Flood::new();
    let mut ports = Vec::new();
    for port in 0..40 {
        ports.push(tokio::spawn(flood_from_port(udp, port, flood.clone())));
    }
    flood.until_refused(40).await;
    let answered = polite_reads(gateway.tcp_addrs()[0], 2, 20).await;
    flood.stop();
    for port in ports {
        within("a port stops", port).await.expect("port task");
    }
    eprintln!("polite master: {answered} of 20 answered");
    assert!(answered >= 19, "polite master: {answered} of 20 answered");
}

/// They take one turn between them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forty_udp_ports_of_one_address_delay_a_polite_master_one_transaction_at_most() {
    // Slow enough that the polite master's next read is queued well within one transaction of
    // the flood, so what it waits for is the queue's order, not the scheduler's.
    let gateway = start(&flood_target(19200, 64)).await;
    let udp = udp_addr(&gateway);
    let flood = Flood::new();
    let ports: Vec<_> = (0..40)
        .map(|port| tokio::spawn(flood_from_port(udp, port, flood.clone())))
        .collect();
    flood.until_refused(40).await;
    // The flood reads slave 1, the polite master slave 2.
    const READS: u16 = 10;
    let answered = polite_reads(gateway.tcp_addrs()[0], 2, READS).await;
    let line = gateway.sim_line("sim").expect("a simulated line");
    let frames = frames_from(&line, Source::Master);
    flood.stop();
    for port in ports {
        within("a port stops", port).await.expect("port task");
    }
    assert_eq!(answered, READS);
    let polite: Vec<usize> = (0..frames.len())
        .filter(|&at| frames[at].first() == Some(&2))
        .collect();
    assert_eq!(
        polite.len(),
        usize::from(READS),
        "each read once on the wire"
    );
    // Between two of its reads: a transaction of the flood that may have started before its
    // next read came, another if the flood's turn came first, and one spare for a slow
    // scheduler. Were each port a master of its own, the flood's 40 turns would come first.
    let between: Vec<usize> = polite.windows(2).map(|w| w[1] - w[0] - 1).collect();
    eprintln!("flood transactions between the polite master's reads: {between:?}");
    assert!(between.iter().all(|&n| n <= 3), "{between:?}");
}

/// Modbus UDP source addresses flooding the line, one read in flight each.
const SOURCES: u16 = 2000;
/// The polite master's reads, one at a time.
const POLITE_READS: u16 = 100;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_thousand_udp_addresses_one_read_each_leave_a_polite_master_always_answered() {
    // Far fewer places than sources: every source waiting holds one place, none more than its
    // share, and each one answered comes back a newcomer, as the polite master does.
    let gateway = start(&flood_target(115200, 8)).await;
    let udp = udp_addr(&gateway);
    let flood = Flood::new();
    let sources: Vec<_> = (0..SOURCES)
        .map(|source| tokio::spawn(flood_from_address(udp, source, flood.clone())))
        .collect();
    flood.until_refused(usize::from(SOURCES)).await;
    let answered = polite_reads(gateway.tcp_addrs()[0], 2, POLITE_READS).await;
    flood.stop();
    let mut refused = 0;
    for source in sources {
        refused += within("a source stops", source).await.expect("source task");
    }
    eprintln!("polite master: {answered} of {POLITE_READS} answered; flood: {refused} refused");
    assert_eq!(answered, POLITE_READS, "the polite master got 0x06");
}

/// A source address of its own on loopback (127.1.0.0/16; all of 127/8 is loopback on Linux)
/// with one read of its own input register in flight until the flood stops, sent again when
/// answered or when no answer came within a pause (a datagram lost). Each answer is its own,
/// or 0x06; how many were 0x06.
async fn flood_from_address(udp: SocketAddr, index: u16, flood: Arc<Flood>) -> usize {
    const PAUSE: Duration = Duration::from_millis(100);
    let [hi, lo] = index.to_be_bytes();
    let address = std::net::Ipv4Addr::new(127, 1, hi, lo);
    let socket = UdpSocket::bind((address, 0)).await.unwrap();
    let request = [0x04, hi, lo, 0x00, 0x01];
    let mut refused = 0;
    for transaction in (0..=u16::MAX).cycle() {
        if flood.is_stopped() {
            break;
        }
        socket
            .send_to(&mbap(transaction, 1, &request), udp)
            .await
            .unwrap();
        let Some(reply) = receive(&socket, PAUSE).await else {
            continue;
        };
        let pdu = &reply[7..];
        if pdu == [0x84, 0x06] {
            flood.refused();
            refused += 1;
        } else {
            assert_eq!(pdu, [0x04, 0x02, hi, lo], "address {address}: its own");
        }
    }
    refused
}

/// One source port of 127.0.0.1 keeping 16 reads of its own input register in flight (as many
/// as `pipeline_depth` lets it) until the flood stops: one more for each reply, and for each
/// pause in the replies (a datagram lost). Each reply is the answer to its own read, or 0x06.
async fn flood_from_port(udp: SocketAddr, index: u16, flood: Arc<Flood>) {
    const PAUSE: Duration = Duration::from_millis(100);
    let socket = master().await;
    let [hi, lo] = index.to_be_bytes();
    let request = [0x04, hi, lo, 0x00, 0x01];
    let mut transaction = 0u16;
    for _ in 0..16 {
        socket
            .send_to(&mbap(transaction, 1, &request), udp)
            .await
            .unwrap();
        transaction += 1;
    }
    while !flood.is_stopped() {
        if let Some(reply) = receive(&socket, PAUSE).await {
            let pdu = &reply[7..];
            if pdu == [0x84, 0x06] {
                flood.refused();
            } else {
                assert_eq!(pdu, [0x04, 0x02, hi, lo], "port {index}: its own");
            }
            assert_eq!(
                &reply[2..7],
                &[0, 0, 0, u8::try_from(pdu.len() + 1).unwrap(), 1]
            );
        }
        socket
            .send_to(&mbap(transaction, 1, &request), udp)
            .await
            .unwrap();
        transaction = transaction.wrapping_add(1);
    }
}
