//! Unit id to (bus, slave address): the `[[route]]` entries first, then the default (with exactly
//! one bus, unit id = slave address 0-247, or 0-255 on a Modbus TCP device; with several,
//! nothing). A pure table built once. The
//! rule that turns a routed unit into an address is the config's
//! [`Route::target`](crate::config::Route::target), which the config's check uses too: routing
//! reads the config, never the other way round. Also [`Inbound`], a request as it entered, with
//! where it routes: what the rules decide by and the journal records.

use crate::config::{Config, UnitSet};
use crate::line::BROADCAST;
use crate::master::{Peer, Protocol};

/// Where a unit's requests go.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Target {
    /// Index into the configured buses.
    pub bus: usize,
    /// Slave address on that bus.
    pub address: u8,
    /// The address is every slave's: 0 on a serial line (not on a Modbus TCP device).
    pub broadcast: bool,
}

/// A request as it entered the gateway, described once where it enters (the dispatcher): who
/// sent it and how, the unit it names and where that routes, its PDU. The rules decide by it and
/// the journal records it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Inbound<'a> {
    pub(crate) peer: &'a Peer,
    pub(crate) protocol: Protocol,
    /// A TLS master's certificate subject, and the role it carries, as written.
    pub(crate) subject: Option<&'a str>,
    pub(crate) role: Option<&'a str>,
    pub(crate) unit: u8,
    /// The bus its unit routes to, and where on it; `None` without a route.
    pub(crate) bus: Option<&'a str>,
    pub(crate) target: Option<Target>,
    /// The virtual unit it addresses, or whose register it writes through: its name.
    pub(crate) virtual_unit: Option<&'a str>,
    pub(crate) pdu: &'a [u8],
}

impl Target {
    fn on(bus: usize, address: u8, config: &Config) -> Target {
        let broadcasts = config.bus[bus].framing.broadcasts();
        Target {
            bus,
            address,
            broadcast: address == BROADCAST && broadcasts,
        }
    }
}

#[derive(Clone, Debug)]
pub struct Router {
    table: [Option<Target>; 256],
    /// The unit ids of the virtual units, which no bus has.
    virtuals: UnitSet,
}

impl Router {
    /// Build the table from a validated configuration.
    pub fn new(config: &Config) -> Router {
        let mut table = [None; 256];
        if let [only] = &config.bus[..] {
            for address in 0..=only.framing.highest_address() {
                table[usize::from(address)] = Some(Target::on(0, address, config));
            }
        }
        for route in &config.route {
            let bus = config.bus.iter().position(|b| b.name == route.bus);
            for unit in route.units.iter() {
                table[usize::from(unit)] = bus.and_then(|bus| {
                    let highest = config.bus[bus].framing.highest_address();
                    let address = route.target(unit, highest)?;
                    Some(Target::on(bus, address, config))
                });
            }
        }
        // A virtual unit's id is its own: no route names it (the check sees to that), and the
        // only bus's addresses yield it.
        let mut virtuals = UnitSet::default();
        for unit in &config.virtual_units {
            table[usize::from(unit.unit)] = None;
            virtuals.insert(unit.unit);
        }
        Router { table, virtuals }
    }

    /// The unit ids of the virtual units.
    pub(crate) fn virtuals(&self) -> UnitSet {
        self.virtuals
    }

    pub(crate) fn resolve(&self, unit: u8) -> Option<Target> {
        self.table[usize::from(unit)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a serial line, where address 0 is a broadcast.
    fn at(bus: usize, address: u8) -> Target {
        Target {
            bus,
            address,
            broadcast: address == 0,
        }
    }

    fn router(text: &str) -> Router {
        Router::new(&Config::from_toml_str(text).unwrap())
    }

    const ONE_BUS: &str = "[[bus]]\nname = \"line1\"\ndevice = \"sim\"\n";
    const TWO_BUSES: &str =
        "[[bus]]\nname = \"a\"\ndevice = \"sim\"\n[[bus]]\nname = \"b\"\ndevice = \"sim\"\n";

    #[test]
    fn with_one_bus_and_no_routes_the_unit_is_the_slave_address() {
        let r = router(ONE_BUS);
        assert_eq!(r.resolve(0), Some(at(0, 0)));
        assert_eq!(r.resolve(17), Some(at(0, 17)));
        assert_eq!(r.resolve(247), Some(at(0, 247)));
        assert_eq!(r.resolve(248), None);
        assert_eq!(r.resolve(255), None);
    }

    #[test]
    fn a_route_takes_precedence_over_the_default() {
        let r = router(&format!(
            "{ONE_BUS}[[route]]\nunits = \"255\"\nbus = \"line1\"\naddress = 17\n\
             [[route]]\nunits = \"1-2\"\nbus = \"line1\"\noffset = 10\n"
        ));
        assert_eq!(r.resolve(255), Some(at(0, 17)));
        assert_eq!(r.resolve(1), Some(at(0, 11)));
        assert_eq!(r.resolve(3), Some(at(0, 3)));
    }

    #[test]
    fn with_several_buses_only_routed_units_go_anywhere() {
        let r = router(&format!(
            "{TWO_BUSES}[[route]]\nunits = \"1-10\"\nbus = \"a\"\n\
             [[route]]\nunits = \"101-110\"\nbus = \"b\"\noffset = -100\n"
        ));
        assert_eq!(r.resolve(5), Some(at(0, 5)));
        assert_eq!(r.resolve(105), Some(at(1, 5)));
        assert_eq!(r.resolve(50), None);
        assert_eq!(r.resolve(0), None);
    }

    #[test]
    fn on_a_modbus_tcp_device_units_0_to_255_are_its_own_and_0_is_no_broadcast() {
        let r = router(
            "[[bus]]\nname = \"inverter\"\ndevice = \"tcp://10.0.0.9:502\"\nframing = \"tcp\"\n",
        );
        let unit = |bus, address| Target {
            bus,
            address,
            broadcast: false,
        };
        assert_eq!(r.resolve(0), Some(unit(0, 0)));
        assert_eq!(r.resolve(255), Some(unit(0, 255)));
        let remapped = router(
            "[[bus]]\nname = \"inverter\"\ndevice = \"tcp://10.0.0.9:502\"\nframing = \"tcp\"\n\
             [[bus]]\nname = \"line\"\ndevice = \"sim\"\n\
             [[route]]\nunits = \"1\"\nbus = \"inverter\"\naddress = 0\n\
             [[route]]\nunits = \"2\"\nbus = \"line\"\naddress = 0\n",
        );
        assert_eq!(remapped.resolve(1), Some(unit(0, 0)));
        assert_eq!(remapped.resolve(2), Some(at(1, 0)));
    }
}
