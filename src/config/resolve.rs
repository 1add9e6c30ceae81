//! Derives the values that depend on other keys, once the configuration has passed its check:
//! a bus's data bits follow its framing, and its stop bits its parity, unless given; the
//! connections one address may hold follow `max_connections`. The printed configuration shows
//! them, so what `check-config` prints is what runs. Knows nothing of how the values are used.

use super::{defaults, Config};
use crate::line::SerialFormat;

impl Config {
    /// Fill in what the file may leave to other keys.
    pub(crate) fn resolve(&mut self) {
        let server = &mut self.server;
        if server.max_connections_per_address.is_none() {
            server.max_connections_per_address = Some(defaults::max_connections_per_address(
                server.max_connections,
            ));
        }
        for bus in &mut self.bus {
            if bus.data_bits.is_none() {
                bus.data_bits = Some(defaults::data_bits(bus.framing));
            }
            if bus.stop_bits.is_none() {
                bus.stop_bits = Some(SerialFormat::default_stop_bits(bus.parity));
            }
        }
    }

    /// [`Config::check`] without the drives, then [`Config::resolve`]: what
    /// [`Config::from_toml_str`] does after parsing (for the loader's property tests).
    #[cfg(test)]
    pub(crate) fn validate(&mut self) -> Result<(), super::ConfigErrors> {
        self.check(None)?;
        self.resolve();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::testing::MINIMAL;

    #[test]
    fn no_parity_defaults_to_two_stop_bits() {
        let c = Config::from_toml_str(&format!("{MINIMAL}\nparity = \"none\"")).unwrap();
        assert_eq!(c.bus[0].stop_bits, Some(2));
        assert_eq!(c.bus[0].format().bits_per_char(), 11);
    }

    #[test]
    fn connections_per_address_default_to_all_but_eight_slots_and_0_lifts_the_limit() {
        for (max, per_address) in [(1024, 1016), (20, 12), (5, 3), (2, 1)] {
            let c = Config::from_toml_str(&format!("[server]\nmax_connections = {max}\n{MINIMAL}"))
                .unwrap();
            assert_eq!(c.server.max_connections_per_address, Some(per_address));
            assert_eq!(c.server.connections_per_address(), Some(per_address));
        }
        let c = Config::from_toml_str(&format!(
            "[server]\nmax_connections_per_address = 0\n{MINIMAL}"
        ))
        .unwrap();
        assert_eq!(c.server.connections_per_address(), None);
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
        let c =
            Config::from_toml_str(&format!("[server]\nmax_connections = 1\n{MINIMAL}")).unwrap();
        assert_eq!(
            c.server.connections_per_address(),
            None,
            "one slot: no limit of its own"
        );
    }
}
