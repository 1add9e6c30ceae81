//! A serial master port over its life in a running gateway, on real ptys: a UART missing at
//! start is opened once it appears and its master served; the port and its master are on
//! `/status` and its frames on the trace; a `pty:` port's link is there while the gateway runs
//! and gone once it stops.

use crate::support::{
    http_get, rtu, sim_line, start, within, Accepter, GatewayConfig, Scrape, Ser2net, TempDir,
};
use std::path::Path;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};

/// Read two holding registers from 0 of `unit`.
const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x02];

/// A gateway with register slaves 1-4 on a simulated line and one serial master port `scada` on
/// `device`.
async fn gateway_with_port(device: &str) -> modbus_gateway::Gateway {
    let port = format!(
        "[[server.serial]]\nname = \"scada\"\ndevice = \"{device}\"\nparity = \"none\"\n\
         reopen_delay = \"20ms\"\n"
    );
    let config = GatewayConfig::new()
        .listen("127.0.0.1:0")
        .server_table(&port)
        .bus(sim_line().sim_slaves("1-4"))
        .to_toml();
    start(&config).await
}

/// Send `request` on the master's end and read a reply of `len` bytes.
async fn exchange(master: &mut SerialStream, request: &[u8], len: usize) -> Vec<u8> {
    master.write_all(request).await.unwrap();
    let mut reply = vec![0u8; len];
    within("the port's reply", master.read_exact(&mut reply))
        .await
        .unwrap();
    reply
}

async fn port_up(gateway: &modbus_gateway::Gateway) -> f64 {
    Scrape::of(gateway)
        .await
        .value("modbus_gateway_serial_port_up{port=\"scada\"}")
}

#[tokio::test]
async fn a_uart_missing_at_start_is_served_once_it_appears_and_is_on_the_status_page() {
    let dir = TempDir::new("serial-port-uart");
    let device = dir.join("ttyS9");
    let gateway = gateway_with_port(device.to_str().unwrap()).await;
    assert_eq!(port_up(&gateway).await, 0.0);
    // The device appears: the far end of a pty pair, the gateway's UART.
    let (mut master, tty) = SerialStream::pair().expect("pty pair");
    std::os::unix::fs::symlink(tty.name().unwrap(), &device).unwrap();
    within("the port opens", async {
        while port_up(&gateway).await != 1.0 {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    let reply = exchange(&mut master, &rtu(1, &READ), 9).await;
    assert_eq!(reply, rtu(1, &[0x03, 0x04, 0, 0, 0, 0]));

    let (code, body) = http_get(gateway.metrics_addr(), "/status").await;
    assert_eq!(code, 200);
    let status: serde_json::Value = serde_json::from_str(&body).unwrap();
    let port = &status["serial_ports"][0];
    assert_eq!(port["name"], "scada");
    assert_eq!(port["device"], device.to_str().unwrap());
    assert_eq!(port["format"], "19200 8N2");
    assert_eq!(
        (port["up"].clone(), port["requests"]["answered"].clone()),
        (true.into(), 1.into())
    );
    let masters = status["masters"].as_array().unwrap();
    let serial = masters
        .iter()
        .find(|m| m["address"] == "serial:scada")
        .unwrap_or_else(|| panic!("{masters:?}"));
    assert_eq!(
        (serial["protocol"].clone(), serial["requests"].clone()),
        ("serial".into(), 1.into())
    );
    drop(tty);
    gateway.shutdown().await;
}

#[tokio::test]
async fn a_pty_port_is_linked_while_the_gateway_runs_and_unlinked_when_it_stops() {
    let dir = TempDir::new("serial-port-pty");
    let link = dir.join("scada");
    let gateway = gateway_with_port(&format!("pty:{}", link.display())).await;
    within("the link", async {
        while !Path::new(&link).exists() {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    // Local software opens the link like any serial port.
    let mut master = tokio_serial::new(link.to_str().unwrap(), 19_200)
        .open_native_async()
        .expect("the pty opens");
    master.set_exclusive(false).unwrap();
    let reply = exchange(&mut master, &rtu(2, &READ), 9).await;
    assert_eq!(reply, rtu(2, &[0x03, 0x04, 0, 0, 0, 0]));
    gateway.shutdown().await;
    assert!(
        std::fs::symlink_metadata(&link).is_err(),
        "{} outlived the gateway",
        link.display()
    );
}

/// The master sits behind a serial device server (ser2net on the far end of its pty): the port
/// connects to it as a bus connects to one, raw or RFC 2217, and serves the master through it.
#[tokio::test]
async fn a_master_behind_a_device_server_is_served_over_raw_tcp_and_rfc_2217() {
    for accepter in [Accepter::Raw, Accepter::Rfc2217] {
        let (mut master, tty) = SerialStream::pair().expect("pty pair");
        let device = tty.name().unwrap();
        let Some(ser2net) = Ser2net::start(&device, "19200n82", accepter).await else {
            return;
        };
        let gateway = gateway_with_port(&ser2net.device()).await;
        within("the port connects", async {
            while port_up(&gateway).await != 1.0 {
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        })
        .await;
        let reply = exchange(&mut master, &rtu(3, &READ), 9).await;
        assert_eq!(
            reply,
            rtu(3, &[0x03, 0x04, 0, 0, 0, 0]),
            "{}",
            ser2net.device()
        );
        gateway.shutdown().await;
        drop(tty);
    }
}
