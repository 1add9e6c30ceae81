//! Modbus/TCP Security: masters on TLS with certificates made at test time; what each role may
//! do, who is refused at the handshake, and that a refusal disturbs nobody else, nor do peers
//! that stay silent or stall mid-handshake.

use crate::support::tls::{
    connector_with, days_from_now, tls_connect, tls_connect_from, tls_master, Issued, Pki, Role,
};
use crate::support::{
    assert_fair, connect_from, crowded_line, exit_status, free_addr, panics_on_this_thread, signal,
    sim_config_with_server, start, until_logged, within, Bus, GatewayConfig, RawMaster, Rotation,
    Scrape,
};
use modbus_gateway::Gateway;
use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::Barrier;

/// Read holding register 0x0010, one word.
const READ: [u8; 5] = [0x03, 0x00, 0x10, 0x00, 0x01];
/// Write 0x1234 to holding register 0x0010.
const WRITE: [u8; 5] = [0x06, 0x00, 0x10, 0x12, 0x34];
/// What the register bank holds there until written.
const READ_ANSWER: [u8; 4] = [0x03, 0x02, 0x00, 0x00];
/// Exception 0x01 (illegal function) to each.
const READ_REFUSED: [u8; 2] = [0x83, 0x01];
const WRITE_REFUSED: [u8; 2] = [0x86, 0x01];

const ROLES: &str = "roles = { operator = \"read_write\", viewer = \"read_only\" }";

/// A CA, the gateway's certificate, and a gateway on the sim line (slaves 1-4) with a TLS
/// listener and `tls_extra` in `[server.tls]`.
async fn tls_gateway(tls_extra: &str) -> (Pki, Issued, Gateway) {
    tls_gateway_with("", tls_extra).await
}

/// [`tls_gateway`] with `server_extra` in `[server]` too.
async fn tls_gateway_with(server_extra: &str, tls_extra: &str) -> (Pki, Issued, Gateway) {
    let pki = Pki::new("plant-ca");
    let (server, gateway) = tls_gateway_of(&pki, server_extra, tls_extra).await;
    (pki, server, gateway)
}

/// [`tls_gateway_with`] on the CA `pki`.
async fn tls_gateway_of(pki: &Pki, server_extra: &str, tls_extra: &str) -> (Issued, Gateway) {
    let server = pki.server("gateway", "gateway", 365);
    let toml = sim_config_with_server(
        &format!(
            "listen_tls = \"127.0.0.1:0\"\n{server_extra}\n{}",
            pki.tls_table(&server, tls_extra)
        ),
        "",
    );
    let gateway = start(&toml).await;
    (server, gateway)
}

fn tls_addr(gateway: &Gateway) -> SocketAddr {
    gateway.tls_addrs()[0]
}

fn requests(outcome: &str, function: &str) -> String {
    format!(
        "modbus_gateway_requests_total{{bus=\"sim\",function=\"{function}\",outcome=\"{outcome}\",\
         protocol=\"tls\",slave=\"1\"}}"
    )
}

fn accepted(role: &str) -> String {
    format!("modbus_gateway_tls_connections_accepted_total{{role=\"{role}\"}}")
}

const HANDSHAKE_FAILED: &str = "modbus_gateway_tcp_connections_rejected_total{protocol=\"tls\",\
                                reason=\"tls_handshake\"}";

#[tokio::test]
async fn an_operator_certificate_reads_and_writes() {
    let (pki, _server, gateway) = tls_gateway(ROLES).await;
    let operator = pki.master("operator", Role::Named("operator"));
    let mut master = tls_master(tls_addr(&gateway), &pki.connector(Some(&operator))).await;
    assert_eq!(master.call(1, 1, &WRITE).await, WRITE, "the write's echo");
    assert_eq!(master.call(2, 1, &READ).await, [0x03, 0x02, 0x12, 0x34]);
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(&requests("ok", "0x06")), 1.0);
    assert_eq!(scrape.value(&accepted("operator")), 1.0);
    assert_eq!(
        scrape.value("modbus_gateway_tcp_connections{protocol=\"tls\"}"),
        1.0
    );
}

#[tokio::test]
async fn tls_1_2_and_tls_1_3_masters_are_both_served() {
    let (pki, _server, gateway) = tls_gateway(ROLES).await;
    let operator = pki.master("operator", Role::Named("operator"));
    for version in [&rustls::version::TLS12, &rustls::version::TLS13] {
        let connector = connector_with(&pki.ca_path, Some(&operator), &[version]);
        let session = tls_connect(tls_addr(&gateway), &connector)
            .await
            .expect("handshake");
        let negotiated = session.get_ref().1.protocol_version();
        assert_eq!(negotiated, Some(version.version));
        let mut master = RawMaster::over(session);
        assert_eq!(
            master.call(1, 1, &READ).await,
            READ_ANSWER,
            "{negotiated:?}"
        );
    }
}

#[tokio::test]
async fn a_viewer_reads_and_gets_exception_01_for_writes_which_never_reach_the_line() {
    let (pki, _server, gateway) = tls_gateway(ROLES).await;
    let viewer = pki.master("viewer", Role::Named("viewer"));
    let line = gateway.sim_line("sim").expect("sim line");
    let mut master = tls_master(tls_addr(&gateway), &pki.connector(Some(&viewer))).await;
    assert_eq!(master.call(1, 1, &READ).await, READ_ANSWER);
    let frames_after_read = line.frames().len();
    assert_eq!(master.call(2, 1, &WRITE).await, WRITE_REFUSED);
    // Write multiple registers, and a user-defined code: refused as well.
    let write_many = [0x10, 0x00, 0x10, 0x00, 0x01, 0x02, 0xAB, 0xCD];
    assert_eq!(master.call(3, 1, &write_many).await, [0x90, 0x01]);
    assert_eq!(master.call(4, 1, &[0x41, 0x00]).await, [0xC1, 0x01]);
    assert_eq!(
        line.frames().len(),
        frames_after_read,
        "nothing more on the line"
    );
    assert_eq!(master.call(5, 1, &READ).await, READ_ANSWER);
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(&requests("read_only", "0x06")), 1.0);
    assert_eq!(scrape.value(&accepted("viewer")), 1.0);
}

/// Without a role, or with one not listed.
#[tokio::test]
async fn a_certificate_without_a_listed_role_gets_the_default_role_access() {
    // By default: nothing, not even reads.
    let (pki, _server, gateway) = tls_gateway(ROLES).await;
    let line = gateway.sim_line("sim").expect("sim line");
    for (file, role) in [
        ("anonymous", Role::Without),
        ("intern", Role::Named("intern")),
    ] {
        let certificate = pki.master(file, role);
        let mut master = tls_master(tls_addr(&gateway), &pki.connector(Some(&certificate))).await;
        assert_eq!(master.call(1, 1, &READ).await, READ_REFUSED, "{file}");
        assert_eq!(master.call(2, 1, &WRITE).await, WRITE_REFUSED, "{file}");
    }
    assert!(line.frames().is_empty(), "nothing reached the line");
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(&requests("no_access", "0x03")), 2.0);
    assert_eq!(scrape.value(&accepted("other")), 2.0);

    // With default_role_access = "read_only": they read, and may not write.
    let (pki, _server, gateway) =
        tls_gateway(&format!("{ROLES}\ndefault_role_access = \"read_only\"")).await;
    let anonymous = pki.master("anonymous", Role::Without);
    let mut master = tls_master(tls_addr(&gateway), &pki.connector(Some(&anonymous))).await;
    assert_eq!(master.call(1, 1, &READ).await, READ_ANSWER);
    assert_eq!(master.call(2, 1, &WRITE).await, WRITE_REFUSED);
}

#[tokio::test]
async fn a_role_with_units_may_address_those_units_only() {
    let (pki, _server, gateway) =
        tls_gateway("roles = { line-b = { access = \"read_write\", units = \"2-3\" } }").await;
    let line = gateway.sim_line("sim").expect("sim line");
    let line_b = pki.master("line-b", Role::Named("line-b"));
    let mut master = tls_master(tls_addr(&gateway), &pki.connector(Some(&line_b))).await;
    assert_eq!(master.call(1, 2, &WRITE).await, WRITE);
    assert_eq!(master.call(2, 3, &READ).await, READ_ANSWER);
    let frames = line.frames().len();
    assert_eq!(master.call(3, 1, &READ).await, READ_REFUSED, "unit 1");
    assert_eq!(master.call(4, 4, &WRITE).await, WRITE_REFUSED, "unit 4");
    assert_eq!(line.frames().len(), frames, "nothing more on the line");
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(&requests("no_access", "0x03")), 1.0);
    assert_eq!(scrape.value(&accepted("line-b")), 1.0);
}

#[tokio::test]
async fn a_read_only_address_keeps_an_operator_certificate_to_reads() {
    let (pki, _server, gateway) = tls_gateway_with("read_only = \"127.0.0.1\"", ROLES).await;
    let operator = pki.master("operator", Role::Named("operator"));
    let mut master = tls_master(tls_addr(&gateway), &pki.connector(Some(&operator))).await;
    assert_eq!(master.call(1, 1, &READ).await, READ_ANSWER);
    assert_eq!(master.call(2, 1, &WRITE).await, WRITE_REFUSED);
}

/// True once the session is closed: a reply never comes.
async fn refused(mut master: RawMaster) -> bool {
    master.send(9, 1, &READ).await;
    master.is_closed().await
}

/// A foreign CA, an expired certificate, no certificate and plain TCP are each refused.
#[tokio::test]
async fn bad_certificates_and_plain_tcp_are_refused_while_other_masters_are_served() {
    let panics = panics_on_this_thread();
    let (pki, _server, gateway) = tls_gateway(ROLES).await;
    let at = tls_addr(&gateway);
    let operator = pki.master("operator", Role::Named("operator"));
    let mut working = tls_master(at, &pki.connector(Some(&operator))).await;
    assert_eq!(working.call(1, 1, &READ).await, READ_ANSWER);

    // A certificate with the operator role, from a CA the gateway does not trust.
    let rogue = Pki::new("rogue-ca");
    let forged = rogue.master("operator", Role::Named("operator"));
    // It trusts the gateway's CA, so only the gateway can refuse it.
    let connector = pki.connector(Some(&forged));
    let expired = pki.master_valid("expired", Role::Named("operator"), (-30, -1));
    // A certificate of the right CA, but for servers only (extended key usage serverAuth).
    let server_only = pki.server("server-only", "operator", 365);
    let attempts: [(&str, tokio_rustls::TlsConnector); 4] = [
        ("another CA", connector),
        ("expired", pki.connector(Some(&expired))),
        ("no certificate", pki.connector(None)),
        ("a server certificate", pki.connector(Some(&server_only))),
    ];
    for (n, (what, connector)) in attempts.into_iter().enumerate() {
        // TLS 1.3 lets the client finish before the server has checked its certificate: the
        // refusal is a closed session either way.
        if let Ok(session) = tls_connect(at, &connector).await {
            assert!(refused(RawMaster::over(session)).await, "{what}: closed");
        }
        let tid = 10 + n as u16;
        assert_eq!(
            working.call(tid, 1, &READ).await,
            READ_ANSWER,
            "after {what}, the operator is still served"
        );
    }
    // A Modbus TCP master on the TLS port gets no answer: at most a TLS alert record (content
    // type 0x15), then the connection closes.
    let mut plain = tokio::net::TcpStream::connect(at).await.expect("connect");
    plain
        .write_all(&RawMaster::adu(1, 1, &READ))
        .await
        .expect("send");
    let mut got = Vec::new();
    let _ = within("plain TCP is closed", plain.read_to_end(&mut got)).await;
    assert!(
        got.is_empty() || got[0] == 0x15,
        "not a Modbus reply: {got:02X?}"
    );
    assert_eq!(working.call(20, 1, &READ).await, READ_ANSWER);

    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(HANDSHAKE_FAILED), 5.0);
    assert_eq!(
        scrape.value(&accepted("operator")),
        1.0,
        "only the operator"
    );
    assert_eq!(panics_on_this_thread(), panics);
}

#[tokio::test]
async fn a_certificate_the_crl_revokes_is_refused_and_the_others_are_served() {
    let pki = Pki::new("plant-ca");
    let stolen = pki.master("stolen-hmi", Role::Named("operator"));
    let operator = pki.master("operator", Role::Named("operator"));
    let crl = pki.crl("plant-ca.crl", &[&stolen]);
    let tls_extra = format!("{ROLES}\ncrl = \"{}\"", crl.display());
    let (_server, gateway) = tls_gateway_of(&pki, "", &tls_extra).await;
    let at = tls_addr(&gateway);
    if let Ok(session) = tls_connect(at, &pki.connector(Some(&stolen))).await {
        assert!(refused(RawMaster::over(session)).await, "revoked: closed");
    }
    let mut master = tls_master(at, &pki.connector(Some(&operator))).await;
    assert_eq!(master.call(1, 1, &WRITE).await, WRITE);
    assert_eq!(Scrape::of(&gateway).await.value(HANDSHAKE_FAILED), 1.0);
}

#[tokio::test(start_paused = true)]
async fn a_peer_that_never_finishes_its_handshake_is_closed_at_the_handshake_timeout() {
    let (_pki, _server, gateway) = tls_gateway("handshake_timeout = \"4s\"").await;
    let mut silent = tokio::net::TcpStream::connect(tls_addr(&gateway))
        .await
        .expect("connect");
    let started = tokio::time::Instant::now();
    // The header of a handshake record whose 64 bytes never come: past the first bytes, so the
    // handshake timeout (not the 3 s for a peer that sends nothing) closes it.
    silent
        .write_all(&[0x16, 0x03, 0x01, 0x00, 0x40])
        .await
        .expect("send");
    let mut byte = [0u8; 1];
    let read = within("the gateway closes", silent.read(&mut byte)).await;
    assert!(matches!(read, Ok(0) | Err(_)), "closed: {read:?}");
    let waited = started.elapsed();
    assert!(
        (std::time::Duration::from_secs(4)..std::time::Duration::from_secs(5)).contains(&waited),
        "closed after {waited:?}"
    );
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(HANDSHAKE_FAILED), 1.0);
    drop(silent.write_all(b"late").await);
}

#[tokio::test]
async fn the_server_certificate_expiry_is_exported_as_a_unix_time() {
    let (_pki, server, gateway) = tls_gateway(ROLES).await;
    let scrape = Scrape::of(&gateway).await;
    let expiry = scrape.value("modbus_gateway_tls_certificate_expiry_seconds");
    assert!(
        (expiry - days_from_now(365)).abs() < 120.0,
        "expiry {expiry}, certificate {}",
        server.cert_path.display()
    );
}

const MASTERS: usize = 200;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_hundred_tls_masters_polling_at_once_are_answered_correctly_and_fairly() {
    let pki = Pki::new("plant-ca");
    let server = pki.server("gateway", "gateway", 365);
    let gateway = GatewayConfig::new()
        .listen_tls("127.0.0.1:0")
        .server_table(&pki.tls_table(&server, "roles = { viewer = \"read_only\" }"))
        .bus(crowded_line())
        .start()
        .await;
    let at = tls_addr(&gateway);
    let viewer = pki.master("viewer", Role::Named("viewer"));
    let connector = pki.connector(Some(&viewer));
    let barrier = Arc::new(Barrier::new(MASTERS));
    let rotation = Rotation::new(MASTERS);
    let mut masters = Vec::new();
    for m in 0..MASTERS {
        let (barrier, rotation, connector) = (barrier.clone(), rotation.clone(), connector.clone());
        masters.push(tokio::spawn(async move {
            let mut master = tls_master(at, &connector).await;
            let unit = 1 + (m % 4) as u8;
            // Input register N reads N: each master asks for its own and checks the answer.
            let register = m as u16;
            let request = [0x04, (register >> 8) as u8, register as u8, 0x00, 0x01];
            barrier.wait().await;
            let mut counted = 0usize;
            for tid in 1.. {
                let pdu = master.call(tid, unit, &request).await;
                assert_eq!(pdu, [0x04, 0x02, request[1], request[2]], "master {m}");
                match rotation.completed() {
                    None => break,
                    Some(counts) => counted += usize::from(counts),
                }
            }
            counted
        }));
    }
    assert_fair(masters, "TLS master").await;
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(&accepted("viewer")), MASTERS as f64);
}

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// The certificate a TLS session's server presented.
fn server_certificate(
    session: &tokio_rustls::client::TlsStream<tokio::net::TcpStream>,
) -> rustls::pki_types::CertificateDer<'static> {
    let certificates = session
        .get_ref()
        .1
        .peer_certificates()
        .expect("a server certificate");
    certificates[0].clone().into_owned()
}

/// A TLS session with a gateway process, once it listens on `addr`.
async fn tls_session_when_listening(
    addr: SocketAddr,
    connector: &tokio_rustls::TlsConnector,
) -> tokio_rustls::client::TlsStream<tokio::net::TcpStream> {
    within("the gateway listens", async {
        loop {
            if let Ok(session) = tls_connect(addr, connector).await {
                return session;
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    })
    .await
}

/// Open connections keep theirs; a broken key is refused by name.
#[tokio::test]
async fn sighup_rotates_the_certificate_for_new_masters_and_names_a_broken_key() {
    let pki = Pki::new("plant-ca");
    let first = pki.server("gateway", "gateway-2026", 365);
    let (listen, tls, metrics) = (free_addr(), free_addr(), free_addr());
    let config = pki.dir.join("gateway.toml");
    let log = pki.dir.join("gateway.log");
    let text = GatewayConfig::new()
        .listen(listen)
        .listen_tls(tls)
        .server_table(&pki.tls_table(&first, ROLES))
        .metrics_listen(metrics)
        .bus(Bus::sim("sim").baud(115_200).sim_slaves("1"))
        .to_toml();
    std::fs::write(&config, text).unwrap();
    let child = Command::new(BINARY)
        .args(["--config", config.to_str().unwrap(), "run"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let operator = pki.master("operator", Role::Named("operator"));
    let connector = pki.connector(Some(&operator));
    let session = tls_session_when_listening(tls, &connector).await;
    assert_eq!(server_certificate(&session), first.der());
    let mut open = RawMaster::over(session);
    assert_eq!(open.call(1, 1, &WRITE).await, WRITE);

    // Renewed in place, as certbot or a plant's PKI would.
    let renewed = pki.server("gateway", "gateway-2027", 730);
    signal(&child, "HUP");
    until_logged(&log, "configuration reloaded").await;
    let session = tls_connect(tls, &connector).await.expect("handshake");
    assert_eq!(
        server_certificate(&session),
        renewed.der(),
        "a new master sees the new one"
    );
    let mut new = RawMaster::over(session);
    assert_eq!(new.call(1, 1, &READ).await, [0x03, 0x02, 0x12, 0x34]);
    assert_eq!(
        open.call(2, 1, &READ).await,
        [0x03, 0x02, 0x12, 0x34],
        "the open session works"
    );

    // A key file broken mid-copy: refused by name; the renewed certificate stays in force.
    std::fs::write(&renewed.key_path, "-----BEGIN PRIVATE KEY-----\ntruncated").unwrap();
    signal(&child, "HUP");
    until_logged(&log, "configuration not reloaded").await;
    let session = tls_connect(tls, &connector).await.expect("handshake");
    assert_eq!(server_certificate(&session), renewed.der());
    assert_eq!(
        RawMaster::over(session).call(1, 1, &READ).await,
        [0x03, 0x02, 0x12, 0x34]
    );
    assert_eq!(open.call(3, 1, &READ).await, [0x03, 0x02, 0x12, 0x34]);

    // Three plain Modbus TCP masters on the TLS port: three refusals, one warning.
    for _ in 0..3 {
        let mut plain = tokio::net::TcpStream::connect(tls).await.expect("connect");
        plain
            .write_all(&RawMaster::adu(1, 1, &READ))
            .await
            .expect("send");
        let _ = within("closed", plain.read_to_end(&mut Vec::new())).await;
    }
    signal(&child, "TERM");
    assert_eq!(exit_status(child).await.code(), Some(0));
    let text = std::fs::read_to_string(&log).unwrap();
    let warnings = text.matches("TLS handshake failed").count();
    assert_eq!(warnings, 1, "once a minute per peer: {text}");
    let refusal = text
        .lines()
        .find(|line| line.contains("configuration not reloaded"))
        .unwrap();
    assert!(refusal.contains("server.tls.private_key"), "{refusal}");
    assert!(text.contains("TLS server certificate loaded"), "{text}");
}

/// `check-config` on a configuration with a TLS table for `server`: its exit code, stdout, stderr.
fn check_config(pki: &Pki, server: &Issued) -> (Option<i32>, String, String) {
    let config = pki.dir.join("check.toml");
    let text = GatewayConfig::new()
        .default_listen()
        .listen_tls("127.0.0.1:802")
        .server_table(&pki.tls_table(server, ROLES))
        .bus(Bus::sim("sim"))
        .to_toml();
    std::fs::write(&config, text).unwrap();
    let output = Command::new(BINARY)
        .args(["--config", config.to_str().unwrap(), "check-config"])
        .output()
        .unwrap();
    let text = |bytes: Vec<u8>| String::from_utf8(bytes).unwrap();
    (
        output.status.code(),
        text(output.stdout),
        text(output.stderr),
    )
}

#[test]
fn check_config_reports_the_certificate_expiry_in_days_and_warns_within_thirty() {
    let pki = Pki::new("plant-ca");
    let server = pki.server("gateway", "gateway", 365);
    let (code, stdout, stderr) = check_config(&pki, &server);
    assert_eq!(code, Some(0), "{stderr}");
    assert!(
        stdout.contains("# TLS: server certificate CN=gateway, expires 20")
            && stdout.contains(
                "(in 364 days); client certificates must chain to 1 CA certificate(s); \
             roles: operator read_write, viewer read_only, any other certificate none."
            ),
        "{stdout}"
    );
    assert!(stderr.is_empty(), "{stderr}");

    let soon = pki.server("soon", "gateway", 10);
    let (code, stdout, stderr) = check_config(&pki, &soon);
    assert_eq!(code, Some(0), "a warning, not an error");
    assert!(stdout.contains("(in 9 days)"), "{stdout}");
    assert!(
        stderr
            .contains("warning: server.tls.certificate: the server certificate expires in 9 days"),
        "{stderr}"
    );
}

#[test]
fn check_config_names_a_key_that_is_not_the_certificates_and_exits_2() {
    let pki = Pki::new("plant-ca");
    let server = pki.server("gateway", "gateway", 365);
    let other = pki.server("other", "other", 365);
    std::fs::copy(&other.key_path, &server.key_path).unwrap();
    let (code, _, stderr) = check_config(&pki, &server);
    assert_eq!(code, Some(2));
    assert!(
        stderr.contains("server.tls.private_key: ")
            && stderr.contains("is not the key of the certificate in"),
        "{stderr}"
    );
}

#[tokio::test]
async fn a_master_outside_allow_is_closed_before_any_handshake() {
    let (pki, _server, gateway) = tls_gateway_with("allow = \"10.0.0.0/8\"", ROLES).await;
    let operator = pki.master("operator", Role::Named("operator"));
    let attempt = tls_connect(tls_addr(&gateway), &pki.connector(Some(&operator))).await;
    assert!(attempt.is_err(), "no TLS session without a handshake");
    let scrape = Scrape::of(&gateway).await;
    let not_allowed =
        "modbus_gateway_tcp_connections_rejected_total{protocol=\"tls\",reason=\"not_allowed\"}";
    assert_eq!(scrape.value(not_allowed), 1.0);
    assert_eq!(scrape.get(HANDSHAKE_FAILED), None, "no handshake was tried");
}

#[tokio::test(start_paused = true)]
async fn an_idle_tls_session_ends_with_close_notify_not_a_cut() {
    let (pki, _server, gateway) = tls_gateway_with("idle_timeout = \"5s\"", ROLES).await;
    let operator = pki.master("operator", Role::Named("operator"));
    let mut session = tls_connect(tls_addr(&gateway), &pki.connector(Some(&operator)))
        .await
        .expect("handshake");
    session
        .write_all(&RawMaster::adu(1, 1, &READ))
        .await
        .expect("send");
    let mut reply = [0u8; 11];
    within("reply", session.read_exact(&mut reply))
        .await
        .expect("reply");
    // rustls reads a close without close_notify as an UnexpectedEof error.
    let end = within("idle close", session.read(&mut [0u8; 1])).await;
    assert!(matches!(end, Ok(0)), "a clean TLS close: {end:?}");
}

/// A TLS master's handshake, under a trickle of silent connections.
#[tokio::test(start_paused = true)]
async fn a_tls_handshake_completes_within_a_second_amid_a_trickle_of_silent_sockets() {
    let (pki, _server, gateway) = tls_gateway_with("", ROLES).await;
    let operator = pki.master("operator", Role::Named("operator"));
    let connector = pki.connector(Some(&operator));
    // 40 connections that never send a byte, one every 25 ms from eight hosts (five each): more
    // than the 32 handshakes worked on at once, all within the 10 s handshake timeout.
    let mut silent = Vec::new();
    for i in 0..40u8 {
        silent.push(connect_from([127, 0, 0, 10 + i % 8], tls_addr(&gateway)).await);
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
    // On the paused clock a handshake on loopback takes no time at all, whatever the machine's
    // load; waiting for a turn a silent connection holds would take until its handshake
    // timeout, nine seconds on.
    let started = tokio::time::Instant::now();
    let session = tokio::time::timeout(
        Duration::from_secs(5),
        tls_connect_from([127, 0, 0, 1], tls_addr(&gateway), &connector),
    )
    .await;
    let took = started.elapsed();
    let session = session
        .unwrap_or_else(|_| panic!("no handshake within 5 s"))
        .expect("handshake");
    assert!(took < Duration::from_secs(1), "the handshake took {took:?}");
    let mut master = RawMaster::over(session);
    assert_eq!(master.call(1, 1, &READ).await, READ_ANSWER);
    drop(silent);
}

/// Peers of one address; the others are served at once.
#[tokio::test(start_paused = true)]
async fn peers_stalling_mid_handshake_hold_eight_turns_at_most_and_others_are_served() {
    let (pki, _server, gateway) = tls_gateway_with("", ROLES).await;
    let operator = pki.master("operator", Role::Named("operator"));
    // 40 peers of one host send the first byte of a ClientHello (a handshake record) and stall:
    // more than the 32 handshakes worked on at once.
    let mut stalled = Vec::new();
    for _ in 0..40 {
        let mut peer = connect_from([127, 0, 0, 20], tls_addr(&gateway)).await;
        peer.write_all(&[0x16]).await.expect("send");
        stalled.push(peer);
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    let started = tokio::time::Instant::now();
    let mut master = tls_master_from([127, 0, 0, 21], &gateway, &pki, &operator).await;
    // At once on the paused clock: not once a stalled peer's 10 s handshake timeout frees a turn.
    assert!(
        started.elapsed() < Duration::from_secs(1),
        "the handshake waited {:?}",
        started.elapsed()
    );
    assert_eq!(master.call(1, 1, &READ).await, READ_ANSWER);
    drop(stalled);
}

#[tokio::test(start_paused = true)]
async fn a_connection_that_sends_nothing_is_closed_after_three_seconds() {
    let (_pki, _server, gateway) = tls_gateway_with("", ROLES).await;
    let mut silent = connect_from([127, 0, 0, 22], tls_addr(&gateway)).await;
    let started = tokio::time::Instant::now();
    let read = within("the gateway closes", silent.read(&mut [0u8; 1])).await;
    assert!(matches!(read, Ok(0) | Err(_)), "closed: {read:?}");
    let waited = started.elapsed();
    assert!(
        (Duration::from_secs(3)..Duration::from_secs(4)).contains(&waited),
        "closed after {waited:?}, not at the 10 s handshake timeout"
    );
    assert_eq!(Scrape::of(&gateway).await.value(HANDSHAKE_FAILED), 1.0);
}

async fn tls_master_from(
    source: [u8; 4],
    gateway: &Gateway,
    pki: &Pki,
    master: &Issued,
) -> RawMaster {
    let session = tls_connect_from(source, tls_addr(gateway), &pki.connector(Some(master)))
        .await
        .expect("handshake");
    RawMaster::over(session)
}
