//! The `virtual-unit-` scenario's line and unit: the demo's four drives on the simulated line,
//! each polled by its device template, and a `[[virtual]]` unit laid out from their values, which
//! the gateway answers from memory; and the wait until it answers a read normally, as a master
//! reading before the first polls would get 0x0B. Knows nothing of the load or the figures.

use crate::gateway::Gateway;
use crate::masters::{Answer, Conn};
use std::fmt::Write as _;
use std::time::{Duration, Instant};
use test_support::Bus;
use tokio::net::TcpStream;

/// The virtual unit's id.
pub(crate) const UNIT: u8 = 100;

/// One drive on the line: its address, the simulator's model, the template that polls it, and
/// whether it answers a read with the extra count byte of its factory setting
/// (`wide_read_count`), as the demo's pd-inverter does.
struct Drive {
    address: u8,
    model: &'static str,
    template: &'static str,
    wide_read_count: bool,
}

/// The drives of config/demo.toml.
const DRIVES: [Drive; 4] = [
    Drive {
        address: 1,
        model: "gd20",
        template: "goodrive20",
        wide_read_count: false,
    },
    Drive {
        address: 2,
        model: "gd300",
        template: "goodrive300",
        wide_read_count: false,
    },
    Drive {
        address: 3,
        model: "gd10",
        template: "goodrive10",
        wide_read_count: false,
    },
    Drive {
        address: 4,
        model: "pd-inverter",
        template: "pd-inverter",
        wide_read_count: true,
    },
];

/// The values of each drive the unit shows, each template's, with the template's scale: a
/// block of one register per drive for each, in this order.
const SHOWN: [(&str, f64); 2] = [
    ("drive_output_frequency_hertz", 0.01),
    ("drive_dc_bus_voltage_volts", 0.1),
];

/// The unit's holding registers, 0 up: every drive's output frequency, then every drive's DC
/// bus voltage.
#[allow(
    clippy::cast_possible_truncation,
    reason = "2 values of 4 drives: 8 registers"
)]
pub(crate) const REGISTERS: u16 = (SHOWN.len() * DRIVES.len()) as u16;

/// The masters' read: every register of the unit, 0 up.
pub(crate) const READ: [u8; 5] = {
    let [hi, lo] = REGISTERS.to_be_bytes();
    [0x03, 0x00, 0x00, hi, lo]
};

/// How often each drive is polled: its values' `max_age` is three times this. Short, so that
/// the unit answers soon after the start.
const POLL_INTERVAL: &str = "1s";
/// The share of the line the polls may take: all of it, as no master's read goes there. At the
/// default (0.2) the 9600-baud line polls about 5 times a second, and a round of the drives'
/// templates (about 13 reads) takes 2.5 s: a value is then often older than its 3 s `max_age`
/// when read, and the read gets 0x0B.
const POLL_SHARE: f64 = 1.0;
/// How long the gateway may take to poll every value the unit shows once.
const FRESH_LIMIT: Duration = Duration::from_secs(30);
/// How often the bench tries the unit until then.
const FRESH_CHECK: Duration = Duration::from_millis(100);

/// `bus` with the drives: the simulator's models, and a `[[bus.slave]]` each polling its
/// template every [`POLL_INTERVAL`], within [`POLL_SHARE`] of the line.
pub(crate) fn drives(bus: Bus) -> Bus {
    let mut bus = bus.key("poll_share", POLL_SHARE);
    let mut slaves = String::new();
    for d in &DRIVES {
        let _ = writeln!(
            slaves,
            "[[bus.slave]]\naddress = {}\ntemplate = \"{}\"\npoll_interval = \"{POLL_INTERVAL}\"",
            d.address, d.template
        );
        if d.wide_read_count {
            slaves.push_str("wide_read_count = true\n");
        }
        bus = bus.sim_slave(&d.address.to_string(), &[("model", d.model.into())]);
    }
    bus.text(&slaves)
}

/// The `[[virtual]]` unit on bus `bus`'s drives, as TOML.
pub(crate) fn table(bus: &str) -> String {
    let mut toml = format!("[[virtual]]\nunit = {UNIT}\nname = \"bench\"\n");
    let registers = SHOWN
        .iter()
        .flat_map(|shown| DRIVES.iter().map(move |d| (shown, d.address)));
    for (register, ((name, scale), address)) in registers.enumerate() {
        let _ = writeln!(
            toml,
            "[[virtual.register]]\nregister = {register}\nvalue = \"{bus}/{address}/{name}\"\n\
             scale = {scale:?}"
        );
    }
    toml
}

/// Wait (at most [`FRESH_LIMIT`]) until a read of every register of the unit is answered
/// normally: every value it shows has been polled.
pub(crate) async fn until_answered(gateway: &Gateway) -> Result<(), String> {
    let stream = TcpStream::connect(gateway.listen)
        .await
        .map_err(|e| format!("the virtual unit: connect: {e}"))?;
    stream.set_nodelay(true).map_err(|e| e.to_string())?;
    let mut conn = Conn::Tcp(stream);
    let mut reply = vec![0u8; 512];
    let started = Instant::now();
    for tid in 1u16.. {
        match conn
            .exchange(tid, UNIT, &READ, &mut reply)
            .await
            .map_err(|e| format!("the virtual unit: {e}"))?
        {
            Answer::Normal => return Ok(()),
            Answer::Exception if started.elapsed() < FRESH_LIMIT => {
                tokio::time::sleep(FRESH_CHECK).await;
            }
            Answer::Exception => break,
            Answer::Unexpected => {
                return Err(format!(
                    "the virtual unit: unexpected reply {:02X?}",
                    &reply[..16]
                ))
            }
        }
    }
    Err(format!(
        "the virtual unit still answered an exception after {FRESH_LIMIT:?}"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use modbus_gateway::gateway::config_from_toml;
    use test_support::GatewayConfig;

    #[test]
    fn the_unit_lays_out_every_register_the_masters_read_from_values_the_drives_templates_poll() {
        let text = GatewayConfig::new()
            .bus(drives(Bus::sim("bench")))
            .to_toml()
            + &table("bench");
        let config = config_from_toml(&text).unwrap_or_else(|e| panic!("{e}\n{text}"));
        assert_eq!(config.virtual_units.len(), 1);
        let unit = &config.virtual_units[0];
        assert_eq!(unit.unit, UNIT);
        let registers: Vec<u32> = unit.register.iter().map(|r| r.register).collect();
        assert_eq!(registers, (0..u32::from(REGISTERS)).collect::<Vec<_>>());
        assert_eq!(READ[4], 8);
        let slaves = &config.bus[0].slave;
        assert_eq!(slaves.len(), DRIVES.len());
        assert!(slaves.iter().all(|s| s.poll_interval.is_some()));
    }
}
