//! The `simulate` subcommand as a user runs it: the demo's drives answering RTU masters on the far
//! end of a pty, a real serial path, and the demo's line on a TCP socket as a serial device server
//! in transparent mode (`--listen`), to raw bytes and to pymodbus's RTU-over-TCP master.

use crate::support::{demo_path, exit_status, rtu, within};
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_modbus::client::{rtu, Reader, Writer};
use tokio_modbus::prelude::SlaveContext;
use tokio_modbus::Slave;
use tokio_serial::{SerialPortBuilderExt, SerialStream};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// The serving process and the path it announced; stopped (and its exit checked) on drop.
pub struct Simulator {
    child: Option<Child>,
    pub path: String,
}

impl Simulator {
    async fn start(device: &str) -> Simulator {
        Self::start_with(demo_path(), device, "9600 baud 8E1").await
    }

    /// `simulate` on `config`'s simulated bus, which must announce `format`.
    pub async fn start_with(config: &str, device: &str, format: &str) -> Simulator {
        Self::start_on(config, &["--device", device], format).await
    }

    /// `simulate --listen listen` on the demo's drives; `path` is `tcp://ADDR`.
    pub async fn listen(listen: &str) -> Simulator {
        Self::listen_with(demo_path(), listen, "9600 baud 8E1").await
    }

    /// `simulate --listen listen` on `config`'s simulated bus, which must announce `format`.
    pub async fn listen_with(config: &str, listen: &str, format: &str) -> Simulator {
        Self::start_on(config, &["--listen", listen], format).await
    }

    async fn start_on(config: &str, on: &[&str], format: &str) -> Simulator {
        let mut child = Command::new(BINARY)
            .args(["--config", config, "simulate"])
            .args(on)
            .env("MBGW__LOG__LEVEL", "warn")
            .env_remove("RUST_LOG")
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("binary runs");
        let stdout = child.stdout.take().expect("stdout piped");
        let line = within(
            "simulate announces its device",
            tokio::task::spawn_blocking(move || {
                let mut line = String::new();
                BufReader::new(stdout).read_line(&mut line).map(|_| line)
            }),
        )
        .await
        .unwrap()
        .unwrap();
        // "serving bus demo on /dev/pts/N at 9600 baud 8E1"
        let path = line
            .split_whitespace()
            .nth(4)
            .unwrap_or_else(|| panic!("unexpected announcement: {line:?}"))
            .to_owned();
        assert!(line.contains(format), "{line}");
        Simulator {
            child: Some(child),
            path,
        }
    }

    /// SIGTERM, then the exit status must be 0.
    pub async fn stop(mut self) {
        let child = self.child.take().expect("running");
        let killed = Command::new("kill")
            .args(["-s", "TERM", &child.id().to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        let status = exit_status(child).await;
        assert_eq!(status.code(), Some(0));
    }
}

impl Drop for Simulator {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

#[tokio::test]
async fn simulate_on_a_new_pty_answers_the_tokio_modbus_rtu_client() {
    let simulator = Simulator::start("pty").await;
    // A pty takes no parity; its bytes pass at once whatever the baud.
    let port = tokio_serial::new(&simulator.path, 9600)
        .open_native_async()
        .expect("the announced pty opens");
    let mut client = rtu::attach_slave(port, Slave(1));
    within("identifying codes", async {
        for (unit, code) in [(1, 0x0106), (2, 0x010A), (3, 0x010D)] {
            client.set_slave(Slave(unit));
            let words = client
                .read_holding_registers(0x2103, 1)
                .await
                .unwrap()
                .unwrap();
            assert_eq!(words, [code], "unit {unit}");
        }
        client.set_slave(Slave(2));
        client
            .write_single_register(0x2001, 2500)
            .await
            .unwrap()
            .unwrap();
        let setpoint = client
            .read_holding_registers(0x3001, 1)
            .await
            .unwrap()
            .unwrap();
        assert_eq!(setpoint, [2500], "the frequency reference follows 2001H");
        // The drive's own exception code comes through: 17 words is too many.
        let refused = client.read_holding_registers(0x3000, 17).await.unwrap();
        assert!(refused.is_err(), "{refused:?}");
    })
    .await;
    drop(client);
    simulator.stop().await;
}

/// Send one frame, read `reply.len()` bytes.
async fn exchange<S>(port: &mut S, request: &[u8], reply_len: usize) -> Vec<u8>
where
    S: AsyncRead + AsyncWrite + Unpin,
{
    port.write_all(request).await.unwrap();
    let mut reply = vec![0u8; reply_len];
    within("the reply", port.read_exact(&mut reply))
        .await
        .unwrap();
    reply
}

#[tokio::test]
async fn simulate_on_a_given_device_reproduces_the_manuals_worked_frames_byte_for_byte() {
    // Our end of the pair plays the RTU master; the simulator opens the other end by its path
    // (with the demo's 8E1, which a pty refuses, so it falls back to no parity).
    let (mut master, tty) = SerialStream::pair().expect("pty pair");
    let path = tokio_serial::SerialPort::name(&tty).expect("pty path");
    let simulator = Simulator::start(&path).await;
    assert_eq!(simulator.path, path);
    // Goodrive manuals: read P00.04 and P00.05 of slave 1 (50.00 Hz and 0.00 Hz by default).
    assert_eq!(
        exchange(
            &mut master,
            &[0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA],
            9
        )
        .await,
        [0x01, 0x03, 0x04, 0x13, 0x88, 0x00, 0x00, 0x7E, 0x9D]
    );
    // Diagnostics 0000 to slave 1: the echo.
    let echo = [0x01, 0x08, 0x00, 0x00, 0x12, 0xAB, 0xAD, 0x14];
    assert_eq!(exchange(&mut master, &echo, 8).await, echo);
    // GD10 manual: state word 1 of slave 1 reads 0003H, stopped.
    assert_eq!(
        exchange(
            &mut master,
            &[0x01, 0x03, 0x21, 0x00, 0x00, 0x01, 0x8E, 0x36],
            7
        )
        .await,
        [0x01, 0x03, 0x02, 0x00, 0x03, 0xF8, 0x45]
    );
    // GD10 manual: P00.01 = 3 is out of range, exception 04.
    assert_eq!(
        exchange(
            &mut master,
            &[0x01, 0x06, 0x00, 0x01, 0x00, 0x03, 0x98, 0x0B],
            5
        )
        .await,
        [0x01, 0x86, 0x04, 0x43, 0xA3]
    );
    drop(tty);
    simulator.stop().await;
}

#[tokio::test]
async fn simulate_on_an_ascii_bus_answers_the_manuals_ascii_frames_byte_for_byte() {
    // The demo's drives on config/demo-ascii.toml's 9600 7E1 ASCII line; our end of the pty pair
    // plays the ASCII master (a pty refuses even parity, so the simulator falls back to none).
    let config = concat!(env!("CARGO_MANIFEST_DIR"), "/config/demo-ascii.toml");
    let (mut master, tty) = SerialStream::pair().expect("pty pair");
    let path = tokio_serial::SerialPort::name(&tty).expect("pty path");
    let simulator = Simulator::start_with(config, &path, "7E1 (Modbus ASCII)").await;
    // Goodrive manuals, ASCII mode: read 0004H-0005H of slave 01H (50.00 Hz and 0.00 Hz).
    let reply = b":010304138800005D\r\n";
    assert_eq!(
        exchange(&mut master, b":010300040002F6\r\n", reply.len()).await,
        reply
    );
    // The same with lower-case hex from the master, and a write echoed: P00.11 (000BH) = 50.
    let write = b":0106000b0032bc\r\n";
    assert_eq!(
        exchange(&mut master, write, write.len()).await,
        b":0106000B0032BC\r\n"
    );
    // A frame whose LRC fails is ignored: the next request's reply is the first to come.
    master.write_all(b":010300040002F7\r\n").await.unwrap();
    let p00_05 = b":0103020000FA\r\n";
    assert_eq!(
        exchange(&mut master, b":010300050001F6\r\n", p00_05.len()).await,
        p00_05
    );
    drop(tty);
    simulator.stop().await;
}

/// A client of `simulate --listen` at its announced `tcp://ADDR`.
async fn connect(simulator: &Simulator) -> TcpStream {
    let addr = simulator
        .path
        .strip_prefix("tcp://")
        .unwrap_or_else(|| panic!("not a tcp:// address: {}", simulator.path));
    let stream = within("connecting", TcpStream::connect(addr))
        .await
        .expect("the announced address takes connections");
    stream.set_nodelay(true).unwrap();
    stream
}

/// Goodrive manuals: read P00.04 and P00.05 of slave 1 (50.00 Hz and 0.00 Hz by default).
const READ_P00_04: [u8; 8] = [0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA];
const P00_04_REPLY: [u8; 9] = [0x01, 0x03, 0x04, 0x13, 0x88, 0x00, 0x00, 0x7E, 0x9D];

#[tokio::test]
async fn simulate_listen_serves_the_line_raw_on_tcp_one_client_at_a_time_with_state_kept() {
    let simulator = Simulator::listen("127.0.0.1:0").await;
    let mut client = connect(&simulator).await;
    let sent = Instant::now();
    assert_eq!(exchange(&mut client, &READ_P00_04, 9).await, P00_04_REPLY);
    // The request and the reply crossed a 9600 baud 8E1 wire: 17 characters of 11 bits.
    assert!(sent.elapsed() >= Duration::from_micros(17 * 11 * 1_000_000 / 9600));
    // Split mid-frame into two TCP segments, it is still one request and one reply.
    client.write_all(&READ_P00_04[..3]).await.unwrap();
    // scenario: a gap between the two segments, so they are not sent as one.
    tokio::time::sleep(Duration::from_millis(20)).await;
    assert_eq!(
        exchange(&mut client, &READ_P00_04[3..], 9).await,
        P00_04_REPLY
    );
    // Slave 2's frequency reference (2001H) = 25.00 Hz, echoed.
    let write = rtu(2, &[0x06, 0x20, 0x01, 0x09, 0xC4]);
    assert_eq!(exchange(&mut client, &write, write.len()).await, write);
    // A second master while this one is served is refused: closed without a byte.
    let mut second = connect(&simulator).await;
    let mut rest = Vec::new();
    let refused = within("the refusal", second.read_to_end(&mut rest)).await;
    assert!(
        rest.is_empty() && refused.is_ok_or_reset(),
        "{refused:?} {rest:?}"
    );
    drop(client);
    // The next client is served, by the same slaves: 3001H follows 2001H. One that connects
    // before the simulator has seen the first one's end is refused as the second was: again.
    let reply = within("the next client served", async {
        loop {
            let mut client = connect(&simulator).await;
            let request = rtu(2, &[0x03, 0x30, 0x01, 0x00, 0x01]);
            let mut reply = vec![0u8; 7];
            if client.write_all(&request).await.is_ok()
                && client.read_exact(&mut reply).await.is_ok()
            {
                break reply;
            }
            tokio::task::yield_now().await;
        }
    })
    .await;
    assert_eq!(reply, rtu(2, &[0x03, 0x02, 0x09, 0xC4]));
    simulator.stop().await;
}

/// What reading a refused connection may give: its end, or a reset if our bytes were unread.
trait Refusal {
    fn is_ok_or_reset(&self) -> bool;
}

impl Refusal for std::io::Result<usize> {
    fn is_ok_or_reset(&self) -> bool {
        match self {
            Ok(n) => *n == 0,
            Err(e) => e.kind() == std::io::ErrorKind::ConnectionReset,
        }
    }
}

#[tokio::test]
async fn simulate_listen_on_an_address_in_use_exits_1_naming_it() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let output = within(
        "simulate gives up",
        tokio::task::spawn_blocking({
            let addr = addr.clone();
            move || {
                Command::new(BINARY)
                    .args(["--config", demo_path(), "simulate", "--listen", &addr])
                    .env_remove("RUST_LOG")
                    .output()
            }
        }),
    )
    .await
    .unwrap()
    .unwrap();
    assert_eq!(output.status.code(), Some(1));
    let log = String::from_utf8_lossy(&output.stdout) + String::from_utf8_lossy(&output.stderr);
    assert!(log.contains(&format!("cannot listen on {addr}")), "{log}");
}

#[tokio::test]
async fn simulate_listen_on_an_ascii_bus_carries_ascii_frames_split_across_segments() {
    let config = concat!(env!("CARGO_MANIFEST_DIR"), "/config/demo-ascii.toml");
    let simulator = Simulator::listen_with(config, "127.0.0.1:0", "7E1 (Modbus ASCII)").await;
    let mut client = connect(&simulator).await;
    // Goodrive manuals, ASCII mode: read 0004H-0005H of slave 01H, its LF in the second segment.
    client.write_all(b":010300040002").await.unwrap();
    // scenario: a gap between the two segments, so they are not sent as one.
    tokio::time::sleep(Duration::from_millis(20)).await;
    let reply = b":010304138800005D\r\n";
    assert_eq!(exchange(&mut client, b"F6\r\n", reply.len()).await, reply);
    drop(client);
    simulator.stop().await;
}

/// Run `line`, one of docs/command-line.md's mbpoll reads of the pty, on `path` instead of the
/// page's; whether it succeeded, and the last line it printed.
async fn mbpoll_read(line: &str, path: &str) -> (bool, String) {
    let command = line.split('#').next().unwrap().replace("/dev/pts/5", path);
    let args: Vec<String> = command.split_whitespace().map(str::to_owned).collect();
    let output = within(
        "mbpoll reads",
        tokio::task::spawn_blocking(move || Command::new(&args[0]).args(&args[1..]).output()),
    )
    .await
    .unwrap()
    .expect("mbpoll runs");
    let printed = String::from_utf8_lossy(&output.stdout) + String::from_utf8_lossy(&output.stderr);
    let last = printed
        .lines()
        .rfind(|line| !line.trim().is_empty())
        .unwrap_or_default()
        .to_owned();
    (output.status.success(), last)
}

#[tokio::test]
async fn mbpoll_on_the_pty_fails_unit_4_as_the_command_line_page_says() {
    let page = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/command-line.md"));
    let reads: Vec<&str> = page
        .lines()
        .filter(|line| line.starts_with("mbpoll -m rtu ") && line.contains(" /dev/pts/5 "))
        .collect();
    assert_eq!(reads.len(), 2, "the page's reads of unit 2 and unit 4");
    assert!(
        reads[0].contains("-a 2 ") && reads[1].contains("-a 4 "),
        "{reads:?}"
    );
    if crate::support::tool("mbpoll").is_none() {
        return;
    }
    let simulator = Simulator::start_with(demo_path(), "pty", "9600 baud 8E1").await;
    let path = &simulator.path;
    let (ok, last) = mbpoll_read(reads[0], path).await;
    assert!(ok && last.ends_with("0x010A"), "{last}");
    // Unit 4's reply read as a standard one: its CRC is wrong, and three bytes stay on the pty.
    let failed = "Read output (holding) register failed: ";
    assert_eq!(
        mbpoll_read(reads[1], path).await,
        (false, format!("{failed}Invalid CRC"))
    );
    // They begin the next reply read, of unit 2; what that leaves spoils unit 4's read again.
    assert_eq!(
        mbpoll_read(reads[0], path).await,
        (false, format!("{failed}Response not from requested slave"))
    );
    assert_eq!(
        mbpoll_read(reads[1], path).await,
        (false, format!("{failed}Connection timed out"))
    );
    // Then nothing is left over, and unit 2 reads again.
    let (ok, last) = mbpoll_read(reads[0], path).await;
    assert!(ok && last.ends_with("0x010A"), "{last}");
    simulator.stop().await;
}
