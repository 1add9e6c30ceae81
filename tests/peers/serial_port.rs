//! Third-party masters on a serial master port (`[[server.serial]]`, a `pty:` port): pymodbus's
//! serial client in RTU and ASCII (tests/peers/pymodbus_port_master.py) and libmodbus's RTU
//! master through Debian's libmodbus5 (tests/peers/libmodbus_port_master.py). Behind the port,
//! two buses: the simulated drives of config/demo.toml and pymodbus's RTU server on a pty cable
//! (whose script logs the bytes its line carried). Each master's own log of its line is checked
//! byte for byte against what the slaves' line carried and against the manuals' frames; what the
//! port must keep silent (a unit it does not answer, a broadcast) is a request after which the
//! master read no byte at all. Its writes meet the rules and the journal as protocol `serial`.

use super::{ascii_frames, python_with_pymodbus, run_to_end, unhex, Pymodbus, UNIT};
use crate::support::{python_with_libmodbus, start, until_exists, Scrape, TempDir};
use modbus_gateway::testing::line::rtu;
use std::ffi::OsString;
use std::path::PathBuf;

const PYMODBUS_MASTER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/peers/pymodbus_port_master.py"
);
const LIBMODBUS_MASTER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/peers/libmodbus_port_master.py"
);

/// What the master asks, in the scripts' words, and what it must get.
const OPS: [(&str, &str); 12] = [
    // The GD300's identifying code (2103H), from the simulated line.
    ("read:2:8451:1", "266"),
    // pymodbus's server: registers 0-1 hold 1000 and 1001; written, then read back.
    ("read:10:0:2", "1000 1001"),
    ("writes:10:0:7,8", "2"),
    ("read:10:0:2", "7 8"),
    // The GD300's frequency reference (2001H) to 25.00 Hz.
    ("write:2:8193:2500", "2500"),
    // A unit the port does not answer: silence.
    ("read:9:0:1", "none"),
    // A unit it answers that has no route: the gateway's 0x0A, as an exception frame.
    ("read:20:0:1", "exception 10"),
    // A broadcast: the reference of both drives to 12.34 Hz, never answered...
    ("write:0:8193:1234", "none"),
    // ...which reached them.
    ("read:2:8193:1", "1234"),
    // A run command (2000H) to unit 2: the rule for serial masters denies it (0x02, registers).
    ("write:2:8192:1", "exception 2"),
    // The same as a broadcast: it reaches unit 2 too, so it is denied and, a broadcast, silent.
    ("write:0:8192:1", "none"),
    // Unit 2 never started: its state word (2100H) says stopped (3), not running forward (1).
    ("read:2:8448:1", "3"),
];

/// One op as the master's log has it: the bytes it sent and read back, and its result.
#[derive(Debug, Default)]
struct Op {
    sent: Vec<u8>,
    received: Vec<u8>,
    result: String,
}

/// The ops of a script's standard output: pymodbus's `sent HEX` / `received HEX` lines, or
/// libmodbus's debug lines (`[01][03]...` sent, `<01><03>...` received).
fn ops_of(stdout: &str) -> Vec<Op> {
    let bracketed = |line: &str, open: char, close: char| -> Vec<u8> {
        line.split(close)
            .filter_map(|b| b.strip_prefix(open))
            .map(|b| u8::from_str_radix(b, 16).expect("libmodbus prints hex"))
            .collect()
    };
    let mut ops: Vec<Op> = Vec::new();
    for line in stdout.lines() {
        if line.starts_with("op ") {
            ops.push(Op::default());
            continue;
        }
        let Some(op) = ops.last_mut() else { continue };
        if let Some(hex) = line.strip_prefix("sent ") {
            op.sent.extend(unhex(hex));
        } else if let Some(hex) = line.strip_prefix("received ") {
            op.received.extend(unhex(hex));
        } else if let Some(result) = line.strip_prefix("result ") {
            op.result = result.to_owned();
        } else if line.starts_with('[') {
            op.sent.extend(bracketed(line, '[', ']'));
        } else if line.starts_with('<') {
            op.received.extend(bracketed(line, '<', '>'));
        }
    }
    ops
}

/// The gateway: port `scada` (`framing`) at `dir`/scada, port `hmi` (RTU, read only) at
/// `dir`/hmi; the demo's GD20 and GD300 on a simulated line (units 1-2 and broadcasts), the
/// pymodbus server on `slave` (unit 10); a rule for serial masters on the drives' run command;
/// the journal in `dir`.
fn config(framing: &str, slave: &str, dir: &TempDir) -> String {
    let dir = dir.path().display();
    format!(
        r#"
[server]
listen = ["127.0.0.1:0"]

[[server.serial]]
name = "scada"
device = "pty:{dir}/scada"
baud = 9600
parity = "none"
framing = "{framing}"
units = "1-2,10,20"
answer_within = "3s"

[[server.serial]]
name = "hmi"
device = "pty:{dir}/hmi"
baud = 9600
parity = "none"
units = "1-2,10"
answer_within = "3s"
read_only = true

[audit]
path = "{dir}/journal.jsonl"

[[bus]]
name = "drives"
device = "sim"
baud = 9600
parity = "even"

[[bus.sim_slave]]
address = 1
model = "gd20"
params = {{ "P00.01" = 2, "P00.06" = 8 }}

[[bus.sim_slave]]
address = 2
model = "gd300"
params = {{ "P00.01" = 2, "P00.06" = 8 }}

[[bus]]
name = "pymodbus"
device = "{slave}"
baud = 115200
parity = "none"
response_timeout = "1s"

[[route]]
units = "0-2"
bus = "drives"

[[route]]
units = {UNIT}
bus = "pymodbus"

[[rule]]
name = "serial masters do not start drives"
protocols = ["serial"]
units = "1-2"
registers = "0x2000"
action = "deny"
"#
    )
}

/// Run `script` with `args` under `python`, the ops it logged.
async fn master(python: &OsString, script: &str, args: &[String]) -> Vec<Op> {
    let mut all = vec![script.to_owned()];
    all.extend_from_slice(args);
    let output = run_to_end(PathBuf::from(python), all).await;
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{stdout}");
    ops_of(&stdout)
}

/// The gateway with its ports' links in place.
async fn gateway(framing: &str, slave: &Pymodbus, dir: &TempDir) -> modbus_gateway::Gateway {
    let gateway = start(&config(framing, &slave.path, dir)).await;
    until_exists(&dir.join("scada")).await;
    until_exists(&dir.join("hmi")).await;
    gateway
}

fn op_args(link: &std::path::Path) -> Vec<String> {
    std::iter::once(link.display().to_string())
        .chain(OPS.iter().map(|(op, _)| (*op).to_owned()))
        .collect()
}

/// Every op got its result; the silent ones read no byte.
fn check_results(ops: &[Op]) {
    let results: Vec<&str> = ops.iter().map(|op| op.result.as_str()).collect();
    let expected: Vec<&str> = OPS.iter().map(|(_, result)| *result).collect();
    assert_eq!(results, expected, "{ops:#?}");
    for (op, (asked, result)) in ops.iter().zip(OPS) {
        assert!(!op.sent.is_empty(), "{asked}: nothing sent");
        if result == "none" {
            assert_eq!(op.received, b"", "{asked}: the port must stay silent");
        }
    }
}

/// The ops to the pymodbus server (unit 10), as RTU frames each way: what its line must carry.
fn to_pymodbus_slave(frames: impl Iterator<Item = (Vec<u8>, Vec<u8>)>) -> (Vec<u8>, Vec<u8>) {
    let (requests, replies): (Vec<Vec<u8>>, Vec<Vec<u8>>) = frames.unzip();
    (requests.concat(), replies.concat())
}

/// The port's counts, the journal's lines for the two denied writes, and the read-only port.
async fn check_counts_and_journal(gateway: &modbus_gateway::Gateway, dir: &TempDir) {
    let scrape = Scrape::of(gateway).await;
    let counted = |outcome: &str| {
        scrape.value(&format!(
            "modbus_gateway_serial_requests_total{{outcome=\"{outcome}\",port=\"scada\"}}"
        ))
    };
    let counts: Vec<f64> = [
        "answered",
        "exception",
        "broadcast",
        "not_addressed",
        "bad_frame",
        "too_late",
    ]
    .iter()
    .map(|o| counted(o))
    .collect();
    assert_eq!(counts, [7.0, 2.0, 2.0, 1.0, 0.0, 0.0]);
    let journal = std::fs::read_to_string(dir.join("journal.jsonl")).expect("the journal");
    let writes: Vec<serde_json::Value> = journal
        .lines()
        .map(|line| serde_json::from_str(line).expect("a journal line is JSON"))
        .filter(|line: &serde_json::Value| line["kind"] == "write")
        .collect();
    let denied: Vec<(&str, &str, i64, &str)> = writes
        .iter()
        .filter(|w| w["action"] == "deny")
        .map(|w| {
            (
                w["master"].as_str().unwrap(),
                w["protocol"].as_str().unwrap(),
                w["unit"].as_i64().unwrap(),
                w["rule"].as_str().unwrap(),
            )
        })
        .collect();
    let rule = "serial masters do not start drives";
    assert_eq!(
        denied,
        [
            ("serial:scada", "serial", 2, rule),
            ("serial:scada", "serial", 0, rule)
        ],
        "{journal}"
    );
}

#[tokio::test]
async fn pymodbus_rtu_and_ascii_masters_on_a_port_reach_both_lines_byte_for_byte() {
    for framing in ["rtu", "ascii"] {
        let Some(python) = python_with_pymodbus() else {
            return;
        };
        let Some(slave) = Pymodbus::start("rtu").await else {
            return;
        };
        let dir = TempDir::new(&format!("port-peers-{framing}"));
        let gateway = gateway(framing, &slave, &dir).await;
        let mut args = vec![framing.to_owned()];
        args.extend(op_args(&dir.join("scada")));
        let ops = master(&python, PYMODBUS_MASTER, &args).await;
        check_results(&ops);
        // Each op's frames as RTU, whatever the port's framing: (unit, PDU) each way.
        let rtu_of = |bytes: &[u8]| -> Vec<u8> {
            if framing == "rtu" {
                return bytes.to_vec();
            }
            let frames = ascii_frames(bytes).unwrap_or_else(|e| panic!("{e}: {bytes:02X?}"));
            frames
                .iter()
                .flat_map(|(unit, pdu)| rtu::encode(*unit, pdu))
                .collect()
        };
        // The manual's frames for the first read (GD300 manual: 2103H, its identifying code).
        assert_eq!(rtu_of(&ops[0].sent), unhex("0203210300017e05"), "{framing}");
        assert_eq!(
            rtu_of(&ops[0].received),
            unhex("020302010a7dd3"),
            "{framing}"
        );
        // What reached the pymodbus server, and what it answered, is what the master exchanged.
        let expected = to_pymodbus_slave(
            ops[1..4]
                .iter()
                .map(|op| (rtu_of(&op.sent), rtu_of(&op.received))),
        );
        let wire = slave
            .wire_when(|w| w.to_gateway.len() >= expected.1.len())
            .await;
        assert_eq!((wire.to_slave, wire.to_gateway), expected, "{framing}");
        check_counts_and_journal(&gateway, &dir).await;

        // The read-only port: reads pass, a write is refused with 0x01 and never sent.
        let ops = master(
            &python,
            PYMODBUS_MASTER,
            &[
                "rtu".to_owned(),
                dir.join("hmi").display().to_string(),
                "read:10:0:2".to_owned(),
                "write:10:0:99".to_owned(),
                "read:10:0:2".to_owned(),
            ],
        )
        .await;
        let results: Vec<&str> = ops.iter().map(|op| op.result.as_str()).collect();
        assert_eq!(results, ["7 8", "exception 1", "7 8"], "{framing}");
        let journal = std::fs::read_to_string(dir.join("journal.jsonl")).unwrap();
        assert!(
            journal.contains(r#""master":"serial:hmi","protocol":"serial""#)
                && journal.contains(r#""rule":"server.serial[1].read_only","action":"deny""#),
            "{journal}"
        );
        gateway.shutdown().await;
    }
}

#[tokio::test]
async fn libmodbus_rtu_master_on_a_port_reaches_both_lines_byte_for_byte() {
    let Some(python) = python_with_libmodbus() else {
        return;
    };
    // The slave behind the gateway is pymodbus's: it needs pymodbus's Python.
    let Some(slave) = Pymodbus::start("rtu").await else {
        return;
    };
    let dir = TempDir::new("port-peers-libmodbus");
    let gateway = gateway("rtu", &slave, &dir).await;
    let ops = master(&python, LIBMODBUS_MASTER, &op_args(&dir.join("scada"))).await;
    check_results(&ops);
    assert_eq!(ops[0].sent, unhex("0203210300017e05"));
    assert_eq!(ops[0].received, unhex("020302010a7dd3"));
    let expected = to_pymodbus_slave(
        ops[1..4]
            .iter()
            .map(|op| (op.sent.clone(), op.received.clone())),
    );
    let wire = slave
        .wire_when(|w| w.to_gateway.len() >= expected.1.len())
        .await;
    assert_eq!((wire.to_slave, wire.to_gateway), expected);
    check_counts_and_journal(&gateway, &dir).await;
    gateway.shutdown().await;
}

#[tokio::test]
async fn a_reply_later_than_answer_within_never_reaches_a_pymodbus_master() {
    let Some(python) = python_with_pymodbus() else {
        return;
    };
    let dir = TempDir::new("port-peers-late");
    let link = dir.join("late");
    // A drive that takes 400 ms to answer, behind a port that must answer within 100 ms.
    let config = format!(
        r#"
[server]
listen = ["127.0.0.1:0"]

[[server.serial]]
name = "late"
device = "pty:{}"
parity = "none"
answer_within = "100ms"

[[bus]]
name = "drives"
device = "sim"
baud = 115200
parity = "none"

[[bus.sim_slave]]
address = 1
model = "gd20"
processing_delay = "400ms"

[[bus.sim_slave]]
address = 2
model = "gd300"
"#,
        link.display()
    );
    let gateway = start(&config).await;
    until_exists(&link).await;
    let args: Vec<String> = [
        "rtu",
        &link.display().to_string(),
        "read:1:8451:1",
        "read:2:8451:1",
    ]
    .iter()
    .map(|s| (*s).to_owned())
    .collect();
    let ops = master(&python, PYMODBUS_MASTER, &args).await;
    let results: Vec<&str> = ops.iter().map(|op| op.result.as_str()).collect();
    // The slow drive's reply came 400 ms after the request, past the master's 100 ms budget:
    // never sent, though pymodbus waited 1.5 s for it. The next request is answered as usual.
    assert_eq!(results, ["none", "266"], "{ops:#?}");
    assert_eq!(ops[0].received, b"", "a late reply reached the master");
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(
        scrape.value("modbus_gateway_serial_requests_total{outcome=\"too_late\",port=\"late\"}"),
        1.0
    );
    gateway.shutdown().await;
}
