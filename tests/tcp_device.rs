//! A Modbus TCP device behind the gateway (`framing = "tcp"` on `device = "tcp://..."`): many
//! masters, one connection to the device, no crossed reply. Against pymodbus's Modbus TCP server,
//! and against devices written here to misbehave as real ones do: one connection only, a late
//! answer, a device that ignores requests right after a connect, wrong transaction ids, a
//! restart, a close every few requests.

use crate::support::device::{answer_each_after, answer_to, read};
use crate::support::{addr, within, Bus, GatewayConfig, RawMaster, Scrape};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// One request as the device reads it: transaction id, unit, PDU.
type Request = (u16, u8, Vec<u8>);

/// The next MBAP request on `socket`.
async fn next_request(socket: &mut TcpStream) -> Option<Request> {
    let mut header = [0u8; 7];
    socket.read_exact(&mut header).await.ok()?;
    assert_eq!(header[2..4], [0, 0], "protocol id 0");
    let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
    let mut pdu = vec![0u8; length - 1];
    socket.read_exact(&mut pdu).await.ok()?;
    Some((u16::from_be_bytes([header[0], header[1]]), header[6], pdu))
}

/// The MBAP frame of `pdu` from `unit` in transaction `transaction`.
fn reply(transaction: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    crate::support::mbap(transaction, unit, pdu)
}

/// Answer every read `socket` brings with [`answer_to`], until it closes.
async fn answer_every_read(socket: &mut TcpStream) {
    while let Some((transaction, unit, pdu)) = next_request(socket).await {
        let frame = reply(transaction, unit, &answer_to(&pdu));
        if socket.write_all(&frame).await.is_err() {
            return;
        }
    }
}

/// A gateway whose one bus `dev` is the Modbus TCP device at `port`, with `keys` added.
async fn gateway_on(port: u16, keys: &str) -> modbus_gateway::Gateway {
    GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(
            Bus::on("dev", &format!("tcp://127.0.0.1:{port}"))
                .framing("tcp")
                .response_timeout("200ms")
                .text(keys),
        )
        .start()
        .await
}

/// A device that answers every read with [`answer_to`], each connection in its own task;
/// counts its connections.
async fn answering_device() -> (u16, Arc<AtomicUsize>) {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let connections = Arc::new(AtomicUsize::new(0));
    let count = connections.clone();
    tokio::spawn(async move {
        while let Ok((mut socket, _)) = server.accept().await {
            count.fetch_add(1, Ordering::SeqCst);
            tokio::spawn(async move {
                answer_every_read(&mut socket).await;
            });
        }
    });
    (port, connections)
}

#[tokio::test]
async fn many_masters_share_one_connection_to_the_device_and_each_gets_its_own_answer() {
    let (port, connections) = answering_device().await;
    let gateway = gateway_on(port, "").await;
    let mut masters = Vec::new();
    for m in 0..10u16 {
        let addr = addr(&gateway);
        masters.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(addr).await;
            for n in 0..20u16 {
                let register = m * 100 + n;
                assert_eq!(
                    master.call(n, 1, &read(register)).await,
                    answer_to(&read(register))
                );
            }
        }));
    }
    for master in masters {
        within("a master's 20 reads", master).await.unwrap();
    }
    assert_eq!(
        connections.load(Ordering::SeqCst),
        1,
        "one connection to the device"
    );
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value(
            "modbus_gateway_bus_info{bus=\"dev\",format=\"none\",framing=\"tcp\",mode=\"master\",transport=\"tcp\"}"
        ),
        1.0
    );
}

/// A device that serves one connection at a time, as many inverters and meters do: while one is
/// open, another is accepted and closed at once. Returns its port and how many it closed so.
async fn one_connection_device() -> (u16, Arc<AtomicUsize>) {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let refused = Arc::new(AtomicUsize::new(0));
    let count = refused.clone();
    let busy = Arc::new(std::sync::atomic::AtomicBool::new(false));
    tokio::spawn(async move {
        while let Ok((mut socket, _)) = server.accept().await {
            if busy.swap(true, Ordering::SeqCst) {
                count.fetch_add(1, Ordering::SeqCst);
                continue;
            }
            let busy = busy.clone();
            tokio::spawn(async move {
                answer_every_read(&mut socket).await;
                busy.store(false, Ordering::SeqCst);
            });
        }
    });
    (port, refused)
}

/// A device that accepts one connection.
#[tokio::test]
async fn a_one_connection_device_serves_every_master_through_the_gateways_one() {
    let (port, refused) = one_connection_device().await;
    let gateway = gateway_on(port, "").await;
    let mut masters = Vec::new();
    for m in 0..5u16 {
        let addr = addr(&gateway);
        masters.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(addr).await;
            for n in 0..10u16 {
                let register = m * 100 + n;
                assert_eq!(
                    master.call(n, 1, &read(register)).await,
                    answer_to(&read(register))
                );
            }
        }));
    }
    for master in masters {
        within("a master's 10 reads", master).await.unwrap();
    }
    assert_eq!(refused.load(Ordering::SeqCst), 0, "connections refused");
    // A master going to the device on its own is turned away: the gateway holds the one.
    let mut direct = RawMaster::connect(([127, 0, 0, 1], port).into()).await;
    assert!(direct.is_closed().await, "a second connection is closed");
    assert_eq!(refused.load(Ordering::SeqCst), 1);
}

#[tokio::test]
async fn unit_0_and_unit_255_are_units_of_the_device_not_a_broadcast() {
    let (port, _) = answering_device().await;
    let gateway = gateway_on(port, "").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // A read to unit 0 would be refused on a serial line (0x01: no reply comes to a broadcast).
    assert_eq!(master.call(1, 0, &read(4)).await, answer_to(&read(4)));
    assert_eq!(master.call(2, 255, &read(5)).await, answer_to(&read(5)));
}

#[tokio::test]
async fn a_late_answer_is_discarded_and_every_master_after_it_gets_its_own() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = gateway_on(port, "").await;
    let (mut socket, _) = server.accept().await.unwrap();
    let device = tokio::spawn(async move {
        // The first request is answered 300 ms late (its timeout is 200 ms), while the next
        // one waits in the socket; every later one at once.
        let (transaction, unit, pdu) = next_request(&mut socket).await.unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        socket
            .write_all(&reply(transaction, unit, &answer_to(&pdu)))
            .await
            .unwrap();
        answer_every_read(&mut socket).await;
    });
    let addr = addr(&gateway);
    let mut late = RawMaster::connect(addr).await;
    late.send(1, 1, &read(100)).await;
    tokio::time::sleep(Duration::from_millis(20)).await;
    let mut masters = Vec::new();
    for m in 1..=3u16 {
        masters.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(addr).await;
            let register = 100 + m;
            assert_eq!(
                master.call(m, 1, &read(register)).await,
                answer_to(&read(register))
            );
        }));
    }
    assert_eq!(late.recv().await.pdu, [0x83, 0x0B]);
    for master in masters {
        within("the masters after the late one", master)
            .await
            .unwrap();
    }
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_discarded_frames_total{bus=\"dev\"}"),
        1.0,
        "the late answer, discarded"
    );
    device.abort();
}

#[tokio::test]
async fn a_reply_with_another_transaction_id_never_answers_and_the_request_gets_0x0b() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = gateway_on(port, "").await;
    let (mut socket, _) = server.accept().await.unwrap();
    let device = tokio::spawn(async move {
        // Firmware that always answers transaction 0.
        while let Some((_, unit, pdu)) = next_request(&mut socket).await {
            socket
                .write_all(&reply(0, unit, &answer_to(&pdu)))
                .await
                .unwrap();
        }
    });
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(7, 1, &read(3)).await, [0x83, 0x0B]);
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_discarded_frames_total{bus=\"dev\"}"),
        1.0
    );
    device.abort();
}

/// A device that ignores requests right after a connect.
#[tokio::test]
async fn a_device_deaf_right_after_a_connect_is_served_with_connect_delay() {
    let ignoring = |server: TcpListener| {
        tokio::spawn(async move {
            let (mut socket, _) = server.accept().await.unwrap();
            let connected = tokio::time::Instant::now();
            while let Some((transaction, unit, pdu)) = next_request(&mut socket).await {
                // Like an inverter's dongle: nothing in the first 200 ms after the connect.
                if connected.elapsed() < Duration::from_millis(200) {
                    continue;
                }
                let frame = reply(transaction, unit, &answer_to(&pdu));
                socket.write_all(&frame).await.unwrap();
            }
        })
    };
    for (delay, expected) in [("0ms", vec![0x83, 0x0B]), ("300ms", answer_to(&read(9)))] {
        let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = server.local_addr().unwrap().port();
        let device = ignoring(server);
        let gateway = gateway_on(port, &format!("connect_delay = \"{delay}\"\n")).await;
        let mut master = RawMaster::connect(addr(&gateway)).await;
        assert_eq!(
            master.call(1, 1, &read(9)).await,
            expected,
            "connect_delay {delay}"
        );
        device.abort();
    }
}

#[tokio::test]
async fn a_device_restarted_mid_traffic_gives_0x0a_then_is_served_after_reconnect() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = gateway_on(port, "reopen_delay = \"50ms\"\n").await;
    let (mut socket, _) = server.accept().await.unwrap();
    // The device takes the request and goes away without answering.
    let device = tokio::spawn(async move {
        let _ = next_request(&mut socket).await;
        drop(socket);
        drop(server);
    });
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &read(1)).await, [0x83, 0x0A]);
    device.await.unwrap();
    let server = TcpListener::bind(("127.0.0.1", port)).await.unwrap();
    let (mut socket, _) = within("the gateway reconnects", server.accept())
        .await
        .unwrap();
    let device = tokio::spawn(async move {
        answer_every_read(&mut socket).await;
    });
    crate::support::wait_for_bus(&gateway, "dev", true).await;
    assert_eq!(master.call(2, 1, &read(2)).await, answer_to(&read(2)));
    device.abort();
}

/// Through `gateway`, pymodbus's device 1 (holding registers 0-19 at 7) answers a read, a write,
/// the read that shows it, and a read past its registers (exception 02), byte for byte.
async fn answers_as_pymodbus_device_1(gateway: &modbus_gateway::Gateway) {
    let mut master = RawMaster::connect(addr(gateway)).await;
    let cases: [(&[u8], &[u8]); 4] = [
        (
            &[0x03, 0x00, 0x00, 0x00, 0x02],
            &[0x03, 0x04, 0x00, 0x07, 0x00, 0x07],
        ),
        (
            &[0x06, 0x00, 0x01, 0x12, 0x34],
            &[0x06, 0x00, 0x01, 0x12, 0x34],
        ),
        (
            &[0x03, 0x00, 0x00, 0x00, 0x02],
            &[0x03, 0x04, 0x00, 0x07, 0x12, 0x34],
        ),
        (&[0x03, 0x00, 0x30, 0x00, 0x01], &[0x83, 0x02]),
    ];
    for (transaction, (request, answer)) in (1..).zip(cases) {
        assert_eq!(
            master.call(transaction, 1, request).await,
            answer,
            "{request:02X?}"
        );
    }
}

#[tokio::test]
async fn pymodbus_tcp_server_answers_masters_through_the_gateway_byte_for_byte() {
    let Some((_server, port)) = crate::device_link::pymodbus_tcp_server().await else {
        return;
    };
    let gateway = gateway_on(port, "").await;
    answers_as_pymodbus_device_1(&gateway).await;
}

/// The log names it with the key that helps.
#[tokio::test]
async fn a_device_always_answering_transaction_0_is_logged_with_the_key_that_helps() {
    use crate::support::{connect_when_listening, exit_status, free_addr, signal};
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let device = tokio::spawn(async move {
        let (mut socket, _) = server.accept().await.unwrap();
        while let Some((_, unit, pdu)) = next_request(&mut socket).await {
            socket
                .write_all(&reply(0, unit, &answer_to(&pdu)))
                .await
                .unwrap();
        }
    });
    let (listen, metrics) = (free_addr(), free_addr());
    let config = GatewayConfig::new()
        .listen(listen)
        .metrics_listen(metrics)
        .bus(
            Bus::on("dev", &format!("tcp://127.0.0.1:{port}"))
                .framing("tcp")
                .response_timeout("200ms"),
        )
        .to_toml();
    let dir = std::env::temp_dir();
    let path = dir.join(format!("mbgw-tid0-{}.toml", std::process::id()));
    let log = dir.join(format!("mbgw-tid0-{}.log", std::process::id()));
    std::fs::write(&path, config).unwrap();
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_modbus-gateway"))
        .args(["--config", path.to_str().unwrap(), "run"])
        .env_remove("RUST_LOG")
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut master = connect_when_listening(listen).await;
    for transaction in 1..=2 {
        assert_eq!(master.call(transaction, 1, &read(3)).await, [0x83, 0x0B]);
    }
    signal(&child, "TERM");
    assert!(exit_status(child).await.success());
    let text = std::fs::read_to_string(&log).unwrap();
    let told: Vec<&str> = text
        .lines()
        .filter(|line| line.contains("match_transaction_id = false"))
        .collect();
    assert_eq!(told.len(), 1, "once per connection: {text}");
    assert!(
        told[0].contains("WARN") && told[0].contains("sent=1 got=0"),
        "{}",
        told[0]
    );
    device.abort();
    let _ = std::fs::remove_file(path);
    let _ = std::fs::remove_file(log);
}

#[tokio::test]
async fn matched_by_order_such_a_device_is_served_and_a_timeout_resets_its_connection() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let connections = Arc::new(AtomicUsize::new(0));
    let count = connections.clone();
    let device = tokio::spawn(async move {
        while let Ok((mut socket, _)) = server.accept().await {
            let first = count.fetch_add(1, Ordering::SeqCst) == 0;
            tokio::spawn(async move {
                let mut n = 0;
                while let Some((_, unit, pdu)) = next_request(&mut socket).await {
                    n += 1;
                    // Always transaction 0; on the first connection the second answer is late.
                    if first && n == 2 {
                        tokio::time::sleep(Duration::from_millis(300)).await;
                    }
                    if socket
                        .write_all(&reply(0, unit, &answer_to(&pdu)))
                        .await
                        .is_err()
                    {
                        break;
                    }
                }
            });
        }
    });
    let gateway = gateway_on(
        port,
        "match_transaction_id = false\nreopen_delay = \"50ms\"\n",
    )
    .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &read(1)).await, answer_to(&read(1)));
    assert_eq!(master.call(2, 1, &read(2)).await, [0x83, 0x0B], "late");
    // The late answer to register 2 would pass for the next request's: the connection is made
    // anew instead, and the next read gets register 3's own answer.
    within("the gateway reconnects", async {
        while connections.load(Ordering::SeqCst) < 2 || gateway.bus_up("dev") != Some(true) {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    assert_eq!(master.call(3, 1, &read(3)).await, answer_to(&read(3)));
    device.abort();
}

/// Each answer carries its master's own id.
#[tokio::test]
async fn masters_choosing_the_same_transaction_ids_each_get_their_own_answer() {
    let (port, _) = answering_device().await;
    let gateway = gateway_on(port, "").await;
    let addr = addr(&gateway);
    let mut masters = Vec::new();
    for m in 0..4u16 {
        masters.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(addr).await;
            for n in 0..25u16 {
                // Every master counts its transactions from 1, as most do: the ids collide, and
                // the gateway's own ids towards the device keep the answers apart.
                let register = 1000 * m + n;
                master.send(n + 1, 1, &read(register)).await;
                let got = master.recv().await;
                assert_eq!(
                    (got.transaction, got.pdu),
                    (n + 1, answer_to(&read(register)))
                );
            }
        }));
    }
    for master in masters {
        within("a master's 25 reads", master).await.unwrap();
    }
}

#[tokio::test]
async fn a_read_only_master_cannot_hide_a_write_to_the_device_after_a_read() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let seen = Arc::new(std::sync::Mutex::new(Vec::new()));
    let log = seen.clone();
    tokio::spawn(async move {
        let (mut socket, _) = server.accept().await.unwrap();
        while let Some((transaction, unit, pdu)) = next_request(&mut socket).await {
            log.lock().unwrap().push(pdu.clone());
            let answer = if pdu[0] == 0x03 {
                answer_to(&pdu)
            } else {
                pdu.clone()
            };
            socket
                .write_all(&reply(transaction, unit, &answer))
                .await
                .unwrap();
        }
    });
    let gateway = GatewayConfig::new()
        .listen("127.0.0.1:0")
        .read_only(&["127.0.0.1"])
        .bus(
            Bus::on("dev", &format!("tcp://127.0.0.1:{port}"))
                .framing("tcp")
                .response_timeout("200ms"),
        )
        .start()
        .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // A read with a whole MBAP write request after it, inside one request's PDU.
    let mut hidden = read(1);
    hidden.extend(reply(9, 1, &[0x06, 0x00, 0x01, 0xDE, 0xAD]));
    assert_eq!(master.call(1, 1, &hidden).await, [0x83, 0x03]);
    // A write outright: refused as ever.
    assert_eq!(
        master.call(2, 1, &[0x06, 0x00, 0x01, 0xDE, 0xAD]).await,
        [0x86, 0x01]
    );
    assert_eq!(master.call(3, 1, &read(1)).await, answer_to(&read(1)));
    assert_eq!(
        *seen.lock().unwrap(),
        [read(1)],
        "only the plain read reached the device"
    );
}

/// A Modbus/TCP Security device: a second gateway's TLS listener (mutual TLS, roles as
/// `tls_extra` sets them) in front of simulated slaves 1-4; and the CA that signed its
/// certificate.
async fn tls_device(tls_extra: &str) -> (crate::support::tls::Pki, modbus_gateway::Gateway) {
    let pki = crate::support::tls::Pki::new("device-ca");
    let server = pki.server("device", "device", 365);
    let toml = crate::support::sim_config_with_server(
        &format!(
            "listen_tls = \"127.0.0.1:0\"\n{}",
            pki.tls_table(&server, tls_extra)
        ),
        "",
    );
    let device = crate::support::start(&toml).await;
    (pki, device)
}

/// A gateway whose bus `dev` is the `tls://` device at `port`, presenting `client` and trusting
/// `ca`.
async fn gateway_on_tls(
    port: u16,
    client: &crate::support::tls::Issued,
    ca: &std::path::Path,
) -> modbus_gateway::Gateway {
    let tls = format!(
        "[bus.tls]\ncertificate = \"{}\"\nprivate_key = \"{}\"\nca = \"{}\"\n",
        client.cert_path.display(),
        client.key_path.display(),
        ca.display()
    );
    GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(
            Bus::on("dev", &format!("tls://127.0.0.1:{port}"))
                .framing("tcp")
                .response_timeout("1s")
                .key("reopen_delay", "100ms")
                .text(&tls),
        )
        .start()
        .await
}

/// A TLS device is served with the gateway's certificate; its role is the device's to apply.
#[tokio::test]
async fn a_tls_device_gets_the_gateways_certificate_and_applies_its_role_itself() {
    use crate::support::tls::Role;
    let (pki, device) = tls_device("roles = { viewer = \"read_only\" }").await;
    let port = device.tls_addrs()[0].port();
    // The gateway presents a certificate with the role `viewer`: the device lets it read only.
    let client = pki.master("gateway-client", Role::Named("viewer"));
    let gateway = gateway_on_tls(port, &client, &pki.ca_path).await;
    crate::support::wait_for_bus(&gateway, "dev", true).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x03, 0x02, 0x00, 0x00]
    );
    // The device refuses the write (0x01) and the gateway hands that on, byte for byte.
    assert_eq!(
        master.call(2, 1, &[0x06, 0x00, 0x00, 0x12, 0x34]).await,
        [0x86, 0x01]
    );
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value(
            "modbus_gateway_bus_info{bus=\"dev\",format=\"none\",framing=\"tcp\",mode=\"master\",transport=\"tls\"}"
        ),
        1.0
    );
}

#[tokio::test]
async fn a_tls_device_whose_certificate_does_not_chain_to_the_ca_is_never_spoken_to() {
    use crate::support::tls::Role;
    let (pki, device) = tls_device("").await;
    let port = device.tls_addrs()[0].port();
    let client = pki.master("gateway-client", Role::Without);
    // The gateway trusts another CA: the handshake fails, the bus stays down, masters get 0x0A.
    let other = crate::support::tls::Pki::new("other-ca");
    let gateway = gateway_on_tls(port, &client, &other.ca_path).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 1, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x83, 0x0A]
    );
    let scrape = Scrape::of(&gateway).await;
    assert!(scrape.value("modbus_gateway_port_open_errors_total{bus=\"dev\"}") >= 1.0);
    assert_eq!(scrape.value("modbus_gateway_port_up{bus=\"dev\"}"), 0.0);
}

#[tokio::test]
async fn a_tls_device_with_unreadable_files_stops_the_start_naming_each_key() {
    let config = GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(Bus::on("dev", "tls://127.0.0.1:802").framing("tcp").text(
            "[bus.tls]\ncertificate = \"/nonexistent/gw.crt\"\n\
                     private_key = \"/nonexistent/gw.key\"\nca = \"/nonexistent/ca.crt\"\n",
        ))
        .load();
    let error = modbus_gateway::Gateway::start(&config)
        .await
        .err()
        .expect("refused")
        .to_string();
    for key in [
        "bus[0].tls.certificate",
        "bus[0].tls.private_key",
        "bus[0].tls.ca",
    ] {
        assert!(error.contains(key), "{key}: {error}");
    }
}

#[tokio::test]
async fn pymodbus_tls_server_answers_masters_through_a_tls_bus() {
    use crate::support::tls::{Pki, Role};
    let pki = Pki::new("pymodbus-ca");
    let server = pki.server("pymodbus", "pymodbus", 365);
    let (cert, key, ca) = (
        server.cert_path.to_str().unwrap(),
        server.key_path.to_str().unwrap(),
        pki.ca_path.to_str().unwrap(),
    );
    let args = ["tls", cert, key, ca];
    let Some((_server, port)) = crate::device_link::pymodbus_tcp_server_with(&args).await else {
        return;
    };
    let client = pki.master("gateway-client", Role::Without);
    let gateway = gateway_on_tls(port, &client, &pki.ca_path).await;
    answers_as_pymodbus_device_1(&gateway).await;
}

/// A device on `server` that answers reads with [`answer_to`] and writes with their echo, and
/// logs every write's value; it goes away (connection and listener) once `stop_after` requests
/// have come in, if given.
fn logging_device(
    server: TcpListener,
    writes: Arc<std::sync::Mutex<Vec<u16>>>,
    stop_after: Option<usize>,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let (mut socket, _) = server.accept().await.unwrap();
        let mut seen = 0;
        while let Some((transaction, unit, pdu)) = next_request(&mut socket).await {
            seen += 1;
            if stop_after.is_some_and(|n| seen > n) {
                return;
            }
            let answer = if pdu[0] == 0x06 {
                writes
                    .lock()
                    .unwrap()
                    .push(u16::from_be_bytes([pdu[3], pdu[4]]));
                pdu.clone()
            } else {
                answer_to(&pdu)
            };
            if socket
                .write_all(&reply(transaction, unit, &answer))
                .await
                .is_err()
            {
                return;
            }
        }
    })
}

/// Restarted under traffic.
#[tokio::test]
async fn a_restarted_device_gives_0x0a_never_a_wrong_answer_and_no_write_twice() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let writes = Arc::new(std::sync::Mutex::new(Vec::new()));
    let first = logging_device(server, writes.clone(), Some(60));
    let gateway = gateway_on(
        port,
        "reopen_delay = \"50ms\"\nreopen_delay_max = \"100ms\"\n",
    )
    .await;
    let addr = addr(&gateway);
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    // Three readers of registers of their own, and a writer of 1, 2, 3... to register 9.
    let mut masters = Vec::new();
    for m in 0..4u16 {
        let stop = stop.clone();
        masters.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(addr).await;
            let (mut answered, mut unavailable) = (Vec::new(), 0);
            let mut n = 0u16;
            while !stop.load(Ordering::Relaxed) {
                n += 1;
                let request = if m == 3 {
                    vec![0x06, 0x00, 0x09, (n >> 8) as u8, n as u8]
                } else {
                    read(100 * m + n)
                };
                let expected = if m == 3 {
                    request.clone()
                } else {
                    answer_to(&request)
                };
                let got = within("an answer", master.call(n, 1, &request)).await;
                if got == expected {
                    answered.push(n);
                } else {
                    assert_eq!(got[1..], [0x0A], "master {m} request {n}: {got:02X?}");
                    unavailable += 1;
                }
            }
            (answered, unavailable)
        }));
    }
    // The device goes away after 60 requests; once the gateway has noticed, it comes back.
    first.await.unwrap();
    crate::support::wait_for_bus(&gateway, "dev", false).await;
    let server = TcpListener::bind(("127.0.0.1", port)).await.unwrap();
    let second = logging_device(server, writes.clone(), None);
    within("traffic resumes", async {
        let reopened = "modbus_gateway_port_reopens_total{bus=\"dev\"}";
        while Scrape::of(&gateway).await.value(reopened) < 1.0 {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    })
    .await;
    stop.store(true, Ordering::Relaxed);
    let mut unavailable = 0;
    let mut written = Vec::new();
    for (m, master) in masters.into_iter().enumerate() {
        let (answered, refused) = within("a master stops", master).await.unwrap();
        assert!(!answered.is_empty(), "master {m} was answered");
        unavailable += refused;
        if m == 3 {
            written = answered;
        }
    }
    assert!(unavailable >= 1, "someone met the outage");
    // Every write the writer saw answered was carried out once, and no write twice.
    let carried = writes.lock().unwrap().clone();
    let mut unique = carried.clone();
    unique.sort_unstable();
    unique.dedup();
    assert_eq!(
        unique.len(),
        carried.len(),
        "a write carried out twice: {carried:?}"
    );
    for n in written {
        assert!(
            carried.contains(&n),
            "write {n} was answered but never carried out"
        );
    }
    second.abort();
}

/// A device that answers every request `delay` after it came, several at once if they come so,
/// and keeps the most it ever had unanswered at once.
async fn slow_device(delay: Duration) -> (u16, Arc<AtomicUsize>) {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let most = Arc::new(AtomicUsize::new(0));
    let most_seen = most.clone();
    tokio::spawn(async move {
        let (socket, _) = server.accept().await.unwrap();
        answer_each_after(socket, delay, most_seen).await;
    });
    (port, most)
}

/// A device slower than one unit's timeout gets 0x0B for that unit.
#[tokio::test]
async fn a_slow_unit_gets_0x0b_and_its_late_answers_never_reach_another_unit() {
    // Every reply 150 ms after its request: within unit 2's 300 ms, past the bus's 100 ms.
    let (port, _) = slow_device(Duration::from_millis(150)).await;
    let gateway = GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(
            Bus::on("dev", &format!("tcp://127.0.0.1:{port}"))
                .framing("tcp")
                .response_timeout("100ms")
                .slave(2, &[("response_timeout", "300ms".into())]),
        )
        .start()
        .await;
    let mut fast = RawMaster::connect(addr(&gateway)).await;
    let mut patient = RawMaster::connect(addr(&gateway)).await;
    for n in 0..3u16 {
        // Unit 1's request times out; the late answer comes while unit 2's is outstanding.
        assert_eq!(fast.call(n, 1, &read(n)).await, [0x83, 0x0B]);
        let register = 100 + n;
        assert_eq!(
            patient.call(n, 2, &read(register)).await,
            answer_to(&read(register)),
            "unit 2 gets its own answer"
        );
    }
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_discarded_frames_total{bus=\"dev\"}"),
        3.0,
        "unit 1's three late answers"
    );
}

/// With `max_in_flight`, requests overlap at the device up to it.
#[tokio::test]
async fn max_in_flight_lets_requests_overlap_up_to_it_and_each_master_gets_its_own() {
    for in_flight in [1usize, 4] {
        let (port, most) = slow_device(Duration::from_millis(5)).await;
        let gateway = gateway_on(port, &format!("max_in_flight = {in_flight}\n")).await;
        let addr = addr(&gateway);
        let mut masters = Vec::new();
        for m in 0..8u16 {
            masters.push(tokio::spawn(async move {
                let mut master = RawMaster::connect(addr).await;
                for n in 0..10u16 {
                    let register = 100 * m + n;
                    let got = master.call(n, 1, &read(register)).await;
                    assert_eq!(got, answer_to(&read(register)), "max_in_flight {in_flight}");
                }
            }));
        }
        for master in masters {
            within("a master's reads", master).await.unwrap();
        }
        assert_eq!(
            most.load(Ordering::SeqCst),
            in_flight,
            "requests outstanding at the device at once"
        );
    }
}

#[tokio::test]
async fn pipelined_a_late_answer_is_discarded_and_a_read_is_retried_under_its_own_new_id() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    let gateway = gateway_on(port, "max_in_flight = 4\nretries = 1\n").await;
    let (mut socket, _) = server.accept().await.unwrap();
    let device = tokio::spawn(async move {
        // The first try of the first read goes unanswered until its retry has been answered:
        // then its late answer comes, under the first try's id.
        let (first_id, unit, first) = next_request(&mut socket).await.unwrap();
        let (retry_id, _, retried) = next_request(&mut socket).await.unwrap();
        assert_eq!(retried, first, "the retry is the same request");
        assert_ne!(retry_id, first_id, "under an id of its own");
        socket
            .write_all(&reply(retry_id, unit, &answer_to(&retried)))
            .await
            .unwrap();
        socket
            .write_all(&reply(first_id, unit, &[0x03, 0x02, 0xBA, 0xD0]))
            .await
            .unwrap();
        while let Some((transaction, unit, pdu)) = next_request(&mut socket).await {
            socket
                .write_all(&reply(transaction, unit, &answer_to(&pdu)))
                .await
                .unwrap();
        }
    });
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &read(7)).await, answer_to(&read(7)));
    assert_eq!(master.call(2, 1, &read(8)).await, answer_to(&read(8)));
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_discarded_frames_total{bus=\"dev\"}"),
        1.0
    );
    assert_eq!(
        scrape.value("modbus_gateway_retries_total{bus=\"dev\",slave=\"1\"}"),
        1.0
    );
    device.abort();
}

/// A relay on a free port in front of `target` that counts the connections made through it.
async fn counting_relay(target: u16) -> (u16, Arc<AtomicUsize>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let count = Arc::new(AtomicUsize::new(0));
    let counted = count.clone();
    tokio::spawn(async move {
        while let Ok((mut inbound, _)) = listener.accept().await {
            counted.fetch_add(1, Ordering::SeqCst);
            tokio::spawn(async move {
                let Ok(mut outbound) = TcpStream::connect(("127.0.0.1", target)).await else {
                    return;
                };
                let _ = tokio::io::copy_bidirectional(&mut inbound, &mut outbound).await;
            });
        }
    });
    (port, count)
}

/// At once.
#[tokio::test]
async fn pymodbus_and_mbpoll_masters_share_one_connection_to_a_pymodbus_tcp_server() {
    let Some((_server, device)) = crate::device_link::pymodbus_tcp_server().await else {
        return;
    };
    let Some(mbpoll) = crate::support::tool("mbpoll") else {
        return;
    };
    let python = crate::peers::python_with_pymodbus().expect("pymodbus, as the server runs");
    let (port, connections) = counting_relay(device).await;
    let gateway = gateway_on(port, "").await;
    let gateway_port = addr(&gateway).port().to_string();
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/peers/pymodbus_net_master.py"
    );
    let spawn = |program: std::ffi::OsString, args: Vec<String>| {
        tokio::task::spawn_blocking(move || {
            std::process::Command::new(program)
                .args(args)
                .output()
                .expect("the master runs")
        })
    };
    let pymodbus = spawn(
        python,
        [script, "tcp", "127.0.0.1", &gateway_port, "1"]
            .map(String::from)
            .to_vec(),
    );
    let mbpoll = spawn(
        mbpoll.into_os_string(),
        [
            "-m",
            "tcp",
            "-p",
            &gateway_port,
            "-a",
            "1",
            "-0",
            "-1",
            "-r",
            "10",
            "-c",
            "3",
            "127.0.0.1",
        ]
        .map(String::from)
        .to_vec(),
    );
    let raw = async {
        let mut master = RawMaster::connect(addr(&gateway)).await;
        for n in 0..20 {
            let got = master.call(n, 1, &[0x03, 0x00, 0x0A, 0x00, 0x01]).await;
            assert_eq!(got, [0x03, 0x02, 0x00, 0x07]);
        }
    };
    let (pymodbus, mbpoll, ()) = within("three masters at once", async {
        tokio::join!(pymodbus, mbpoll, raw)
    })
    .await;
    let pymodbus = String::from_utf8_lossy(&pymodbus.unwrap().stdout).into_owned();
    assert_eq!(
        pymodbus.lines().collect::<Vec<_>>(),
        ["result 6 ok", "result 3 4242 7", "result 3 7 7 7"],
        "{pymodbus}"
    );
    let mbpoll = mbpoll.unwrap();
    let text = String::from_utf8_lossy(&mbpoll.stdout);
    assert!(mbpoll.status.success(), "{text}");
    for register in 10..13 {
        assert!(text.contains(&format!("[{register}]: \t7")), "{text}");
    }
    assert_eq!(
        connections.load(Ordering::SeqCst),
        1,
        "one connection to the device"
    );
}

/// A device that closes the connection every five requests is reconnected.
#[tokio::test]
async fn a_device_hanging_up_every_five_requests_never_crosses_replies() {
    let server = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = server.local_addr().unwrap().port();
    tokio::spawn(async move {
        while let Ok((mut socket, _)) = server.accept().await {
            tokio::spawn(async move {
                for _ in 0..5 {
                    let Some((transaction, unit, pdu)) = next_request(&mut socket).await else {
                        return;
                    };
                    let frame = reply(transaction, unit, &answer_to(&pdu));
                    if socket.write_all(&frame).await.is_err() {
                        return;
                    }
                }
            });
        }
    });
    let gateway = gateway_on(
        port,
        "reopen_delay = \"20ms\"\nreopen_delay_max = \"20ms\"\n",
    )
    .await;
    let addr = addr(&gateway);
    let mut masters = Vec::new();
    for m in 0..3u16 {
        masters.push(tokio::spawn(async move {
            let mut master = RawMaster::connect(addr).await;
            // 0x0A while the gateway reconnects, else each read's own answer, until 15 answers.
            let (mut answered, mut n) = (0, 0u16);
            while answered < 15 {
                n += 1;
                let register = 100 * m + n % 100;
                let got = master.call(n, 1, &read(register)).await;
                if got == answer_to(&read(register)) {
                    answered += 1;
                } else {
                    assert_eq!(got, [0x83, 0x0A], "master {m} read {register}");
                    tokio::time::sleep(Duration::from_millis(5)).await;
                }
            }
        }));
    }
    for master in masters {
        within("every master answered 15 times", master)
            .await
            .unwrap();
    }
    let reopens = Scrape::of(&gateway)
        .await
        .value("modbus_gateway_port_reopens_total{bus=\"dev\"}");
    assert!(reopens >= 3.0, "reconnected after every close: {reopens}");
}
