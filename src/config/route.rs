//! The `[[route]]` sections, and the one rule that turns a routed unit id into a slave address
//! (the router's table and the checks both use it). Knows nothing of buses' tasks.

use super::UnitSet;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Route {
    pub units: UnitSet,
    pub bus: String,
    /// Every unit goes to this slave address.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub address: Option<u8>,
    /// Slave address = unit + offset (neither given: offset 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset: Option<i32>,
}

impl Route {
    /// The slave address `unit` goes to, if it is within the line's addresses, 0 to `highest`.
    pub fn target(&self, unit: u8, highest: u8) -> Option<u8> {
        let address = match (self.address, self.offset) {
            (Some(address), _) => i64::from(address),
            (None, _) => i64::from(unit) + i64::from(self.unit_offset()),
        };
        u8::try_from(address).ok().filter(|&a| a <= highest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routes_map_units_by_address_or_offset() {
        let fixed = Route {
            units: UnitSet::default(),
            bus: "b".into(),
            address: Some(17),
            offset: None,
        };
        assert_eq!(fixed.target(255, 247), Some(17));
        let shifted = Route {
            units: UnitSet::default(),
            bus: "b".into(),
            address: None,
            offset: Some(-100),
        };
        assert_eq!(shifted.target(101, 247), Some(1));
        assert_eq!(shifted.target(99, 247), None);
        let same = Route {
            units: UnitSet::default(),
            bus: "b".into(),
            address: None,
            offset: None,
        };
        assert_eq!(same.target(248, 247), None);
        // A Modbus TCP device's units go up to 255.
        assert_eq!(same.target(255, 255), Some(255));
    }
}
