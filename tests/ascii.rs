//! Modbus ASCII on the line, end to end: masters on Modbus TCP, an ASCII bus on the simulated
//! line (9600 7E1), the wire's frames as the drive manuals print them, every function code the
//! same as on RTU, the fault knobs in ASCII, metrics and reload.

use crate::support::{addr, start, Bus, GatewayConfig, RawMaster, Scrape};
use modbus_gateway::gateway::load_config;
use modbus_gateway::Gateway;
use std::path::Path;

/// The simulated 9600 line `sim` framed `framing`, register slaves at 1-4, and `extra` keys on
/// the bus.
fn sim_line(framing: &str, extra: &str) -> Bus {
    Bus::sim("sim")
        .framing(framing)
        .baud(9600)
        .text(extra)
        .sim_slaves("1-4")
}

/// An ASCII bus `sim` with register slaves at 1-4, and `extra` keys on the bus.
fn ascii_config(extra: &str) -> String {
    GatewayConfig::new().bus(sim_line("ascii", extra)).to_toml()
}

/// The frames the simulated line carried, as text.
fn wire(gateway: &Gateway) -> Vec<String> {
    gateway
        .sim_line("sim")
        .expect("a sim line")
        .frames()
        .iter()
        .map(|f| String::from_utf8_lossy(&f.bytes).into_owned())
        .collect()
}

#[tokio::test]
async fn the_manuals_ascii_read_of_two_words_from_0004h_goes_over_the_wire_byte_for_byte() {
    let gateway = start(&ascii_config("")).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // Write 1388H to 0004H, then read 0004H-0005H of slave 01H (the manuals' ASCII examples).
    let write = [0x06, 0x00, 0x04, 0x13, 0x88];
    assert_eq!(master.call(1, 1, &write).await, write);
    let read = [0x03, 0x00, 0x04, 0x00, 0x02];
    assert_eq!(
        master.call(2, 1, &read).await,
        [0x03, 0x04, 0x13, 0x88, 0x00, 0x00]
    );
    assert_eq!(
        wire(&gateway),
        [
            ":0106000413885A\r\n",
            ":0106000413885A\r\n",
            ":010300040002F6\r\n",
            ":010304138800005D\r\n",
        ]
    );
}

/// Requests of every function code the register slave knows, and some it does not.
const REQUESTS: &[&[u8]] = &[
    &[0x05, 0x00, 0x03, 0xFF, 0x00],
    &[0x0F, 0x00, 0x08, 0x00, 0x0A, 0x02, 0xFF, 0x01],
    &[0x01, 0x00, 0x00, 0x00, 0x12],
    &[0x02, 0x00, 0x00, 0x00, 0x08],
    &[0x10, 0x00, 0x01, 0x00, 0x02, 0x04, 0x12, 0x34, 0xAB, 0xCD],
    &[0x03, 0x00, 0x00, 0x00, 0x04],
    &[0x04, 0x00, 0x00, 0x00, 0x02],
    &[0x16, 0x00, 0x01, 0x00, 0xF2, 0x00, 0x25],
    &[
        0x17, 0x00, 0x00, 0x00, 0x03, 0x00, 0x05, 0x00, 0x01, 0x02, 0x00, 0x07,
    ],
    &[0x08, 0x00, 0x00, 0x12, 0xAB],
    &[0x2B, 0x0E, 0x01, 0x00],
    &[0x03, 0xFF, 0xF0, 0x00, 0x20],
    &[0x41, 0x01, 0x02],
];

#[tokio::test]
async fn every_function_code_gets_the_same_answer_on_an_ascii_line_as_on_an_rtu_line() {
    let rtu = GatewayConfig::new().bus(sim_line("rtu", "")).start().await;
    let ascii = start(&ascii_config("response_timeout = \"300ms\"")).await;
    let mut on_rtu = RawMaster::connect(addr(&rtu)).await;
    let mut on_ascii = RawMaster::connect(addr(&ascii)).await;
    for (id, request) in (1..).zip(REQUESTS) {
        let expected = on_rtu.call(id, 2, request).await;
        assert_eq!(
            on_ascii.call(id, 2, request).await,
            expected,
            "request {request:02X?}"
        );
    }
    // Every frame on the ASCII wire is ASCII: a colon, upper-case hex, CR LF.
    for frame in wire(&ascii) {
        let hex = frame
            .strip_prefix(':')
            .and_then(|f| f.strip_suffix("\r\n"))
            .unwrap_or_else(|| panic!("not an ASCII frame: {frame:?}"));
        assert!(
            hex.bytes()
                .all(|c| c.is_ascii_digit() || (b'A'..=b'F').contains(&c)),
            "{frame:?}"
        );
    }
}

#[tokio::test]
async fn a_reply_with_a_bad_lrc_gets_0x0b_after_every_retry_and_counts_as_a_crc_error() {
    let gateway = start(
        &(ascii_config("retries = 1\nresponse_timeout = \"200ms\"")
            + "[[bus.sim_slave]]\naddress = 9\ncrc_error_rate = 1.0\n"),
    )
    .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 9, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x83, 0x0B]
    );
    let replies: Vec<String> = wire(&gateway)
        .into_iter()
        .filter(|f| f.starts_with(":090302"))
        .collect();
    assert_eq!(replies.len(), 2, "one reply per try: {replies:?}");
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value(
            "modbus_gateway_requests_total{bus=\"sim\",function=\"0x03\",outcome=\"crc_error\",protocol=\"tcp\",slave=\"9\"}"
        ),
        1.0
    );
}

#[tokio::test(start_paused = true)]
async fn a_reply_cut_short_gets_0x0b_once_the_byte_timeout_has_passed() {
    let gateway = start(
        &(ascii_config("response_timeout = \"200ms\"\nbyte_timeout = \"50ms\"")
            + "[[bus.sim_slave]]\naddress = 9\ntruncate_reply = 7\n"),
    )
    .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let started = tokio::time::Instant::now();
    assert_eq!(
        master.call(1, 9, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x83, 0x0B]
    );
    // The cut reply's seven characters, then the byte timeout; not the 1 s default (on the
    // paused clock, so exact whatever the machine's load).
    assert!(started.elapsed() < std::time::Duration::from_millis(900));
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value(
            "modbus_gateway_requests_total{bus=\"sim\",function=\"0x03\",outcome=\"frame_error\",protocol=\"tcp\",slave=\"9\"}"
        ),
        1.0
    );
}

#[tokio::test]
async fn a_reply_from_another_address_is_discarded_and_the_request_gets_0x0b() {
    let gateway = start(
        &(ascii_config("response_timeout = \"200ms\"")
            + "[[bus.sim_slave]]\naddress = 9\nreply_address = 8\n"),
    )
    .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 9, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x83, 0x0B]
    );
    assert!(wire(&gateway).iter().any(|f| f.starts_with(":0803")));
    let scrape = Scrape::of(&gateway).await;
    assert!(scrape.value("modbus_gateway_discarded_frames_total{bus=\"sim\"}") >= 1.0);
}

#[tokio::test]
async fn the_bus_info_metric_names_the_framing_and_bytes_count_characters_on_the_wire() {
    let gateway = start(&ascii_config("")).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    master.call(1, 1, &[0x03, 0x00, 0x04, 0x00, 0x02]).await;
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value(
            "modbus_gateway_bus_info{bus=\"sim\",format=\"9600 baud 7E1\",framing=\"ascii\",mode=\"master\",transport=\"sim\"}"
        ),
        1.0
    );
    // ":010300040002F6\r\n" is 17 characters; the reply ":01030400000000F8\r\n" 19.
    assert_eq!(
        scrape.value("modbus_gateway_line_sent_bytes_total{bus=\"sim\"}"),
        17.0
    );
    assert_eq!(
        scrape.value("modbus_gateway_line_received_bytes_total{bus=\"sim\"}"),
        19.0
    );
}

/// The reload reopens that bus, which then speaks the new framing.
#[tokio::test]
async fn a_reload_changing_a_bus_framing_reopens_it_speaking_the_new_framing() {
    // A second bus on a serial device that is not there: the same device and format in both
    // configurations, so only the framing can make it reopen.
    let config = |framing: &str| {
        GatewayConfig::new()
            .bus(sim_line(framing, ""))
            .bus(
                Bus::on("serial", "/dev/mbgw-test-no-such-tty")
                    .key("data_bits", 8)
                    .framing(framing),
            )
            .route("200", "serial", 1)
            .route("1", "sim", None)
    };
    let gateway = config("rtu").start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let read = [0x03, 0x00, 0x00, 0x00, 0x01];
    assert_eq!(master.call(1, 1, &read).await, [0x03, 0x02, 0x00, 0x00]);
    let mut ascii = config("ascii").load();
    ascii.metrics.listen = ([127, 0, 0, 1], 0).into();
    let done = gateway.reload(&ascii).unwrap();
    assert_eq!(done.applied, ["bus sim: reopened", "bus serial: reopened"]);
    assert_eq!(master.call(2, 1, &read).await, [0x03, 0x02, 0x00, 0x00]);
    let frames = wire(&gateway);
    assert_eq!(frames.last().unwrap(), ":0103020000FA\r\n");
}

#[tokio::test]
async fn the_ascii_demo_serves_the_drives_of_the_rtu_demo_over_a_7e1_ascii_line() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/demo-ascii.toml");
    let env = [
        ("MBGW__SERVER__LISTEN".to_owned(), "127.0.0.1:0".to_owned()),
        ("MBGW__METRICS__LISTEN".to_owned(), "127.0.0.1:0".to_owned()),
    ];
    let config = load_config(Path::new(path), env).expect("config/demo-ascii.toml is valid");
    let gateway = Gateway::start(&config)
        .await
        .expect("the ASCII demo starts");
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // Identifying codes (2103H): 0x0106 GD20, 0x010A GD300, 0x010D GD10.
    for (unit, code) in [(1u8, 0x0106u16), (2, 0x010A), (3, 0x010D)] {
        let [high, low] = code.to_be_bytes();
        assert_eq!(
            master
                .call(u16::from(unit), unit, &[0x03, 0x21, 0x03, 0x00, 0x01])
                .await,
            [0x03, 0x02, high, low],
            "unit {unit}"
        );
    }
    let frames = gateway.sim_line("demo-ascii").unwrap().frames();
    // Unit 1's request, as the manuals would print it.
    assert_eq!(frames[0].bytes, b":010321030001D7\r\n");
    // Unit 2's, as the README's walkthrough prints them.
    assert_eq!(frames[2].bytes, b":020321030001D6\r\n");
    assert_eq!(frames[3].bytes, b":020302010AEE\r\n");
    assert_eq!(config.bus[0].format().to_string(), "9600 baud 7E1");
}

/// Garbage around a reply, and a pause within the byte timeout.
#[tokio::test]
async fn on_an_ascii_line_noise_around_a_reply_and_a_short_pause_leave_it_whole() {
    let gateway = start(
        &(ascii_config("response_timeout = \"300ms\"\nbyte_timeout = \"200ms\"")
            + "[[bus.sim_slave]]\naddress = 7\ngarbage_before = 3\n\
               [[bus.sim_slave]]\naddress = 8\ngarbage_after = 3\n\
               [[bus.sim_slave]]\naddress = 9\nreply_gap = \"100ms\"\nreply_gap_after = 5\n"),
    )
    .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let read = [0x03, 0x00, 0x00, 0x00, 0x01];
    // Noise before the `:` is not part of the frame; noise after the LF is not either; a reply
    // that pauses 100 ms between characters is within its 200 ms byte timeout.
    for (id, unit) in [(1, 7), (2, 8), (3, 9)] {
        assert_eq!(
            master.call(id, unit, &read).await,
            [0x03, 0x02, 0x00, 0x00],
            "unit {unit}"
        );
    }
    let replies: Vec<String> = wire(&gateway)
        .into_iter()
        .filter(|f| f.contains(":0703") || f.contains(":0903"))
        .collect();
    assert!(
        replies.iter().any(|f| !f.starts_with(':')),
        "garbage went on the wire before unit 7's reply: {replies:?}"
    );
}

/// A pause longer than the byte timeout.
#[tokio::test]
async fn on_an_ascii_line_a_pause_past_byte_timeout_splits_the_reply_giving_0x0b() {
    let gateway = start(
        &(ascii_config("response_timeout = \"300ms\"\nbyte_timeout = \"50ms\"")
            + "[[bus.sim_slave]]\naddress = 9\nreply_gap = \"150ms\"\nreply_gap_after = 5\n"),
    )
    .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 9, &[0x03, 0x00, 0x00, 0x00, 0x01]).await,
        [0x83, 0x0B]
    );
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value(
            "modbus_gateway_requests_total{bus=\"sim\",function=\"0x03\",outcome=\"frame_error\",protocol=\"tcp\",slave=\"9\"}"
        ),
        1.0
    );
}
