//! The Modbus TCP side, and masters that abuse it: pipelining and pipelined floods, malformed
//! and lying MBAP headers, garbage, half-sent requests, the connection limit and its policies,
//! the idle timeout, keepalive.

use crate::support::{addr, panics_on_this_thread, start, start_sim, within, RawMaster};
use modbus_gateway::bus::{Bus, Device};
use modbus_gateway::dispatch::{Client, Dispatcher, Rights};
use modbus_gateway::metrics::Metrics;
use modbus_gateway::routing::Router;
use modbus_gateway::shutdown::Stopping;
use modbus_gateway::sim::{RegisterBank, SimLine};
use modbus_gateway::tcp::session::{self, Activity, SessionError};
use modbus_gateway::tcp::SessionLimits;
use modbus_gateway::Config;
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

#[tokio::test]
async fn with_when_full_refuse_connections_beyond_max_connections_are_refused_and_a_freed_slot_is_reused(
) {
    let gateway = start(&crate::support::sim_config("").replace(
        "listen = \"127.0.0.1:0\"\n",
        "listen = \"127.0.0.1:0\"\nmax_connections = 3\nwhen_full = \"refuse\"\n",
    ))
    .await;
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
    let config =
        Config::from_toml_str("[[bus]]\nname = \"line\"\ndevice = \"sim\"\nbaud = 9600\n").unwrap();
    let line = SimLine::new(config.bus[0].line_timing());
    line.add_slave(1, RegisterBank::new(slave_delay));
    let metrics = Arc::new(Metrics::new());
    let bus = Bus::new(config.bus[0].clone(), Device::Sim(line), &metrics);
    let dispatcher = Dispatcher::new(Router::new(&config), vec![bus.handle()], metrics);
    tokio::spawn(bus.run(Stopping::never()));
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
