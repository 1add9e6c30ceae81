//! Masters that break the rules on purpose (issue 25): a request with a whole frame hidden after
//! it, to make a slave write for a master that may only read, to cross another master's replies,
//! or to make a healthy slave look dead; every unit id and function code at once, to make the
//! metrics grow without end; protocol errors and refusals in a flood, to drown the log. The
//! slaves that matter here frame requests by their function's length and take what follows as
//! the next request: the simulated line, the `simulate` subcommand on a pty, and libmodbus.
//! And a master on a serial master port (issue 41) that sends noise, frames one byte short,
//! requests to units the port does not answer and writes its rule forbids.

use crate::simulate::Simulator;
use crate::support::tls::{tls_master, Pki, Role};
use crate::support::{
    frames_from, free_addr, http_get, pty_config, pty_line, sim_config_with_server, start, within,
    Bus, GatewayConfig, RawMaster, Scrape,
};
use modbus_gateway::testing::line::rtu;
use modbus_gateway::testing::sim::Source;
use std::io::{BufRead, BufReader, Write};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, ChildStdin, Command, Stdio};
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpStream, UdpSocket};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// Read one holding register at 0000H.
const READ_0: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];
/// Read one holding register at 0005H, the one the hidden write aims at.
const READ_5: [u8; 5] = [0x03, 0x00, 0x05, 0x00, 0x01];
/// Write 1234H to holding register 0005H.
const WRITE_5: [u8; 5] = [0x06, 0x00, 0x05, 0x12, 0x34];
/// What the gateway answers a read of the wrong length: illegal data value.
const BAD_LENGTH: [u8; 2] = [0x83, 0x03];

/// `request` (a PDU to `unit`) followed by the CRC a slave expects after it and then `hidden`, a
/// whole RTU frame: what a length-framing slave takes as two requests.
fn smuggle(unit: u8, request: &[u8], hidden: &[u8]) -> Vec<u8> {
    let first = rtu::encode(unit, request);
    let mut pdu = first[1..].to_vec();
    pdu.extend_from_slice(hidden);
    pdu
}

/// One Modbus UDP request from a fresh source port; the reply's PDU.
async fn udp_call(gateway: SocketAddr, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let socket = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    socket
        .send_to(&RawMaster::adu(7, unit, pdu), gateway)
        .await
        .unwrap();
    let mut buf = [0u8; 300];
    let (n, _) = within("a UDP reply", socket.recv_from(&mut buf))
        .await
        .unwrap();
    buf[7..n].to_vec()
}

#[tokio::test]
async fn a_read_only_master_cannot_hide_a_write_after_a_read_over_tcp_udp_or_tls() {
    let pki = Pki::new("hostile-ca");
    let server = pki.server("gateway", "gateway", 365);
    let tls = pki.tls_table(&server, "roles = { viewer = \"read_only\" }");
    let toml = sim_config_with_server(
        &format!(
            "listen_udp = \"127.0.0.1:0\"\nlisten_tls = \"127.0.0.1:0\"\n\
             read_only = [\"127.0.0.0/8\"]\n{tls}"
        ),
        "",
    );
    let gateway = start(&toml).await;
    let line = gateway.sim_line("sim").unwrap();
    let attacks = [
        // The write to the slave the read goes to, and to every slave at once.
        smuggle(1, &READ_0, &rtu::encode(1, &WRITE_5)),
        smuggle(1, &READ_0, &rtu::encode(0, &WRITE_5)),
    ];
    let mut tcp = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    let viewer = pki.master("viewer", Role::Named("viewer"));
    let mut tls = tls_master(gateway.tls_addrs()[0], &pki.connector(Some(&viewer))).await;
    for attack in &attacks {
        assert_eq!(tcp.call(1, 1, attack).await, BAD_LENGTH, "over TCP");
        let udp = udp_call(gateway.udp_addrs()[0], 1, attack).await;
        assert_eq!(udp, BAD_LENGTH, "over UDP");
        assert_eq!(tls.call(1, 1, attack).await, BAD_LENGTH, "over TLS");
    }
    // Nothing went on the line, so nothing was written.
    assert_eq!(tcp.call(2, 1, &READ_5).await, [0x03, 0x02, 0x00, 0x00]);
    let sent = frames_from(&line, Source::Master);
    assert_eq!(sent, [rtu::encode(1, &READ_5)]);
    let scrape = Scrape::of(&gateway).await;
    for protocol in ["tcp", "udp", "tls"] {
        let series = format!(
            "modbus_gateway_requests_total{{bus=\"sim\",function=\"0x03\",outcome=\"bad_length\",\
             protocol=\"{protocol}\",slave=\"1\"}}"
        );
        assert_eq!(scrape.value(&series), 2.0, "{series}");
    }
}

#[tokio::test]
async fn a_tls_role_limited_to_one_unit_cannot_reach_another_inside_a_request() {
    let pki = Pki::new("hostile-units-ca");
    let server = pki.server("gateway", "gateway", 365);
    let tls = pki.tls_table(
        &server,
        "roles = { unit1 = { access = \"read_write\", units = \"1\" } }",
    );
    let toml = sim_config_with_server(&format!("listen_tls = \"127.0.0.1:0\"\n{tls}"), "");
    let gateway = start(&toml).await;
    let line = gateway.sim_line("sim").unwrap();
    let unit1 = pki.master("unit1", Role::Named("unit1"));
    let mut master = tls_master(gateway.tls_addrs()[0], &pki.connector(Some(&unit1))).await;
    let to_unit_2 = rtu::encode(2, &WRITE_5);
    // A write of unit 1 with unit 2's frame after it: refused for its length.
    let write = smuggle(1, &WRITE_5, &to_unit_2);
    assert_eq!(master.call(1, 1, &write).await, [0x86, 0x03]);
    // A user-defined function code's length cannot be checked: refused to a role held to units.
    let mut custom = vec![0x41];
    custom.extend_from_slice(&to_unit_2);
    assert_eq!(master.call(2, 1, &custom).await, [0xC1, 0x01]);
    // Unit 1 itself is served as before.
    assert_eq!(master.call(3, 1, &WRITE_5).await, WRITE_5);
    let sent = frames_from(&line, Source::Master);
    assert_eq!(sent, [rtu::encode(1, &WRITE_5)]);
}

/// libmodbus as an RTU slave on a pty (tests/peers/libmodbus_slave.py): device 10, holding
/// register N at 1000 + N. Stopped when dropped.
struct Libmodbus {
    child: Child,
    stdin: ChildStdin,
    path: String,
    /// The script's lines after `ready`, as it says them.
    said: tokio::sync::mpsc::UnboundedReceiver<String>,
    /// The requests it took whole and acted on, as hex, up to its last `synced`.
    requests: Vec<String>,
}

const LIBMODBUS_UNIT: u8 = 10;

impl Libmodbus {
    /// `None` (the test checks nothing) without Python's ctypes or libmodbus, unless
    /// `MBGW_REQUIRE_TOOLS` is set: then their absence fails the test.
    async fn start() -> Option<Libmodbus> {
        let python = crate::support::python_with_libmodbus()?;
        let script =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/libmodbus_slave.py");
        let mut child = Command::new(python)
            .arg(script)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .expect("python runs");
        let stdin = child.stdin.take().expect("stdin piped");
        let mut lines = BufReader::new(child.stdout.take().expect("stdout piped")).lines();
        let ready = within(
            "libmodbus opens its port",
            tokio::task::spawn_blocking(move || {
                let first = lines.next();
                (first, lines)
            }),
        )
        .await
        .unwrap();
        let (first, lines) = ready;
        let first = first.expect("a line").expect("utf-8");
        let path = first
            .strip_prefix("ready ")
            .unwrap_or_else(|| panic!("unexpected: {first}"))
            .to_owned();
        let (say, said) = tokio::sync::mpsc::unbounded_channel();
        std::thread::spawn(move || {
            for line in lines.map_while(Result::ok) {
                if say.send(line).is_err() {
                    return;
                }
            }
        });
        Some(Libmodbus {
            child,
            stdin,
            path,
            said,
            requests: Vec::new(),
        })
    }

    /// The function codes of every request it acted on before it answered a master that has
    /// its answer now. Its lines are read on a thread of their own, so an answer can be in
    /// before the line saying its request is: the script answers "sync" with a line after
    /// every request it said, and this reads up to that line.
    async fn functions(&mut self) -> Vec<u8> {
        self.stdin
            .write_all(b"sync\n")
            .expect("the script reads its stdin");
        self.stdin.flush().expect("the script reads its stdin");
        let (said, requests) = (&mut self.said, &mut self.requests);
        within("libmodbus says `synced`", async {
            loop {
                let line = said.recv().await.expect("the script runs");
                if line == "synced" {
                    return;
                }
                if let Some(hex) = line.strip_prefix("request ") {
                    requests.push(hex.to_owned());
                }
            }
        })
        .await;
        requests
            .iter()
            .map(|hex| u8::from_str_radix(&hex[2..4], 16).unwrap())
            .collect()
    }
}

impl Drop for Libmodbus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A config file of its own for `simulate`: register-bank slaves 1-4 at 115200 8N2 (a pty takes
/// no parity). Of its own, so that no test reads it while another writes it.
fn simulate_config() -> PathBuf {
    static MADE: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = MADE.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let dir = std::env::temp_dir().join(format!("mbgw-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(format!("slaves-{n}.toml"));
    let slaves = Bus::sim("slaves")
        .baud(115_200)
        .parity("none")
        .sim_slaves("1-4");
    std::fs::write(
        &path,
        GatewayConfig::new().default_listen().bus(slaves).to_toml(),
    )
    .unwrap();
    path
}

async fn simulate_on_a_pty() -> Simulator {
    let config = simulate_config();
    Simulator::start_with(config.to_str().unwrap(), "pty", "115200 baud 8N2").await
}

/// A gateway on the serial device `path`, every master on loopback read-only.
async fn read_only_gateway_on(path: &str, bus: &str) -> modbus_gateway::Gateway {
    GatewayConfig::new()
        .read_only(&["127.0.0.0/8"])
        .bus(pty_line(path).text(bus))
        .start()
        .await
}

#[tokio::test]
async fn no_hidden_frame_reaches_a_slave_that_frames_by_length() {
    // `simulate`: slave 1, register 5 at 0 until written.
    let simulator = simulate_on_a_pty().await;
    let gateway = read_only_gateway_on(&simulator.path, "").await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    for hidden_to in [1, 0] {
        let attack = smuggle(1, &READ_0, &rtu::encode(hidden_to, &WRITE_5));
        assert_eq!(master.call(1, 1, &attack).await, BAD_LENGTH);
    }
    assert_eq!(master.call(2, 1, &READ_5).await, [0x03, 0x02, 0x00, 0x00]);
    drop(gateway);
    simulator.stop().await;

    // libmodbus: device 10, register 5 at 1005 (03EDH).
    let Some(mut slave) = Libmodbus::start().await else {
        return;
    };
    let gateway = read_only_gateway_on(&slave.path, "").await;
    let mut master = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    let unit = LIBMODBUS_UNIT;
    for hidden_to in [unit, 0] {
        let attack = smuggle(unit, &READ_0, &rtu::encode(hidden_to, &WRITE_5));
        assert_eq!(master.call(1, unit, &attack).await, BAD_LENGTH);
    }
    assert_eq!(
        master.call(2, unit, &READ_5).await,
        [0x03, 0x02, 0x03, 0xED]
    );
    assert_eq!(
        slave.functions().await,
        [0x03],
        "libmodbus acted on the read alone"
    );
}

/// Masters of a gateway on the slave at `path`: one hides a read of register 9 after its read of
/// register 0, again and again, while another reads register 2 and must get exactly that.
async fn no_crossed_replies_with(path: &str, unit: u8) {
    // A second: a Python slave on a loaded machine can take more than 200 ms to answer.
    let gateway = start(&pty_config(path, "response_timeout = \"1s\"")).await;
    let addr = gateway.tcp_addrs()[0];
    let mut polite = RawMaster::connect(addr).await;
    // Registers 2 and 9 hold 1002 and 1009 (libmodbus's from the start).
    for write in [
        [0x06, 0x00, 0x02, 0x03, 0xEA],
        [0x06, 0x00, 0x09, 0x03, 0xF1],
    ] {
        assert_eq!(polite.call(0, unit, &write).await, write);
    }
    let attacker = tokio::spawn(async move {
        let mut master = RawMaster::connect(addr).await;
        let attack = smuggle(
            unit,
            &READ_0,
            &rtu::encode(unit, &[0x03, 0x00, 0x09, 0x00, 0x01]),
        );
        for tid in 0..20 {
            assert_eq!(master.call(tid, unit, &attack).await, BAD_LENGTH);
        }
    });
    for tid in 0..40 {
        assert_eq!(
            polite
                .call(tid, unit, &[0x03, 0x00, 0x02, 0x00, 0x01])
                .await,
            [0x03, 0x02, 0x03, 0xEA],
            "read {tid}"
        );
    }
    attacker.await.unwrap();
}

#[tokio::test]
async fn no_master_gets_another_masters_data_when_one_hides_a_second_read() {
    let simulator = simulate_on_a_pty().await;
    no_crossed_replies_with(&simulator.path, 1).await;
    simulator.stop().await;

    let Some(mut slave) = Libmodbus::start().await else {
        return;
    };
    no_crossed_replies_with(&slave.path, LIBMODBUS_UNIT).await;
    let functions = slave.functions().await;
    assert_eq!(functions[..2], [0x06, 0x06]);
    assert_eq!(
        functions[2..],
        [0x03; 40],
        "only the polite reads reached libmodbus"
    );
}

/// A read-only master sends reads with junk after them (a length-framing slave sees a bad CRC
/// and stays silent) to the slave at `path`, three at a time, between another master's reads of
/// register 5, which answers `register_5`. The slave must stay up.
async fn stays_up_with(path: &str, unit: u8, register_5: [u8; 4]) {
    let gateway = read_only_gateway_on(
        path,
        "response_timeout = \"1s\"\nslave_down_after = 3\nslave_probe_interval = \"10s\"",
    )
    .await;
    let mut attacker = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    let mut polite = RawMaster::connect(gateway.tcp_addrs()[0]).await;
    assert_eq!(polite.call(1, unit, &READ_5).await, register_5);
    let over_long = [0x03, 0x00, 0x00, 0x00, 0x01, 0xAA, 0xBB, 0xCC];
    for round in 0..3u16 {
        for tid in 0..3 {
            assert_eq!(attacker.call(tid, unit, &over_long).await, BAD_LENGTH);
        }
        assert_eq!(
            polite.call(round, unit, &READ_5).await,
            register_5,
            "round {round}"
        );
    }
    let scrape = Scrape::of(&gateway).await;
    let up = format!("modbus_gateway_slave_up{{bus=\"pty\",slave=\"{unit}\"}}");
    assert_eq!(scrape.value(&up), 1.0);
}

#[tokio::test]
async fn over_long_reads_from_a_read_only_master_do_not_put_a_healthy_slave_down() {
    let simulator = simulate_on_a_pty().await;
    stays_up_with(&simulator.path, 1, [0x03, 0x02, 0x00, 0x00]).await;
    simulator.stop().await;

    let Some(slave) = Libmodbus::start().await else {
        return;
    };
    stays_up_with(&slave.path, LIBMODBUS_UNIT, [0x03, 0x02, 0x03, 0xED]).await;
}

/// A request PDU of `function` as long as the gateway's table says (a bare code, a header with a
/// zero count), or five bytes where the table cannot tell: so that every protocol's framing,
/// RTU over TCP's too, takes it whole.
fn well_formed(function: u8) -> Vec<u8> {
    use modbus_gateway::testing::pdu::PduLen;
    if function == 0x2B {
        // Read Device Identification, basic.
        return vec![0x2B, 0x0E, 0x01, 0x00];
    }
    let mut pdu = vec![function, 0x00, 0x00, 0x00, 0x01];
    let Some(row) = modbus_gateway::testing::pdu::function(function) else {
        return pdu;
    };
    loop {
        match row.request.of(&pdu, None) {
            PduLen::Exact(len) => {
                pdu.resize(len, 0);
                return pdu;
            }
            // A count byte reached is zero: the next turn measures the whole.
            PduLen::Need(len) => pdu.resize(len, 0),
            _ => return pdu,
        }
    }
}

/// How long the RTU reply at the front of `inbound` to `request` is, once that can be told.
fn rtu_reply_len(inbound: &[u8], request: &[u8]) -> Option<usize> {
    use modbus_gateway::testing::pdu::PduLen;
    let function = *inbound.get(1)?;
    let pdu_len = if function & 0x80 != 0 {
        2
    } else {
        match modbus_gateway::testing::pdu::function(function)?
            .reply
            .of(&inbound[1..], Some(request))
        {
            PduLen::Exact(len) => len,
            _ => return None,
        }
    };
    (inbound.len() >= pdu_len + 3).then_some(pdu_len + 3)
}

/// The gateway binary, stopped on drop.
struct Process(Child);

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Process {
    /// Resident memory now, from /proc.
    fn rss_kib(&self) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.0.id())).unwrap();
        status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .expect("VmRSS")
    }
}

/// Listen addresses of a gateway process: Modbus TCP, UDP, RTU over TCP, metrics.
struct Addrs {
    tcp: SocketAddr,
    udp: SocketAddr,
    rtu: SocketAddr,
    metrics: SocketAddr,
}

/// Run the binary on `buses` (their buses and routes) with read-only masters, its log (warn and
/// up) in `log`.
async fn run_binary(name: &str, buses: GatewayConfig, log: Option<&PathBuf>) -> (Process, Addrs) {
    run_binary_as(name, buses.read_only(&["127.0.0.0/8"]), log).await
}

/// Run the binary on `config` (buses, routes, masters' rights), its log (warn and up) in `log`.
async fn run_binary_as(
    name: &str,
    buses: GatewayConfig,
    log: Option<&PathBuf>,
) -> (Process, Addrs) {
    let addrs = Addrs {
        tcp: free_addr(),
        udp: free_addr(),
        rtu: free_addr(),
        metrics: free_addr(),
    };
    let dir = std::env::temp_dir().join(format!("mbgw-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join(format!("{name}.toml"));
    let text = buses
        .listen(addrs.tcp)
        .listen_udp(addrs.udp)
        .listen_rtu_over_tcp(addrs.rtu)
        .metrics_listen(addrs.metrics)
        .table("log", &[("level", "warn".into())])
        .to_toml();
    std::fs::write(&config, text).unwrap();
    let stderr = match log {
        Some(path) => Stdio::from(std::fs::File::create(path).unwrap()),
        None => Stdio::null(),
    };
    let child = Command::new(BINARY)
        .args(["--config", config.to_str().unwrap(), "run"])
        .env_remove("RUST_LOG")
        .env_remove("JOURNAL_STREAM")
        .stdout(Stdio::null())
        .stderr(stderr)
        .spawn()
        .expect("binary runs");
    let process = Process(child);
    crate::support::connect_when_listening(addrs.tcp).await;
    (process, addrs)
}

/// Every unit id with every function code from one master, pipelined. RTU over TCP has no
/// silence to end a request whose length its bytes cannot tell: each of those goes alone.
async fn sweep_tcp(addr: SocketAddr, rtu_framing: bool) {
    let mut stream = TcpStream::connect(addr).await.unwrap();
    let mut batches: Vec<Vec<u8>> = vec![Vec::new()];
    for function in 1..=u8::MAX {
        let pdu = well_formed(function);
        let unchecked = modbus_gateway::testing::pdu::function(function).is_none_or(|row| {
            row.request.of(&pdu, None) == modbus_gateway::testing::pdu::PduLen::Unknown
        });
        if rtu_framing && unchecked {
            batches.push(vec![function]);
            batches.push(Vec::new());
        } else if let Some(batch) = batches.last_mut() {
            batch.push(function);
        }
    }
    let mut out = Vec::new();
    for unit in 0..=u8::MAX {
        for batch in batches.iter().filter(|b| !b.is_empty()) {
            out.clear();
            for &function in batch {
                let pdu = well_formed(function);
                if rtu_framing {
                    out.extend_from_slice(&rtu::encode(unit, &pdu));
                } else {
                    out.extend_from_slice(&RawMaster::adu(u16::from(function), unit, &pdu));
                }
            }
            stream.write_all(&out).await.unwrap();
            read_replies(&mut stream, batch, rtu_framing).await;
        }
    }
}

/// One reply to each request of `functions`, in their order.
async fn read_replies(stream: &mut TcpStream, functions: &[u8], rtu_framing: bool) {
    let mut replies = 0;
    let mut inbound = Vec::new();
    while replies < functions.len() {
        let mut chunk = [0u8; 4096];
        let n = within("replies", tokio::io::AsyncReadExt::read(stream, &mut chunk))
            .await
            .unwrap();
        assert!(n > 0, "the gateway closed the connection");
        inbound.extend_from_slice(&chunk[..n]);
        while replies < functions.len() {
            let len = if rtu_framing {
                rtu_reply_len(&inbound, &well_formed(functions[replies]))
            } else if inbound.len() >= 6 {
                let len = 6 + usize::from(u16::from_be_bytes([inbound[4], inbound[5]]));
                (inbound.len() >= len).then_some(len)
            } else {
                None
            };
            let Some(len) = len else { break };
            inbound.drain(..len);
            replies += 1;
        }
    }
}

async fn sweep_udp(addr: SocketAddr) {
    let socket = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut buf = [0u8; 300];
    for unit in 0..=u8::MAX {
        for functions in (1..=u8::MAX).collect::<Vec<_>>().chunks(8) {
            for &function in functions {
                let adu = RawMaster::adu(u16::from(function), unit, &well_formed(function));
                socket.send_to(&adu, addr).await.unwrap();
            }
            for _ in functions {
                within("a UDP reply", socket.recv_from(&mut buf))
                    .await
                    .unwrap();
            }
        }
    }
}

/// Series in a scrape: its lines that are not comments.
fn series_count(text: &str) -> usize {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
        .count()
}

/// Every unit with every function code, over each protocol.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_unit_function_and_protocol_leaves_series_and_memory_flat() {
    // Slaves 1-4 on one simulated line; a second bus whose device never opens, so that units
    // without a route are refused (no_route) instead of timing out on the line.
    let buses = GatewayConfig::new()
        .bus(
            Bus::sim("sim")
                .baud(115_200)
                .parity("none")
                .response_timeout("20ms")
                .sim_slaves("1-4"),
        )
        .bus(Bus::on("absent", "/dev/mbgw-hostile-absent"))
        .route("1-4", "sim", None);
    let (gateway, addrs) = run_binary("sweep", buses, None).await;
    let (_, before) = http_get(addrs.metrics, "/metrics").await;
    sweep_tcp(addrs.tcp, false).await;
    sweep_tcp(addrs.rtu, true).await;
    sweep_udp(addrs.udp).await;
    let (_, after) = http_get(addrs.metrics, "/metrics").await;
    let rss = gateway.rss_kib();
    // 3 x 65,025 requests. Labels bounded by the configuration: 4 slaves and `other`, the
    // table's 19 function codes and `other`, the outcomes, 3 protocols.
    let grown = series_count(&after) - series_count(&before);
    eprintln!("the sweep: {grown} new series, resident memory {rss} KiB");
    assert!(grown < 1500, "{grown} new series:\n{after}");
    assert!(
        !after.contains("slave=\"200\""),
        "a unit id nobody answers at is a label"
    );
    assert!(rss < 32 * 1024, "resident memory {rss} KiB after the sweep");
    let refused = Scrape::parse(after)
        .series_of("modbus_gateway_requests_total")
        .len();
    assert!(refused > 0);
}

/// A master reading and writing every address of a virtual unit (`[[virtual]]`), and every
/// function code at its unit id: it gets exceptions, never a reply it should not, while memory
/// and the series stay flat and the polls stay on time (every read of the laid-out block in
/// between is answered fresh, never 0x0B).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hostile_master_at_a_virtual_unit_leaves_memory_flat_and_the_polls_on_time() {
    let bus = Bus::sim("sim")
        .baud(115_200)
        .parity("none")
        .sim_slaves("1")
        .text(
            "[[bus.slave]]\naddress = 1\npoll_interval = \"100ms\"\n\
             [[bus.slave.value]]\nname = \"level\"\nregister = 0\n\
             [[bus.slave.value]]\nname = \"setpoint\"\nregister = 1\n",
        );
    let unit = "[[virtual]]\nunit = 200\nname = \"v\"\nmax_age = \"2s\"\n\
                [[virtual.register]]\nregister = 0\nvalue = \"sim/1/level\"\n\
                [[virtual.register]]\nregister = 1\nvalue = \"sim/1/setpoint\"\nwritable = true\n\
                [[virtual.register]]\nregister = 0\ntable = \"coil\"\nvalue = \"sim/1/level\"\n";
    let config = GatewayConfig::new().bus(bus).tables(unit);
    let (gateway, addrs) = run_binary_as("virtual", config, None).await;
    let mut master = RawMaster::connect(addrs.tcp).await;
    let block = [0x03, 0, 0, 0, 2];
    let fresh = within("the first poll", async {
        loop {
            let reply = master.call(1, 200, &block).await;
            if reply[0] == 0x03 {
                return reply;
            }
        }
    })
    .await;
    assert_eq!(fresh.len(), 6);
    let (_, before) = http_get(addrs.metrics, "/metrics").await;
    let rss_before = gateway.rss_kib();
    let mut transaction = 0u16;
    let mut call = async |master: &mut RawMaster, pdu: &[u8]| {
        transaction = transaction.wrapping_add(1);
        master.call(transaction, 200, pdu).await
    };
    // Every function code.
    for function in 1..=u8::MAX {
        let reply = call(&mut master, &well_formed(function)).await;
        assert!(
            reply[0] == function || reply[0] == function | 0x80,
            "{function:#04x}: {reply:02X?}"
        );
    }
    // Reads of the most a read may ask across the whole address space, each table.
    for function in 1..=4u8 {
        let most: u32 = if function <= 2 { 2000 } else { 125 };
        for first in (0..=0xFFFFu32).step_by(usize::try_from(most).unwrap()) {
            let count = most.min(0x1_0000 - first);
            let [a, b] = u16::try_from(first).unwrap().to_be_bytes();
            let [c, d] = u16::try_from(count).unwrap().to_be_bytes();
            let reply = call(&mut master, &[function, a, b, c, d]).await;
            assert_eq!(reply, [function | 0x80, 0x02], "{function} from {first}");
        }
        assert_eq!(
            call(&mut master, &block).await[0],
            0x03,
            "fresh after FC {function}"
        );
    }
    // A write to every register and every coil; register 1 alone is writable.
    let mut written = 0;
    for address in 0..=0xFFFFu16 {
        let [a, b] = address.to_be_bytes();
        let reply = call(&mut master, &[0x06, a, b, 0x00, 0x07]).await;
        if reply == [0x06, a, b, 0x00, 0x07] {
            written += 1;
        } else {
            let expected = if address == 0 { 0x01 } else { 0x02 };
            assert_eq!(reply, [0x86, expected], "register {address}");
        }
        let coil = call(&mut master, &[0x05, a, b, 0xFF, 0x00]).await;
        let expected = if address == 0 { 0x01 } else { 0x02 };
        assert_eq!(coil, [0x85, expected], "coil {address}");
        if address % 4096 == 0 {
            assert_eq!(
                call(&mut master, &block).await[0],
                0x03,
                "fresh at {address}"
            );
        }
    }
    assert_eq!(written, 1, "register 1, on slave 1 of the line");
    assert_eq!(call(&mut master, &[0x03, 0, 1, 0, 1]).await[0], 0x03);
    let (_, after) = http_get(addrs.metrics, "/metrics").await;
    let rss = gateway.rss_kib();
    let grown = series_count(&after) - series_count(&before);
    eprintln!(
        "the virtual unit's sweep: {grown} new series, resident memory {rss_before} KiB before, \
         {rss} KiB after"
    );
    assert!(grown < 100, "{grown} new series:\n{after}");
    assert!(
        rss < rss_before + 8 * 1024,
        "resident memory grew from {rss_before} to {rss} KiB"
    );
    let scrape = Scrape::parse(after);
    assert_eq!(
        scrape
            .get("modbus_gateway_poll_errors_total{bus=\"sim\",slave=\"1\",outcome=\"timeout\"}")
            .unwrap_or(0.0),
        0.0
    );
    assert_eq!(
        scrape.value(
            "modbus_gateway_virtual_requests_total{name=\"v\",outcome=\"stale\",unit=\"200\"}"
        ),
        0.0,
        "the polls kept every read fresh"
    );
}

/// Lines of `log` that contain `what`.
fn logged(log: &PathBuf, what: &str) -> usize {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter(|l| l.contains(what))
        .count()
}

#[tokio::test]
async fn a_flood_of_protocol_errors_and_refusals_gets_one_warn_line_per_address_and_kind() {
    let dir = std::env::temp_dir().join(format!("mbgw-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let log = dir.join("flood.log");
    let bus = GatewayConfig::new().bus(
        Bus::sim("sim")
            .baud(115_200)
            .parity("none")
            .sim_slaves("1-4"),
    );
    let (_gateway, addrs) = run_binary("flood", bus, Some(&log)).await;
    for n in 0..50u16 {
        // A broken MBAP header (protocol id 1): the connection is closed.
        let mut stream = TcpStream::connect(addrs.tcp).await.unwrap();
        stream
            .write_all(&[0, 1, 0, 1, 0, 6, 1, 3, 0, 0, 0, 1])
            .await
            .unwrap();
        let mut rest = Vec::new();
        let _ = within(
            "the gateway closes",
            tokio::io::AsyncReadExt::read_to_end(&mut stream, &mut rest),
        )
        .await;
        // A write from a read-only master, and a read of the wrong length, each on its own
        // connection.
        let mut master = RawMaster::connect(addrs.tcp).await;
        assert_eq!(master.call(n, 1, &WRITE_5).await, [0x86, 0x01]);
        let mut master = RawMaster::connect(addrs.tcp).await;
        assert_eq!(master.call(n, 1, &[0x03, 0, 0, 0, 1, 0]).await, BAD_LENGTH);
    }
    // Everything was counted, whatever was logged.
    let (_, text) = http_get(addrs.metrics, "/metrics").await;
    let scrape = Scrape::parse(text);
    assert_eq!(
        scrape.value(
            "modbus_gateway_tcp_connections_closed_total{protocol=\"tcp\",reason=\"protocol_error\"}"
        ),
        50.0
    );
    std::io::stderr().flush().unwrap();
    let closed = logged(&log, "connection closed");
    let read_only = logged(&log, "read-only master");
    let length = logged(&log, "not as long as its function code says");
    assert_eq!(
        (closed, read_only, length),
        (1, 1, 1),
        "{}",
        std::fs::read_to_string(&log).unwrap()
    );
}

/// Holding register `register` of `unit`, read by a Modbus TCP master.
async fn register_over_tcp(addr: SocketAddr, unit: u8, register: u16) -> Vec<u8> {
    let mut master = RawMaster::connect(addr).await;
    let [hi, lo] = register.to_be_bytes();
    master.call(1, unit, &[0x03, hi, lo, 0x00, 0x01]).await
}

/// The series of the hostile port's frames that ended in `outcome`.
fn port_series(outcome: &str) -> String {
    format!("modbus_gateway_serial_requests_total{{outcome=\"{outcome}\",port=\"hostile\"}}")
}

/// The port's count of `outcome` in `text`, a scrape.
fn port_count(text: &str, outcome: &str) -> f64 {
    Scrape::parse(text.to_owned()).value(&port_series(outcome))
}

/// Scrape `metrics` until the port's count of `outcome` is at least `n`; that scrape.
async fn port_counted(metrics: SocketAddr, outcome: &str, n: f64) -> String {
    within(&format!("{n} {outcome} frames counted"), async {
        loop {
            let (_, text) = http_get(metrics, "/metrics").await;
            if port_count(&text, outcome) >= n {
                return text;
            }
            tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        }
    })
    .await
}

/// A master on a serial master port that means harm: garbage at the pty's full speed, frames one
/// byte short, 10,000 requests to units the port does not answer, and a thousand writes to a
/// slave its rule forbids, a broadcast among them. The port keeps answering, the bus keeps
/// serving the network, nothing of it reaches the line (the line's sent bytes are only the good
/// reads'), the forbidden slave's register is as it was, and memory and series stay flat.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hostile_serial_port_master_takes_nothing_down_and_reaches_no_forbidden_slave() {
    use tokio::io::AsyncReadExt;
    let dir = crate::support::TempDir::new("hostile-port");
    let link = dir.join("port");
    let (tcp, metrics) = (free_addr(), free_addr());
    let port = format!(
        "[[server.serial]]\nname = \"hostile\"\ndevice = \"pty:{}\"\nbaud = 115200\n\
         parity = \"none\"\nunits = \"1-2\"\n",
        link.display()
    );
    let mut text = GatewayConfig::new()
        .listen(tcp)
        .server_table(&port)
        .metrics_listen(metrics)
        .table("log", &[("level", "error".into())])
        .bus(
            Bus::sim("sim")
                .baud(115_200)
                .parity("none")
                .sim_slaves("1-4"),
        )
        .to_toml();
    text.push_str(
        "\n[[rule]]\nname = \"nothing from the port writes unit 2\"\nprotocols = [\"serial\"]\n\
         units = 2\nfunctions = \"write\"\naction = \"deny\"\n",
    );
    let config = dir.join("hostile-port.toml");
    std::fs::write(&config, text).unwrap();
    let gateway = Process(
        Command::new(BINARY)
            .args(["--config", config.to_str().unwrap(), "run"])
            .env_remove("RUST_LOG")
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("binary runs"),
    );
    crate::support::connect_when_listening(tcp).await;
    let mut master = within("the port's pty is linked", async {
        loop {
            let opened = tokio_serial::SerialPortBuilderExt::open_native_async(tokio_serial::new(
                link.to_str().unwrap(),
                115_200,
            ));
            if let Ok(port) = opened {
                return port;
            }
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    })
    .await;
    let read_1 = rtu::encode(1, &READ_0);
    let mut reply = vec![0u8; 7];
    // A good read of unit 1, asked again as a master would while the port may still be reading
    // noise (a request that came amid noise is part of it): each try waits longer than
    // `answer_within`, so no late reply to an earlier try can follow.
    let mut answered = async |master: &mut tokio_serial::SerialStream, after: &str| {
        within(&format!("the port answers after {after}"), async {
            loop {
                AsyncWriteExt::write_all(master, &read_1).await.unwrap();
                let wait = std::time::Duration::from_secs(1);
                if tokio::time::timeout(wait, master.read_exact(&mut reply))
                    .await
                    .is_ok()
                {
                    return reply.clone();
                }
            }
        })
        .await
    };
    let first = answered(&mut master, "nothing").await;
    assert_eq!(&first[..3], [0x01, 0x03, 0x02], "{first:02X?}");
    let register_2 = register_over_tcp(tcp, 2, 0).await;
    let (_, before) = http_get(metrics, "/metrics").await;
    let rss_before = gateway.rss_kib();

    // 256 KiB of noise as fast as the pty takes it; no byte is 0, 1 or 2, so that no frame it
    // happens to hold is for a unit the port answers, or a broadcast.
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let noise: Vec<u8> = (0..256 * 1024)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 24) as u8 | 0x03
        })
        .collect();
    AsyncWriteExt::write_all(&mut master, &noise).await.unwrap();
    port_counted(metrics, "bad_frame", port_count(&before, "bad_frame") + 1.0).await;
    assert_eq!(answered(&mut master, "the noise").await, first);

    // Frames one byte short, to units 1 and 2: a read, a write, a write of two registers.
    let shorts = [
        rtu::encode(1, &READ_0),
        rtu::encode(2, &WRITE_5),
        rtu::encode(
            2,
            &[0x10, 0x00, 0x05, 0x00, 0x02, 0x04, 0xBE, 0xEF, 0xBE, 0xEF],
        ),
    ];
    let bad = port_count(&http_get(metrics, "/metrics").await.1, "bad_frame");
    for (n, short) in (1..).zip(shorts.iter().cycle().take(60)) {
        AsyncWriteExt::write_all(&mut master, &short[..short.len() - 1])
            .await
            .unwrap();
        // Each is broken by the silence after it, before the next comes.
        port_counted(metrics, "bad_frame", bad + f64::from(n)).await;
    }
    assert_eq!(answered(&mut master, "the short frames").await, first);

    // 10,000 reads and writes to units the port does not answer, 100 frames to a write.
    let not_addressed = port_count(&http_get(metrics, "/metrics").await.1, "not_addressed");
    let mut units = (3..=247u8).cycle();
    for batch in 1..=100u32 {
        let mut out = Vec::new();
        for _ in 0..100 {
            let unit = units.next().unwrap();
            let pdu: &[u8] = if unit.is_multiple_of(2) {
                &READ_0
            } else {
                &WRITE_5
            };
            out.extend(rtu::encode(unit, pdu));
        }
        AsyncWriteExt::write_all(&mut master, &out).await.unwrap();
        port_counted(
            metrics,
            "not_addressed",
            not_addressed + f64::from(batch * 100),
        )
        .await;
    }
    assert_eq!(
        answered(&mut master, "the units it does not answer").await,
        first
    );

    // A thousand writes to unit 2, which its rule forbids: each refused (0x01), unsent; and
    // broadcasts, which reach unit 2 too, refused and silent.
    for n in 0..1000u16 {
        let [hi, lo] = n.to_be_bytes();
        AsyncWriteExt::write_all(&mut master, &rtu::encode(2, &[0x06, 0x00, 0x00, hi, lo]))
            .await
            .unwrap();
        let mut refused = [0u8; 5];
        within("a refused write", master.read_exact(&mut refused))
            .await
            .unwrap();
        assert_eq!(refused, rtu::encode(2, &[0x86, 0x01])[..], "write {n}");
        if n.is_multiple_of(100) {
            AsyncWriteExt::write_all(&mut master, &rtu::encode(0, &[0x06, 0x00, 0x00, hi, lo]))
                .await
                .unwrap();
        }
    }
    // The next answer is the read's: nothing else was sent back meanwhile.
    assert_eq!(answered(&mut master, "the forbidden writes").await, first);

    let (_, after) = http_get(metrics, "/metrics").await;
    let rss = gateway.rss_kib();
    let scrape = Scrape::parse(after.clone());
    let before = Scrape::parse(before);
    // Only the good reads went on the line, 8 bytes each: the port's answered requests (the
    // refused writes are its exceptions).
    let answered_reads = scrape.delta(&before, &port_series("answered"));
    assert!(answered_reads >= 4.0, "{answered_reads} reads answered");
    assert_eq!(
        scrape.delta(&before, "modbus_gateway_line_sent_bytes_total{bus=\"sim\"}"),
        8.0 * answered_reads,
        "bytes on the line beyond the good reads'"
    );
    assert_eq!(scrape.delta(&before, &port_series("exception")), 1000.0);
    assert_eq!(
        register_over_tcp(tcp, 2, 0).await,
        register_2,
        "unit 2 written"
    );
    assert_eq!(
        scrape.value("modbus_gateway_serial_port_up{port=\"hostile\"}"),
        1.0
    );
    let grown = series_count(&after) - series_count(&before.text);
    eprintln!(
        "the hostile port: {grown} new series, resident memory {rss_before} KiB before, {rss} KiB after"
    );
    assert!(grown < 60, "{grown} new series:\n{after}");
    assert!(
        rss < rss_before + 8 * 1024,
        "resident memory grew from {rss_before} KiB to {rss} KiB"
    );
}
