//! The motor on a simulated drive: every actual value a drive reports, worked out consistently
//! from one output frequency. Knows nothing of registers, ramps or the line.

/// The motor on a simulated drive, driving a pump-like load: torque grows with the square of the
/// speed. Gives every actual value the drive reports a consistent figure for one output frequency.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Motor {
    /// Rated voltage, V.
    pub voltage: u16,
    /// Rated current, 0.01 A.
    pub(crate) current: u32,
    /// Rated frequency, 0.01 Hz.
    pub frequency: u32,
    /// Rated speed, rpm (below synchronous speed by the rated slip).
    pub speed: u32,
    pub(crate) poles: u32,
    /// DC bus voltage of the drive, 0.1 V.
    pub(crate) bus_voltage: u16,
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
    pub(crate) fn output_voltage(&self, frequency: i32) -> u16 {
        rounded_u16(f64::from(self.voltage) * self.fraction(frequency).min(1.0))
    }

    /// Output current, 0.01 A: magnetising current plus the load's share; 0 with no output.
    pub(crate) fn output_current(&self, frequency: i32, energised: bool) -> u32 {
        if !energised {
            return 0;
        }
        let share = 0.3 + 0.7 * self.load(frequency);
        rounded_u32(f64::from(self.current) * share)
    }

    /// Shaft speed, rpm: synchronous speed less the slip the load causes.
    pub(crate) fn speed(&self, frequency: i32) -> u32 {
        let synchronous = f64::from(frequency.unsigned_abs()) * 1.2 / f64::from(self.poles);
        let rated_synchronous = f64::from(self.frequency) * 1.2 / f64::from(self.poles);
        let rated_slip = (rated_synchronous - f64::from(self.speed)) / rated_synchronous;
        let slip = rated_slip * self.load(frequency) / 0.8;
        rounded_u32(synchronous * (1.0 - slip).max(0.0))
    }

    /// Output torque, 0.1 % of rated; 0 with no output.
    pub(crate) fn torque(&self, frequency: i32, energised: bool) -> u16 {
        if !energised || frequency == 0 {
            return 0;
        }
        rounded_u16(1000.0 * self.load(frequency))
    }

    /// Output power, 0.1 % of rated.
    pub(crate) fn power(&self, frequency: i32, energised: bool) -> u16 {
        let torque = f64::from(self.torque(frequency, energised));
        rounded_u16(torque * self.fraction(frequency))
    }
}

// A float-to-integer `as` saturates, so a figure beyond a register's range reads its maximum (as
// a drive's display does) rather than wrapping; truncating the fraction after rounding is the
// intent.
#[allow(clippy::cast_possible_truncation)]
fn rounded_u16(value: f64) -> u16 {
    value.round() as u16
}

#[allow(clippy::cast_possible_truncation)]
fn rounded_u32(value: f64) -> u32 {
    value.round() as u32
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
