//! Access control: `server.allow` refuses masters at accept, `server.read_only` keeps masters'
//! writes off the line. Both logged and counted.

use crate::support::{addr, sim_config_with_server, start, RawMaster, Scrape};
use modbus_gateway::testing::sim::Source;

const READ_1: [u8; 5] = [0x03, 0x00, 0x01, 0x00, 0x01];

#[tokio::test]
async fn masters_outside_server_allow_are_refused_at_accept_and_counted() {
    let gateway = start(&sim_config_with_server(
        "allow = [\"10.0.0.0/8\", \"::1\"]",
        "",
    ))
    .await;
    let mut outsider = RawMaster::connect(addr(&gateway)).await;
    assert!(outsider.is_closed().await, "127.0.0.1 is not allowed");
    let scrape = Scrape::of(&gateway).await;
    let refused =
        "modbus_gateway_tcp_connections_rejected_total{protocol=\"tcp\",reason=\"not_allowed\"}";
    assert_eq!(scrape.value(refused), 1.0);
    assert_eq!(
        scrape.value("modbus_gateway_tcp_connections_accepted_total{protocol=\"tcp\"}"),
        0.0
    );

    // The same master, once its network is listed (as one comma-separated string).
    let gateway = start(&sim_config_with_server(
        "allow = \"10.0.0.0/8, 127.0.0.0/8\"",
        "",
    ))
    .await;
    let mut insider = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(insider.call(1, 1, &READ_1).await, [0x03, 0x02, 0, 0]);
}

#[tokio::test]
async fn read_only_masters_read_but_anything_else_gets_0x01_and_never_reaches_the_line() {
    let gateway = start(&sim_config_with_server("read_only = [\"127.0.0.1\"]", "")).await;
    let line = gateway.sim_line("sim").expect("a sim line");
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ_1).await, [0x03, 0x02, 0, 0]);
    let refused: [&[u8]; 4] = [
        // Write single register 1 = 0x1234.
        &[0x06, 0x00, 0x01, 0x12, 0x34],
        // Write multiple registers: register 1, one register, two bytes, 0x1234.
        &[0x10, 0x00, 0x01, 0x00, 0x01, 0x02, 0x12, 0x34],
        // Diagnostics 01: restart communications.
        &[0x08, 0x00, 0x01, 0x00, 0x00],
        // A user-defined function code: it may do anything.
        &[0x41, 0x00],
    ];
    for (tid, pdu) in (2..).zip(refused) {
        assert_eq!(
            master.call(tid, 1, pdu).await,
            [pdu[0] | 0x80, 0x01],
            "{pdu:02X?}"
        );
    }
    // Still 0: the write never happened, and only the two reads went on the wire.
    assert_eq!(master.call(9, 1, &READ_1).await, [0x03, 0x02, 0, 0]);
    let sent: Vec<u8> = line
        .frames()
        .iter()
        .filter(|f| f.from == Source::Master)
        .map(|f| f.bytes[1])
        .collect();
    assert_eq!(sent, [0x03, 0x03]);

    let scrape = Scrape::of(&gateway).await;
    // A function code the gateway does not know is counted as `other`.
    for function in ["0x06", "0x10", "0x08", "other"] {
        let series = format!(
            "modbus_gateway_requests_total{{bus=\"sim\",function=\"{function}\",outcome=\"read_only\",protocol=\"tcp\",slave=\"1\"}}"
        );
        assert_eq!(scrape.value(&series), 1.0, "{series}");
    }
    let exceptions =
        "modbus_gateway_exceptions_total{bus=\"sim\",code=\"0x01\",slave=\"1\",source=\"gateway\"}";
    assert_eq!(scrape.value(exceptions), 4.0);
}

#[tokio::test]
async fn a_master_outside_read_only_may_write() {
    let gateway = start(&sim_config_with_server(
        "read_only = [\"192.168.0.0/16\"]",
        "",
    ))
    .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let write = [0x06, 0x00, 0x01, 0x12, 0x34];
    assert_eq!(master.call(1, 1, &write).await, write);
    assert_eq!(master.call(2, 1, &READ_1).await, [0x03, 0x02, 0x12, 0x34]);
}
