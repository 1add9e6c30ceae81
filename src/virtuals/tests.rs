//! A virtual unit's answers from a store the tests fill: encodings, staleness on the paused
//! clock, the exceptions, and what a write becomes.

use super::*;
use crate::pdu::ExceptionCode::{
    GatewayTargetFailedToRespond, IllegalDataAddress, IllegalDataValue, IllegalFunction,
};
use crate::values::Values;
use std::collections::BTreeMap;
use std::time::SystemTime;

const LINE: &str = r#"
[[bus]]
name = "line1"
device = "sim"

[[bus.slave]]
address = 2
poll_interval = "1s"

[[bus.slave.value]]
name = "frequency_hertz"
register = 0x3000
scale = 0.01

[[bus.slave.value]]
name = "power_watts"
register = 0x10
type = "f32"

[[bus.slave.value]]
name = "energy_joules"
register = 0x20
type = "i32"
word_order = "little"
scale = 0.1

[[bus.slave.value]]
name = "running"
register = 5
table = "coil"

[[bus.slave.value]]
name = "setpoint_hertz"
register = 0x2001
scale = 0.01

[[bus.slave]]
address = 5
template = "eastron-sdm120"
"#;

/// The configuration `LINE` with `virtual_units`, its store, and the units.
fn units(virtual_units: &str) -> (Config, Arc<Store>, Units) {
    let config = Config::from_toml_str(&format!("{LINE}{virtual_units}")).expect("valid");
    let values = Values::new();
    values.apply(&config, &[]);
    let store = values.store().clone();
    let units = Units::new(&config, store.clone(), &Arc::new(TraceHub::new()));
    (config, store, units)
}

/// Slave `slave`'s value `name` reads `value` now.
fn set(store: &Store, slave: u8, name: &str, value: f64) {
    let labels = BTreeMap::new();
    let (_, at) = store.locate(std::iter::once(("line1", slave, name, &labels)));
    store.read(at[0].expect("configured"), value, SystemTime::now());
}

fn read(units: &Units, pdu: &[u8]) -> Result<Vec<u8>, Declined> {
    units.read(units.get(200).expect("unit 200"), pdu, Instant::now())
}

const OWN: &str = r#"
[[virtual]]
unit = 200
name = "copy"

[[virtual.register]]
register = 0
value = "line1/2/frequency_hertz"
scale = 0.01

[[virtual.register]]
register = 1
value = "line1/2/power_watts"
type = "f32"

[[virtual.register]]
register = 3
value = "line1/2/power_watts"
type = "f32"
word_order = "little"

[[virtual.register]]
register = 5
value = "line1/2/energy_joules"
type = "i32"

[[virtual.register]]
register = 7
value = "line1/2/frequency_hertz"
type = "i16"
scale = 0.1
offset = -50

[[virtual.register]]
register = 0
table = "coil"
value = "line1/2/running"
type = "bool"

[[virtual.register]]
register = 10
value = "line1/2/setpoint_hertz"
scale = 0.1
writable = true

[[virtual.register]]
register = 11
value = "line1/2/energy_joules"
type = "u32"
writable = true
"#;

#[tokio::test(start_paused = true)]
async fn each_encoding_reads_back_exactly_from_the_polled_values() {
    let (_, store, units) = units(OWN);
    set(&store, 2, "frequency_hertz", 50.0);
    set(&store, 2, "power_watts", 1234.5);
    set(&store, 2, "energy_joules", -123_456.0);
    set(&store, 2, "running", 1.0);
    let reply = read(&units, &[0x03, 0, 0, 0, 8]).expect("answered");
    assert_eq!(
        reply,
        [
            0x03, 16, // 8 registers
            0x13, 0x88, // 50 Hz in 0.01 Hz: 5000
            0x44, 0x9A, 0x50, 0x00, // 1234.5, ABCD
            0x50, 0x00, 0x44, 0x9A, // and CDAB
            0xFF, 0xFE, 0x1D, 0xC0, // -123456, i32 ABCD
            0x03, 0xE8, // (50 - -50) / 0.1 = 1000
        ]
    );
    assert_eq!(read(&units, &[0x01, 0, 0, 0, 1]), Ok(vec![0x01, 1, 0x01]));
    // Half a float is the master's to ask for.
    assert_eq!(
        read(&units, &[0x03, 0, 2, 0, 1]),
        Ok(vec![0x03, 2, 0x50, 0x00])
    );
}

#[tokio::test(start_paused = true)]
async fn a_block_touching_one_stale_register_is_0x0b_whole_and_fresh_parts_still_answer() {
    let (_, store, units) = units(OWN);
    let stale = Err(Declined(GatewayTargetFailedToRespond));
    assert_eq!(read(&units, &[0x03, 0, 0, 0, 1]), stale, "never read");
    set(&store, 2, "frequency_hertz", 50.0);
    set(&store, 2, "power_watts", 1.0);
    // Three poll intervals of 1 s.
    tokio::time::advance(Duration::from_millis(2_000)).await;
    set(&store, 2, "power_watts", 2.0);
    tokio::time::advance(Duration::from_millis(1_001)).await;
    assert_eq!(read(&units, &[0x03, 0, 0, 0, 3]), stale, "0 is 3.001 s old");
    assert!(read(&units, &[0x03, 0, 1, 0, 2]).is_ok(), "1-2 are 1 s old");
    let labels = BTreeMap::new();
    let (_, at) = store.locate(std::iter::once(("line1", 2, "power_watts", &labels)));
    store.failed(at[0].unwrap(), "timeout");
    assert_eq!(
        read(&units, &[0x03, 0, 1, 0, 2]),
        stale,
        "its last poll failed"
    );
}

#[tokio::test(start_paused = true)]
async fn what_is_not_laid_out_is_0x02_and_out_of_range_values_0x0b() {
    let (_, store, units) = units(OWN);
    for name in ["frequency_hertz", "power_watts", "energy_joules"] {
        set(&store, 2, name, 1.0);
    }
    let unmapped = Err(Declined(IllegalDataAddress));
    assert_eq!(
        read(&units, &[0x03, 0, 8, 0, 2]),
        unmapped,
        "9 is not laid out"
    );
    assert_eq!(
        read(&units, &[0x04, 0, 0, 0, 1]),
        unmapped,
        "no input registers"
    );
    assert_eq!(read(&units, &[0x03, 0xFF, 0x83, 0, 125]), unmapped);
    assert_eq!(
        read(&units, &[0x03, 0, 0, 0, 0]),
        Err(Declined(IllegalDataValue))
    );
    assert_eq!(
        read(&units, &[0x03, 0, 0, 0, 126]),
        Err(Declined(IllegalDataValue))
    );
    set(&store, 2, "frequency_hertz", 700.0);
    assert_eq!(
        read(&units, &[0x03, 0, 0, 0, 1]),
        Err(Declined(GatewayTargetFailedToRespond)),
        "70000 is no u16"
    );
}

#[tokio::test(start_paused = true)]
async fn a_write_becomes_its_source_registers_write_in_the_sources_encoding() {
    let (_, _, units) = units(OWN);
    let unit = units.get(200).unwrap();
    let slave2 = Target {
        bus: 0,
        address: 2,
        broadcast: false,
    };
    // 25.5 Hz in 0.1 Hz (255) is 2550 in the slave's 0.01 Hz, at 2001H with FC 06.
    let (writes, normal) = units.write(unit, &[0x06, 0, 10, 0, 255]).unwrap();
    assert_eq!(
        writes,
        [SourceWrite {
            target: slave2,
            pdu: vec![0x06, 0x20, 0x01, 0x09, 0xF6],
        }]
    );
    assert_eq!(normal, [0x06, 0, 10, 0, 255]);
    // 123456 (u32 ABCD) is 1234560 raw at 0.1, i32 CDAB: two registers with FC 10.
    let (writes, normal) = units
        .write(
            unit,
            &[0x10, 0, 10, 0, 3, 6, 0, 100, 0x00, 0x01, 0xE2, 0x40],
        )
        .unwrap();
    assert_eq!(writes[0].pdu, [0x06, 0x20, 0x01, 0x03, 0xE8]);
    assert_eq!(
        writes[1].pdu,
        [0x10, 0x00, 0x20, 0, 2, 4, 0xD6, 0x80, 0x00, 0x12]
    );
    assert_eq!(normal, [0x10, 0, 10, 0, 3]);
    let refused = |pdu: &[u8]| units.write(unit, pdu).err();
    assert_eq!(
        refused(&[0x06, 0, 0, 0, 1]),
        Some(Declined(IllegalFunction)),
        "read-only"
    );
    assert_eq!(
        refused(&[0x06, 0, 11, 0, 1]),
        Some(Declined(IllegalDataAddress)),
        "half"
    );
    assert_eq!(
        refused(&[0x06, 0, 12, 0, 1]),
        Some(Declined(IllegalDataAddress)),
        "half"
    );
    assert_eq!(
        refused(&[0x06, 0, 20, 0, 1]),
        Some(Declined(IllegalDataAddress))
    );
    // 6553.6 Hz is no u16 in 0.01 Hz.
    assert_eq!(
        refused(&[0x06, 0, 10, 0xFF, 0xFF]),
        Some(Declined(IllegalDataValue))
    );
}

#[tokio::test(start_paused = true)]
async fn a_meter_presented_through_its_own_template_gives_the_meters_words() {
    let (_, store, units) = units(
        "[[virtual]]\nunit = 200\nname = \"meter\"\ntemplate = \"eastron-sdm120\"\n\
         source = { bus = \"line1\", slave = 5 }\n",
    );
    set(&store, 5, "energy_meter_voltage_volts", 230.0);
    set(&store, 5, "energy_meter_current_amperes", 5.0);
    let reply = units
        .read(units.get(200).unwrap(), &[0x04, 0, 0, 0, 2], Instant::now())
        .unwrap();
    assert_eq!(reply, [0x04, 4, 0x43, 0x66, 0x00, 0x00]);
    // 0002H-0005H are not the SDM120's.
    assert_eq!(
        units.read(units.get(200).unwrap(), &[0x04, 0, 0, 0, 8], Instant::now()),
        Err(Declined(IllegalDataAddress))
    );
}
