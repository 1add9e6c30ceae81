//! The gateway as a service: a graceful stop that finishes the transaction on the wire and
//! answers what is queued, in-process and as the binary receiving SIGTERM.

use crate::support::{addr, http_get, start, within, RawMaster, Scrape};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// Write 5000 to holding register 0004H (the drives' manuals' worked example); echoed back.
const WRITE: [u8; 5] = [0x06, 0x00, 0x04, 0x13, 0x88];

/// One 115200 baud simulated line whose slave 1 takes `delay` to answer.
fn slow_line(delay: &str, shutdown_timeout: &str) -> String {
    format!(
        "[server]\nlisten = \"127.0.0.1:0\"\nshutdown_timeout = \"{shutdown_timeout}\"\n\
         [metrics]\nlisten = \"127.0.0.1:0\"\n\
         [[bus]]\nname = \"sim\"\ndevice = \"sim\"\nbaud = 115200\nresponse_timeout = \"5s\"\n\
         queue_timeout = \"30s\"\n\
         [[bus.sim_slave]]\naddress = 1\nprocessing_delay = \"{delay}\"\n"
    )
}

/// Wait until the bus has taken `n` requests off its queue (the last one is on the wire).
async fn until_taken(metrics: std::net::SocketAddr, n: f64) {
    within("the bus takes the request", async {
        loop {
            let (_, text) = http_get(metrics, "/metrics").await;
            let scrape = Scrape::parse(text);
            if scrape.get("modbus_gateway_queue_wait_seconds_count{bus=\"sim\"}") == Some(n) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
}

#[tokio::test]
async fn a_stop_serves_the_queue_until_the_timeout_then_answers_0x0a_and_closes() {
    // Each answer takes 1 s; the stop allows 1.5 s: the request on the wire and the next one
    // are served, the third would start after the deadline.
    let gateway = start(&slow_line("1s", "1500ms")).await;
    let metrics = gateway.metrics_addr();
    let modbus = addr(&gateway);
    let mut masters = Vec::new();
    for tid in 0..3u16 {
        let mut master = RawMaster::connect(modbus).await;
        master.send(tid, 1, &WRITE).await;
        masters.push(master);
        if tid == 0 {
            until_taken(metrics, 1.0).await;
        }
    }
    // All three are queued or on the wire when the stop comes.
    within("the other two are queued", async {
        loop {
            let scrape = Scrape::of(&gateway).await;
            if scrape.get("modbus_gateway_queue_depth{bus=\"sim\"}") == Some(2.0) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    let stopped = tokio::spawn(gateway.shutdown());
    let mut replies = Vec::new();
    for master in &mut masters {
        replies.push(master.recv().await.pdu);
    }
    assert_eq!(
        replies[0], WRITE,
        "the write on the wire is answered by the slave"
    );
    assert_eq!(
        replies[1], WRITE,
        "the next one started before the deadline"
    );
    assert_eq!(
        replies[2],
        [0x86, 0x0A],
        "the last one would have started after it"
    );
    for master in &mut masters {
        assert!(master.is_closed().await, "connections close once answered");
    }
    within("the gateway stops", stopped).await.unwrap();
    assert!(
        tokio::net::TcpStream::connect(modbus).await.is_err(),
        "no longer accepting"
    );
}

#[tokio::test]
async fn sigterm_while_a_write_is_on_the_wire_still_delivers_the_slaves_reply_and_exits_0() {
    let path = std::env::temp_dir().join(format!("mbgw-stop-{}.toml", std::process::id()));
    let listen = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let metrics = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let (listen_addr, metrics_addr) = (listen.local_addr().unwrap(), metrics.local_addr().unwrap());
    drop((listen, metrics));
    let config = slow_line("1s", "3s")
        .replacen("127.0.0.1:0", &listen_addr.to_string(), 1)
        .replacen("127.0.0.1:0", &metrics_addr.to_string(), 1);
    std::fs::write(&path, config).unwrap();
    let mut child = Command::new(BINARY)
        .args(["--config", path.to_str().unwrap(), "run"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut master = within("the gateway listens", async {
        loop {
            if let Ok(stream) = tokio::net::TcpStream::connect(listen_addr).await {
                drop(stream);
                return RawMaster::connect(listen_addr).await;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    master.send(1, 1, &WRITE).await;
    until_taken(metrics_addr, 1.0).await;
    let sent_term = Instant::now();
    let status = Command::new("kill")
        .args(["-s", "TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    assert_eq!(master.recv().await.pdu, WRITE, "the slave's own reply");
    assert!(master.is_closed().await);
    let status = within(
        "the gateway exits",
        tokio::task::spawn_blocking(move || child.wait()),
    )
    .await
    .unwrap()
    .unwrap();
    let _ = std::fs::remove_file(&path);
    assert_eq!(status.code(), Some(0));
    assert!(
        sent_term.elapsed() < Duration::from_secs(3),
        "exited {:?} after SIGTERM, past the 3 s shutdown timeout",
        sent_term.elapsed()
    );
}
