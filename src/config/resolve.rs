//! Derives the values that depend on other keys, once the configuration has passed its check:
//! a bus's data bits follow its framing, and its stop bits its parity, unless given. The printed configuration shows them, so
//! what `check-config` prints is what runs. Knows nothing of how the values are used.

use super::{defaults, Config, ConfigErrors};
use crate::line::SerialFormat;

impl Config {
    /// Fill in what the file may leave to other keys.
    pub fn resolve(&mut self) {
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
    /// [`Config::from_toml_str`] does after parsing.
    pub fn validate(&mut self) -> Result<(), ConfigErrors> {
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
}
