//! The Modbus TCP side, and masters that abuse it: pipelined requests come back in order, and a
//! malformed or lying MBAP header, garbage, a half-sent request or a master that never reads
//! closes that connection only; at the connection limit the one idle longest makes room (or the
//! newcomer is refused), a PLC polling every second is never the one; idle timeout, keepalive.

use crate::support::{
    addr, panics_on_this_thread, sim_bus_filled, sim_config_with_server, start, start_sim, tool,
    within, Bus, GatewayConfig, RawMaster, Scrape,
};
use modbus_gateway::testing::metrics::Metrics;
use modbus_gateway::testing::session::{self, Activity, SessionError};
use modbus_gateway::testing::shutdown::Stopping;
use modbus_gateway::testing::sim::RegisterBank;
use modbus_gateway::testing::{Client, Dispatcher, Rights};
use modbus_gateway::testing::{Router, RECENTLY_ANSWERED};
use modbus_gateway::testing::{SessionLimits, UpstreamFraming as Upstream};
use modbus_gateway::Gateway;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[tokio::test]
async fn pipelined_requests_come_back_in_order_with_their_own_transaction_ids() {
    let gateway = start_sim("").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let mut burst = Vec::new();
    for i in 0..12u16 {
        let unit = 1 + (i % 4) as u8;
        burst.extend(RawMaster::adu(
            0x100 + i,
            unit,
            &[0x04, 0x00, i as u8, 0x00, 0x01],
        ));
    }
    master.send_raw(&burst).await;
    for i in 0..12u16 {
        let reply = master.recv().await;
        assert_eq!(reply.transaction, 0x100 + i);
        assert_eq!(reply.unit, 1 + (i % 4) as u8);
        assert_eq!(
            reply.pdu,
            [0x04, 0x02, 0x00, i as u8],
            "input register {i} reads {i}"
        );
    }
}

#[tokio::test]
async fn a_wrong_protocol_id_closes_that_connection_and_no_other() {
    let panics = panics_on_this_thread();
    let gateway = start_sim("").await;
    let mut good = RawMaster::connect(addr(&gateway)).await;
    let mut bad = RawMaster::connect(addr(&gateway)).await;
    let mut adu = RawMaster::adu(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]);
    adu[3] = 0x01;
    bad.send_raw(&adu).await;
    assert!(bad.is_closed().await);
    assert_eq!(
        good.call(7, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x03, 0x02, 0, 0]
    );
    assert_eq!(
        panics_on_this_thread(),
        panics,
        "closed by the protocol, not by a panic"
    );
}

#[tokio::test]
async fn a_length_field_outside_2_to_254_closes_the_connection() {
    let panics = panics_on_this_thread();
    let gateway = start_sim("").await;
    for length in [0u16, 1, 255, 0xFFFF] {
        let mut master = RawMaster::connect(addr(&gateway)).await;
        let mut adu = RawMaster::adu(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]);
        adu[4..6].copy_from_slice(&length.to_be_bytes());
        master.send_raw(&adu).await;
        assert!(master.is_closed().await, "length {length}");
    }
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x03, 0x02, 0, 0]
    );
    assert_eq!(panics_on_this_thread(), panics, "no session panicked");
}

/// The frame timeout of sessions on an in-memory pipe.
const FRAME_TIMEOUT: Duration = Duration::from_millis(200);

/// xorshift64: reproducible noise without a dependency.
fn noise(seed: u64, len: usize) -> Vec<u8> {
    let mut x = seed | 1;
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect()
}

#[tokio::test]
async fn random_bytes_never_take_the_gateway_down() {
    let panics = panics_on_this_thread();
    let gateway = start_sim("response_timeout = \"20ms\"").await;
    for seed in 1..=64u64 {
        let mut stream = tokio::net::TcpStream::connect(addr(&gateway))
            .await
            .unwrap();
        let _ = stream
            .write_all(&noise(seed, 64 + (seed as usize * 37) % 1024))
            .await;
        let _ = stream.shutdown().await;
        let mut sink = Vec::new();
        let _ = within("gateway answers or closes", stream.read_to_end(&mut sink)).await;
    }
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 2, &[0x04, 0x00, 0x09, 0x00, 0x01]).await,
        [0x04, 0x02, 0, 9]
    );
    assert_eq!(panics_on_this_thread(), panics, "no session panicked");
}

/// With `when_full = "refuse"`, connections beyond `max_connections` are refused.
#[tokio::test]
async fn when_full_refuse_refuses_beyond_max_connections_and_reuses_a_freed_slot() {
    let keys = "max_connections = 3\nmax_connections_per_address = 0\nwhen_full = \"refuse\"";
    let gateway = start(&sim_config_with_server(keys, "")).await;
    let mut open = Vec::new();
    for tid in 0..3 {
        let mut master = RawMaster::connect(addr(&gateway)).await;
        assert_eq!(
            master.call(tid, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]).await[0],
            0x03
        );
        open.push(master);
    }
    let mut refused = RawMaster::connect(addr(&gateway)).await;
    assert!(refused.is_closed().await, "the fourth master is refused");
    drop(open.pop());
    // The slot frees once the gateway has seen the close; until then new masters are refused.
    let reply = within("a freed slot is reused", async {
        loop {
            let mut master = RawMaster::connect(addr(&gateway)).await;
            if let Some(reply) = master.try_call(9, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]).await {
                return reply;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    assert_eq!(reply, [0x03, 0x02, 0, 0]);
}

/// A session over an in-memory pipe on the paused clock, in front of a sim bus.
async fn session_on_pipe(
    idle_timeout: Duration,
    slave_delay: Duration,
) -> (
    tokio::io::DuplexStream,
    tokio::task::JoinHandle<SessionError>,
) {
    let config = GatewayConfig::new().bus(Bus::sim("line").baud(9600)).load();
    let metrics = Arc::new(Metrics::new());
    let (_, bus) = sim_bus_filled(config.bus[0].clone(), &metrics, |line| {
        line.add_slave(1, RegisterBank::new(slave_delay));
    });
    let dispatcher = Dispatcher::new(Router::new(&config), vec![bus], metrics);
    let (client, server) = tokio::io::duplex(4096);
    let limits = SessionLimits {
        pipeline_depth: 4,
        idle_timeout: Some(idle_timeout),
        frame_timeout: FRAME_TIMEOUT,
    };
    let task = tokio::spawn(async move {
        let client = Client::new(1, "127.0.0.1:1502".parse().unwrap(), Rights::ReadWrite);
        let activity = Activity::default();
        session::run(
            server,
            Upstream::Mbap,
            client,
            &activity,
            &dispatcher,
            limits,
            Stopping::never(),
        )
        .await
    });
    (client, task)
}

/// Read holding register 0 of unit 1 over the pipe; the reply PDU.
async fn read_register_0(client: &mut tokio::io::DuplexStream) -> Vec<u8> {
    let request = RawMaster::adu(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]);
    client.write_all(&request).await.unwrap();
    let mut reply = [0u8; 11];
    client.read_exact(&mut reply).await.unwrap();
    reply[7..].to_vec()
}

#[tokio::test(start_paused = true)]
async fn an_idle_connection_is_closed_after_idle_timeout_and_not_before() {
    let idle = Duration::from_secs(10);
    let (mut client, session) = session_on_pipe(idle, Duration::ZERO).await;
    tokio::time::sleep(idle - Duration::from_millis(10)).await;
    assert!(!session.is_finished());
    read_register_0(&mut client).await;
    let answered = tokio::time::Instant::now();
    let reason = session.await.unwrap();
    assert!(matches!(reason, SessionError::Idle(_)), "{reason}");
    let waited = answered.elapsed();
    assert!(
        waited >= idle && waited <= idle + Duration::from_millis(1),
        "{waited:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_connection_waiting_for_a_slow_reply_is_not_idle() {
    let idle = Duration::from_millis(100);
    let (mut client, session) = session_on_pipe(idle, Duration::from_millis(500)).await;
    assert_eq!(read_register_0(&mut client).await, [0x03, 0x02, 0x00, 0x00]);
    assert!(matches!(session.await.unwrap(), SessionError::Idle(_)));
}

const READ_1: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];
/// The gateway's own answer to a unit no route serves (0x0A): no line time, as cheap as a
/// request gets.
const NO_ROUTE_UNIT: u8 = 250;
const REFUSED_FULL: &str =
    "modbus_gateway_tcp_connections_rejected_total{protocol=\"tcp\",reason=\"max_connections\"}";
const EVICTED: &str =
    "modbus_gateway_tcp_connections_closed_total{protocol=\"tcp\",reason=\"evicted\"}";

#[tokio::test(start_paused = true)]
async fn at_max_connections_a_new_master_closes_the_connection_idle_longest() {
    let keys = "max_connections = 3\nmax_connections_per_address = 0";
    let gateway = start(&sim_config_with_server(keys, "")).await;
    let mut masters = Vec::new();
    for tid in 0..3 {
        let mut master = RawMaster::connect(addr(&gateway)).await;
        assert_eq!(master.call(tid, 1, &READ_1).await, [0x03, 0x02, 0, 0]);
        masters.push(master);
    }
    // A minute of quiet: none of them is working any more...
    tokio::time::sleep(RECENTLY_ANSWERED).await;
    // ...until the first polls again: the second is now the one idle longest.
    assert_eq!(masters[0].call(9, 1, &READ_1).await, [0x03, 0x02, 0, 0]);
    let mut newcomer = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(newcomer.call(1, 1, &READ_1).await, [0x03, 0x02, 0, 0]);
    assert!(
        masters[1].is_closed().await,
        "the master idle longest made room"
    );
    for i in [0, 2] {
        assert_eq!(masters[i].call(10, 1, &READ_1).await, [0x03, 0x02, 0, 0]);
    }
    let scrape = Scrape::of(&gateway).await;
    let closed = "modbus_gateway_tcp_connections_closed_total{protocol=\"tcp\",reason=\"evicted\"}";
    assert_eq!(scrape.value(closed), 1.0);
    assert_eq!(scrape.value(REFUSED_FULL), 0.0);
}

#[tokio::test]
async fn at_max_connections_with_every_master_waiting_for_a_reply_a_new_one_is_refused() {
    let slow = "[[bus.sim_slave]]\naddress = 9\nprocessing_delay = \"400ms\"";
    let keys = "max_connections = 2\nmax_connections_per_address = 0";
    let gateway = start(&sim_config_with_server(
        keys,
        &format!("response_timeout = \"2s\"\n{slow}"),
    ))
    .await;
    let line = gateway.sim_line("sim").expect("a sim line");
    let mut first = RawMaster::connect(addr(&gateway)).await;
    let mut second = RawMaster::connect(addr(&gateway)).await;
    // Two different reads, or the second would join the first rather than queue behind it.
    let other_read = [0x03, 0x00, 0x07, 0x00, 0x01];
    first.send(1, 9, &READ_1).await;
    second.send(2, 9, &other_read).await;
    // Both requests are in: one on the wire, one queued behind it.
    within("both requests are in flight", async {
        loop {
            let on_wire = line.stats().master_frames;
            let queued = Scrape::of(&gateway)
                .await
                .value("modbus_gateway_queue_depth{bus=\"sim\"}");
            if on_wire == 1 && queued == 1.0 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    let mut third = RawMaster::connect(addr(&gateway)).await;
    assert!(third.is_closed().await, "no connection is idle: refused");
    assert_eq!(first.recv().await.pdu, [0x03, 0x02, 0, 0]);
    assert_eq!(second.recv().await.pdu, [0x03, 0x02, 0, 0]);
    let scrape = Scrape::of(&gateway).await;
    let refused = "modbus_gateway_tcp_connections_rejected_total{protocol=\"tcp\",reason=\"max_connections\"}";
    assert_eq!(scrape.value(refused), 1.0);
    let closed = "modbus_gateway_tcp_connections_closed_total{protocol=\"tcp\",reason=\"evicted\"}";
    assert_eq!(scrape.value(closed), 0.0);
}

#[tokio::test(start_paused = true)]
async fn half_a_request_closes_the_connection_at_frame_timeout_and_not_before() {
    let (mut client, session) = session_on_pipe(Duration::from_secs(60), Duration::ZERO).await;
    // A request in two pieces, both within the frame timeout, is answered.
    let request = RawMaster::adu(1, 1, &READ_1);
    client.write_all(&request[..4]).await.unwrap();
    tokio::time::sleep(FRAME_TIMEOUT - Duration::from_millis(50)).await;
    client.write_all(&request[4..]).await.unwrap();
    let mut reply = [0u8; 11];
    client.read_exact(&mut reply).await.unwrap();
    assert_eq!(reply[7..], [0x03, 0x02, 0, 0]);
    // Half a header, then nothing.
    client.write_all(&request[..3]).await.unwrap();
    let sent = tokio::time::Instant::now();
    tokio::time::sleep(FRAME_TIMEOUT - Duration::from_millis(1)).await;
    assert!(!session.is_finished(), "closed before the frame timeout");
    let reason = session.await.unwrap();
    assert!(matches!(reason, SessionError::FrameTimeout(_)), "{reason}");
    assert!(sent.elapsed() <= FRAME_TIMEOUT + Duration::from_millis(1));
}

#[tokio::test(start_paused = true)]
async fn a_request_trickling_in_a_byte_at_a_time_is_closed_at_frame_timeout() {
    let (mut client, session) = session_on_pipe(Duration::from_secs(60), Duration::ZERO).await;
    let request = RawMaster::adu(1, 1, &READ_1);
    let started = tokio::time::Instant::now();
    tokio::spawn(async move {
        for byte in request {
            if client.write_all(&[byte]).await.is_err() {
                break;
            }
            tokio::time::sleep(FRAME_TIMEOUT / 4).await;
        }
    });
    let reason = session.await.unwrap();
    assert!(matches!(reason, SessionError::FrameTimeout(_)), "{reason}");
    assert!(
        started.elapsed() <= FRAME_TIMEOUT + Duration::from_millis(1),
        "bytes kept coming, but the request never completed: {:?}",
        started.elapsed()
    );
}

#[tokio::test]
async fn an_mbap_length_longer_than_what_came_closes_the_connection_and_is_counted() {
    let gateway = start(&sim_config_with_server("frame_timeout = \"300ms\"", "")).await;
    let mut liar = RawMaster::connect(addr(&gateway)).await;
    let mut adu = RawMaster::adu(1, 1, &READ_1);
    adu[4..6].copy_from_slice(&20u16.to_be_bytes());
    liar.send_raw(&adu).await;
    assert!(
        liar.is_closed().await,
        "closed: the promised bytes never came"
    );
    let closed =
        "modbus_gateway_tcp_connections_closed_total{protocol=\"tcp\",reason=\"frame_timeout\"}";
    within("the close is counted", async {
        while Scrape::of(&gateway).await.value(closed) != 1.0 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    let mut honest = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(honest.call(2, 1, &READ_1).await, [0x03, 0x02, 0, 0]);
}

#[tokio::test]
async fn an_mbap_length_shorter_than_the_request_answers_the_cut_request_then_closes() {
    let panics = panics_on_this_thread();
    let gateway = start(&sim_config_with_server("frame_timeout = \"300ms\"", "")).await;
    let mut liar = RawMaster::connect(addr(&gateway)).await;
    let mut adu = RawMaster::adu(7, 1, &READ_1);
    // Length 3: unit id and two PDU bytes; the last three bytes start a "next header".
    adu[4..6].copy_from_slice(&3u16.to_be_bytes());
    liar.send_raw(&adu).await;
    let reply = liar.recv().await;
    assert_eq!((reply.transaction, reply.unit), (7, 1));
    assert_eq!(
        reply.pdu[0], 0x83,
        "the cut request gets an exception: {reply:?}"
    );
    assert!(
        liar.is_closed().await,
        "the leftover bytes never become a request"
    );
    assert_eq!(panics_on_this_thread(), panics, "no session panicked");
}

#[tokio::test]
async fn a_flood_of_pipelined_requests_is_read_a_pipeline_at_a_time_and_answered_in_order() {
    // A queue shorter than the flood: were the flood read at once, masters would get 0x06.
    let gateway = GatewayConfig::new()
        .pipeline_depth(8)
        .bus(
            Bus::sim("sim")
                .baud(115_200)
                .parity("none")
                .queue_depth(32)
                .queue_timeout("1h")
                .sim_slaves("1-2"),
        )
        .start()
        .await;
    let mut flooder = RawMaster::connect(addr(&gateway)).await;
    let flood: Vec<u8> = (0..400u16)
        .flat_map(|tid| RawMaster::adu(tid, 1, &[0x04, 0x00, tid as u8, 0x00, 0x01]))
        .collect();
    flooder.send_raw(&flood).await;
    let mut other = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        other.call(1, 2, &[0x04, 0x00, 0x05, 0x00, 0x01]).await,
        [0x04, 0x02, 0x00, 0x05],
        "another master is served during the flood"
    );
    for tid in 0..400u16 {
        let reply = flooder.recv().await;
        assert_eq!(reply.transaction, tid);
        assert_eq!(reply.pdu, [0x04, 0x02, 0x00, tid as u8]);
    }
    let scrape = Scrape::of(&gateway).await;
    let full = scrape.series_of("modbus_gateway_requests_total");
    assert!(
        full.iter()
            .all(|(series, _)| !series.contains("queue_full")),
        "{full:?}"
    );
}

#[test]
fn keepalive_probes_start_after_the_configured_silence() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let _client = std::net::TcpStream::connect(listener.local_addr().unwrap()).unwrap();
    let (accepted, _) = listener.accept().unwrap();
    accepted.set_nonblocking(true).unwrap();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let _guard = runtime.enter();
    let stream = tokio::net::TcpStream::from_std(accepted).unwrap();
    modbus_gateway::testing::set_keepalive(&stream, Duration::from_secs(60)).unwrap();
    let socket = socket2::SockRef::from(&stream);
    assert!(socket.keepalive().unwrap());
    assert_eq!(
        socket.tcp_keepalive_time().unwrap(),
        Duration::from_secs(60)
    );
    assert_eq!(
        socket.tcp_keepalive_interval().unwrap(),
        Duration::from_secs(20)
    );
    assert_eq!(socket.tcp_keepalive_retries().unwrap(), 3);
    assert_eq!(
        socket.tcp_user_timeout().unwrap(),
        Some(Duration::from_secs(120)),
        "unacknowledged replies to a vanished master give up as soon as the probes do"
    );
}

/// The TCP timer `ss` shows on the gateway's side of its one connection on `port`.
fn gateway_side_timer(ss: &std::path::Path, port: u16) -> String {
    let output = std::process::Command::new(ss)
        .args([
            "-tnoH",
            "state",
            "established",
            &format!("( sport = :{port} )"),
        ])
        .output()
        .expect("ss runs");
    String::from_utf8_lossy(&output.stdout).into_owned()
}

#[tokio::test]
async fn accepted_connections_get_keepalive_probes_unless_it_is_off() {
    let Some(ss) = tool("ss") else { return };
    for (keepalive, expected) in [("30s", true), ("0s", false)] {
        let keys = format!("keepalive = \"{keepalive}\"");
        let gateway = start(&sim_config_with_server(&keys, "")).await;
        let mut master = RawMaster::connect(addr(&gateway)).await;
        master.call(1, 1, &READ_1).await;
        let sockets = gateway_side_timer(&ss, addr(&gateway).port());
        assert_eq!(sockets.lines().count(), 1, "{sockets}");
        assert_eq!(
            sockets.contains("timer:(keepalive,"),
            expected,
            "keepalive = {keepalive}: {sockets}"
        );
    }
}

/// A PLC on its own host polling every second for `polls` seconds; each poll must be answered on
/// the same connection, which must never be closed.
async fn plc_polling_every_second(gateway: &Gateway, polls: u16) -> tokio::task::JoinHandle<()> {
    let mut plc = RawMaster::connect_from([127, 0, 0, 2], addr(gateway)).await;
    tokio::spawn(async move {
        for tid in 0..polls {
            let reply = plc.try_call(tid, 1, &READ_1).await;
            assert_eq!(
                reply.as_deref(),
                Some(&[0x03, 0x02, 0, 0][..]),
                "poll {tid}: the PLC was closed"
            );
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
    })
}

#[tokio::test(start_paused = true)]
async fn a_plc_polling_every_second_is_never_evicted_by_a_burst_of_newcomers() {
    let keys = "max_connections = 4\nmax_connections_per_address = 0";
    let gateway = start(&sim_config_with_server(keys, "")).await;
    let plc = plc_polling_every_second(&gateway, 20).await;
    // Between two polls, each second, a burst of newcomers, more than there are slots; some
    // send a request, some nothing.
    let mut newcomers = Vec::new();
    for second in 0..20u16 {
        tokio::time::sleep(Duration::from_millis(500)).await;
        for i in 0..6u16 {
            let mut newcomer = RawMaster::connect(addr(&gateway)).await;
            if i % 2 == 0 {
                newcomer.send(second * 10 + i, NO_ROUTE_UNIT, &READ_1).await;
            }
            newcomers.push(newcomer);
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    within("the PLC polls twenty times", plc)
        .await
        .expect("the PLC was never closed");
    let scrape = Scrape::of(&gateway).await;
    assert!(
        scrape.value(EVICTED) > 0.0,
        "newcomers made room for each other"
    );
}

/// By an attacker keeping its connections fresh.
#[tokio::test(start_paused = true)]
async fn a_plc_polling_every_second_is_never_evicted_by_fresh_attacker_connections() {
    let keys = "max_connections = 20\nmax_connections_per_address = 0";
    let gateway = start(&sim_config_with_server(keys, "")).await;
    let plc = plc_polling_every_second(&gateway, 15).await;
    // 19 connections, each answered every 300 ms, cheaply: every slot is taken.
    let mut attackers = Vec::new();
    for _ in 0..19 {
        attackers.push(RawMaster::connect(addr(&gateway)).await);
    }
    let gateway_addr = addr(&gateway);
    let attack = tokio::spawn(async move {
        for round in 0..60u16 {
            let mut fresh = Vec::new();
            for mut attacker in attackers.drain(..) {
                if attacker
                    .try_call(round, NO_ROUTE_UNIT, &READ_1)
                    .await
                    .is_some()
                {
                    fresh.push(attacker);
                }
            }
            attackers = fresh;
            // And a newcomer each round, which would close the connection idle longest; kept
            // fresh too if it gets in.
            let mut newcomer = RawMaster::connect(gateway_addr).await;
            if newcomer
                .try_call(round, NO_ROUTE_UNIT, &READ_1)
                .await
                .is_some()
            {
                attackers.push(newcomer);
            }
            tokio::time::sleep(Duration::from_millis(300)).await;
        }
    });
    within("the PLC polls fifteen times", plc)
        .await
        .expect("the PLC was never closed");
    attack.abort();
    let scrape = Scrape::of(&gateway).await;
    assert!(
        scrape.value(REFUSED_FULL) > 0.0,
        "the newcomers were refused instead"
    );
}

#[tokio::test]
async fn connections_beyond_max_connections_per_address_are_refused_at_accept_and_counted() {
    let keys = "max_connections_per_address = 2";
    let gateway = start(&sim_config_with_server(keys, "")).await;
    let per_address = "modbus_gateway_tcp_connections_rejected_total{protocol=\"tcp\",\
                       reason=\"max_connections_per_address\"}";
    assert_eq!(Scrape::of(&gateway).await.value(per_address), 0.0);
    let mut one = RawMaster::connect_from([127, 0, 0, 3], addr(&gateway)).await;
    let mut two = RawMaster::connect_from([127, 0, 0, 3], addr(&gateway)).await;
    let mut three = RawMaster::connect_from([127, 0, 0, 3], addr(&gateway)).await;
    assert!(three.is_closed().await, "a third from one address");
    let mut other = RawMaster::connect_from([127, 0, 0, 4], addr(&gateway)).await;
    for (tid, master) in [&mut one, &mut two, &mut other].into_iter().enumerate() {
        assert_eq!(
            master.call(tid as u16, 1, &READ_1).await,
            [0x03, 0x02, 0, 0]
        );
    }
    // One closes: the address has room again.
    drop(one);
    let reply = within("a freed place is reused", async {
        loop {
            let mut again = RawMaster::connect_from([127, 0, 0, 3], addr(&gateway)).await;
            if let Some(reply) = again.try_call(9, 1, &READ_1).await {
                return reply;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    assert_eq!(reply, [0x03, 0x02, 0, 0]);
    let scrape = Scrape::of(&gateway).await;
    assert!(scrape.value(per_address) >= 1.0);
    assert_eq!(scrape.value(REFUSED_FULL), 0.0);
}

/// Read 125 holding registers of unit 1: a 259-byte reply, from the cache after the first.
const READ_125: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x7D];

/// A master on its own host that sends reads as fast as the gateway takes them and never reads
/// a reply; the task ends, with the time, once its connection has been closed under it.
async fn never_reading(source: [u8; 4], gateway: &Gateway) -> tokio::task::JoinHandle<Duration> {
    let socket = tokio::net::TcpSocket::new_v4().expect("a socket");
    socket.bind(SocketAddr::from((source, 0))).expect("bind");
    // A small window, so that a few replies fill it.
    socket.set_recv_buffer_size(4096).expect("SO_RCVBUF");
    let mut stream = within("connect", socket.connect(addr(gateway)))
        .await
        .expect("accepted");
    let started = tokio::time::Instant::now();
    tokio::spawn(async move {
        let requests: Vec<u8> = (0..64u16)
            .flat_map(|tid| RawMaster::adu(tid, 1, &READ_125))
            .collect();
        while stream.write_all(&requests).await.is_ok() {}
        started.elapsed()
    })
}

/// A master that never reads its replies.
#[tokio::test(start_paused = true)]
async fn a_non_reading_master_is_closed_after_frame_timeout_and_newcomers_are_admitted() {
    let frame_timeout = Duration::from_secs(10);
    let keys = "max_connections = 4\nmax_connections_per_address = 0\nframe_timeout = \"10s\"";
    let cached = "[[bus.slave]]\naddress = 1\ncache = \"1h\"";
    let gateway = start(&sim_config_with_server(keys, cached)).await;
    let mut stalled = Vec::new();
    for host in 10..14 {
        stalled.push(never_reading([127, 0, 0, host], &gateway).await);
    }
    // Every slot is taken, and every session waits for its master to read.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let mut newcomer = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        newcomer.try_call(1, 1, &READ_1).await.as_deref(),
        Some(&[0x03, 0x02, 0, 0][..]),
        "a newcomer is served: a session blocked in a write made room"
    );
    let mut closed_after = Vec::new();
    for master in stalled {
        closed_after.push(within("closed", master).await.expect("writer task"));
    }
    closed_after.sort();
    // One made room; the others were closed a frame timeout after their writes blocked
    // (within the first two seconds).
    assert!(closed_after[0] < Duration::from_secs(3), "{closed_after:?}");
    for after in &closed_after[1..] {
        assert!(
            (frame_timeout..frame_timeout + Duration::from_secs(2)).contains(after),
            "{closed_after:?}"
        );
    }
    let scrape = Scrape::of(&gateway).await;
    let write_timeout =
        "modbus_gateway_tcp_connections_closed_total{protocol=\"tcp\",reason=\"write_timeout\"}";
    assert_eq!(scrape.value(write_timeout), 3.0);
    assert_eq!(scrape.value(EVICTED), 1.0);
    assert_eq!(
        newcomer.call(2, 1, &READ_1).await,
        [0x03, 0x02, 0, 0],
        "the newcomer is still served"
    );
}
