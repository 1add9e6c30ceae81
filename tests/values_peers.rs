//! Plant values read from a third-party slave on the real serial path: pymodbus's RTU server
//! (`tests/peers/pymodbus_values_slave.py`, on the pty cable of `peers::Pymodbus`) holds a value
//! of every type, f32 and i32 in each of the four 32-bit layouts of docs/plant-values.md, 64-bit
//! values in both word orders, bits of a register, coils, discrete inputs and input registers;
//! the gateway polls them and must give each number exactly, on `GET /values` and on `/metrics`,
//! in as few reads as the polling plan allows.
//!
//! The registers below are written by hand as the wire carries them (the documentation's worked
//! layouts, and the IEEE 754 and two's complement encodings of the other numbers), not made by
//! any encoder of the gateway's. pymodbus's own replies are checked against them too, so that a
//! wrong number is the gateway's decoding, not the fixture.
//!
//! Python comes as for `peers` (`MBGW_PYTHON`, else a `python3` with pymodbus, else the test checks
//! nothing and says so, or fails under `MBGW_REQUIRE_TOOLS=1`).

use crate::peers::{Pymodbus, Wire};
use crate::support::{http_get, pty_line, within, GatewayConfig, Scrape, PATIENCE};
use modbus_gateway::testing::line::rtu;
use std::collections::BTreeMap;
use std::time::Duration;

const SCRIPT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/peers/pymodbus_values_slave.py"
);
/// The slave's address on the line.
const SLAVE: u8 = 7;
/// The line's name in the gateway (`pty_line`).
const BUS: &str = "pty";

/// One plant value: its name, the table and register it starts at, its other keys as written
/// in an inline `[[bus.slave.value]]` table, what the slave holds from that register on (the
/// registers as on the wire, high byte first; coils and inputs as 0 and 1), and the number the
/// gateway must make of it.
type Plant = (
    &'static str,
    &'static str,
    u16,
    &'static str,
    &'static [u16],
    f64,
);

const PLANT: [Plant; 28] = [
    // f32 1234.5 = 0x449A5000 in the four layouts of docs/plant-values.md: AB CD, CD AB, BA DC,
    // DC BA. ABCD spells out the defaults; the others leave out what is "big".
    (
        "plant_f32_abcd",
        "holding",
        0,
        r#"type = "f32", word_order = "big", byte_order = "big""#,
        &[0x449A, 0x5000],
        1234.5,
    ),
    (
        "plant_f32_cdab",
        "holding",
        2,
        r#"type = "f32", word_order = "little""#,
        &[0x5000, 0x449A],
        1234.5,
    ),
    (
        "plant_f32_badc",
        "holding",
        4,
        r#"type = "f32", byte_order = "little""#,
        &[0x9A44, 0x0050],
        1234.5,
    ),
    (
        "plant_f32_dcba",
        "holding",
        6,
        r#"type = "f32", word_order = "little", byte_order = "little""#,
        &[0x0050, 0x9A44],
        1234.5,
    ),
    // i32 -123456 = 0xFFFE1DC0, the same four; ABCD by default (no order keys at all).
    (
        "plant_i32_abcd",
        "holding",
        8,
        r#"type = "i32""#,
        &[0xFFFE, 0x1DC0],
        -123_456.0,
    ),
    (
        "plant_i32_cdab",
        "holding",
        10,
        r#"type = "i32", word_order = "little""#,
        &[0x1DC0, 0xFFFE],
        -123_456.0,
    ),
    (
        "plant_i32_badc",
        "holding",
        12,
        r#"type = "i32", byte_order = "little""#,
        &[0xFEFF, 0xC01D],
        -123_456.0,
    ),
    (
        "plant_i32_dcba",
        "holding",
        14,
        r#"type = "i32", word_order = "little", byte_order = "little""#,
        &[0xC01D, 0xFEFF],
        -123_456.0,
    ),
    // 65000 = 0xFDE8: above i16's range, so a signed reading shows.
    (
        "plant_u16",
        "holding",
        16,
        r#"type = "u16""#,
        &[0xFDE8],
        65_000.0,
    ),
    // -200 = 0xFF38.
    (
        "plant_i16",
        "holding",
        17,
        r#"type = "i16""#,
        &[0xFF38],
        -200.0,
    ),
    // 0x1234 = 4660 with its two bytes swapped; the type left out is u16.
    (
        "plant_u16_bytes_swapped",
        "holding",
        18,
        r#"byte_order = "little""#,
        &[0x3412],
        4660.0,
    ),
    // 4000000000 = 0xEE6B2800: above i32's range.
    (
        "plant_u32",
        "holding",
        19,
        r#"type = "u32""#,
        &[0xEE6B, 0x2800],
        4_000_000_000.0,
    ),
    // 2^53 - 1 = 0x001FFFFFFFFFFFFF, the largest integer an f64 holds exactly.
    (
        "plant_u64",
        "holding",
        21,
        r#"type = "u64""#,
        &[0x001F, 0xFFFF, 0xFFFF, 0xFFFF],
        9_007_199_254_740_991.0,
    ),
    // 0x00123456789ABCDE = 5124095576030430, four different registers, least significant first.
    (
        "plant_u64_words_reversed",
        "holding",
        25,
        r#"type = "u64", word_order = "little""#,
        &[0xBCDE, 0x789A, 0x3456, 0x0012],
        5_124_095_576_030_430.0,
    ),
    // -(2^53 - 1) = 0xFFE0000000000001: the sign across all four registers.
    (
        "plant_i64",
        "holding",
        29,
        r#"type = "i64""#,
        &[0xFFE0, 0x0000, 0x0000, 0x0001],
        -9_007_199_254_740_991.0,
    ),
    // -123456.5 = 0xC0FE240800000000.
    (
        "plant_f64",
        "holding",
        33,
        r#"type = "f64""#,
        &[0xC0FE, 0x2408, 0x0000, 0x0000],
        -123_456.5,
    ),
    // e = 0x4005BF0A8B145769, every byte reversed: 69 57 14 8B 0A BF 05 40.
    (
        "plant_f64_bytes_reversed",
        "holding",
        37,
        r#"type = "f64", word_order = "little", byte_order = "little""#,
        &[0x6957, 0x148B, 0x0ABF, 0x0540],
        std::f64::consts::E,
    ),
    // -1000 = 0xFC18, x 0.25 + 40.
    (
        "plant_scaled_celsius",
        "holding",
        41,
        r#"type = "i16", scale = 0.25, offset = 40, unit = "Cel""#,
        &[0xFC18],
        -210.0,
    ),
    // Bits 0, 1 and 15 of 0x8001: the least and the most significant are on.
    ("plant_bit_0", "holding", 42, r#"bit = 0"#, &[0x8001], 1.0),
    (
        "plant_bit_1",
        "holding",
        42,
        r#"type = "i16", bit = 1"#,
        &[0x8001],
        0.0,
    ),
    (
        "plant_bit_15",
        "holding",
        42,
        r#"type = "bool", bit = 15"#,
        &[0x8001],
        1.0,
    ),
    // A register as bool: not 0. Its one bit on is in the high byte.
    (
        "plant_bool_register",
        "holding",
        43,
        r#"type = "bool""#,
        &[0x0100],
        1.0,
    ),
    // Input registers 0-1 and 10, with nothing between them at the slave: two reads, since a
    // read across the hole would be answered with exception 02.
    (
        "plant_input_u32",
        "input",
        0,
        r#"type = "u32""#,
        &[0x0001, 0xE240],
        123_456.0,
    ),
    (
        "plant_input_i16",
        "input",
        10,
        r#"type = "i16""#,
        &[0x8000],
        -32_768.0,
    ),
    // Coils 3 on and 4 off; discrete inputs 7 on and 8 off. The type left out is bool.
    ("plant_coil_3", "coil", 3, "", &[1], 1.0),
    ("plant_coil_4", "coil", 4, r#"type = "bool""#, &[0], 0.0),
    ("plant_discrete_7", "discrete", 7, "", &[1], 1.0),
    ("plant_discrete_8", "discrete", 8, "", &[0], 0.0),
];

/// The reads that poll [`PLANT`], and no more: one per table where its values are contiguous,
/// two on the input registers, whose values have a hole between them.
const READS: [[u8; 5]; 5] = [
    [0x03, 0x00, 0x00, 0x00, 0x2C], // holding registers 0-43
    [0x04, 0x00, 0x00, 0x00, 0x02], // input registers 0-1
    [0x04, 0x00, 0x0A, 0x00, 0x01], // input register 10
    [0x01, 0x00, 0x03, 0x00, 0x02], // coils 3-4
    [0x02, 0x00, 0x07, 0x00, 0x02], // discrete inputs 7-8
];

/// The function code that reads `table`.
fn function(table: &str) -> u8 {
    match table {
        "coil" => 0x01,
        "discrete" => 0x02,
        "holding" => 0x03,
        "input" => 0x04,
        _ => panic!("no table {table}"),
    }
}

/// What the slave holds, by function code and address: every value's registers (or bits).
/// Values that share a register must agree on it.
fn held() -> BTreeMap<(u8, u16), u16> {
    let mut held = BTreeMap::new();
    for (name, table, register, _, words, _) in PLANT {
        for (address, &word) in (register..).zip(words) {
            let before = held.insert((function(table), address), word);
            assert!(
                before.is_none_or(|before| before == word),
                "{name} holds {word:04X} at {table} {address}, another value {before:04X?}"
            );
        }
    }
    held
}

/// The script's argument: the slave and each table's runs of consecutive addresses.
fn tables_json(held: &BTreeMap<(u8, u16), u16>) -> String {
    let mut tables = serde_json::Map::new();
    tables.insert("slave".into(), SLAVE.into());
    for table in ["holding", "input", "coil", "discrete"] {
        let mut runs: Vec<(u16, Vec<u16>)> = Vec::new();
        for (&(_, address), &word) in held.range((function(table), 0)..=(function(table), u16::MAX))
        {
            match runs.last_mut() {
                Some((first, words))
                    if usize::from(*first) + words.len() == usize::from(address) =>
                {
                    words.push(word);
                }
                _ => runs.push((address, vec![word])),
            }
        }
        tables.insert(table.into(), serde_json::json!(runs));
    }
    serde_json::Value::Object(tables).to_string()
}

/// The reply PDU to the read `request`, from what the slave holds.
fn reply(held: &BTreeMap<(u8, u16), u16>, request: &[u8; 5]) -> Vec<u8> {
    let function = request[0];
    let first = u16::from_be_bytes([request[1], request[2]]);
    let count = u16::from_be_bytes([request[3], request[4]]);
    let at = |address: u16| held.get(&(function, address)).copied().unwrap_or(0);
    let mut pdu = vec![function];
    if function <= 0x02 {
        // Bits, the first in the first byte's least significant bit.
        let mut bytes = vec![0u8; usize::from(count).div_ceil(8)];
        for i in 0..count {
            if at(first + i) != 0 {
                bytes[usize::from(i / 8)] |= 1 << (i % 8);
            }
        }
        pdu.push(bytes.len() as u8);
        pdu.extend(bytes);
    } else {
        pdu.push((2 * count) as u8);
        for i in 0..count {
            pdu.extend(at(first + i).to_be_bytes());
        }
    }
    pdu
}

/// The `[[bus.slave]]` that lists every value of [`PLANT`], polled every 200 ms.
fn slave_toml() -> String {
    let values: Vec<String> = PLANT
        .iter()
        .map(|(name, table, register, keys, _, _)| {
            let keys = if keys.is_empty() {
                String::new()
            } else {
                format!(", {keys}")
            };
            format!("  {{ name = \"{name}\", table = \"{table}\", register = {register}{keys} }},")
        })
        .collect();
    format!(
        "[[bus.slave]]\naddress = {SLAVE}\npoll_interval = \"200ms\"\nvalue = [\n{}\n]\n",
        values.join("\n")
    )
}

/// `GET /values`, once every value of [`PLANT`] has been read (the last listing after the
/// patience, whatever it holds).
async fn values_once_read(metrics: std::net::SocketAddr) -> serde_json::Value {
    let deadline = tokio::time::Instant::now() + PATIENCE;
    loop {
        let (status, body) = http_get(metrics, "/values").await;
        assert_eq!(status, 200, "{body}");
        let listing: serde_json::Value = serde_json::from_str(&body).expect("/values is JSON");
        let values = listing["values"].as_array().expect("a list of values");
        let all_read = values.len() == PLANT.len() && values.iter().all(|v| !v["value"].is_null());
        if all_read || tokio::time::Instant::now() >= deadline {
            return listing;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// The RTU frames to the slave in `wire`, 8 bytes each (every poll is a read), and any
/// incomplete one at its end left out; the replies back, split by their length.
fn frames(wire: &Wire) -> (Vec<&[u8]>, Vec<&[u8]>) {
    let requests = wire.to_slave.chunks_exact(8).collect();
    let mut replies = Vec::new();
    let mut rest = &wire.to_gateway[..];
    while rest.len() >= 3 {
        let len = if rest[1] & 0x80 != 0 {
            5
        } else {
            5 + usize::from(rest[2])
        };
        if rest.len() < len {
            break;
        }
        replies.push(&rest[..len]);
        rest = &rest[len..];
    }
    (requests, replies)
}

#[tokio::test]
async fn each_type_and_each_32_bit_layout_is_decoded_exactly_from_pymodbus_rtu_slave() {
    let held = held();
    let tables = tables_json(&held);
    let Some(slave) = Pymodbus::start_script(SCRIPT, &[&tables]).await else {
        return;
    };
    let gateway = GatewayConfig::new()
        .bus(pty_line(&slave.path).text(&slave_toml()))
        .start()
        .await;

    // Every value on GET /values: exactly its number, read, with no error.
    let listing = values_once_read(gateway.metrics_addr()).await;
    let listed = listing["values"].as_array().expect("a list of values");
    assert_eq!(listed.len(), PLANT.len(), "{listing:#}");
    for (name, table, register, _, words, expected) in PLANT {
        let entry = listed
            .iter()
            .find(|v| v["name"] == name)
            .unwrap_or_else(|| panic!("{name} is not on /values: {listing:#}"));
        let what = format!("{name} ({table} {register}: {words:04X?})");
        assert_eq!(entry["bus"], BUS, "{what}");
        assert_eq!(entry["slave"], SLAVE, "{what}");
        assert_eq!(entry["value"].as_f64(), Some(expected), "{what}: {entry}");
        assert!(entry["error"].is_null(), "{what}: {entry}");
        assert!(entry["read_at"].is_string(), "{what}: {entry}");
    }
    let scaled = listed.iter().find(|v| v["name"] == "plant_scaled_celsius");
    assert_eq!(scaled.map(|v| &v["unit"]), Some(&"Cel".into()));

    // The same numbers as gauges.
    let scrape = Scrape::of(&gateway).await;
    for (name, _, _, _, _, expected) in PLANT {
        let series = format!("{name}{{bus=\"{BUS}\",slave=\"{SLAVE}\"}}");
        assert_eq!(scrape.value(&series), expected, "{series}");
    }

    // On the wire: the five reads of the plan, each polled again after its 200 ms, and nothing
    // else; and pymodbus answered each with what the fixture says it holds, no exception.
    let requests: Vec<Vec<u8>> = READS.iter().map(|read| rtu::encode(SLAVE, read)).collect();
    let answered = |read: &[u8; 5]| rtu::encode(SLAVE, &reply(&held, read));
    let wire = slave
        .wire_when(|wire| {
            let (sent, got) = frames(wire);
            sent.len() == got.len()
                && requests
                    .iter()
                    .all(|r| sent.iter().filter(|s| **s == r.as_slice()).count() >= 2)
        })
        .await;
    let (sent, got) = frames(&wire);
    for (i, frame) in sent.iter().enumerate() {
        let Some(read) = requests.iter().position(|r| r.as_slice() == *frame) else {
            panic!("request {i} on the wire is none of the plan's reads: {frame:02X?}");
        };
        if let Some(reply) = got.get(i) {
            assert_eq!(
                *reply,
                answered(&READS[read]).as_slice(),
                "pymodbus's reply {i}, to {:02X?}",
                READS[read]
            );
        }
    }
    for (read, request) in READS.iter().zip(&requests) {
        let times = sent.iter().filter(|s| **s == request.as_slice()).count();
        assert!(
            times >= 2,
            "read {read:02X?} went {times} times: {sent:02X?}"
        );
    }
    assert_eq!(sent.len(), got.len(), "every request answered: {wire:02X?}");

    // The gateway counted those polls (each once its answer is in, so a moment after the wire
    // log has it), and none failed.
    let polls = format!("modbus_gateway_polls_total{{bus=\"{BUS}\",slave=\"{SLAVE}\"}}");
    let scrape = within("the gateway counts two rounds of polls", async {
        loop {
            let scrape = Scrape::of(&gateway).await;
            if scrape.get(&polls).is_some_and(|n| n >= 10.0) {
                return scrape;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    let failed = scrape.series_of("modbus_gateway_poll_errors_total");
    assert!(failed.iter().all(|(_, n)| *n == 0.0), "{failed:?}");
}
