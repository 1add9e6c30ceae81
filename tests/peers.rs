//! Third-party Modbus peers on the real serial path: pymodbus's RTU serial server (Python, run by
//! `tests/peers/pymodbus_slave.py`) as the slave behind the gateway, on a pty cable. The script's
//! wire log shows every byte either way, so these tests check the line as well as the masters.
//!
//! Python comes from `MBGW_PYTHON` (`.ci/run` points it at a venv with the pinned pymodbus), else
//! a `python3` on the PATH that has pymodbus; without one a test checks nothing and says so, or
//! fails under `MBGW_REQUIRE_TOOLS=1`, as for the other external tools.

use crate::support::{addr, pty_config, start, within, RawMaster, Scrape};
use modbus_gateway::line::rtu;
use std::ffi::OsString;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/peers/pymodbus_slave.py");

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
const RESPONSE_TIMEOUT: &str = "response_timeout = \"300ms\"";

/// A Python that can run the script, if there is one (see the module doc).
fn python_with_pymodbus() -> Option<OsString> {
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
#[derive(Default)]
struct Wire {
    to_slave: Vec<u8>,
    to_gateway: Vec<u8>,
}

/// The slave script, running; killed when dropped, whatever the test's outcome.
struct Pymodbus {
    child: Child,
    /// The gateway's end of the cable.
    path: String,
    wire: Arc<Mutex<Wire>>,
}

impl Pymodbus {
    /// Start the script and wait until pymodbus has its port open; `None` without Python.
    async fn start() -> Option<Pymodbus> {
        let python = python_with_pymodbus()?;
        let mut child = Command::new(python)
            .arg(SCRIPT)
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

fn unhex(text: &str) -> Vec<u8> {
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).expect("the script writes hex"))
        .collect()
}

/// Each PDU as an RTU frame to or from [`UNIT`], back to back: what the line carries.
fn frames(pdus: &[&[u8]]) -> Vec<u8> {
    pdus.iter().flat_map(|pdu| rtu::encode(UNIT, pdu)).collect()
}

#[tokio::test]
async fn pymodbus_serial_server_answers_pass_through_the_gateway_byte_for_byte() {
    let Some(slave) = Pymodbus::start().await else {
        return;
    };
    let gateway = start(&pty_config(&slave.path, RESPONSE_TIMEOUT)).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // (request PDU, pymodbus's reply PDU)
    let cases: [(&[u8], &[u8]); 5] = [
        // 03 read holding registers 0-2: 1000, 1001, 1002.
        (
            &[0x03, 0x00, 0x00, 0x00, 0x03],
            &[0x03, 0x06, 0x03, 0xE8, 0x03, 0xE9, 0x03, 0xEA],
        ),
        // 06 write register 1 = 0x1234: echo.
        (
            &[0x06, 0x00, 0x01, 0x12, 0x34],
            &[0x06, 0x00, 0x01, 0x12, 0x34],
        ),
        // 10 write registers 2-3 = 7, 8: start and count.
        (
            &[0x10, 0x00, 0x02, 0x00, 0x02, 0x04, 0x00, 0x07, 0x00, 0x08],
            &[0x10, 0x00, 0x02, 0x00, 0x02],
        ),
        // 03 read registers 0-3 back: 1000 and both writes.
        (
            &[0x03, 0x00, 0x00, 0x00, 0x04],
            &[0x03, 0x08, 0x03, 0xE8, 0x12, 0x34, 0x00, 0x07, 0x00, 0x08],
        ),
        // 03 read register 0x20, which the slave does not have: exception 02, illegal address.
        (&[0x03, 0x00, 0x20, 0x00, 0x01], &[0x83, 0x02]),
    ];
    within("five transactions", async {
        for (transaction, (request, reply)) in (1..).zip(cases) {
            assert_eq!(
                master.call(transaction, UNIT, request).await,
                reply,
                "request {request:02X?}"
            );
        }
    })
    .await;

    let requests: Vec<&[u8]> = cases.iter().map(|(request, _)| *request).collect();
    let replies: Vec<&[u8]> = cases.iter().map(|(_, reply)| *reply).collect();
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
    let Some(slave) = Pymodbus::start().await else {
        return;
    };
    let gateway = start(&pty_config(&slave.path, RESPONSE_TIMEOUT)).await;
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
