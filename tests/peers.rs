//! Third-party Modbus peers on the real serial path: pymodbus's serial server (Python, run by
//! `tests/peers/pymodbus_slave.py`, RTU or ASCII) as the slave behind the gateway, on a pty cable,
//! and pymodbus's ASCII client (`tests/peers/pymodbus_ascii_master.py`) as the master of the
//! `simulate` subcommand's drives; its RTU-over-TCP, UDP and TLS clients as masters of the
//! gateway (the TLS ones in `tls_walkthrough`, with the walkthrough's certificates) and of
//! `simulate --listen` directly; in `serial_port`, pymodbus's serial client and libmodbus's RTU
//! master on a serial master port of the gateway. The scripts log
//! every byte either way, so these tests check the line as well as the masters; ASCII frames are
//! read by a decoder of this file's own, not the gateway's codec, so the check is independent of
//! the code under test.
//!
//! Python comes from `MBGW_PYTHON` (`.ci/run` points it at a venv with the pinned pymodbus), else
//! a `python3` on the PATH that has pymodbus; without one a test checks nothing and says so, or
//! fails under `MBGW_REQUIRE_TOOLS=1`, as for the other external tools.

mod serial_port;
mod tls_walkthrough;

use crate::support::cases::{FIVE_TRANSACTIONS, READ_HOLDING_0_2, WRITES_READ_BACK};
use crate::support::{
    addr, pty_config, pty_line, start, within, Bus, GatewayConfig, RawMaster, Scrape,
};
use modbus_gateway::testing::line::rtu;
use std::ffi::OsString;
use std::io::{BufRead, BufReader, Read};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/peers/pymodbus_slave.py");
const ASCII_MASTER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/peers/pymodbus_ascii_master.py"
);
const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");
/// The drives of config/demo.toml on a 9600 7E1 Modbus ASCII line.
const ASCII_DEMO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/config/demo-ascii.toml");

/// The script's device id. Not 1: see [`IGNORED`].
const UNIT: u8 = 10;
/// Read holding registers 0-1.
const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x02];
/// The script's registers 0-1 hold 1000 and 1001.
const READ_REPLY: [u8; 6] = [0x03, 0x04, 0x03, 0xE8, 0x03, 0xE9];
/// User-defined function code 0x64 with two data bytes; on the wire 0A 64 00 00 42 23.
/// pymodbus 3.16's RTU server knows no such request and answers nothing. Its framer keeps
/// unknown bytes as noise and hunts through them for a frame: wherever a byte in a function
/// code's place is a code it knows (or >= 0x80), it checks a CRC and, when that fails, drops its
/// whole buffer, a real request queued behind the noise included (after 0A 41 12 34 5E 9F the
/// next read goes unanswered). No byte of this frame, nor the unit id that starts the next
/// frame, is a code it knows, so the next real request is found behind the noise and answered.
const IGNORED: [u8; 3] = [0x64, 0x00, 0x00];
/// Time enough for a Python slave on a loaded 2-core machine (the whole suite in parallel): at
/// 300 ms, pymodbus now and then answered late and a read got the gateway's 0x0B.
const RESPONSE_TIMEOUT: &str = "response_timeout = \"1s\"";

/// A Python that can run the script, if there is one (see the module doc).
pub(crate) fn python_with_pymodbus() -> Option<OsString> {
    let can_run = |python: &OsString| {
        Command::new(python)
            .args(["-c", "import serial, pymodbus.server, pymodbus.simulator"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|status| status.success())
    };
    if let Some(python) = std::env::var_os("MBGW_PYTHON") {
        assert!(
            can_run(&python),
            "MBGW_PYTHON={python:?} cannot import pymodbus and pyserial"
        );
        return Some(python);
    }
    let python = crate::support::tool("python3")?.into_os_string();
    if can_run(&python) {
        return Some(python);
    }
    assert!(
        std::env::var_os("MBGW_REQUIRE_TOOLS").is_none(),
        "pymodbus is required (MBGW_REQUIRE_TOOLS is set): set MBGW_PYTHON to a Python that has \
         it, as .ci/run does"
    );
    eprintln!("python3 has no pymodbus and MBGW_PYTHON is not set: this test checks nothing here");
    None
}

/// The bytes the script's cable carried so far, each way.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct Wire {
    pub(crate) to_slave: Vec<u8>,
    pub(crate) to_gateway: Vec<u8>,
}

/// The slave script, running; killed when dropped, whatever the test's outcome. Also the far end
/// of `device_server`'s ser2net.
pub(crate) struct Pymodbus {
    child: Child,
    /// The gateway's end of the cable (or ser2net's).
    pub(crate) path: String,
    wire: Arc<Mutex<Wire>>,
}

impl Pymodbus {
    /// Start the script with `framer` (`rtu`, `ascii`) and wait until pymodbus has its port
    /// open; `None` without Python.
    pub(crate) async fn start(framer: &str) -> Option<Pymodbus> {
        Pymodbus::start_script(SCRIPT, &[framer]).await
    }

    /// [`Pymodbus::start`] for a sibling of the script that serves other tables through its
    /// cable (`tests/peers/pymodbus_values_slave.py`), with `args`.
    pub(crate) async fn start_script(script: &str, args: &[&str]) -> Option<Pymodbus> {
        let python = python_with_pymodbus()?;
        let mut child = Command::new(python)
            .arg(script)
            .args(args)
            // Kept open by `child`: the script exits when it closes, should the kill be missed.
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("python starts");
        let stdout = child.stdout.take().expect("piped stdout");
        let (ready, path) = tokio::sync::oneshot::channel();
        let wire = Arc::new(Mutex::new(Wire::default()));
        let log = Arc::clone(&wire);
        std::thread::spawn(move || {
            let mut ready = Some(ready);
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { return };
                let Some((what, value)) = line.split_once(' ') else {
                    continue;
                };
                let mut wire = log.lock().unwrap();
                match what {
                    "ready" => {
                        if let Some(ready) = ready.take() {
                            let _ = ready.send(value.to_owned());
                        }
                    }
                    "to-slave" => wire.to_slave.extend(unhex(value)),
                    "to-gateway" => wire.to_gateway.extend(unhex(value)),
                    _ => {}
                }
            }
        });
        let mut slave = Pymodbus {
            child,
            path: String::new(),
            wire,
        };
        slave.path = within("pymodbus opens its port", path)
            .await
            .expect("the script says `ready PATH` (its errors are above)");
        Some(slave)
    }

    /// What the cable carried so far.
    pub(crate) fn wire_now(&self) -> Wire {
        self.wire.lock().unwrap().clone()
    }

    /// The wire once `done` holds for it; the last one seen after the patience, whatever it is.
    pub(crate) async fn wire_when(&self, done: impl Fn(&Wire) -> bool) -> Wire {
        let deadline = tokio::time::Instant::now() + crate::support::PATIENCE;
        loop {
            let wire = self.wire_now();
            if done(&wire) || tokio::time::Instant::now() >= deadline {
                return wire;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    /// The wire, once it carried at least these many bytes each way.
    async fn wire(&self, to_slave: usize, to_gateway: usize) -> (Vec<u8>, Vec<u8>) {
        within("the wire log", async {
            loop {
                {
                    let wire = self.wire.lock().unwrap();
                    if wire.to_slave.len() >= to_slave && wire.to_gateway.len() >= to_gateway {
                        return (wire.to_slave.clone(), wire.to_gateway.clone());
                    }
                }
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await
    }
}

impl Drop for Pymodbus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub(crate) fn unhex(text: &str) -> Vec<u8> {
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).expect("the script writes hex"))
        .collect()
}

/// Send each case's request to [`UNIT`] in turn and check its reply PDU; the requests and the
/// replies, each in order, for checking the wire.
async fn call_each<'a>(
    master: &mut RawMaster,
    cases: &[(&'a [u8], &'a [u8])],
    what: &str,
) -> (Vec<&'a [u8]>, Vec<&'a [u8]>) {
    within(what, async {
        for (transaction, (request, reply)) in (1..).zip(cases) {
            assert_eq!(
                master.call(transaction, UNIT, request).await,
                *reply,
                "request {request:02X?}"
            );
        }
    })
    .await;
    cases.iter().copied().unzip()
}

/// Each PDU as an RTU frame to or from [`UNIT`], back to back: what the line carries.
fn frames(pdus: &[&[u8]]) -> Vec<u8> {
    pdus.iter().flat_map(|pdu| rtu::encode(UNIT, pdu)).collect()
}

#[tokio::test]
async fn pymodbus_serial_server_answers_pass_through_the_gateway_byte_for_byte() {
    let Some(slave) = Pymodbus::start("rtu").await else {
        return;
    };
    let gateway = start(&pty_config(&slave.path, RESPONSE_TIMEOUT)).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let (requests, replies) = call_each(&mut master, &FIVE_TRANSACTIONS, "five transactions").await;
    let (to_slave, to_gateway) = slave
        .wire(frames(&requests).len(), frames(&replies).len())
        .await;
    assert_eq!(to_slave, frames(&requests), "the requests on the wire");
    assert_eq!(
        to_gateway,
        frames(&replies),
        "the slave's answers on the wire"
    );
}

#[tokio::test]
async fn a_real_slave_that_ignores_one_masters_function_code_still_answers_another_master() {
    let Some(slave) = Pymodbus::start("rtu").await else {
        return;
    };
    // Each ignored request costs two timeouts (its own, then the window in which a late reply
    // to it is discarded): half a second keeps the ten within the test's patience.
    let gateway = start(&pty_config(&slave.path, "response_timeout = \"500ms\"")).await;
    let mut a = RawMaster::connect(addr(&gateway)).await;
    let mut b = RawMaster::connect(addr(&gateway)).await;

    within("the whole exchange", async {
        assert_eq!(a.call(1, UNIT, &READ).await, READ_REPLY, "A's first read");
        for transaction in 2..12 {
            assert_eq!(
                a.call(transaction, UNIT, &IGNORED).await,
                [0xE4, 0x0B],
                "A's ignored request {transaction}: the gateway's own timeout exception"
            );
        }
        // Right after A's ten: pymodbus is as alive as ever, and B gets its answer.
        assert_eq!(
            b.call(1, UNIT, &READ).await,
            READ_REPLY,
            "B's read, right after A's ignored requests, goes to the slave and is answered"
        );
    })
    .await;

    let mut on_the_line: Vec<&[u8]> = vec![&READ[..]];
    on_the_line.extend([&IGNORED[..]; 10]);
    on_the_line.push(&READ[..]);
    let answers = frames(&[&READ_REPLY[..], &READ_REPLY[..]]);
    let (to_slave, to_gateway) = slave.wire(frames(&on_the_line).len(), answers.len()).await;
    assert_eq!(
        to_slave,
        frames(&on_the_line),
        "every request went on the wire"
    );
    assert_eq!(
        to_gateway, answers,
        "pymodbus answered both reads, nothing else"
    );
    let up = format!("modbus_gateway_slave_up{{bus=\"pty\",slave=\"{UNIT}\"}}");
    assert_eq!(Scrape::of(&gateway).await.value(&up), 1.0);
}

/// A Modbus ASCII frame as read off the wire: its address and PDU.
type AsciiFrame = (u8, Vec<u8>);

/// Every Modbus ASCII frame in `wire`, back to back, read by the spec (Modbus over Serial Line
/// V1.02, 2.5.2) and nothing else: `:`, upper-case hex pairs of address, PDU and LRC, where the
/// LRC makes the byte sum 0, then CR LF. The first byte out of place is an error naming its
/// offset. Not the gateway's `line::ascii`: this is the independent reading, and it is stricter
/// (no lower case, no noise between frames), as it checks what peers send.
fn ascii_frames(wire: &[u8]) -> Result<Vec<AsciiFrame>, String> {
    let digit = |c: u8| match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    };
    let mut frames = Vec::new();
    let mut at = 0;
    while at < wire.len() {
        if wire[at] != b':' {
            return Err(format!(
                "byte {at} is {:?}, not the ':' of a frame",
                char::from(wire[at])
            ));
        }
        let hex_at = at + 1;
        let end = wire[hex_at..]
            .windows(2)
            .position(|pair| pair == b"\r\n")
            .map(|n| hex_at + n)
            .ok_or_else(|| format!("the frame at byte {at} has no CR LF"))?;
        let hex = &wire[hex_at..end];
        let nibbles = hex
            .iter()
            .enumerate()
            .map(|(i, &c)| {
                digit(c).ok_or_else(|| {
                    format!(
                        "byte {} is {:?}, not an upper-case hex digit",
                        hex_at + i,
                        char::from(c)
                    )
                })
            })
            .collect::<Result<Vec<u8>, String>>()?;
        // Address, function code and LRC at least, each a pair.
        if nibbles.len() % 2 != 0 || nibbles.len() < 6 {
            return Err(format!(
                "the frame at byte {at} has {} hex digits",
                nibbles.len()
            ));
        }
        let bytes: Vec<u8> = nibbles.chunks(2).map(|p| p[0] << 4 | p[1]).collect();
        let sum = bytes.iter().fold(0u8, |sum, &b| sum.wrapping_add(b));
        if sum != 0 {
            return Err(format!(
                "the frame at byte {at}: the LRC leaves a byte sum of {sum:02X}, not 00"
            ));
        }
        frames.push((bytes[0], bytes[1..bytes.len() - 1].to_vec()));
        at = end + 2;
    }
    Ok(frames)
}

/// The frames to or from `unit`, as [`ascii_frames`] returns them, and their length on the wire:
/// `:`, two characters for each of address, PDU bytes and LRC, CR LF.
fn ascii_expected(unit: u8, pdus: &[&[u8]]) -> (Vec<AsciiFrame>, usize) {
    let frames = pdus.iter().map(|pdu| (unit, pdu.to_vec())).collect();
    let len = pdus.iter().map(|pdu| 1 + 2 * (pdu.len() + 2) + 2).sum();
    (frames, len)
}

#[test]
fn the_ascii_wire_check_reads_the_manuals_worked_frames_and_refuses_any_other_bytes() {
    // Goodrive20 manual 7.3.2.1: slave 01H, read two words from 0004H, and the reply.
    let request = b":010300040002F6\r\n"; // : 01 03 0004 0002 LRC F6 (sum 0A) CR LF
    let reply = b":010304138800005D\r\n"; // : 01 03 04 1388 0000 LRC 5D (sum A3) CR LF
    let both = [&request[..], &reply[..]].concat();
    assert_eq!(
        ascii_frames(&both),
        Ok(vec![
            (0x01, vec![0x03, 0x00, 0x04, 0x00, 0x02]),
            (0x01, vec![0x03, 0x04, 0x13, 0x88, 0x00, 0x00]),
        ])
    );
    let refused: [(&[u8], &str); 7] = [
        (b":010304138800005d\r\n", "lower-case LRC"),
        (
            b":010300040002F5\r\n",
            "the one's complement, as the manual's C code has it",
        ),
        (b":010300040002F6\r", "CR without LF"),
        (b":010300040002F6\n", "LF without CR"),
        (b"\x00:010300040002F6\r\n", "a byte before the colon"),
        (b":01030004000F6\r\n", "an odd count of hex digits"),
        (b":01FF\r\n", "no function code"),
    ];
    for (wire, what) in refused {
        assert!(
            ascii_frames(wire).is_err(),
            "{what}: {:?}",
            ascii_frames(wire)
        );
    }
}

/// Through the gateway.
#[tokio::test]
async fn pymodbus_ascii_serial_server_answers_every_function_byte_for_byte() {
    let Some(slave) = Pymodbus::start("ascii").await else {
        return;
    };
    // 8N2, as the script's side: ASCII's default 7E1 cannot be had on a pty. It refuses parity;
    // and it keeps 8 data bits whatever it is asked, which the gateway's one setting of the port
    // does not notice but pyserial's second one fails on (the script says more). 7-bit ASCII
    // characters cross it unchanged either way.
    let bus = format!("framing = \"ascii\"\ndata_bits = 8\n{RESPONSE_TIMEOUT}");
    let gateway = start(&pty_config(&slave.path, &bus)).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // (request PDU, pymodbus's reply PDU), from the script's tables: coils on at multiples of 3,
    // discrete inputs on at odd addresses, holding registers 1000 + n, input registers 2000 + n.
    let cases: [(&[u8], &[u8]); 12] = [
        // 01 read coils 0-9: 0, 3, 6 in the first byte (LSB first), 9 in the second.
        (&[0x01, 0x00, 0x00, 0x00, 0x0A], &[0x01, 0x02, 0x49, 0x02]),
        // 02 read discrete inputs 0-11: 1, 3, 5, 7, then 9 and 11.
        (&[0x02, 0x00, 0x00, 0x00, 0x0C], &[0x02, 0x02, 0xAA, 0x0A]),
        // 04 read input registers 0-1: 2000, 2001.
        (
            &[0x04, 0x00, 0x00, 0x00, 0x02],
            &[0x04, 0x04, 0x07, 0xD0, 0x07, 0xD1],
        ),
        READ_HOLDING_0_2,
        // 05 write coil 1 on: echo.
        (
            &[0x05, 0x00, 0x01, 0xFF, 0x00],
            &[0x05, 0x00, 0x01, 0xFF, 0x00],
        ),
        // 05 write coil 3 off: echo.
        (
            &[0x05, 0x00, 0x03, 0x00, 0x00],
            &[0x05, 0x00, 0x03, 0x00, 0x00],
        ),
        // 0F write coils 4-7 = on, off, on, off (one data byte, 0101 LSB first): start, count.
        (
            &[0x0F, 0x00, 0x04, 0x00, 0x04, 0x01, 0x05],
            &[0x0F, 0x00, 0x04, 0x00, 0x04],
        ),
        // 01 read coils 0-9 back: 0, 1, 4, 6 (3 is off now) and 9.
        (&[0x01, 0x00, 0x00, 0x00, 0x0A], &[0x01, 0x02, 0x53, 0x02]),
        WRITES_READ_BACK[0],
        WRITES_READ_BACK[1],
        WRITES_READ_BACK[2],
        WRITES_READ_BACK[3],
    ];
    let (requests, replies) = call_each(&mut master, &cases, "twelve transactions").await;
    let (requests, requests_len) = ascii_expected(UNIT, &requests);
    let (replies, replies_len) = ascii_expected(UNIT, &replies);
    let (to_slave, to_gateway) = slave.wire(requests_len, replies_len).await;
    assert_eq!(
        ascii_frames(&to_slave),
        Ok(requests),
        "the requests on the wire: {}",
        String::from_utf8_lossy(&to_slave)
    );
    assert_eq!(
        ascii_frames(&to_gateway),
        Ok(replies),
        "the slave's answers on the wire: {}",
        String::from_utf8_lossy(&to_gateway)
    );
}

/// An ASCII slave answering in lower-case hex.
#[tokio::test]
async fn a_lower_case_hex_ascii_slave_is_understood_and_its_replies_pass_unchanged() {
    let Some(slave) = Pymodbus::start("ascii-lower").await else {
        return;
    };
    // 8N2: see the test above.
    let bus = format!("framing = \"ascii\"\ndata_bits = 8\n{RESPONSE_TIMEOUT}");
    let gateway = start(&pty_config(&slave.path, &bus)).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // (request PDU, reply PDU): replies whose hex has letters, so lower case shows.
    let cases: [(&[u8], &[u8]); 3] = [
        // 03 read holding registers 0-1: 1000, 1001; on the wire 03e8 03e9.
        (
            &[0x03, 0x00, 0x00, 0x00, 0x02],
            &[0x03, 0x04, 0x03, 0xE8, 0x03, 0xE9],
        ),
        // 04 read input registers 0-1: 2000, 2001; on the wire 07d0 07d1.
        (
            &[0x04, 0x00, 0x00, 0x00, 0x02],
            &[0x04, 0x04, 0x07, 0xD0, 0x07, 0xD1],
        ),
        // 02 read discrete inputs 0-11: odd ones on; on the wire aa 0a.
        (&[0x02, 0x00, 0x00, 0x00, 0x0C], &[0x02, 0x02, 0xAA, 0x0A]),
    ];
    let (requests, replies) = call_each(&mut master, &cases, "three transactions").await;
    let (requests, requests_len) = ascii_expected(UNIT, &requests);
    let (replies, replies_len) = ascii_expected(UNIT, &replies);
    let (to_slave, to_gateway) = slave.wire(requests_len, replies_len).await;
    let answers = String::from_utf8_lossy(&to_gateway);
    assert!(
        to_gateway.iter().any(u8::is_ascii_lowercase)
            && !to_gateway.iter().any(u8::is_ascii_uppercase),
        "the slave answered in lower case: {answers}"
    );
    assert_eq!(
        ascii_frames(&to_gateway.to_ascii_uppercase()),
        Ok(replies),
        "the slave's answers, but for their case: {answers}"
    );
    assert_eq!(
        ascii_frames(&to_slave),
        Ok(requests),
        "the gateway's requests, in upper case: {}",
        String::from_utf8_lossy(&to_slave)
    );
}

/// A child process, killed when dropped, whatever the test's outcome.
struct Running(Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::test]
async fn a_pymodbus_ascii_master_reads_and_writes_the_simulated_drives_on_a_pty() {
    let Some(python) = python_with_pymodbus() else {
        return;
    };
    let mut simulator = Running(
        Command::new(BINARY)
            .args(["--config", ASCII_DEMO, "simulate", "--device", "pty"])
            .env("MBGW__LOG__LEVEL", "warn")
            .env_remove("RUST_LOG")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("the binary runs"),
    );
    let stdout = simulator.0.stdout.take().expect("piped stdout");
    let line = within(
        "simulate announces its pty",
        tokio::task::spawn_blocking(move || {
            let mut line = String::new();
            BufReader::new(stdout).read_line(&mut line).map(|_| line)
        }),
    )
    .await
    .expect("the reading task runs")
    .expect("read simulate's stdout");
    // "serving bus demo-ascii on /dev/pts/N at 9600 baud 7E1 (Modbus ASCII)"
    let path = line
        .split_whitespace()
        .nth(4)
        .unwrap_or_else(|| panic!("unexpected announcement: {line:?}"))
        .to_owned();
    assert!(line.contains("9600 baud 7E1"), "{line}");

    let mut master = Running(
        Command::new(python)
            .args([ASCII_MASTER, &path])
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("python starts"),
    );
    let mut stdout = master.0.stdout.take().expect("piped stdout");
    let output = within(
        "the pymodbus master's run",
        tokio::task::spawn_blocking(move || {
            let mut output = String::new();
            stdout.read_to_string(&mut output).map(|_| output)
        }),
    )
    .await
    .expect("the reading task runs")
    .expect("read the master's stdout");
    // Its stdout is closed: it has exited.
    let status = master.0.wait().expect("wait for the master");
    assert!(status.success(), "the master script: {status}\n{output}");

    let (mut sent, mut received, mut results) = (Vec::new(), Vec::new(), Vec::new());
    for line in output.lines() {
        match line.split_once(' ') {
            Some(("sent", hex)) => sent.extend(unhex(hex)),
            Some(("received", hex)) => received.extend(unhex(hex)),
            Some(("result", result)) => results.push(result),
            _ => panic!("not a line the script writes: {line:?}"),
        }
    }
    // What pymodbus made of the answers: unit, function code, address, words or exception code.
    let expected = [
        // Each drive's identifying code: GD20 0106H, GD300 010AH, GD10 010DH (tripped or not).
        format!("1 03 2103 {}", 0x0106),
        format!("2 03 2103 {}", 0x010A),
        format!("3 03 2103 {}", 0x010D),
        // Unit 2's frequency reference 2001H = 25.00 Hz, and its running value 3001H follows.
        "2 06 2001 2500".to_owned(),
        "2 03 3001 2500".to_owned(),
        // 17 words is one more than a Goodrive reads at once: exception 03, illegal value.
        "2 03 3000 exception 3".to_owned(),
    ];
    assert_eq!(results, expected, "pymodbus's results\n{output}");

    // The same on the wire, as frames to and from each unit.
    let requests: Vec<AsciiFrame> = vec![
        (1, vec![0x03, 0x21, 0x03, 0x00, 0x01]), // read 2103H, one word
        (2, vec![0x03, 0x21, 0x03, 0x00, 0x01]),
        (3, vec![0x03, 0x21, 0x03, 0x00, 0x01]),
        (2, vec![0x06, 0x20, 0x01, 0x09, 0xC4]), // write 2001H = 2500
        (2, vec![0x03, 0x30, 0x01, 0x00, 0x01]), // read 3001H, one word
        (2, vec![0x03, 0x30, 0x00, 0x00, 0x11]), // read 3000H, 17 words
    ];
    let replies: Vec<AsciiFrame> = vec![
        (1, vec![0x03, 0x02, 0x01, 0x06]), // two bytes: 0106H
        (2, vec![0x03, 0x02, 0x01, 0x0A]),
        (3, vec![0x03, 0x02, 0x01, 0x0D]),
        (2, vec![0x06, 0x20, 0x01, 0x09, 0xC4]), // the echo
        (2, vec![0x03, 0x02, 0x09, 0xC4]),       // 2500
        (2, vec![0x83, 0x03]),                   // exception 03
    ];
    assert_eq!(
        ascii_frames(&sent),
        Ok(requests),
        "pymodbus's requests on the wire: {}",
        String::from_utf8_lossy(&sent)
    );
    assert_eq!(
        ascii_frames(&received),
        Ok(replies),
        "the simulated drives' answers on the wire: {}",
        String::from_utf8_lossy(&received)
    );
}

/// pymodbus's network master script.
const NET_MASTER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/peers/pymodbus_net_master.py"
);

/// Run the network master script as `kind` against `addr` for `unit`; its result lines.
async fn net_master(
    python: &OsString,
    kind: &str,
    addr: std::net::SocketAddr,
    unit: u8,
) -> Vec<String> {
    let args = vec![
        NET_MASTER.to_owned(),
        kind.to_owned(),
        addr.ip().to_string(),
        addr.port().to_string(),
        unit.to_string(),
    ];
    let output = run_to_end(python.into(), args).await;
    assert!(output.status.success(), "{kind}: {:?}", output.status);
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(str::to_owned)
        .collect()
}

/// Through the gateway.
#[tokio::test]
async fn pymodbus_rtu_over_tcp_and_udp_masters_write_and_read_the_sim_line() {
    let Some(python) = python_with_pymodbus() else {
        return;
    };
    let gateway = GatewayConfig::new()
        .listen_rtu_over_tcp("127.0.0.1:0")
        .listen_udp("127.0.0.1:0")
        .bus(Bus::sim("sim").baud(115_200).sim_slaves("1-2"))
        .start()
        .await;
    let rtu_over_tcp = gateway.rtu_over_tcp_addrs()[0];
    let udp = gateway.udp_addrs()[0];
    for (kind, addr, unit) in [("rtu-over-tcp", rtu_over_tcp, 1), ("udp", udp, 2)] {
        assert_eq!(
            net_master(&python, kind, addr, unit).await,
            ["result 6 ok", "result 3 4242 0", "result 3 0 0 0"],
            "{kind}"
        );
    }
    // Each wrote its own slave; a Modbus TCP master reads both writes back.
    let mut tcp = crate::support::RawMaster::connect(gateway.tcp_addrs()[0]).await;
    for unit in [1, 2] {
        assert_eq!(
            tcp.call(u16::from(unit), unit, &[0x03, 0x00, 0x05, 0x00, 0x01])
                .await,
            [0x03, 0x02, 0x10, 0x92]
        );
    }
}

/// Through the gateway.
#[tokio::test]
async fn pymodbus_rtu_over_tcp_and_udp_masters_reach_pymodbus_rtu_slave_on_a_pty() {
    let Some(python) = python_with_pymodbus() else {
        return;
    };
    let Some(slave) = Pymodbus::start("rtu").await else {
        return;
    };
    let gateway = GatewayConfig::new()
        .listen_rtu_over_tcp("127.0.0.1:0")
        .listen_udp("127.0.0.1:0")
        .bus(pty_line(&slave.path).text(RESPONSE_TIMEOUT))
        .start()
        .await;
    // The script's registers 0-9 hold 1000-1009; each master writes register 5 and reads it
    // back with register 6, then reads 0-2.
    for (kind, addr) in [
        ("rtu-over-tcp", gateway.rtu_over_tcp_addrs()[0]),
        ("udp", gateway.udp_addrs()[0]),
    ] {
        assert_eq!(
            net_master(&python, kind, addr, UNIT).await,
            [
                "result 6 ok",
                "result 3 4242 1006",
                "result 3 1000 1001 1002"
            ],
            "{kind}"
        );
    }
}

/// Run `program` with `args` to its end (bounded by the patience); its output.
#[tokio::test]
async fn pymodbus_rtu_over_tcp_master_writes_and_reads_simulate_listen_directly() {
    let Some(python) = python_with_pymodbus() else {
        return;
    };
    // simulate serves a file: the register-bank slaves 1-4 of the "sim" line, at 9600 8E1.
    let config = std::env::temp_dir().join(format!("mbgw-listen-{}.toml", std::process::id()));
    std::fs::write(&config, crate::support::sim_config("")).unwrap();
    let simulator =
        crate::simulate::Simulator::listen_with(config.to_str().unwrap(), "127.0.0.1:0", "8E1")
            .await;
    let _ = std::fs::remove_file(&config);
    let addr: std::net::SocketAddr = simulator.path.trim_start_matches("tcp://").parse().unwrap();
    // pymodbus sends each request as soon as the last reply is in: the server keeps the gap.
    assert_eq!(
        net_master(&python, "rtu-over-tcp", addr, 3).await,
        ["result 6 ok", "result 3 4242 0", "result 3 0 0 0"]
    );
    simulator.stop().await;
}

async fn run_to_end(program: std::path::PathBuf, args: Vec<String>) -> std::process::Output {
    let mut command = Command::new(program);
    command.args(args);
    run_command(command).await
}

/// Run `command` to its end (bounded by the patience), its standard error passed through; its
/// output.
async fn run_command(mut command: Command) -> std::process::Output {
    let what = format!("{:?} finishes", command.get_program());
    within(
        &what,
        tokio::task::spawn_blocking(move || command.stderr(Stdio::inherit()).output()),
    )
    .await
    .expect("the task runs")
    .expect("the program runs")
}

/// Run mbpoll (libmodbus's command-line master) with `args`; its standard output.
async fn mbpoll(mbpoll: &std::path::Path, args: Vec<String>) -> String {
    let output = run_to_end(mbpoll.to_owned(), args).await;
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(output.status.success(), "{:?}\n{text}", output.status);
    text
}

#[tokio::test]
async fn mbpoll_writes_and_reads_the_sim_line_over_modbus_tcp_beside_the_other_kinds() {
    // Debian's mbpoll (1.4.11) speaks Modbus TCP and RTU only: neither RTU over TCP nor UDP.
    let Some(tool) = crate::support::tool("mbpoll") else {
        return;
    };
    let gateway = GatewayConfig::new()
        .bus(Bus::sim("sim").baud(115_200).sim_slaves("1-2"))
        .start()
        .await;
    let port = gateway.tcp_addrs()[0].port().to_string();
    let common = |extra: &[&str]| -> Vec<String> {
        let mut args: Vec<String> = ["-m", "tcp", "-p", &port, "-a", "2", "-0", "-1"]
            .iter()
            .map(|s| (*s).to_owned())
            .collect();
        args.extend(extra.iter().map(|s| (*s).to_owned()));
        args
    };
    mbpoll(&tool, common(&["-r", "5", "127.0.0.1", "4242"])).await;
    let read = mbpoll(&tool, common(&["-r", "5", "-c", "2", "127.0.0.1"])).await;
    assert!(read.contains("[5]: \t4242"), "{read}");
    assert!(read.contains("[6]: \t0"), "{read}");
}
