//! Unit id to (bus, slave address): the `[[route]]` entries first, then the default (with exactly
//! one bus, unit id = slave address 0-247; with several, nothing). A pure table built once. The
//! rule that turns a routed unit into an address is the config's
//! [`Route::target`](crate::config::Route::target), which the config's check uses too: routing
//! reads the config, never the other way round.

use crate::config::{Config, MAX_SLAVE_ADDRESS};

/// Where a unit's requests go.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Target {
    /// Index into the configured buses.
    pub bus: usize,
    /// Slave address on that bus; 0 is broadcast.
    pub address: u8,
}

#[derive(Clone, Debug)]
pub struct Router {
    table: [Option<Target>; 256],
}

impl Router {
    /// Build the table from a validated configuration.
    pub fn new(config: &Config) -> Router {
        let mut table = [None; 256];
        if config.bus.len() == 1 {
            for address in 0..=MAX_SLAVE_ADDRESS {
                table[usize::from(address)] = Some(Target { bus: 0, address });
            }
        }
        for route in &config.route {
            let bus = config.bus.iter().position(|b| b.name == route.bus);
            for unit in route.units.iter() {
                table[usize::from(unit)] = bus
                    .zip(route.target(unit))
                    .map(|(bus, address)| Target { bus, address });
            }
        }
        Router { table }
    }

    pub(crate) fn resolve(&self, unit: u8) -> Option<Target> {
        self.table[usize::from(unit)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn router(text: &str) -> Router {
        Router::new(&Config::from_toml_str(text).unwrap())
    }

    const ONE_BUS: &str = "[[bus]]\nname = \"line1\"\ndevice = \"sim\"\n";
    const TWO_BUSES: &str =
        "[[bus]]\nname = \"a\"\ndevice = \"sim\"\n[[bus]]\nname = \"b\"\ndevice = \"sim\"\n";

    #[test]
    fn with_one_bus_and_no_routes_the_unit_is_the_slave_address() {
        let r = router(ONE_BUS);
        assert_eq!(r.resolve(0), Some(Target { bus: 0, address: 0 }));
        assert_eq!(
            r.resolve(17),
            Some(Target {
                bus: 0,
                address: 17
            })
        );
        assert_eq!(
            r.resolve(247),
            Some(Target {
                bus: 0,
                address: 247
            })
        );
        assert_eq!(r.resolve(248), None);
        assert_eq!(r.resolve(255), None);
    }

    #[test]
    fn a_route_takes_precedence_over_the_default() {
        let r = router(&format!(
            "{ONE_BUS}[[route]]\nunits = \"255\"\nbus = \"line1\"\naddress = 17\n\
             [[route]]\nunits = \"1-2\"\nbus = \"line1\"\noffset = 10\n"
        ));
        assert_eq!(
            r.resolve(255),
            Some(Target {
                bus: 0,
                address: 17
            })
        );
        assert_eq!(
            r.resolve(1),
            Some(Target {
                bus: 0,
                address: 11
            })
        );
        assert_eq!(r.resolve(3), Some(Target { bus: 0, address: 3 }));
    }

    #[test]
    fn with_several_buses_only_routed_units_go_anywhere() {
        let r = router(&format!(
            "{TWO_BUSES}[[route]]\nunits = \"1-10\"\nbus = \"a\"\n\
             [[route]]\nunits = \"101-110\"\nbus = \"b\"\noffset = -100\n"
        ));
        assert_eq!(r.resolve(5), Some(Target { bus: 0, address: 5 }));
        assert_eq!(r.resolve(105), Some(Target { bus: 1, address: 5 }));
        assert_eq!(r.resolve(50), None);
        assert_eq!(r.resolve(0), None);
    }
}
