//! Virtual units (`[[virtual]]`, docs/virtual-units.md) in a running gateway, through real
//! sockets: the demo's drive read through its virtual register, each encoding exact, a meter
//! presented through its own template giving the meter's words, staleness when a slave stops
//! while another bus's registers still answer, the exceptions, a writable register's write
//! reaching its slave in the slave's encoding, journaled, and stopped by a deny rule; and a
//! hundred masters at once.

use crate::support::{addr, frames_from, within, Bus, GatewayConfig, RawMaster, Scrape};
use modbus_gateway::testing::sim::Source;
use modbus_gateway::Gateway;
use std::time::Duration;

/// Call `pdu` to `unit` until the answer is not `refused` (a value not yet polled), and return
/// that answer.
async fn answered(
    master: &mut RawMaster,
    unit: u8,
    pdu: &[u8],
    mut done: impl FnMut(&[u8]) -> bool,
) -> Vec<u8> {
    within("a virtual unit's answer", async {
        let mut transaction = 1000u16;
        loop {
            transaction = transaction.wrapping_add(1);
            let reply = master.call(transaction, unit, pdu).await;
            if done(&reply) {
                return reply;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await
}

/// Not an exception.
fn normal(reply: &[u8]) -> bool {
    reply.first().is_some_and(|f| f & 0x80 == 0)
}

/// The frames the gateway put on bus `bus`'s simulated line, as slave address and PDU.
fn sent(gateway: &Gateway, bus: &str) -> Vec<(u8, Vec<u8>)> {
    let line = gateway.sim_line(bus).expect("a sim line");
    frames_from(&line, Source::Master)
        .into_iter()
        .map(|frame| (frame[0], frame[1..frame.len() - 2].to_vec()))
        .collect()
}

/// The demo as shipped, its unit 100 the drives' frequencies; the Goodrive300 at 2 polled every
/// 300 ms and ramping to 50 Hz in 3 s: a master reads 5000 at unit 100's register 1, and none of
/// its reads reaches the line.
#[tokio::test]
async fn the_demos_gd300_run_to_50_hz_reads_5000_at_its_virtual_register_off_the_line() {
    let config = crate::support::demo_with_a_quick_drive_2();
    assert_eq!(config.virtual_units[0].unit, 100, "the demo's virtual unit");
    let gateway = Gateway::start(&config).await.expect("the demo starts");
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let read = [0x03, 0x00, 0x00, 0x00, 0x04];
    let stopped = answered(&mut master, 100, &read, normal).await;
    assert_eq!(
        stopped,
        [0x03, 8, 0, 0, 0, 0, 0, 0, 0, 0],
        "four stopped drives"
    );
    let set = [0x06, 0x20, 0x01, 0x13, 0x88];
    assert_eq!(master.call(1, 2, &set).await, set);
    let run = [0x06, 0x20, 0x00, 0x00, 0x01];
    assert_eq!(master.call(2, 2, &run).await, run);
    let mut seen = Vec::new();
    let at_50 = answered(&mut master, 100, &read, |reply| {
        let hz = u16::from_be_bytes([reply[4], reply[5]]);
        if seen.last() != Some(&hz) {
            seen.push(hz);
        }
        hz == 5000
    })
    .await;
    assert_eq!(&at_50[2..6], [0, 0, 0x13, 0x88], "drive 2 at 50.00 Hz");
    let before = sent(&gateway, "demo").len();
    for t in 0..50 {
        assert_eq!(master.call(3000 + t, 100, &read).await, at_50);
    }
    let frames = sent(&gateway, "demo");
    assert!(frames.iter().all(|(slave, _)| (1..=4).contains(slave)));
    // Only the polls went on the line meanwhile: no master's read is a poll's block.
    let scrape = Scrape::of(&gateway).await;
    let masters_on_the_line: f64 = scrape
        .series_of("modbus_gateway_requests_total")
        .iter()
        .filter(|(series, _)| series.contains("bus=\"demo\""))
        .map(|(_, v)| *v)
        .sum();
    assert_eq!(
        masters_on_the_line,
        2.0,
        "the two writes; {} polls beside",
        frames.len() - before
    );
    assert!(
        scrape
            .get("modbus_gateway_virtual_requests_total{name=\"drives\",outcome=\"answered\",unit=\"100\"}")
            .is_some_and(|n| n >= 52.0)
    );
}

/// Slave 1 of bus "a", plain registers, listing one value of each kind every 100 ms.
const VALUES: &str = r#"
[[bus.slave]]
address = 1
poll_interval = "100ms"

[[bus.slave.value]]
name = "power_watts"
register = 0x10
type = "f32"

[[bus.slave.value]]
name = "energy_joules"
register = 0x20
type = "i32"

[[bus.slave.value]]
name = "level_ratio"
register = 0x30
type = "i16"
scale = 0.01
offset = -100

[[bus.slave.value]]
name = "running"
register = 0x40
table = "coil"
"#;

/// Unit 200: the values of slave 1 of bus "a" in other encodings, its register 20 writable.
const UNIT_200: &str = r#"
[[virtual]]
unit = 200
name = "copy"

[[virtual.register]]
register = 0
value = "a/1/power_watts"
type = "f32"

[[virtual.register]]
register = 2
value = "a/1/power_watts"
type = "f32"
word_order = "little"

[[virtual.register]]
register = 4
value = "a/1/energy_joules"
type = "i32"

[[virtual.register]]
register = 6
value = "a/1/level_ratio"
type = "u16"
scale = 0.5
offset = 10

[[virtual.register]]
register = 0
table = "coil"
value = "a/1/running"
type = "bool"

[[virtual.register]]
register = 7
value = "b/1/level_ratio"

[[virtual.register]]
register = 20
value = "a/1/level_ratio"
type = "i16"
scale = 0.1
writable = true

[[virtual.register]]
register = 21
value = "b/1/level_ratio"
type = "i16"
scale = 0.1
writable = true
"#;

fn two_buses(tail: &str) -> GatewayConfig {
    GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(
            Bus::sim("a")
                .baud(115_200)
                .parity("none")
                .sim_slaves("1")
                .text(VALUES),
        )
        .bus(
            Bus::sim("b")
                .baud(115_200)
                .parity("none")
                .sim_slaves("1")
                .text(VALUES),
        )
        .route("1", "a", 1)
        .route("2", "b", 1)
        .tables(tail)
}

/// Write `words` to slave `unit`'s holding registers from `first`.
async fn preset(master: &mut RawMaster, unit: u8, first: u16, words: &[u16]) {
    let mut pdu = vec![0x10];
    pdu.extend(first.to_be_bytes());
    pdu.extend(u16::try_from(words.len()).unwrap().to_be_bytes());
    pdu.push(u8::try_from(2 * words.len()).unwrap());
    pdu.extend(words.iter().flat_map(|w| w.to_be_bytes()));
    assert_eq!(master.call(1, unit, &pdu).await, pdu[..5]);
}

#[tokio::test]
async fn f32_in_abcd_and_cdab_i32_a_coil_and_scale_and_offset_read_back_exactly() {
    let gateway = two_buses(UNIT_200).start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // 1234.5 (f32 449A5000), -123456 (i32 FFFE1DC0), 25.0 as (raw x 0.01 - 100): 12500.
    preset(&mut master, 1, 0x10, &[0x449A, 0x5000]).await;
    preset(&mut master, 1, 0x20, &[0xFFFE, 0x1DC0]).await;
    preset(&mut master, 1, 0x30, &[12_500]).await;
    assert_eq!(
        master.call(2, 1, &[0x05, 0x00, 0x40, 0xFF, 0x00]).await,
        [0x05, 0x00, 0x40, 0xFF, 0x00]
    );
    preset(&mut master, 2, 0x30, &[10_200]).await;
    let reply = answered(&mut master, 200, &[0x03, 0, 0, 0, 8], |r| {
        normal(r)
            && r.get(2..4) == Some(&[0x44, 0x9A][..])
            && r.get(16..18) == Some(&[0x00, 0x02][..])
    })
    .await;
    assert_eq!(
        reply,
        [
            0x03, 16, //
            0x44, 0x9A, 0x50, 0x00, // 1234.5 ABCD
            0x50, 0x00, 0x44, 0x9A, // CDAB
            0xFF, 0xFE, 0x1D, 0xC0, // -123456
            0x00, 0x1E, // (25.0 - 10) / 0.5 = 30
            0x00, 0x02, // bus b's level: 10200 x 0.01 - 100 = 2.0
        ]
    );
    let coil = answered(&mut master, 200, &[0x01, 0, 0, 0, 1], normal).await;
    assert_eq!(coil, [0x01, 1, 0x01]);
}

/// The demo's SDM120 meter (`model = "sdm120"`) at 5, its values read once and then from its
/// cache, so that a master reading the meter gets what the poll got.
fn meter_bus() -> Bus {
    Bus::sim("m").baud(115_200).parity("none").text(
        r#"
[[bus.slave]]
address = 5
template = "eastron-sdm120"
poll_interval = "100ms"
cache = "1h"

[[bus.sim_slave]]
address = 5
model = "sdm120"
"#,
    )
}

#[tokio::test]
async fn an_sdm120_presented_through_its_own_template_gives_the_meters_own_words() {
    let gateway = GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(meter_bus())
        .tables(
            "[[virtual]]\nunit = 200\nname = \"meter\"\ntemplate = \"eastron-sdm120\"\n\
             source = { bus = \"m\", slave = 5 }\n",
        )
        .start()
        .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // Each of the template's runs, as the poll read it: voltage, current, power, ..., the
    // frequency and energies 0046H-004FH, the totals 0156H-0159H.
    for (first, count) in [
        (0x0000u16, 2u16),
        (0x0006, 2),
        (0x000C, 2),
        (0x0046, 10),
        (0x0156, 4),
    ] {
        let [a, b] = first.to_be_bytes();
        let read = [0x04, a, b, 0, u8::try_from(count).unwrap()];
        let emulated = answered(&mut master, 200, &read, normal).await;
        let meter = master.call(7, 5, &read).await;
        assert_eq!(emulated, meter, "input registers {first:#06x}+{count}");
    }
    assert_eq!(
        master.call(8, 200, &[0x04, 0, 0, 0, 4]).await,
        [0x84, 0x02],
        "0002H is not the SDM120's, as on the meter"
    );
}

/// The SDM120 presented as an SDM630: its system registers (total power at 0034H, the
/// frequency and energies from 0046H) carry the SDM120's own words; a per-phase register,
/// which a single-phase meter has no value for, reads 0x0B.
#[tokio::test]
async fn an_sdm120_presented_as_an_sdm630_answers_the_system_registers_from_its_own() {
    let gateway = GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(meter_bus())
        .tables(
            "[[virtual]]\nunit = 200\nname = \"sdm630\"\ntemplate = \"eastron-sdm630\"\n\
             source = { bus = \"m\", slave = 5 }\n",
        )
        .start()
        .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // (SDM630 register, SDM120 register, count): total power is the SDM120's active power.
    for (sdm630, sdm120, count) in [(0x0034u16, 0x000Cu16, 2u8), (0x0046, 0x0046, 10)] {
        let [a, b] = sdm630.to_be_bytes();
        let emulated = answered(&mut master, 200, &[0x04, a, b, 0, count], normal).await;
        let [a, b] = sdm120.to_be_bytes();
        let meter = master.call(7, 5, &[0x04, a, b, 0, count]).await;
        assert_eq!(
            emulated, meter,
            "SDM630 {sdm630:#06x} from SDM120 {sdm120:#06x}"
        );
    }
    assert_eq!(
        master.call(8, 200, &[0x04, 0, 0, 0, 2]).await,
        [0x84, 0x0B],
        "phase 1's voltage: the SDM120 has no such value"
    );
}

#[tokio::test]
async fn a_stopped_slaves_registers_read_0x0b_while_another_buss_still_answer() {
    let config = two_buses(UNIT_200);
    let gateway = config.start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let bus_a = [0x03, 0, 0, 0, 2];
    let bus_b = [0x03, 0, 7, 0, 1];
    // Bus b's level at 2.0: a u16 holds it (at its power-on 0 it is -100, which none does).
    preset(&mut master, 2, 0x30, &[10_200]).await;
    answered(&mut master, 200, &bus_a, normal).await;
    answered(&mut master, 200, &bus_b, normal).await;
    // Slave 1 of bus "a" stops answering: its polls time out, and its registers are stale.
    let mut stopped = config.load();
    stopped.bus[0].sim_slave[0].offline = true;
    gateway.reload(&stopped).expect("reloads");
    let stale = answered(&mut master, 200, &bus_a, |r| !normal(r)).await;
    assert_eq!(stale, [0x83, 0x0B]);
    assert_eq!(
        master.call(9, 200, &[0x03, 0, 4, 0, 4]).await,
        [0x83, 0x0B],
        "a block touching one stale register is stale whole"
    );
    for t in 0..20 {
        assert!(
            normal(&master.call(100 + t, 200, &bus_b).await),
            "bus b's still answers"
        );
    }
    let scrape = Scrape::of(&gateway).await;
    assert!(
        scrape.value(
            "modbus_gateway_virtual_requests_total{name=\"copy\",outcome=\"stale\",unit=\"200\"}"
        ) >= 2.0
    );
}

#[tokio::test]
async fn what_is_not_laid_out_is_0x02_and_what_a_unit_does_not_do_0x01() {
    let gateway = two_buses(UNIT_200).start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    for (pdu, expected, why) in [
        (
            &[0x03, 0, 8, 0, 1][..],
            [0x83, 0x02],
            "holding 8 is not laid out",
        ),
        (&[0x03, 0, 6, 0, 3][..], [0x83, 0x02], "7 is, 8 is not"),
        (&[0x04, 0, 0, 0, 1][..], [0x84, 0x02], "no input register"),
        (&[0x02, 0, 0, 0, 1][..], [0x82, 0x02], "no discrete input"),
        (&[0x03, 0, 0, 0, 0][..], [0x83, 0x03], "no register at all"),
        (
            &[0x06, 0, 0, 0, 1][..],
            [0x86, 0x01],
            "holding 0 is not writable",
        ),
        (
            &[0x06, 0, 9, 0, 1][..],
            [0x86, 0x02],
            "holding 9 is not laid out",
        ),
        (
            &[0x05, 0, 0, 0xFF, 0][..],
            [0x85, 0x01],
            "coil 0 is not writable",
        ),
        (
            &[0x08, 0, 0, 0x12, 0x34][..],
            [0x88, 0x01],
            "no diagnostics",
        ),
        (&[0x2B, 0x0E, 1, 0][..], [0xAB, 0x01], "no identification"),
        (
            &[0x17, 0, 0, 0, 1, 0, 20, 0, 1, 2, 0, 1][..],
            [0x97, 0x01],
            "no read/write",
        ),
    ] {
        assert_eq!(master.call(1, 200, pdu).await, expected, "{why}");
    }
    assert!(
        sent(&gateway, "a")
            .iter()
            .all(|(_, pdu)| matches!(pdu[0], 0x01 | 0x03)),
        "the polls' reads alone reached a slave"
    );
}

/// The journal's lines, each parsed.
fn journal(path: &std::path::Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .map(|line| serde_json::from_str(line).expect("a JSON line"))
        .collect()
}

/// The journal's writes with their outcomes, once there are `count` of them.
async fn journaled(
    path: &std::path::Path,
    count: usize,
) -> Vec<(serde_json::Value, serde_json::Value)> {
    within("the journal's outcomes", async {
        loop {
            let lines = journal(path);
            let writes: Vec<_> = lines
                .iter()
                .filter(|l| l["kind"] == "write")
                .filter_map(|w| {
                    let outcome = lines
                        .iter()
                        .find(|l| l["kind"] == "outcome" && l["id"] == w["id"])?;
                    Some((w.clone(), outcome.clone()))
                })
                .collect();
            if writes.len() >= count {
                return writes;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await
}

#[tokio::test]
async fn a_writable_registers_write_reaches_its_slave_in_its_encoding_journaled_and_ruled() {
    let dir = crate::support::TempDir::new("virtual-writes");
    let path = dir.path().join("writes.jsonl");
    let audit = format!("[audit]\npath = \"{}\"\n", path.display());
    let gateway = two_buses(&format!("{UNIT_200}{audit}")).start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // 25.5 in 0.1 (255) is (25.5 + 100) / 0.01 = 12550 (3106H) in slave 1's encoding.
    let write = [0x06, 0x00, 0x14, 0x00, 0xFF];
    assert_eq!(master.call(1, 200, &write).await, write);
    let to_slave = [0x06, 0x00, 0x30, 0x31, 0x06];
    assert_eq!(
        sent(&gateway, "a")
            .iter()
            .filter(|(_, pdu)| pdu[0] == 0x06)
            .collect::<Vec<_>>(),
        [&(1u8, to_slave.to_vec())]
    );
    assert_eq!(
        master.call(2, 1, &[0x03, 0, 0x30, 0, 1]).await,
        [0x03, 2, 0x31, 0x06]
    );
    let writes = journaled(&path, 2).await;
    let (master_write, outcome) = &writes[0];
    assert_eq!(master_write["unit"], 200);
    assert_eq!(master_write["virtual"], "copy");
    assert_eq!(master_write["bus"], serde_json::Value::Null);
    assert_eq!(master_write["values"], "00FF");
    assert_eq!(outcome["carried_out"], "yes");
    let (source_write, outcome) = &writes[1];
    assert_eq!(
        (source_write["bus"].as_str(), source_write["slave"].as_u64()),
        (Some("a"), Some(1))
    );
    assert_eq!(source_write["virtual"], "copy");
    assert_eq!(source_write["start"], 0x30);
    assert_eq!(source_write["values"], "3106");
    assert_eq!(outcome["carried_out"], "yes");
    // A value slave 1's i16 cannot hold (raw 33000): refused, nothing sent.
    assert_eq!(
        master.call(3, 200, &[0x06, 0x00, 0x14, 0x09, 0xC4]).await,
        [0x86, 0x03]
    );
    assert_eq!(
        sent(&gateway, "a")
            .iter()
            .filter(|(_, pdu)| pdu[0] == 0x06)
            .count(),
        1
    );

    // A rule protecting slave 1 of bus "a" stops a write through the virtual unit; one on the
    // virtual unit itself too. Neither reaches the line, and both are journaled.
    // A write of registers 20 and 21 (slave 1 of bus "a", then of bus "b") under a rule
    // protecting bus b's: decided whole before either is sent.
    let both = [0x10, 0x00, 0x14, 0x00, 0x02, 0x04, 0x00, 0xFF, 0x00, 0xFF];
    for (rule, pdu) in [
        ("buses = [\"a\"]\nunits = \"1\"\n", &write[..]),
        ("units = \"200\"\n", &write[..]),
        ("buses = [\"b\"]\nunits = \"2\"\n", &both[..]),
    ] {
        let rule = format!(
            "[[rule]]\nname = \"protect\"\n{rule}functions = [\"write\"]\naction = \"deny\"\n"
        );
        let ruled = two_buses(&format!("{UNIT_200}{audit}{rule}")).load();
        gateway.reload(&ruled).expect("reloads");
        let expected = [pdu[0] | 0x80, 0x01];
        assert_eq!(master.call(4, 200, pdu).await, expected, "{rule}");
        for bus in ["a", "b"] {
            let writes = sent(&gateway, bus)
                .iter()
                .filter(|(_, p)| p[0] == 0x06 || p[0] == 0x10)
                .count();
            assert_eq!(writes, usize::from(bus == "a"), "{rule}: bus {bus}");
        }
    }
    let writes = journaled(&path, 6).await;
    let (refused, outcome) = &writes[2];
    assert_eq!(refused["values"], "09C4");
    assert_eq!(
        (&outcome["outcome"], &outcome["carried_out"]),
        (&"gateway_exception".into(), &"no".into()),
        "the virtual unit refused it, no slave: {outcome}"
    );
    // One entry each, the master's write to the virtual unit: none of them became a write to
    // a slave.
    let denied: Vec<_> = writes[3..]
        .iter()
        .map(|(w, o)| {
            (
                w["bus"].clone(),
                o["outcome"].clone(),
                o["carried_out"].clone(),
            )
        })
        .collect();
    assert_eq!(
        denied,
        vec![(serde_json::Value::Null, "denied".into(), "no".into()); 3]
    );
    let detail = writes[5].1["detail"].as_str().unwrap_or_default();
    assert!(detail.contains("write to slave 1 of b"), "{detail}");
    let scrape = Scrape::of(&gateway).await;
    let count = |outcome: &str| {
        scrape.value(&format!(
            "modbus_gateway_virtual_requests_total{{name=\"copy\",outcome=\"{outcome}\",unit=\"200\"}}"
        ))
    };
    assert_eq!((count("written"), count("exception")), (1.0, 1.0));
    assert_eq!(count("denied"), 3.0);
}

#[tokio::test]
async fn a_hundred_masters_reading_a_virtual_unit_at_once_are_all_answered() {
    let gateway = two_buses(UNIT_200).start().await;
    let mut first = RawMaster::connect(addr(&gateway)).await;
    let read = [0x03, 0, 0, 0, 6];
    let expected = answered(&mut first, 200, &read, normal).await;
    let mut masters = tokio::task::JoinSet::new();
    for i in 0..100u16 {
        let mut master = RawMaster::connect(addr(&gateway)).await;
        masters.spawn(async move {
            let mut replies = Vec::new();
            for t in 0..20u16 {
                replies.push(master.call(i * 100 + t, 200, &read).await);
            }
            replies
        });
    }
    let replies = within("100 masters", masters.join_all()).await;
    let answers: Vec<&Vec<u8>> = replies.iter().flatten().collect();
    assert_eq!(answers.len(), 2000);
    assert!(answers
        .iter()
        .all(|r| normal(r) && r.len() == expected.len()));
}

/// A read of unit 200's block from another master: the reply PDU.
const BLOCK: [u8; 5] = [0x03, 0, 0, 0, 6];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rtu_over_tcp_udp_tls_roles_and_a_serial_port_all_reach_a_virtual_unit() {
    use modbus_gateway::testing::line::rtu;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let pki = crate::support::tls::Pki::new("virtual-ca");
    let server = pki.server("gateway", "gateway", 365);
    let tls = pki.tls_table(
        &server,
        "roles = { reader = { access = \"read_only\", units = \"200\" }, \
         line = { access = \"read_write\", units = \"1-2\" } }",
    );
    let dir = crate::support::TempDir::new("virtual-protocols");
    let link = dir.path().join("port");
    let port = format!(
        "[[server.serial]]\nname = \"scada\"\ndevice = \"pty:{}\"\nbaud = 115200\n\
         parity = \"none\"\nunits = \"200\"\n",
        link.display()
    );
    let gateway = two_buses(UNIT_200)
        .listen_rtu_over_tcp("127.0.0.1:0")
        .listen_udp("127.0.0.1:0")
        .listen_tls("127.0.0.1:0")
        .server_table(&format!("{tls}{port}"))
        .start()
        .await;
    let mut tcp = RawMaster::connect(addr(&gateway)).await;
    let expected = answered(&mut tcp, 200, &BLOCK, normal).await;

    // RTU over TCP: the same PDU in an RTU frame, its CRC the gateway's.
    let mut rtu_master = tokio::net::TcpStream::connect(gateway.rtu_over_tcp_addrs()[0])
        .await
        .unwrap();
    rtu_master
        .write_all(&rtu::encode(200, &BLOCK))
        .await
        .unwrap();
    let mut frame = vec![0u8; 1 + expected.len() + 2];
    within("an RTU reply", rtu_master.read_exact(&mut frame))
        .await
        .unwrap();
    assert_eq!(frame, rtu::encode(200, &expected));

    // UDP.
    let socket = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let adu = RawMaster::adu(7, 200, &BLOCK);
    socket.send_to(&adu, gateway.udp_addrs()[0]).await.unwrap();
    let mut buf = [0u8; 300];
    let (n, _) = within("a UDP reply", socket.recv_from(&mut buf))
        .await
        .unwrap();
    assert_eq!(buf[7..n], expected[..]);

    // TLS: a reader of unit 200 reads and may not write; a role held to units 1-2 reaches
    // neither.
    let tls_at = gateway.tls_addrs()[0];
    let reader = pki.master("reader", crate::support::tls::Role::Named("reader"));
    let mut master = crate::support::tls::tls_master(tls_at, &pki.connector(Some(&reader))).await;
    assert_eq!(master.call(1, 200, &BLOCK).await, expected);
    assert_eq!(
        master.call(2, 200, &[0x06, 0, 20, 0, 1]).await,
        [0x86, 0x01]
    );
    let line = pki.master("line", crate::support::tls::Role::Named("line"));
    let mut master = crate::support::tls::tls_master(tls_at, &pki.connector(Some(&line))).await;
    assert_eq!(master.call(3, 200, &BLOCK).await, [0x83, 0x01]);

    // A master on the serial port.
    let mut serial = within("the port's pty is linked", async {
        loop {
            let opened = tokio_serial::SerialPortBuilderExt::open_native_async(tokio_serial::new(
                link.to_str().unwrap(),
                115_200,
            ));
            if let Ok(port) = opened {
                return port;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    serial.write_all(&rtu::encode(200, &BLOCK)).await.unwrap();
    let mut frame = vec![0u8; 1 + expected.len() + 2];
    within("the port's reply", serial.read_exact(&mut frame))
        .await
        .unwrap();
    assert_eq!(frame, rtu::encode(200, &expected));

    let scrape = Scrape::of(&gateway).await;
    let denied =
        "modbus_gateway_virtual_requests_total{name=\"copy\",outcome=\"denied\",unit=\"200\"}";
    assert_eq!(
        scrape.value(denied),
        2.0,
        "the reader's write, the line role's read"
    );
}
