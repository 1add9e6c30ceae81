//! A drive's parameter table: each parameter's address, name, factory default, range (which may
//! name another parameter) and the manuals' modify marks, and the values checked against it.
//! Knows nothing of registers other than parameters, of exception codes or of the line.

use super::SetupError;
use std::collections::BTreeMap;

/// When a parameter may be written, in the manuals' marks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Modify {
    /// ○: at any time.
    Always,
    /// ◎: only while the drive is stopped.
    Stopped,
    /// ●: never (read-only records and actual values).
    Never,
}

/// A bound of a parameter's range: a number, or the current value of another parameter.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Limit {
    Value(u16),
    Param(u16),
}

/// One function-code parameter: register address, name, factory default, range and modify rule.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct ParamSpec {
    pub address: u16,
    pub name: &'static str,
    pub default: u16,
    pub min: Limit,
    pub max: Limit,
    pub(crate) modify: Modify,
}

/// Why a parameter write is refused; each model maps these to its manual's exception codes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ParamRefusal {
    /// No parameter at this address.
    NoSuchAddress,
    /// The parameter can never be written.
    ReadOnly,
    /// The parameter cannot be written while the drive runs.
    WhileRunning,
    /// The value is outside the parameter's range.
    OutOfRange,
}

/// A drive's parameter values, checked against its table.
#[derive(Clone, Debug)]
pub(crate) struct Params {
    table: &'static [ParamSpec],
    values: BTreeMap<u16, u16>,
}

impl Params {
    /// Every parameter of `table` at its factory default.
    pub(crate) fn new(table: &'static [ParamSpec]) -> Self {
        let mut params = Params {
            table,
            values: BTreeMap::new(),
        };
        params.restore_defaults();
        params
    }

    pub(crate) fn restore_defaults(&mut self) {
        self.values = self.table.iter().map(|p| (p.address, p.default)).collect();
    }

    pub(crate) fn spec(&self, address: u16) -> Option<&'static ParamSpec> {
        self.table.iter().find(|p| p.address == address)
    }

    pub(crate) fn by_name(&self, name: &str) -> Option<&'static ParamSpec> {
        self.table.iter().find(|p| p.name == name)
    }

    /// The value of the parameter at `address`, if there is one.
    pub(crate) fn get(&self, address: u16) -> Option<u16> {
        self.values.get(&address).copied()
    }

    /// The value of a parameter the model knows is in its table.
    pub(crate) fn value(&self, address: u16) -> u16 {
        self.get(address).unwrap_or(0)
    }

    fn limit(&self, limit: Limit) -> u16 {
        match limit {
            Limit::Value(v) => v,
            Limit::Param(address) => self.value(address),
        }
    }

    /// The range `address` accepts now (bounds that name other parameters use their values).
    pub(crate) fn range(&self, spec: &ParamSpec) -> (u16, u16) {
        (self.limit(spec.min), self.limit(spec.max))
    }

    /// Whether writing `value` to `address` is allowed, without writing it.
    pub(crate) fn check(
        &self,
        address: u16,
        value: u16,
        running: bool,
    ) -> Result<(), ParamRefusal> {
        let spec = self.spec(address).ok_or(ParamRefusal::NoSuchAddress)?;
        match spec.modify {
            Modify::Never => return Err(ParamRefusal::ReadOnly),
            Modify::Stopped if running => return Err(ParamRefusal::WhileRunning),
            _ => {}
        }
        let (min, max) = self.range(spec);
        if value < min || value > max {
            return Err(ParamRefusal::OutOfRange);
        }
        Ok(())
    }

    /// Check and write.
    pub(crate) fn write(
        &mut self,
        address: u16,
        value: u16,
        running: bool,
    ) -> Result<(), ParamRefusal> {
        self.check(address, value, running)?;
        self.values.insert(address, value);
        Ok(())
    }

    /// Set a value with no modify rule applied (power-on settings, records the drive keeps
    /// itself). Only the range is checked.
    pub(crate) fn force(&mut self, address: u16, value: u16) -> Result<(), ParamRefusal> {
        let spec = self.spec(address).ok_or(ParamRefusal::NoSuchAddress)?;
        let (min, max) = self.range(spec);
        if value < min || value > max {
            return Err(ParamRefusal::OutOfRange);
        }
        self.values.insert(address, value);
        Ok(())
    }

    /// Apply the configured power-on values by name. Each is range-checked against the table
    /// as it stands once all are applied, so `P00.03 = 10000` and `P00.04 = 9000` work in any
    /// order.
    pub(crate) fn apply(&mut self, settings: &BTreeMap<String, u16>) -> Result<(), SetupError> {
        let mut resolved = Vec::with_capacity(settings.len());
        for (name, &value) in settings {
            let spec = self.by_name(name).ok_or_else(|| SetupError {
                param: name.clone(),
                reason: "is not a parameter this simulated drive has".into(),
            })?;
            self.values.insert(spec.address, value);
            resolved.push((name, spec, value));
        }
        for (name, spec, value) in resolved {
            let (min, max) = self.range(spec);
            if value < min || value > max {
                return Err(SetupError {
                    param: name.clone(),
                    reason: format!("{value} is outside {min}..={max}"),
                });
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TABLE: &[ParamSpec] = &[
        ParamSpec {
            address: 0x0003,
            name: "P00.03",
            default: 5000,
            min: Limit::Param(0x0004),
            max: Limit::Value(40000),
            modify: Modify::Stopped,
        },
        ParamSpec {
            address: 0x0004,
            name: "P00.04",
            default: 5000,
            min: Limit::Value(0),
            max: Limit::Param(0x0003),
            modify: Modify::Stopped,
        },
        ParamSpec {
            address: 0x071B,
            name: "P07.27",
            default: 0,
            min: Limit::Value(0),
            max: Limit::Value(100),
            modify: Modify::Never,
        },
    ];

    #[test]
    fn parameter_writes_follow_the_modify_marks_and_ranges_that_name_other_parameters() {
        let mut params = Params::new(TABLE);
        assert_eq!(
            params.write(0x0004, 5001, false),
            Err(ParamRefusal::OutOfRange)
        );
        assert_eq!(
            params.write(0x0003, 10000, true),
            Err(ParamRefusal::WhileRunning)
        );
        assert_eq!(params.write(0x0003, 10000, false), Ok(()));
        assert_eq!(params.write(0x0004, 9000, false), Ok(()));
        assert_eq!(params.write(0x071B, 1, false), Err(ParamRefusal::ReadOnly));
        assert_eq!(
            params.write(0x0005, 1, false),
            Err(ParamRefusal::NoSuchAddress)
        );
        params.restore_defaults();
        assert_eq!(params.value(0x0003), 5000);
    }

    #[test]
    fn power_on_values_apply_in_any_order_and_name_the_bad_one() {
        let mut params = Params::new(TABLE);
        let settings = BTreeMap::from([("P00.04".to_owned(), 9000), ("P00.03".to_owned(), 10000)]);
        params.apply(&settings).unwrap();
        assert_eq!(params.value(0x0004), 9000);
        let mut params = Params::new(TABLE);
        let bad = BTreeMap::from([("P00.99".to_owned(), 1)]);
        assert_eq!(params.apply(&bad).unwrap_err().param, "P00.99");
        let bad = BTreeMap::from([("P07.27".to_owned(), 101)]);
        assert_eq!(params.apply(&bad).unwrap_err().param, "P07.27");
    }
}
