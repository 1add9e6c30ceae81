//! What the simulated drives (VFDs) share: the output-frequency ramp, the motor quantities derived
//! from it, a parameter table with the manuals' modify rules, and the settings a drive powers on
//! with. The models ([`super::goodrive`], [`super::pd_inverter`]) own their register maps and
//! exception codes; this module knows nothing of either.

use crate::line::SerialFormat;
use std::collections::BTreeMap;
use std::time::Duration;
use tokio::time::Instant;

/// What the configuration tells a simulated drive at power-on.
#[derive(Clone, Debug, PartialEq)]
pub struct DriveSettings {
    /// The drive's own slave address on the line.
    pub address: u8,
    /// The line's format, which the drive's communication parameters report.
    pub format: SerialFormat,
    /// The shortest time the drive takes to answer once it has recognised a request; its
    /// response-delay parameter can make it longer.
    pub processing_delay: Duration,
    /// Parameter values that replace the factory defaults, by the manual's name ("P00.11",
    /// "Pd-05") in fieldbus units (50.00 Hz is 5000). May set read-only records too.
    pub params: BTreeMap<String, u16>,
    /// A fault the drive has tripped with at power-on (the manual's fault code).
    pub trip: Option<u16>,
}

impl DriveSettings {
    pub fn new(address: u8, format: SerialFormat) -> Self {
        DriveSettings {
            address,
            format,
            processing_delay: Duration::ZERO,
            params: BTreeMap::new(),
            trip: None,
        }
    }
}

/// A setting a drive model cannot accept, named by the parameter (or `trip`).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{param}: {reason}")]
pub struct SetupError {
    pub param: String,
    pub reason: String,
}

/// When a parameter may be written, in the manuals' marks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Modify {
    /// ○: at any time.
    Always,
    /// ◎: only while the drive is stopped.
    Stopped,
    /// ●: never (read-only records and actual values).
    Never,
}

/// A bound of a parameter's range: a number, or the current value of another parameter.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Limit {
    Value(u16),
    Param(u16),
}

/// One function-code parameter: register address, name, factory default, range and modify rule.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ParamSpec {
    pub address: u16,
    pub name: &'static str,
    pub default: u16,
    pub min: Limit,
    pub max: Limit,
    pub modify: Modify,
}

/// Why a parameter write is refused; each model maps these to its manual's exception codes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
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
pub struct Params {
    table: &'static [ParamSpec],
    values: BTreeMap<u16, u16>,
}

impl Params {
    /// Every parameter of `table` at its factory default.
    pub fn new(table: &'static [ParamSpec]) -> Self {
        let mut params = Params {
            table,
            values: BTreeMap::new(),
        };
        params.restore_defaults();
        params
    }

    pub fn restore_defaults(&mut self) {
        self.values = self.table.iter().map(|p| (p.address, p.default)).collect();
    }

    pub fn spec(&self, address: u16) -> Option<&'static ParamSpec> {
        self.table.iter().find(|p| p.address == address)
    }

    pub fn by_name(&self, name: &str) -> Option<&'static ParamSpec> {
        self.table.iter().find(|p| p.name == name)
    }

    /// The value of the parameter at `address`, if there is one.
    pub fn get(&self, address: u16) -> Option<u16> {
        self.values.get(&address).copied()
    }

    /// The value of a parameter the model knows is in its table.
    pub fn value(&self, address: u16) -> u16 {
        self.get(address).unwrap_or(0)
    }

    fn limit(&self, limit: Limit) -> u16 {
        match limit {
            Limit::Value(v) => v,
            Limit::Param(address) => self.value(address),
        }
    }

    /// The range `address` accepts now (bounds that name other parameters use their values).
    pub fn range(&self, spec: &ParamSpec) -> (u16, u16) {
        (self.limit(spec.min), self.limit(spec.max))
    }

    /// Whether writing `value` to `address` is allowed, without writing it.
    pub fn check(&self, address: u16, value: u16, running: bool) -> Result<(), Refusal> {
        let spec = self.spec(address).ok_or(Refusal::NoSuchAddress)?;
        match spec.modify {
            Modify::Never => return Err(Refusal::ReadOnly),
            Modify::Stopped if running => return Err(Refusal::WhileRunning),
            _ => {}
        }
        let (min, max) = self.range(spec);
        if value < min || value > max {
            return Err(Refusal::OutOfRange);
        }
        Ok(())
    }

    /// Check and write.
    pub fn write(&mut self, address: u16, value: u16, running: bool) -> Result<(), Refusal> {
        self.check(address, value, running)?;
        self.values.insert(address, value);
        Ok(())
    }

    /// Set a value with no modify rule applied (power-on settings, records the drive keeps
    /// itself). Only the range is checked.
    pub fn force(&mut self, address: u16, value: u16) -> Result<(), Refusal> {
        let spec = self.spec(address).ok_or(Refusal::NoSuchAddress)?;
        let (min, max) = self.range(spec);
        if value < min || value > max {
            return Err(Refusal::OutOfRange);
        }
        self.values.insert(address, value);
        Ok(())
    }

    /// Apply the configured power-on values by name. Each is range-checked against the table
    /// as it stands once all are applied, so `P00.03 = 10000` and `P00.04 = 9000` work in any
    /// order.
    pub fn apply(&mut self, settings: &BTreeMap<String, u16>) -> Result<(), SetupError> {
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

/// How fast the output frequency may change: full scale (the maximum frequency, in 0.01 Hz) in
/// the acceleration or deceleration time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rates {
    pub full_scale: u32,
    pub accel: Duration,
    pub decel: Duration,
}

impl Rates {
    /// 0.01 Hz per second; a zero time changes the frequency at once.
    fn per_second(&self, time: Duration) -> f64 {
        if time.is_zero() {
            f64::INFINITY
        } else {
            f64::from(self.full_scale) / time.as_secs_f64()
        }
    }
}

/// The output frequency of a drive, moving toward its target at the acceleration rate while its
/// magnitude grows and at the deceleration rate while it shrinks; a change of direction passes
/// through 0 Hz. Signed, in 0.01 Hz: positive is forward. Lazy: it is worked out when asked.
#[derive(Clone, Debug)]
pub struct Ramp {
    frequency: f64,
    target: f64,
    at: Instant,
}

impl Ramp {
    /// Standing still at `now`.
    pub fn new(now: Instant) -> Self {
        Ramp {
            frequency: 0.0,
            target: 0.0,
            at: now,
        }
    }

    /// Move the ramp on to `now` with `rates`, which must be the rates in force since the last
    /// call: call this before changing a ramp time or the maximum frequency.
    pub fn advance(&mut self, now: Instant, rates: Rates) {
        let mut remaining = now.saturating_duration_since(self.at).as_secs_f64();
        self.at = self.at.max(now);
        while remaining > 0.0 && self.frequency != self.target {
            let shrinking = (self.frequency > 0.0 && self.target < self.frequency)
                || (self.frequency < 0.0 && self.target > self.frequency);
            let rate = rates.per_second(if shrinking { rates.decel } else { rates.accel });
            let crosses_zero = self.frequency * self.target < 0.0;
            let stop_at = if crosses_zero { 0.0 } else { self.target };
            let distance = (stop_at - self.frequency).abs();
            let needed = distance / rate;
            if needed <= remaining {
                self.frequency = stop_at;
                remaining -= needed;
            } else {
                self.frequency += (stop_at - self.frequency).signum() * rate * remaining;
                remaining = 0.0;
            }
        }
    }

    /// Head for `target` (signed 0.01 Hz) from `now`.
    pub fn set_target(&mut self, now: Instant, target: i32, rates: Rates) {
        self.advance(now, rates);
        self.target = f64::from(target);
    }

    /// Drop the output at `now` (coast to stop, a trip).
    pub fn coast(&mut self, now: Instant) {
        self.at = self.at.max(now);
        self.frequency = 0.0;
        self.target = 0.0;
    }

    /// Signed output frequency in 0.01 Hz as of the last [`Ramp::advance`].
    pub fn frequency(&self) -> i32 {
        self.frequency.round() as i32
    }

    pub fn target(&self) -> i32 {
        self.target.round() as i32
    }

    /// True once the output has reached its target.
    pub fn settled(&self) -> bool {
        self.frequency == self.target
    }
}

/// The motor on a simulated drive, driving a pump-like load: torque grows with the square of the
/// speed. Gives every actual value the drive reports a consistent figure for one output frequency.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Motor {
    /// Rated voltage, V.
    pub voltage: u16,
    /// Rated current, 0.01 A.
    pub current: u32,
    /// Rated frequency, 0.01 Hz.
    pub frequency: u32,
    /// Rated speed, rpm (below synchronous speed by the rated slip).
    pub speed: u32,
    pub poles: u32,
    /// DC bus voltage of the drive, 0.1 V.
    pub bus_voltage: u16,
}

impl Motor {
    /// Load as a fraction of rated torque at `frequency` (0.01 Hz, either sign).
    fn load(&self, frequency: i32) -> f64 {
        let speed = f64::from(frequency.unsigned_abs()) / f64::from(self.frequency);
        0.1 + 0.7 * speed * speed
    }

    fn fraction(&self, frequency: i32) -> f64 {
        f64::from(frequency.unsigned_abs()) / f64::from(self.frequency)
    }

    /// Output voltage, V: V/f linear up to the rated frequency.
    pub fn output_voltage(&self, frequency: i32) -> u16 {
        (f64::from(self.voltage) * self.fraction(frequency).min(1.0)).round() as u16
    }

    /// Output current, 0.01 A: magnetising current plus the load's share; 0 with no output.
    pub fn output_current(&self, frequency: i32, energised: bool) -> u32 {
        if !energised {
            return 0;
        }
        let share = 0.3 + 0.7 * self.load(frequency);
        (f64::from(self.current) * share).round() as u32
    }

    /// Shaft speed, rpm: synchronous speed less the slip the load causes.
    pub fn speed(&self, frequency: i32) -> u32 {
        let synchronous = f64::from(frequency.unsigned_abs()) * 1.2 / f64::from(self.poles);
        let rated_synchronous = f64::from(self.frequency) * 1.2 / f64::from(self.poles);
        let rated_slip = (rated_synchronous - f64::from(self.speed)) / rated_synchronous;
        let slip = rated_slip * self.load(frequency) / 0.8;
        (synchronous * (1.0 - slip).max(0.0)).round() as u32
    }

    /// Output torque, 0.1 % of rated; 0 with no output.
    pub fn torque(&self, frequency: i32, energised: bool) -> u16 {
        if !energised || frequency == 0 {
            return 0;
        }
        (1000.0 * self.load(frequency)).round() as u16
    }

    /// Output power, 0.1 % of rated.
    pub fn power(&self, frequency: i32, energised: bool) -> u16 {
        let torque = f64::from(self.torque(frequency, energised));
        (torque * self.fraction(frequency)).round() as u16
    }
}

/// The big-endian word at `at` in a PDU.
pub fn word(pdu: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]))
}

/// An exception response PDU.
pub fn exception(function: u8, code: u8) -> Vec<u8> {
    vec![function | crate::pdu::EXCEPTION_BIT, code]
}

#[cfg(test)]
mod tests {
    use super::*;

    const RATES: Rates = Rates {
        full_scale: 5000,
        accel: Duration::from_secs(10),
        decel: Duration::from_secs(20),
    };

    fn after(start: Instant, secs: f64) -> Instant {
        start + Duration::from_secs_f64(secs)
    }

    #[test]
    fn the_ramp_reaches_full_scale_in_the_acceleration_time_and_no_sooner() {
        let t0 = Instant::now();
        let mut ramp = Ramp::new(t0);
        ramp.set_target(t0, 5000, RATES);
        ramp.advance(after(t0, 5.0), RATES);
        assert_eq!(ramp.frequency(), 2500);
        ramp.advance(after(t0, 9.99), RATES);
        assert!(ramp.frequency() < 5000);
        ramp.advance(after(t0, 10.0), RATES);
        assert_eq!(ramp.frequency(), 5000);
        assert!(ramp.settled());
    }

    #[test]
    fn a_reversal_decelerates_to_zero_then_accelerates_the_other_way() {
        let t0 = Instant::now();
        let mut ramp = Ramp::new(t0);
        ramp.set_target(t0, 5000, RATES);
        ramp.set_target(after(t0, 10.0), -2500, RATES);
        // 5000 -> 0 takes the full deceleration time (20 s), then 0 -> -2500 takes 5 s.
        ramp.advance(after(t0, 30.0), RATES);
        assert_eq!(ramp.frequency(), 0);
        ramp.advance(after(t0, 32.5), RATES);
        assert_eq!(ramp.frequency(), -1250);
        ramp.advance(after(t0, 40.0), RATES);
        assert_eq!(ramp.frequency(), -2500);
    }

    #[test]
    fn a_zero_ramp_time_changes_the_output_at_once() {
        let t0 = Instant::now();
        let mut ramp = Ramp::new(t0);
        let instant = Rates {
            accel: Duration::ZERO,
            ..RATES
        };
        ramp.set_target(t0, 4000, instant);
        ramp.advance(after(t0, 0.001), instant);
        assert_eq!(ramp.frequency(), 4000);
    }

    #[test]
    fn motor_values_rise_with_the_output_and_vanish_without_it() {
        let motor = Motor {
            voltage: 380,
            current: 1300,
            frequency: 5000,
            speed: 1440,
            poles: 4,
            bus_voltage: 5400,
        };
        assert_eq!(motor.output_voltage(5000), 380);
        assert_eq!(motor.output_voltage(2500), 190);
        assert_eq!(motor.output_current(0, false), 0);
        assert!(motor.output_current(2500, true) < motor.output_current(5000, true));
        // At rated frequency the pump load takes 80 % torque and the rated slip.
        assert_eq!(motor.speed(5000), 1440);
        assert!(motor.speed(-2500) < 750 && motor.speed(-2500) > 700);
        assert_eq!(motor.torque(5000, true), 800);
        assert_eq!(motor.power(5000, true), 800);
        assert_eq!(motor.power(0, true), 0);
    }

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
        assert_eq!(params.write(0x0004, 5001, false), Err(Refusal::OutOfRange));
        assert_eq!(
            params.write(0x0003, 10000, true),
            Err(Refusal::WhileRunning)
        );
        assert_eq!(params.write(0x0003, 10000, false), Ok(()));
        assert_eq!(params.write(0x0004, 9000, false), Ok(()));
        assert_eq!(params.write(0x071B, 1, false), Err(Refusal::ReadOnly));
        assert_eq!(params.write(0x0005, 1, false), Err(Refusal::NoSuchAddress));
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
