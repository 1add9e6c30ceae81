//! A line behind a real serial device server: ser2net (test-support's `ser2net`) in front of
//! the gateway's end of `tests/peers/pymodbus_slave.py`'s pty cable, with pymodbus's RTU or ASCII
//! serial server on the far end, and the gateway's bus on `device = "tcp://..."` (ser2net's raw
//! accepter) or `"rfc2217://..."` (its `telnet(rfc2217)` one). Third-party masters (pymodbus's
//! Modbus TCP client, `tests/peers/pymodbus_net_master.py`, and mbpoll) and raw ones drive it.
//!
//! "As on a local line" is checked literally: the same gateway has a second bus on a second
//! pymodbus on a local pty, the same requests go to both, and the answers and the bytes each
//! slave's cable carried must be the same, and the answers the ones the script's tables hold.
//! The script logs every byte on its cable, so the wire is read beside the answers: an IAC not
//! escaped, a byte dropped or a write sent twice shows there.
//!
//! ser2net killed and restarted is a device server's power cut: the masters of the gateway get
//! their answers or 0x0A, never another master's, and no write twice. A reply that the slave
//! gives while ser2net is down waits in the pty, and ser2net forwards it when it next opens the
//! pty, which is when the gateway reconnects: a stale reply that reaches the socket after the
//! first request has gone out (a converter's buffer does the same).
//!
//! The first two tests check the fixture itself, with no gateway: ser2net carries pymodbus's
//! RTU-over-TCP client to the slave, and its RFC 2217 accepter changes the pty's settings only when
//! a client asks (so the RFC 2217 test's reading of the pty would fail if the gateway sent none).
//!
//! ser2net, Python with pymodbus (`MBGW_PYTHON`), mbpoll and stty are external tools: without one
//! a test checks nothing and says so, or fails under `MBGW_REQUIRE_TOOLS=1`.

use crate::peers::{python_with_pymodbus, Pymodbus as Slave, Wire};
use crate::support::cases::WRITES_READ_BACK;
use crate::support::{
    tool, wait_for_bus, within, Accepter, Bus, GatewayConfig, RawMaster, Scrape, Ser2net, PATIENCE,
};
use modbus_gateway::testing::line::rtu;
use modbus_gateway::Gateway;
use std::ffi::OsString;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// pymodbus's network master (Modbus TCP, RTU over TCP, UDP), one request per argument set.
const NET_MASTER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/peers/pymodbus_net_master.py"
);

/// The script's device id.
const UNIT: u8 = 10;
/// The unit the gateway routes to the local pty line's slave (also device [`UNIT`] there).
const LOCAL_UNIT: u8 = 11;
/// What ser2net sets the pty to at each connection: not what the RFC 2217 test's bus asks for.
const SER2NET_SETTINGS: &str = "9600n81";
/// How often a condition is looked at again.
const POLL: Duration = Duration::from_millis(10);

/// pymodbus's RTU slave behind ser2net (its `accepter`), and a gateway whose bus `net` is that
/// ser2net with the keys `keys` sets, connected; `None` (having said why) without the tools.
async fn rtu_slave_behind_ser2net(
    accepter: Accepter,
    keys: impl FnOnce(Bus) -> Bus,
) -> Option<(Slave, Ser2net, Gateway)> {
    let slave = Slave::start("rtu").await?;
    let ser2net = Ser2net::start(&slave.path, SER2NET_SETTINGS, accepter).await?;
    let gateway = GatewayConfig::new()
        .bus(keys(Bus::on("net", &ser2net.device())))
        .start()
        .await;
    wait_for_bus(&gateway, "net", true).await;
    Some((slave, ser2net, gateway))
}

/// Each PDU as an RTU frame to or from [`UNIT`], back to back: what an RTU line carries.
fn frames(pdus: &[&[u8]]) -> Vec<u8> {
    pdus.iter().flat_map(|pdu| rtu::encode(UNIT, pdu)).collect()
}

/// `pdu` to or from [`UNIT`] as a frame of `framing` (`rtu`, `ascii`). ASCII by the spec, here
/// rather than the gateway's codec: `:`, upper-case hex of address, PDU and LRC (the byte sum's
/// two's complement), CR LF.
fn frame(framing: &str, pdu: &[u8]) -> Vec<u8> {
    if framing == "rtu" {
        return rtu::encode(UNIT, pdu);
    }
    let mut bytes = vec![UNIT];
    bytes.extend_from_slice(pdu);
    let sum = bytes.iter().fold(0u8, |sum, &b| sum.wrapping_add(b));
    bytes.push(sum.wrapping_neg());
    let hex: String = bytes.iter().map(|b| format!("{b:02X}")).collect();
    format!(":{hex}\r\n").into_bytes()
}

#[test]
fn an_ascii_frame_is_made_as_the_manuals_worked_example() {
    // Goodrive20 manual 7.3.2.1 (slave 01H, read two words from 0004H), readdressed to UNIT
    // (0AH): the LRC moves from F6 by the address's difference, to ED.
    assert_eq!(
        frame("ascii", &[0x03, 0x00, 0x04, 0x00, 0x02]),
        b":0A0300040002ED\r\n"
    );
}

/// How many times `frame` occurs in `wire`.
fn occurrences(wire: &[u8], frame: &[u8]) -> usize {
    wire.windows(frame.len()).filter(|w| *w == frame).count()
}

/// Run `program` with `args` to its end (bounded), its standard error passed through.
async fn run(program: impl Into<OsString>, args: Vec<String>) -> std::process::Output {
    let mut command = Command::new(program.into());
    command.args(args).stderr(Stdio::inherit());
    let what = format!("{command:?} finishes");
    within(&what, tokio::task::spawn_blocking(move || command.output()))
        .await
        .expect("the task runs")
        .expect("the program runs")
}

/// pymodbus's Modbus TCP client against the gateway at `port` for `unit`: its result lines (a
/// write of register 5 = 4242, registers 5-6 read back, registers 0-2 read).
async fn pymodbus_master(python: &OsString, port: u16, unit: u8) -> Vec<String> {
    let args = [
        NET_MASTER,
        "tcp",
        "127.0.0.1",
        &port.to_string(),
        &unit.to_string(),
    ];
    let output = run(python, args.map(str::to_owned).to_vec()).await;
    assert!(
        output.status.success(),
        "pymodbus master: {:?}",
        output.status
    );
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(str::to_owned)
        .collect()
}

/// mbpoll (libmodbus) against the gateway at `port` for `unit`: it writes register 5 = 4343,
/// then reads registers 5-6; the register lines of its read.
async fn mbpoll(mbpoll: &std::path::Path, port: u16, unit: u8) -> Vec<String> {
    let common = |extra: &[&str]| -> Vec<String> {
        let port = port.to_string();
        let unit = unit.to_string();
        // -0: register numbers from 0, as the PDU has them; -1: one poll, not a loop.
        let mut args: Vec<String> = ["-m", "tcp", "-p", &port, "-a", &unit, "-0", "-1"]
            .iter()
            .map(|s| (*s).to_owned())
            .collect();
        args.extend(extra.iter().map(|s| (*s).to_owned()));
        args
    };
    let mut text = String::new();
    for args in [
        common(&["-r", "5", "127.0.0.1", "4343"]),
        common(&["-r", "5", "-c", "2", "127.0.0.1"]),
    ] {
        let output = run(mbpoll, args).await;
        text = String::from_utf8_lossy(&output.stdout).into_owned();
        assert!(
            output.status.success(),
            "mbpoll: {:?}\n{text}",
            output.status
        );
    }
    text.lines()
        .filter(|line| line.starts_with('['))
        .map(str::to_owned)
        .collect()
}

/// A pymodbus slave behind ser2net's raw accepter (bus "net", unit [`UNIT`]) and another on a
/// local pty (bus "pty", unit [`LOCAL_UNIT`] routed to its address [`UNIT`]), both with `framing`,
/// behind one gateway; `None` without the tools.
struct TwoLines {
    net: Slave,
    local: Slave,
    _ser2net: Ser2net,
    gateway: Gateway,
    python: OsString,
    framing: &'static str,
}

impl TwoLines {
    async fn start(framing: &'static str) -> Option<TwoLines> {
        let python = python_with_pymodbus()?;
        let net = Slave::start(framing).await?;
        let ser2net = Ser2net::start(&net.path, SER2NET_SETTINGS, Accepter::Raw).await?;
        let local = Slave::start(framing).await?;
        let line = |bus: Bus| {
            bus.baud(115_200)
                .parity("none")
                .framing(framing)
                .response_timeout("1s")
        };
        let gateway = GatewayConfig::new()
            .bus(line(Bus::on("net", &ser2net.device())))
            .bus(line(Bus::on("pty", &local.path)))
            .route(&UNIT.to_string(), "net", UNIT)
            .route(&LOCAL_UNIT.to_string(), "pty", UNIT)
            .start()
            .await;
        wait_for_bus(&gateway, "net", true).await;
        wait_for_bus(&gateway, "pty", true).await;
        Some(TwoLines {
            net,
            local,
            _ser2net: ser2net,
            gateway,
            python,
            framing,
        })
    }

    fn port(&self) -> u16 {
        self.gateway.tcp_addrs()[0].port()
    }

    /// pymodbus's client, then mbpoll, then a raw master's requests of every kind, each to the
    /// slave behind ser2net and to the local one: the same answers from both, the ones the script's
    /// tables hold; then the same bytes on both cables.
    async fn third_party_masters_get_the_local_lines_answers(&self) {
        for unit in [UNIT, LOCAL_UNIT] {
            assert_eq!(
                pymodbus_master(&self.python, self.port(), unit).await,
                [
                    "result 6 ok",
                    "result 3 4242 1006",
                    "result 3 1000 1001 1002"
                ],
                "pymodbus's Modbus TCP client, unit {unit}"
            );
        }
        if let Some(tool) = tool("mbpoll") {
            for unit in [UNIT, LOCAL_UNIT] {
                assert_eq!(
                    mbpoll(&tool, self.port(), unit).await,
                    ["[5]: \t4343", "[6]: \t1006"],
                    "mbpoll, unit {unit}"
                );
            }
        }
        let mut master = RawMaster::connect(self.gateway.tcp_addrs()[0]).await;
        within("the raw master's requests", async {
            for (transaction, (request, reply)) in (1..).zip(CASES) {
                let net = master.call(transaction, UNIT, request).await;
                let local = master.call(transaction, LOCAL_UNIT, request).await;
                assert_eq!(
                    net, local,
                    "request {request:02X?}: behind ser2net, locally"
                );
                assert_eq!(net, reply, "request {request:02X?}");
            }
        })
        .await;
        // Both cables, once each log has the last exchange (the script's log lines are read on a
        // thread of their own, so an answer can be in before its line is).
        let (request, reply) = CASES[CASES.len() - 1];
        let (request, reply) = (frame(self.framing, request), frame(self.framing, reply));
        let complete =
            |wire: &Wire| wire.to_slave.ends_with(&request) && wire.to_gateway.ends_with(&reply);
        let local = self.local.wire_when(complete).await;
        let net = self.net.wire_when(complete).await;
        assert!(complete(&local), "the local cable: {local:02X?}");
        assert_eq!(net, local, "the cable behind ser2net and the local one");
    }
}

/// (request PDU, the script's reply PDU), in order: reads of each table, writes, a read of the
/// writes, an exception.
const CASES: [(&[u8], &[u8]); 9] = [
    // 01 read coils 0-15: on at 0, 3, 6 (49), 9, 12, 15 (92).
    (&[0x01, 0x00, 0x00, 0x00, 0x10], &[0x01, 0x02, 0x49, 0x92]),
    // 02 read discrete inputs 0-15: on where odd.
    (&[0x02, 0x00, 0x00, 0x00, 0x10], &[0x02, 0x02, 0xAA, 0xAA]),
    // 04 read input registers 0-1: 2000, 2001.
    (
        &[0x04, 0x00, 0x00, 0x00, 0x02],
        &[0x04, 0x04, 0x07, 0xD0, 0x07, 0xD1],
    ),
    // 03 read holding registers 6-7: 1006, 1007.
    (
        &[0x03, 0x00, 0x06, 0x00, 0x02],
        &[0x03, 0x04, 0x03, 0xEE, 0x03, 0xEF],
    ),
    // 05 write coil 1 on: echo.
    (
        &[0x05, 0x00, 0x01, 0xFF, 0x00],
        &[0x05, 0x00, 0x01, 0xFF, 0x00],
    ),
    // 06 and 10 writes of registers 1-3, the read of registers 0-3 that shows them, and a read
    // of register 0x20, which the slave does not have: exception 02.
    WRITES_READ_BACK[0],
    WRITES_READ_BACK[1],
    WRITES_READ_BACK[2],
    WRITES_READ_BACK[3],
];

#[tokio::test]
async fn ser2net_raw_carries_pymodbus_rtu_over_tcp_client_to_the_pty_slave() {
    let Some(slave) = Slave::start("rtu").await else {
        return;
    };
    let python = python_with_pymodbus().expect("the slave's Python");
    let Some(ser2net) = Ser2net::start(&slave.path, SER2NET_SETTINGS, Accepter::Raw).await else {
        return;
    };
    let addr = ser2net.addr();
    let args = [
        NET_MASTER,
        "rtu-over-tcp",
        "127.0.0.1",
        &addr.port().to_string(),
        &UNIT.to_string(),
    ];
    let output = run(&python, args.map(str::to_owned).to_vec()).await;
    let results = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "{:?}\n{results}\nser2net:\n{}",
        output.status,
        ser2net.output()
    );
    assert_eq!(
        results.lines().collect::<Vec<_>>(),
        [
            "result 6 ok",
            "result 3 4242 1006",
            "result 3 1000 1001 1002"
        ]
    );
}

/// The pty's settings as `stty -a` prints them.
async fn stty(path: &str) -> String {
    let Some(stty) = tool("stty") else {
        panic!("stty (coreutils) is missing");
    };
    let output = run(stty, vec!["-F".into(), path.into(), "-a".into()]).await;
    assert!(
        output.status.success(),
        "stty -F {path}: {:?}",
        output.status
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// Whether `stty -a`'s output says `baud` baud and two stop bits (`cstopb`, not `-cstopb`).
fn stty_says(settings: &str, baud: u32, two_stop_bits: bool) -> bool {
    let speed = settings.contains(&format!("speed {baud} baud;"));
    let cstopb = settings
        .split(|c: char| c.is_whitespace() || c == ';')
        .any(|word| word == "cstopb");
    speed && cstopb == two_stop_bits
}

/// Poll the pty's settings until they say `baud` and the stop bits; the last reading either way.
async fn pty_settings_until(path: &str, baud: u32, two_stop_bits: bool) -> String {
    let deadline = tokio::time::Instant::now() + PATIENCE;
    loop {
        let settings = stty(path).await;
        if stty_says(&settings, baud, two_stop_bits) || tokio::time::Instant::now() >= deadline {
            return settings;
        }
        tokio::time::sleep(POLL).await;
    }
}

#[test]
fn the_stty_reading_tells_one_stop_bit_from_two() {
    let one = "speed 9600 baud; line = 0;\n-parenb -parodd -cmspar cs8 -hupcl -cstopb cread clocal";
    let two = "speed 19200 baud; line = 0;\n-parenb -parodd -cmspar cs8 -hupcl cstopb cread clocal";
    assert!(stty_says(one, 9600, false));
    assert!(!stty_says(one, 9600, true));
    assert!(!stty_says(one, 19200, false));
    assert!(stty_says(two, 19200, true));
    assert!(!stty_says(two, 192, true));
}

#[tokio::test]
async fn ser2net_rfc2217_sets_the_pty_from_what_a_client_sends_and_not_otherwise() {
    use tokio::io::AsyncWriteExt;
    let Some(slave) = Slave::start("rtu").await else {
        return;
    };
    let Some(ser2net) = Ser2net::start(&slave.path, SER2NET_SETTINGS, Accepter::Rfc2217).await
    else {
        return;
    };
    let mut client = within("connect", tokio::net::TcpStream::connect(ser2net.addr()))
        .await
        .expect("ser2net accepts");
    // Connected, nothing negotiated: the connector's 9600n81.
    let before = pty_settings_until(&slave.path, 9600, false).await;
    assert!(stty_says(&before, 9600, false), "{before}");
    // IAC WILL COM-PORT-OPTION (44), then IAC SB 44 <command> <value> IAC SE for each of
    // SET-BAUDRATE (1) = 19200 (four bytes, big-endian), SET-DATASIZE (2) = 8, SET-PARITY (3) =
    // 1 (none), SET-STOPSIZE (4) = 2.
    let mut negotiation = vec![0xFF, 0xFB, 44];
    for (command, value) in [
        (1, &19_200u32.to_be_bytes()[..]),
        (2, &[8][..]),
        (3, &[1][..]),
        (4, &[2][..]),
    ] {
        negotiation.extend([0xFF, 0xFA, 44, command]);
        negotiation.extend(value);
        negotiation.extend([0xFF, 0xF0]);
    }
    client.write_all(&negotiation).await.unwrap();
    let after = pty_settings_until(&slave.path, 19_200, true).await;
    assert!(stty_says(&after, 19_200, true), "{after}");
}

#[tokio::test]
async fn pymodbus_and_mbpoll_reach_an_rtu_slave_behind_ser2net_as_on_a_local_line() {
    let Some(lines) = TwoLines::start("rtu").await else {
        return;
    };
    lines
        .third_party_masters_get_the_local_lines_answers()
        .await;
    // RTU: the very frames of the requests and the answers, each as the spec has it.
    let replies: Vec<&[u8]> = CASES.iter().map(|(_, reply)| *reply).collect();
    let wire = lines.net.wire_now();
    assert!(wire.to_gateway.ends_with(&frames(&replies)), "{wire:02X?}");
}

#[tokio::test]
async fn pymodbus_and_mbpoll_reach_an_ascii_slave_behind_ser2net_as_on_a_local_line() {
    let Some(lines) = TwoLines::start("ascii").await else {
        return;
    };
    lines
        .third_party_masters_get_the_local_lines_answers()
        .await;
    let wire = lines.net.wire_now();
    assert!(
        wire.to_slave.starts_with(b":") && wire.to_gateway.ends_with(b"\r\n"),
        "ASCII on the cable: {:?}",
        String::from_utf8_lossy(&wire.to_slave)
    );
}

#[tokio::test]
async fn rfc2217_bus_sets_ser2nets_line_to_its_own_format_and_0xff_crosses_both_ways() {
    let Some(slave) = Slave::start("rtu").await else {
        return;
    };
    let Some(ser2net) = Ser2net::start(&slave.path, SER2NET_SETTINGS, Accepter::Rfc2217).await
    else {
        return;
    };
    // 19200 8N2: neither the connector's 9600n81 nor the pty's own 38400.
    let gateway = GatewayConfig::new()
        .bus(
            Bus::on("net", &ser2net.device())
                .baud(19_200)
                .parity("none")
                .key("stop_bits", 2u8)
                .response_timeout("1s"),
        )
        .start()
        .await;
    wait_for_bus(&gateway, "net", true).await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    // Each request or reply holds 0xFF, Telnet's IAC, which must cross unescaped on the line.
    let cases: [(&[u8], &[u8]); 4] = [
        // 06 write register 5 = 0xFFFF: echo.
        (
            &[0x06, 0x00, 0x05, 0xFF, 0xFF],
            &[0x06, 0x00, 0x05, 0xFF, 0xFF],
        ),
        // 03 read it back: a reply of FF FF.
        (&[0x03, 0x00, 0x05, 0x00, 0x01], &[0x03, 0x02, 0xFF, 0xFF]),
        // 10 write registers 6-7 = 0x00FF, 0xFF00: start and count.
        (
            &[0x10, 0x00, 0x06, 0x00, 0x02, 0x04, 0x00, 0xFF, 0xFF, 0x00],
            &[0x10, 0x00, 0x06, 0x00, 0x02],
        ),
        // 03 read registers 5-7.
        (
            &[0x03, 0x00, 0x05, 0x00, 0x03],
            &[0x03, 0x06, 0xFF, 0xFF, 0x00, 0xFF, 0xFF, 0x00],
        ),
    ];
    within("four transactions", async {
        for (transaction, (request, reply)) in (1..).zip(cases) {
            assert_eq!(
                master.call(transaction, UNIT, request).await,
                reply,
                "request {request:02X?}"
            );
        }
    })
    .await;
    let (requests, replies): (Vec<&[u8]>, Vec<&[u8]>) = cases.iter().copied().unzip();
    let expected = Wire {
        to_slave: frames(&requests),
        to_gateway: frames(&replies),
    };
    let wire = slave.wire_when(|wire| *wire == expected).await;
    assert_eq!(wire, expected, "every FF once on the cable, either way");
    // While the gateway is connected, the pty runs at what the bus says, not ser2net's 9600n81.
    let settings = pty_settings_until(&slave.path, 19_200, true).await;
    assert!(
        stty_says(&settings, 19_200, true),
        "the pty's settings after the gateway connected:\n{settings}"
    );
}

/// A master cannot reset the converter's line with a telnet command hidden in its data.
#[tokio::test]
async fn a_telnet_command_hidden_in_a_masters_data_cannot_reset_the_converter() {
    let Some((slave, _ser2net, gateway)) = rtu_slave_behind_ser2net(Accepter::Rfc2217, |bus| {
        bus.baud(19_200)
            .parity("none")
            .key("stop_bits", 2u8)
            .response_timeout("1s")
    })
    .await
    else {
        return;
    };
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    // Registers 0-4 written with the bytes of IAC SB COM-PORT-OPTION SET-BAUDRATE 1200 IAC SE:
    // unescaped, ser2net would take them as its client's command and run the line at 1200 baud.
    let command = [0xFF, 0xFA, 0x2C, 0x01, 0x00, 0x00, 0x04, 0xB0, 0xFF, 0xF0];
    let mut write = vec![0x10, 0x00, 0x00, 0x00, 0x05, 0x0A];
    write.extend(command);
    let mut read_back = vec![0x03, 0x0A];
    read_back.extend(command);
    within("the write and its read-back", async {
        assert_eq!(
            master.call(1, UNIT, &write).await,
            [0x10, 0x00, 0x00, 0x00, 0x05]
        );
        assert_eq!(
            master.call(2, UNIT, &[0x03, 0x00, 0x00, 0x00, 0x05]).await,
            read_back
        );
    })
    .await;
    // The slave got the bytes as data, and the line still runs at what the bus says.
    let wire = slave
        .wire_when(|wire| occurrences(&wire.to_slave, &frame("rtu", &write)) == 1)
        .await;
    assert_eq!(
        occurrences(&wire.to_slave, &frame("rtu", &write)),
        1,
        "{wire:02X?}"
    );
    let settings = pty_settings_until(&slave.path, 19_200, true).await;
    assert!(
        stty_says(&settings, 19_200, true),
        "after the write:\n{settings}"
    );
}

#[tokio::test]
async fn rfc2217_bus_sets_the_line_again_when_it_reconnects_to_a_restarted_ser2net() {
    let Some((slave, mut ser2net, gateway)) = rtu_slave_behind_ser2net(Accepter::Rfc2217, |bus| {
        bus.baud(19_200)
            .parity("none")
            .key("stop_bits", 2u8)
            .response_timeout("1s")
            .key("reopen_delay", "100ms")
    })
    .await
    else {
        return;
    };
    let settings = pty_settings_until(&slave.path, 19_200, true).await;
    assert!(
        stty_says(&settings, 19_200, true),
        "first connect:\n{settings}"
    );
    let before = Scrape::of(&gateway).await;
    // A killed ser2net puts nothing back: the pty keeps 19200 8N2 unless told otherwise. Set it to
    // what neither ser2net nor the bus would, so only a new negotiation makes it 19200 8N2 again.
    ser2net.stop();
    let args = ["-F", &slave.path, "4800", "-cstopb"];
    let set = run("stty", args.map(str::to_owned).to_vec()).await;
    assert!(set.status.success(), "stty sets the pty");
    assert!(stty_says(&stty(&slave.path).await, 4800, false));
    ser2net.restart().await;
    within("the gateway reconnects", async {
        while Scrape::of(&gateway).await.delta(&before, REOPENS) < 1.0 {
            tokio::time::sleep(POLL).await;
        }
    })
    .await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    assert_eq!(
        within(
            "a read",
            master.call(1, UNIT, &[0x03, 0x00, 0x00, 0x00, 0x01])
        )
        .await,
        [0x03, 0x02, 0x03, 0xE8],
        "register 0 after the reconnect"
    );
    let settings = pty_settings_until(&slave.path, 19_200, true).await;
    assert!(
        stty_says(&settings, 19_200, true),
        "after the reconnect:\n{settings}"
    );
}

/// A reply left in the pty while ser2net was down.
#[tokio::test]
async fn a_reply_left_while_ser2net_was_down_is_not_the_answer_after_reconnect() {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let Some((slave, mut ser2net, gateway)) = rtu_slave_behind_ser2net(Accepter::Raw, |bus| {
        bus.baud(115_200)
            .parity("none")
            .response_timeout("1s")
            .key("reopen_delay", "100ms")
            .key("reopen_delay_max", "100ms")
    })
    .await
    else {
        return;
    };
    ser2net.stop();
    wait_for_bus(&gateway, "net", false).await;
    // While ser2net is down, a read of register 1 goes to the slave from the pty's own side, and
    // its answer (1001) waits in the pty for whoever reads it next: ser2net, once it is back.
    let stale_read = rtu::encode(UNIT, &[0x03, 0x00, 0x01, 0x00, 0x01]);
    let stale_reply = rtu::encode(UNIT, &[0x03, 0x02, 0x03, 0xE9]);
    let mut pty = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOCTTY)
        .open(&slave.path)
        .expect("open the pty");
    pty.write_all(&stale_read).expect("write to the pty");
    let wire = slave
        .wire_when(|wire| wire.to_gateway.ends_with(&stale_reply))
        .await;
    assert!(
        wire.to_gateway.ends_with(&stale_reply),
        "the slave answers: {wire:02X?}"
    );
    drop(pty);
    // A master reads register 0 (1000) all along: 0x0A while the line is down, then 1000.
    let stop = Arc::new(AtomicBool::new(false));
    let tally = Arc::new(Tally::default());
    let reader = master_loop(
        &gateway,
        Arc::clone(&tally),
        Arc::clone(&stop),
        |_| vec![0x03, 0x00, 0x00, 0x00, 0x01],
        |_| vec![0x03, 0x02, 0x03, 0xE8],
    );
    until_counts("0x0A while down", &[Arc::clone(&tally)], &[1], false).await;
    ser2net.restart().await;
    until_counts(
        "answers after the reconnect",
        &[Arc::clone(&tally)],
        &[TRAFFIC],
        true,
    )
    .await;
    stop.store(true, Ordering::Relaxed);
    within("the reader stops", reader)
        .await
        .expect("the reader got 1000 or 0x0A, never 1001");
}

/// One master's tally: answers as expected, and 0x0A; and whether it got anything else.
#[derive(Default)]
struct Tally {
    answered: AtomicUsize,
    unavailable: AtomicUsize,
    failed: AtomicBool,
}

/// A master on its own connection that sends `request(n)` for n = 1, 2... until `stop`, each
/// answered by `reply(n)` or by exception 0x0A, within the patience; anything else fails the test.
/// It returns the n of the requests answered normally.
fn master_loop(
    gateway: &Gateway,
    tally: Arc<Tally>,
    stop: Arc<AtomicBool>,
    request: impl Fn(u16) -> Vec<u8> + Send + 'static,
    reply: impl Fn(u16) -> Vec<u8> + Send + 'static,
) -> tokio::task::JoinHandle<Vec<u16>> {
    let addr = gateway.tcp_addrs()[0];
    tokio::spawn(async move {
        let mut master = RawMaster::connect(addr).await;
        let mut answered = Vec::new();
        let mut n = 0u16;
        while !stop.load(Ordering::Relaxed) {
            n += 1;
            let request = request(n);
            let got = within(
                &format!("an answer to {request:02X?}"),
                master.call(n, UNIT, &request),
            )
            .await;
            if got == reply(n) {
                answered.push(n);
                tally.answered.fetch_add(1, Ordering::Relaxed);
            } else if got == [request[0] | 0x80, 0x0A] {
                tally.unavailable.fetch_add(1, Ordering::Relaxed);
            } else {
                tally.failed.store(true, Ordering::Relaxed);
                panic!(
                    "request {n} {request:02X?}: {got:02X?}, neither its answer {:02X?} nor 0x0A",
                    reply(n)
                );
            }
            // Pace the masters while the line is down, when 0x0A comes at once.
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
        answered
    })
}

/// Until every tally's count (`answered` or `unavailable`) reaches its floor; a master that got a
/// wrong answer fails the test at once.
async fn until_counts(what: &str, tallies: &[Arc<Tally>], floors: &[usize], answered: bool) {
    within(what, async {
        loop {
            assert!(
                !tallies.iter().any(|t| t.failed.load(Ordering::Relaxed)),
                "{what}: a master got a wrong answer (its panic is above)"
            );
            let reached = tallies.iter().zip(floors).all(|(tally, floor)| {
                let count = if answered {
                    &tally.answered
                } else {
                    &tally.unavailable
                };
                count.load(Ordering::Relaxed) >= *floor
            });
            if reached {
                return;
            }
            tokio::time::sleep(POLL).await;
        }
    })
    .await;
}

/// Answers each master gets before ser2net is killed, and again after the reconnect.
const TRAFFIC: usize = 20;

const REOPENS: &str = "modbus_gateway_port_reopens_total{bus=\"net\"}";
const OPEN_ERRORS: &str = "modbus_gateway_port_open_errors_total{bus=\"net\"}";

/// The write of holding register 9 = `n`, as a PDU.
fn write_9(n: u16) -> Vec<u8> {
    let [hi, lo] = n.to_be_bytes();
    vec![0x06, 0x00, 0x09, hi, lo]
}

/// The gateway reconnects with back-off.
#[tokio::test]
async fn ser2net_restarted_mid_traffic_gives_0x0a_then_reconnects_and_no_write_twice() {
    let Some((slave, mut ser2net, gateway)) = rtu_slave_behind_ser2net(Accepter::Raw, |bus| {
        bus.baud(115_200)
            .parity("none")
            .response_timeout("1s")
            .key("reopen_delay", "100ms")
            .key("reopen_delay_max", "400ms")
    })
    .await
    else {
        return;
    };

    let stop = Arc::new(AtomicBool::new(false));
    let tallies: Vec<Arc<Tally>> = (0..4).map(|_| Arc::default()).collect();
    // Three readers, each of its own register (k holds 1000 + k): a reply meant for another
    // master would show another value. One writer of register 9 = 1, 2, 3...
    let mut readers = Vec::new();
    for register in 0..3u8 {
        let [hi, lo] = (1000 + u16::from(register)).to_be_bytes();
        readers.push(master_loop(
            &gateway,
            Arc::clone(&tallies[usize::from(register)]),
            Arc::clone(&stop),
            move |_| vec![0x03, 0x00, register, 0x00, 0x01],
            move |_| vec![0x03, 0x02, hi, lo],
        ));
    }
    let writer = master_loop(
        &gateway,
        Arc::clone(&tallies[3]),
        Arc::clone(&stop),
        write_9,
        write_9,
    );

    until_counts("traffic before the restart", &tallies, &[TRAFFIC; 4], true).await;
    let before = Scrape::of(&gateway).await;
    let killed = tokio::time::Instant::now();
    ser2net.stop();
    wait_for_bus(&gateway, "net", false).await;
    let unavailable: Vec<usize> = tallies
        .iter()
        .map(|t| t.unavailable.load(Ordering::Relaxed) + 1)
        .collect();
    until_counts("0x0A to every master", &tallies, &unavailable, false).await;
    // Down for four refused reconnects. With the delay doubling from 100 ms (at most 400) they
    // come at least 100 + 200 + 400 ms apart from the first, whenever that is; at a steady
    // 100 ms, 300 ms.
    within("four refused reconnects", async {
        while Scrape::of(&gateway).await.delta(&before, OPEN_ERRORS) < 4.0 {
            tokio::time::sleep(POLL).await;
        }
    })
    .await;
    let four_refused = killed.elapsed();
    assert!(
        four_refused >= Duration::from_millis(500),
        "four reconnects within {four_refused:?} of the kill: no back-off"
    );
    ser2net.restart().await;
    wait_for_bus(&gateway, "net", true).await;
    let floors: Vec<usize> = tallies
        .iter()
        .map(|t| t.answered.load(Ordering::Relaxed) + TRAFFIC)
        .collect();
    until_counts("traffic after the reconnect", &tallies, &floors, true).await;
    stop.store(true, Ordering::Relaxed);
    for reader in readers {
        within("a reader stops", reader).await.expect("reader");
    }
    let written = within("the writer stops", writer).await.expect("writer");
    let after = Scrape::of(&gateway).await;
    assert_eq!(
        after.delta(&before, REOPENS),
        1.0,
        "one outage, one reconnect counted"
    );

    // Every write the writer sent reached the slave at most once, and an answered one exactly
    // once: each value is written once, so each frame is unique on the cable.
    let last = tallies[3].answered.load(Ordering::Relaxed)
        + tallies[3].unavailable.load(Ordering::Relaxed);
    let last = u16::try_from(last).expect("fewer than 65536 writes");
    let frame_of = |n: u16| rtu::encode(UNIT, &write_9(n));
    let final_write = *written.last().expect("writes were answered");
    let wire = slave
        .wire_when(|wire| occurrences(&wire.to_slave, &frame_of(final_write)) > 0)
        .await;
    for n in 1..=last {
        let times = occurrences(&wire.to_slave, &frame_of(n));
        if written.contains(&n) {
            assert_eq!(times, 1, "answered write {n} on the cable");
        } else {
            assert!(times <= 1, "write {n} (0x0A) on the cable {times} times");
        }
    }
}
