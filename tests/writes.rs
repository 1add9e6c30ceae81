//! Writes under control: `[[rule]]` through real sockets (Modbus TCP, RTU over TCP, UDP, TLS
//! roles), each match key and each action, with the simulated line's frame record showing what
//! reached the slaves; and the journal (`[audit]`): every write from every protocol with its
//! master, rule and outcome, reads not at all.

use crate::support::tls::{tls_master, Pki, Role};
use crate::support::{
    addr, connect_from, frames_from, mbap, rtu, sim_config_with_server, sim_line, start, Bus,
    GatewayConfig, RawMaster, Scrape,
};
use modbus_gateway::testing::sim::Source;
use modbus_gateway::Gateway;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpStream, UdpSocket};

/// Write 0x1388 (50.00 Hz) to holding register 0x2000: the wallbox's setpoint in these tests.
const SETPOINT: [u8; 5] = [0x06, 0x20, 0x00, 0x13, 0x88];
/// Write two registers from 0x1FFF: the setpoint and the register below it.
const PAST_SETPOINT: [u8; 10] = [0x10, 0x1F, 0xFF, 0x00, 0x02, 0x04, 0x00, 0x01, 0x13, 0x88];
/// Write 1 to holding register 0x0010.
const OTHER_WRITE: [u8; 5] = [0x06, 0x00, 0x10, 0x00, 0x01];
/// Read holding register 0x0010.
const READ: [u8; 5] = [0x03, 0x00, 0x10, 0x00, 0x01];

/// A folder of its own for one test's journal.
fn dir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mbgw-writes-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("a temp dir");
    dir
}

fn audit_table(journal: &Path) -> String {
    format!("[audit]\npath = \"{}\"\n", journal.display())
}

/// The journal's lines, each parsed (every line must be whole JSON).
fn lines(journal: &Path) -> Vec<Value> {
    std::fs::read_to_string(journal)
        .expect("the journal")
        .lines()
        .map(|line| serde_json::from_str(line).unwrap_or_else(|e| panic!("{line}: {e}")))
        .collect()
}

/// Each journaled write with its outcome (if written yet), in order.
fn writes(journal: &Path) -> Vec<(Value, Option<Value>)> {
    let all = lines(journal);
    all.iter()
        .filter(|l| l["kind"] == "write")
        .map(|w| {
            let outcome = all
                .iter()
                .find(|l| l["kind"] == "outcome" && l["id"] == w["id"])
                .cloned();
            (w.clone(), outcome)
        })
        .collect()
}

/// The journal's writes once each has its outcome (outcomes are written as requests end).
async fn ended_writes(journal: &Path, count: usize) -> Vec<(Value, Value)> {
    for _ in 0..200 {
        let all = writes(journal);
        if all.len() >= count && all.iter().all(|(_, o)| o.is_some()) {
            return all.into_iter().map(|(w, o)| (w, o.unwrap())).collect();
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    panic!("{count} ended writes expected: {:#?}", writes(journal));
}

/// The PDUs the gateway put on the sim line, as slave address and PDU.
fn sent(gateway: &Gateway, bus: &str) -> Vec<(u8, Vec<u8>)> {
    let line = gateway.sim_line(bus).expect("a sim line");
    frames_from(&line, Source::Master)
        .into_iter()
        .map(|frame| (frame[0], frame[1..frame.len() - 2].to_vec()))
        .collect()
}

/// A read-only house lets only the wallbox setpoint be written.
#[tokio::test]
async fn a_read_only_house_admits_only_the_wallbox_setpoint_journaling_every_write() {
    let journal = dir("wallbox").join("writes.jsonl");
    let toml = format!(
        "{}\n{}\n{}",
        sim_config_with_server("", ""),
        r#"
        [[rule]]
        name = "wallbox setpoint"
        units = "1"
        functions = "write"
        registers = "0x2000-0x2001"
        action = "allow"

        [[rule]]
        name = "read only"
        functions = "write"
        action = "deny"
        "#,
        audit_table(&journal)
    );
    let gateway = start(&toml).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &SETPOINT).await, SETPOINT, "the setpoint");
    // Running over the allowed range from below: the allow does not cover it, the deny does.
    assert_eq!(master.call(2, 1, &PAST_SETPOINT).await, [0x90, 0x01]);
    assert_eq!(master.call(3, 1, &OTHER_WRITE).await, [0x86, 0x01]);
    assert_eq!(master.call(4, 2, &SETPOINT).await, [0x86, 0x01], "unit 2");
    assert_eq!(
        master.call(5, 2, &READ).await,
        [0x03, 0x02, 0, 0],
        "reads go on"
    );
    // A hostile master: a read of the setpoint that writes register 0x0010 is no setpoint write.
    let read_setpoint_write_other = [0x17, 0x20, 0x00, 0, 1, 0x00, 0x10, 0, 1, 2, 0xAB, 0xCD];
    assert_eq!(
        master.call(6, 1, &read_setpoint_write_other).await,
        [0x97, 0x01]
    );
    // The setpoint write with a second write hidden after it: refused by its length first.
    let hidden = [&SETPOINT[..], &OTHER_WRITE[..]].concat();
    assert_eq!(master.call(7, 1, &hidden).await, [0x86, 0x03]);
    assert_eq!(
        sent(&gateway, "sim"),
        [(1, SETPOINT.to_vec()), (2, READ.to_vec())],
        "only the setpoint and the read reached the line"
    );

    let ended = ended_writes(&journal, 6).await;
    assert_eq!(ended.len(), 6, "the read is not journaled");
    assert_eq!(ended[4].1["outcome"], "denied");
    // What the master sent is kept as evidence, hidden bytes and all.
    assert_eq!(ended[5].0["values"], "13880600100001");
    assert_eq!(ended[5].1["outcome"], "gateway_exception");
    assert_eq!(ended[5].1["exception"], 3);
    let ended = &ended[..4];
    let port = master_port(&ended[0].0);
    for (write, _) in ended {
        assert_eq!(write["protocol"], "tcp");
        assert_eq!(master_port(write), port, "{write}");
    }
    let summary: Vec<(Value, Value, Value, Value)> = ended
        .iter()
        .map(|(w, o)| {
            (
                w["rule"].clone(),
                w["action"].clone(),
                o["outcome"].clone(),
                o["exception"].clone(),
            )
        })
        .collect();
    let expected = [
        ("wallbox setpoint", "allow", "answered", Value::Null),
        ("read only", "deny", "denied", Value::from(1)),
        ("read only", "deny", "denied", Value::from(1)),
        ("read only", "deny", "denied", Value::from(1)),
    ];
    let expected: Vec<_> = expected
        .into_iter()
        .map(|(r, a, o, e)| (Value::from(r), Value::from(a), Value::from(o), e))
        .collect();
    assert_eq!(summary, expected);
    let (setpoint, outcome) = &ended[0];
    assert_eq!(setpoint["unit"], 1);
    assert_eq!(setpoint["bus"], "sim");
    assert_eq!(setpoint["slave"], 1);
    assert_eq!(setpoint["function"], 6);
    assert_eq!(setpoint["table"], "holding");
    assert_eq!(setpoint["start"], 0x2000);
    assert_eq!(setpoint["count"], 1);
    assert_eq!(setpoint["values"], "1388");
    assert_eq!(outcome["carried_out"], "yes");
    assert_eq!(ended[1].0["start"], 0x1FFF);
    assert_eq!(ended[1].0["count"], 2);
    assert_eq!(ended[1].0["values"], "00011388");

    let scrape = Scrape::of(&gateway).await;
    let series = |action: &str, outcome: &str| {
        format!(
            "modbus_gateway_writes_total{{action=\"{action}\",outcome=\"{outcome}\",protocol=\"tcp\"}}"
        )
    };
    assert_eq!(scrape.value(&series("allow", "answered")), 1.0);
    assert_eq!(scrape.value(&series("deny", "denied")), 4.0);
    assert_eq!(scrape.value(&series("allow", "gateway_exception")), 1.0);
    let denied = "modbus_gateway_requests_total{bus=\"sim\",function=\"0x06\",outcome=\"denied\",protocol=\"tcp\",slave=\"1\"}";
    assert_eq!(scrape.value(denied), 1.0);
}

fn master_port(write: &Value) -> String {
    write["master"].as_str().expect("a master").to_owned()
}

#[tokio::test]
async fn a_deny_rule_about_registers_answers_0x02_and_one_about_functions_0x01() {
    let toml = format!(
        "{}\n{}",
        sim_config_with_server("", ""),
        r#"
        [[rule]]
        registers = "0x2000-0x20FF"
        action = "deny"

        [[rule]]
        functions = [5, 6, 15, 16]
        action = "deny"
        "#,
    );
    let gateway = start(&toml).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // Reads of the protected range are refused too: the rule names no function.
    let read_protected = [0x03, 0x20, 0x10, 0x00, 0x01];
    assert_eq!(master.call(1, 1, &read_protected).await, [0x83, 0x02]);
    assert_eq!(master.call(2, 1, &OTHER_WRITE).await, [0x86, 0x01]);
    // Write coil 3 on: FC 05 is listed.
    assert_eq!(
        master.call(3, 1, &[0x05, 0, 3, 0xFF, 0]).await,
        [0x85, 0x01]
    );
    // Mask Write Register (0x16) is not listed, and outside the range: it goes on.
    let mask = [0x16, 0x00, 0x10, 0x00, 0xF2, 0x00, 0x25];
    assert_eq!(master.call(4, 1, &mask).await, mask);
    // A user-defined code may touch any register: the registers rule takes it.
    assert_eq!(master.call(5, 1, &[0x41, 0x00]).await, [0xC1, 0x02]);
    assert_eq!(sent(&gateway, "sim"), [(1, mask.to_vec())]);
}

#[tokio::test]
async fn a_rule_on_masters_takes_only_the_listed_source_addresses() {
    let journal = dir("masters").join("w.jsonl");
    let toml = format!(
        "{}\n[[rule]]\nmasters = \"127.0.0.2\"\nfunctions = \"write\"\naction = \"deny\"\n{}",
        sim_config_with_server("", ""),
        audit_table(&journal)
    );
    let gateway = start(&toml).await;
    let mut listed = RawMaster::over(connect_from([127, 0, 0, 2], addr(&gateway)).await);
    let mut other = RawMaster::over(connect_from([127, 0, 0, 3], addr(&gateway)).await);
    assert_eq!(listed.call(1, 1, &OTHER_WRITE).await, [0x86, 0x01]);
    assert_eq!(listed.call(2, 1, &READ).await, [0x03, 0x02, 0, 0]);
    assert_eq!(other.call(1, 1, &OTHER_WRITE).await, OTHER_WRITE);
    let ended = ended_writes(&journal, 2).await;
    assert!(master_port(&ended[0].0).starts_with("127.0.0.2:"));
    assert_eq!(ended[0].1["outcome"], "denied");
    assert!(master_port(&ended[1].0).starts_with("127.0.0.3:"));
    assert_eq!(ended[1].1["outcome"], "answered");
    assert_eq!(ended[1].0["rule"], Value::Null, "no rule matched");
}

#[tokio::test]
async fn rules_on_protocols_deny_udp_writes_and_acknowledge_rtu_over_tcp_ones_unsent() {
    let journal = dir("protocols").join("w.jsonl");
    let toml = format!(
        "{}\n{}\n{}",
        sim_config_with_server(
            "listen_udp = \"127.0.0.1:0\"\nlisten_rtu_over_tcp = \"127.0.0.1:0\"",
            ""
        ),
        r#"
        [[rule]]
        protocols = "udp"
        functions = "write"
        action = "deny"

        [[rule]]
        name = "rtu masters pretend"
        protocols = ["rtu_over_tcp"]
        action = "acknowledge"
        "#,
        audit_table(&journal)
    );
    let gateway = start(&toml).await;
    // Modbus UDP: refused.
    let socket = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    socket
        .send_to(&mbap(7, 1, &OTHER_WRITE), gateway.udp_addrs()[0])
        .await
        .unwrap();
    let mut buf = [0u8; 64];
    let (len, _) = tokio::time::timeout(Duration::from_secs(5), socket.recv_from(&mut buf))
        .await
        .expect("a reply")
        .unwrap();
    assert_eq!(&buf[..len], mbap(7, 1, &[0x86, 0x01]));
    // RTU over TCP: the normal reply, the write kept off the line; its read goes on.
    let mut rtu_master = TcpStream::connect(gateway.rtu_over_tcp_addrs()[0])
        .await
        .unwrap();
    for (pdu, reply) in [
        (&SETPOINT[..], &SETPOINT[..]),
        (&PAST_SETPOINT[..], &PAST_SETPOINT[..5]),
        (&READ[..], &[0x03, 0x02, 0, 0][..]),
    ] {
        rtu_master.write_all(&rtu(1, pdu)).await.unwrap();
        let expected = rtu(1, reply);
        let mut got = vec![0u8; expected.len()];
        tokio::time::timeout(Duration::from_secs(5), rtu_master.read_exact(&mut got))
            .await
            .expect("an answer")
            .unwrap();
        assert_eq!(got, expected, "{pdu:02X?}");
    }
    // Read/Write Multiple Registers' reply carries data only the slave has: not acknowledged.
    let read_write = [0x17, 0, 0x10, 0, 1, 0, 0x11, 0, 1, 2, 0, 7];
    rtu_master.write_all(&rtu(1, &read_write)).await.unwrap();
    let expected = rtu(1, &[0x97, 0x01]);
    let mut got = vec![0u8; expected.len()];
    rtu_master.read_exact(&mut got).await.unwrap();
    assert_eq!(got, expected);
    // And Modbus TCP is under neither rule.
    let mut tcp = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(tcp.call(1, 1, &OTHER_WRITE).await, OTHER_WRITE);
    assert_eq!(
        sent(&gateway, "sim"),
        [(1, READ.to_vec()), (1, OTHER_WRITE.to_vec())]
    );
    let ended = ended_writes(&journal, 5).await;
    let got: Vec<(&str, &str, &str)> = ended
        .iter()
        .map(|(w, o)| {
            (
                w["protocol"].as_str().unwrap(),
                w["action"].as_str().unwrap(),
                o["outcome"].as_str().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        got,
        [
            ("udp", "deny", "denied"),
            ("rtu_over_tcp", "acknowledge", "acknowledged"),
            ("rtu_over_tcp", "acknowledge", "acknowledged"),
            ("rtu_over_tcp", "acknowledge", "denied"),
            ("tcp", "allow", "answered"),
        ]
    );
    assert_eq!(ended[1].0["rule"], "rtu masters pretend");
    assert_eq!(ended[1].1["carried_out"], "no");
    let acknowledged = "modbus_gateway_requests_total{bus=\"sim\",function=\"0x06\",outcome=\"acknowledged\",protocol=\"rtu_over_tcp\",slave=\"1\"}";
    assert_eq!(Scrape::of(&gateway).await.value(acknowledged), 1.0);
}

#[tokio::test]
async fn rules_on_buses_and_units_decide_by_where_a_request_goes() {
    let toml = format!(
        "{}\n{}",
        GatewayConfig::new()
            .bus(Bus::sim("a").baud(19200).sim_slaves("1-4"))
            .bus(Bus::sim("b").baud(19200).sim_slaves("1-4"))
            .route("1-4", "a", None)
            .route("11-14", "b", None)
            .to_toml(),
        r#"
        [[rule]]
        buses = "b"
        units = "12"
        functions = "write"
        action = "deny"
        "#,
    );
    // Units 11-14 are slaves 1-4 of bus b (offset -10).
    let toml = toml.replace(
        "units = \"11-14\"\nbus = \"b\"",
        "units = \"11-14\"\nbus = \"b\"\noffset = -10",
    );
    let gateway = start(&toml).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 12, &OTHER_WRITE).await, [0x86, 0x01]);
    assert_eq!(master.call(2, 11, &OTHER_WRITE).await, OTHER_WRITE);
    assert_eq!(master.call(3, 2, &OTHER_WRITE).await, OTHER_WRITE, "bus a");
    assert_eq!(sent(&gateway, "b"), [(1, OTHER_WRITE.to_vec())]);
    assert_eq!(sent(&gateway, "a"), [(2, OTHER_WRITE.to_vec())]);
}

/// docs/writes.md's "Write-protect register ranges" rules, as the page has them: drives 1-4
/// keep their parameters in 0000H-1FFFH, and none may be restarted.
fn drive_parameters() -> String {
    let page = include_str!("../docs/writes.md");
    let example = page
        .split_once("#### Write-protect register ranges")
        .and_then(|(_, after)| after.split_once("```toml\n"))
        .and_then(|(_, block)| block.split_once("```"))
        .map(|(toml, _)| toml.to_owned());
    example.expect("docs/writes.md's drive parameters example")
}

/// The sim line with drives 1-4, whose unit 200 is the broadcast and units 101-104 the drives.
fn routed_line() -> GatewayConfig {
    GatewayConfig::new()
        .bus(sim_line().sim_slaves("1-4"))
        .route("200", "sim", 0)
        .route_offset("101-104", "sim", -100)
}

#[tokio::test]
async fn a_units_deny_rule_holds_its_slaves_against_broadcasts_and_routed_units() {
    let journal = dir("slaves").join("w.jsonl");
    let toml = format!(
        "{}{}{}",
        routed_line().to_toml(),
        drive_parameters(),
        audit_table(&journal)
    );
    let gateway = start(&toml).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // Write 1 to register 0005H, a drive parameter, by four ways to reach drive 1.
    let parameter = [0x06, 0x00, 0x05, 0x00, 0x01];
    for (tid, unit) in [(1, 1), (2, 0), (3, 200), (4, 101)] {
        assert_eq!(
            master.call(tid, unit, &parameter).await,
            [0x86, 0x02],
            "unit {unit}"
        );
    }
    // A broadcast outside the ranges, and a read of a parameter through a routed unit, go on.
    let outside = [0x06, 0x30, 0x00, 0x00, 0x01];
    assert_eq!(master.call(5, 0, &outside).await, outside);
    let read = [0x03, 0x00, 0x05, 0x00, 0x01];
    assert_eq!(master.call(6, 104, &read).await[..2], [0x03, 0x02]);
    assert_eq!(
        sent(&gateway, "sim"),
        [(0, outside.to_vec()), (4, read.to_vec())],
        "no parameter write reached the line"
    );
    let ended = ended_writes(&journal, 5).await;
    let seen: Vec<_> = ended
        .iter()
        .map(|(w, o)| {
            let text = |v: &Value| v.as_str().unwrap_or("null").to_owned();
            let slave = w["slave"].as_u64();
            (
                w["unit"].as_u64(),
                slave,
                text(&w["rule"]),
                text(&w["action"]),
                text(&o["outcome"]),
            )
        })
        .collect();
    let denied = |unit, slave| {
        let rule = "drive parameters".to_owned();
        (
            Some(unit),
            Some(slave),
            rule,
            "deny".to_owned(),
            "denied".to_owned(),
        )
    };
    assert_eq!(
        seen,
        [
            denied(1, 1),
            denied(0, 0),
            denied(200, 0),
            denied(101, 1),
            (
                Some(0),
                Some(0),
                "null".into(),
                "allow".into(),
                "broadcast".into()
            ),
        ]
    );
}

#[tokio::test]
async fn the_drive_parameters_example_keeps_restarts_and_tunnels_off_the_drives() {
    let gateway = start(&format!(
        "{}{}",
        routed_line().to_toml(),
        drive_parameters()
    ))
    .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let refused: [(&[u8], u8); 4] = [
        // Restart Communications Option, Force Listen Only Mode, Clear Counters: 0x01.
        (&[0x08, 0x00, 0x01, 0x00, 0x00], 0x01),
        (&[0x08, 0x00, 0x04, 0x00, 0x00], 0x01),
        (&[0x08, 0x00, 0x0A, 0x00, 0x00], 0x01),
        // A CANopen General Reference may write any object: refused as the ranges are, 0x02.
        (&[0x2B, 0x0D, 0x00, 0x20, 0x00, 0x01], 0x02),
    ];
    for (tid, (pdu, code)) in (1..).zip(refused) {
        for unit in [2, 102] {
            let answer = master.call(tid, unit, pdu).await;
            assert_eq!(answer, [pdu[0] | 0x80, code], "{pdu:02X?} to unit {unit}");
        }
    }
    // The diagnostics that only read go to the drives: echo, a counter, identification.
    let reads: [&[u8]; 3] = [
        &[0x08, 0x00, 0x00, 0x12, 0x34],
        &[0x08, 0x00, 0x0B, 0x00, 0x00],
        &[0x2B, 0x0E, 0x01, 0x00],
    ];
    for (tid, pdu) in (10..).zip(reads) {
        master.call(tid, 102, pdu).await;
    }
    let expected: Vec<_> = reads.iter().map(|pdu| (2, pdu.to_vec())).collect();
    assert_eq!(sent(&gateway, "sim"), expected);
}

#[tokio::test]
async fn a_tls_role_rule_on_units_denies_the_role_a_broadcast_that_reaches_them() {
    let journal = dir("tls-slaves").join("w.jsonl");
    let pki = Pki::new("plant-ca");
    let server = pki.server("gateway", "gateway", 365);
    let roles = "roles = { operator = \"read_write\" }";
    let toml = format!(
        "{}\n{}{}",
        routed_line()
            .server_table(&format!(
                "listen_tls = \"127.0.0.1:0\"\n{}",
                pki.tls_table(&server, roles)
            ))
            .to_toml(),
        "[[rule]]\nname = \"not the drives\"\nroles = \"operator\"\nunits = \"1-3\"\n\
         functions = \"write\"\naction = \"deny\"\n",
        audit_table(&journal)
    );
    let gateway = start(&toml).await;
    let operator = pki.master("operator", Role::Named("operator"));
    let mut operator = tls_master(gateway.tls_addrs()[0], &pki.connector(Some(&operator))).await;
    // Units 0 and 200 broadcast to drives 1-3 as well; unit 103 is drive 3.
    for (tid, unit) in [(1, 0), (2, 200), (3, 103), (4, 3)] {
        let answer = operator.call(tid, unit, &OTHER_WRITE).await;
        assert_eq!(answer, [0x86, 0x01], "unit {unit}");
    }
    // Drive 4 is not the rule's, by its own id or by 104.
    assert_eq!(operator.call(5, 104, &OTHER_WRITE).await, OTHER_WRITE);
    assert_eq!(sent(&gateway, "sim"), [(4, OTHER_WRITE.to_vec())]);
    let ended = ended_writes(&journal, 5).await;
    for (write, outcome) in &ended[..4] {
        assert_eq!(write["rule"], "not the drives", "{write}");
        assert_eq!(write["role"], "operator");
        assert_eq!(outcome["outcome"], "denied");
    }
    assert_eq!(ended[4].0["rule"], Value::Null);
}

#[tokio::test]
async fn a_multiple_write_whose_byte_count_disagrees_with_its_quantity_gets_0x03() {
    let journal = dir("miscounted").join("w.jsonl");
    let toml = format!(
        "{}{}{}",
        sim_config_with_server("", ""),
        "[[rule]]\nregisters = \"0x2000-0x2001\"\naction = \"allow\"\n\
         [[rule]]\nfunctions = \"write\"\naction = \"deny\"\n",
        audit_table(&journal)
    );
    let gateway = start(&toml).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let miscounted: [&[u8]; 5] = [
        // 2001H for 1 register by its quantity, 2 by its byte count (4): 2002H too, to some.
        &[0x10, 0x20, 0x01, 0x00, 0x01, 0x04, 0x0D, 0x0D, 0xBE, 0xEF],
        // 2000H for 2 registers by its quantity, 1 by its byte count.
        &[0x10, 0x20, 0x00, 0x00, 0x02, 0x02, 0x0D, 0x0D],
        // A quantity of 0.
        &[0x10, 0x20, 0x00, 0x00, 0x00, 0x00],
        // 9 coils from 2000H in one byte (they take two).
        &[0x0F, 0x20, 0x00, 0x00, 0x09, 0x01, 0xFF],
        // Read 2000H, write 2001H: 1 register by its quantity, 2 by its byte count.
        &[
            0x17, 0x20, 0x00, 0, 1, 0x20, 0x01, 0, 1, 4, 0x0D, 0x0D, 0xBE, 0xEF,
        ],
    ];
    for (tid, pdu) in (1..).zip(miscounted) {
        let answer = master.call(tid, 1, pdu).await;
        assert_eq!(answer, [pdu[0] | 0x80, 0x03], "{pdu:02X?}");
    }
    // The same write with its byte count agreeing is the rule's to allow.
    let agreed = [0x10, 0x20, 0x00, 0x00, 0x02, 0x04, 0x0D, 0x0D, 0xBE, 0xEF];
    assert_eq!(master.call(9, 1, &agreed).await, agreed[..5]);
    assert_eq!(sent(&gateway, "sim"), [(1, agreed.to_vec())], "none went");
    let scrape = Scrape::of(&gateway).await;
    let bad = |function: &str| {
        scrape.value(&format!(
            "modbus_gateway_requests_total{{bus=\"sim\",function=\"{function}\",\
             outcome=\"bad_length\",protocol=\"tcp\",slave=\"1\"}}"
        ))
    };
    assert_eq!((bad("0x10"), bad("0x0F"), bad("0x17")), (3.0, 1.0, 1.0));
    // Journaled as what the bytes hold, refused by the gateway with 0x03.
    let ended = ended_writes(&journal, 6).await;
    assert_eq!(ended[0].0["values"], "0D0DBEEF");
    for (_, outcome) in &ended[..5] {
        assert_eq!(outcome["outcome"], "gateway_exception");
        assert_eq!(outcome["exception"], 3);
        assert_eq!(outcome["carried_out"], "no");
    }
}

/// The writes are acknowledged; the journal names the certificate and the role.
#[tokio::test]
async fn a_tls_role_rule_acknowledges_operator_writes_and_journals_their_role() {
    let journal = dir("tls").join("w.jsonl");
    let pki = Pki::new("plant-ca");
    let server = pki.server("gateway", "gateway", 365);
    let toml = format!(
        "{}\n{}\n{}",
        sim_config_with_server(
            &format!(
                "listen_tls = \"127.0.0.1:0\"\n{}",
                pki.tls_table(
                    &server,
                    "roles = { operator = \"read_write\", viewer = \"read_only\" }"
                )
            ),
            ""
        ),
        "[[rule]]\nname = \"commissioning\"\nroles = \"operator\"\nunits = \"3\"\naction = \"acknowledge\"\n",
        audit_table(&journal)
    );
    let gateway = start(&toml).await;
    let operator = pki.master("operator", Role::Named("operator"));
    let viewer = pki.master("viewer", Role::Named("viewer"));
    let tls = gateway.tls_addrs()[0];
    let mut operator = tls_master(tls, &pki.connector(Some(&operator))).await;
    let mut viewer = tls_master(tls, &pki.connector(Some(&viewer))).await;
    assert_eq!(
        operator.call(1, 3, &OTHER_WRITE).await,
        OTHER_WRITE,
        "acknowledged"
    );
    assert_eq!(operator.call(2, 2, &OTHER_WRITE).await, OTHER_WRITE, "sent");
    assert_eq!(
        viewer.call(1, 3, &OTHER_WRITE).await,
        [0x86, 0x01],
        "read only"
    );
    assert_eq!(sent(&gateway, "sim"), [(2, OTHER_WRITE.to_vec())]);
    let ended = ended_writes(&journal, 3).await;
    let operator_entry = &ended[0].0;
    assert_eq!(operator_entry["protocol"], "tls");
    assert_eq!(operator_entry["role"], "operator");
    assert!(
        operator_entry["subject"]
            .as_str()
            .unwrap()
            .contains("operator"),
        "{operator_entry}"
    );
    assert_eq!(operator_entry["rule"], "commissioning");
    assert_eq!(ended[0].1["outcome"], "acknowledged");
    assert_eq!(ended[1].1["outcome"], "answered");
    assert_eq!(ended[1].0["rule"], Value::Null);
    // The viewer's refusal is its role's: a rule of its own, checked before [[rule]].
    assert_eq!(ended[2].0["role"], "viewer");
    assert_eq!(ended[2].0["rule"], "server.tls.roles.viewer");
    assert_eq!(ended[2].0["action"], "deny");
    assert_eq!(ended[2].1["outcome"], "denied");
}

/// A timeout, a slave exception, a broadcast and read-only refusals.
#[tokio::test]
async fn the_journal_records_timeouts_exceptions_broadcasts_and_refusals_but_no_read() {
    let journal = dir("outcomes").join("w.jsonl");
    // With fsync: each write waits for its entry to reach the disk, then goes on.
    let toml = format!(
        "{}\n{}fsync = true\n",
        sim_config_with_server(
            "read_only = \"127.0.0.9\"",
            "response_timeout = \"100ms\"\nturnaround_delay = \"20ms\""
        ),
        audit_table(&journal)
    );
    let gateway = start(&toml).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // Slave 5 is not on the line.
    assert_eq!(master.call(1, 5, &OTHER_WRITE).await, [0x86, 0x0B]);
    // A user-defined code the register bank refuses: the slave's own exception.
    assert_eq!(master.call(2, 1, &[0x41, 0x01, 0x02]).await, [0xC1, 0x01]);
    // Unit 0 is every slave.
    assert_eq!(master.call(3, 0, &OTHER_WRITE).await, OTHER_WRITE);
    for tid in 4..10 {
        assert_eq!(master.call(tid, 1, &READ).await[0], 0x03);
    }
    let mut read_only = RawMaster::over(connect_from([127, 0, 0, 9], addr(&gateway)).await);
    assert_eq!(read_only.call(1, 1, &OTHER_WRITE).await, [0x86, 0x01]);
    // Diagnostics: restart communications may change the slave.
    assert_eq!(
        read_only.call(2, 1, &[0x08, 0x00, 0x01, 0x00, 0x00]).await,
        [0x88, 0x01]
    );
    let ended = ended_writes(&journal, 5).await;
    assert_eq!(ended.len(), 5, "no read is journaled: {ended:#?}");
    let outcome = |i: usize| {
        (
            ended[i].1["outcome"].as_str().unwrap().to_owned(),
            ended[i].1["carried_out"].as_str().unwrap().to_owned(),
        )
    };
    assert_eq!(outcome(0), ("timeout".into(), "maybe".into()));
    assert_eq!(ended[0].1["exception"], 0x0B);
    assert!(ended[0].1["detail"]
        .as_str()
        .unwrap()
        .contains("may have been carried out"));
    assert_eq!(outcome(1), ("slave_exception".into(), "no".into()));
    assert_eq!(ended[1].1["exception"], 1);
    assert_eq!(ended[1].0["values"], "0102", "what follows the code");
    assert_eq!(outcome(2), ("broadcast".into(), "maybe".into()));
    assert_eq!(ended[2].0["slave"], 0);
    assert_eq!(outcome(3), ("denied".into(), "no".into()));
    assert_eq!(ended[3].0["rule"], "server.read_only");
    assert_eq!(ended[4].0["function"], 8);
    assert_eq!(ended[4].0["values"], "00010000");
    let first = lines(&journal);
    assert_eq!(first[0]["kind"], "open");
}

#[tokio::test]
async fn a_reload_applies_new_rules_between_requests_and_keeps_a_journal_it_cannot_open() {
    let dir = dir("reload");
    let journal = dir.join("w.jsonl");
    let base = sim_config_with_server("", "");
    let first = format!("{base}\n{}", audit_table(&journal));
    let gateway = start(&first).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &OTHER_WRITE).await, OTHER_WRITE);
    let denied = format!(
        "{base}\n[[rule]]\nfunctions = \"write\"\naction = \"deny\"\n[audit]\npath = \"{}\"\n",
        dir.join("missing/folder/w.jsonl").display()
    );
    let done = gateway
        .reload(&modbus_gateway::gateway::config_from_toml(&denied).unwrap())
        .unwrap();
    assert!(done.applied.contains(&"rules".to_owned()), "{done:?}");
    assert_eq!(done.kept.len(), 1, "{done:?}");
    assert!(done.kept[0].contains("audit.path"), "{done:?}");
    // The same connection, the new rule; the old journal still records.
    assert_eq!(master.call(2, 1, &OTHER_WRITE).await, [0x86, 0x01]);
    let ended = ended_writes(&journal, 2).await;
    assert_eq!(ended[1].1["outcome"], "denied");
}

#[tokio::test]
async fn a_journal_that_cannot_be_opened_stops_the_start_naming_audit_path() {
    let toml = format!(
        "{}\n[audit]\npath = \"/nonexistent-dir-of-mbgw/w.jsonl\"\n",
        sim_config_with_server("", "")
    );
    let config = modbus_gateway::gateway::config_from_toml(&toml).unwrap();
    let error = Gateway::start(&config).await.err().expect("no start");
    assert!(error.to_string().starts_with("audit.path: "), "{error}");
}
