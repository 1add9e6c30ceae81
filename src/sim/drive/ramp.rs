//! The output frequency of a drive as it moves toward its target at the configured acceleration
//! and deceleration rates. Pure time math over `Instant`s; knows nothing of registers or the line.

use std::time::Duration;
use tokio::time::Instant;

/// How fast the output frequency may change: full scale (the maximum frequency, in 0.01 Hz) in
/// the acceleration or deceleration time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Rates {
    pub(crate) full_scale: u32,
    pub accel: Duration,
    pub(crate) decel: Duration,
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
pub(crate) struct Ramp {
    frequency: f64,
    target: f64,
    at: Instant,
}

impl Ramp {
    /// Standing still at `now`.
    pub(crate) fn new(now: Instant) -> Self {
        Ramp {
            frequency: 0.0,
            target: 0.0,
            at: now,
        }
    }

    /// Move the ramp on to `now` with `rates`, which must be the rates in force since the last
    /// call: call this before changing a ramp time or the maximum frequency.
    pub(crate) fn advance(&mut self, now: Instant, rates: Rates) {
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
    pub(crate) fn set_target(&mut self, now: Instant, target: i32, rates: Rates) {
        self.advance(now, rates);
        self.target = f64::from(target);
    }

    /// Drop the output at `now` (coast to stop, a trip).
    pub(crate) fn coast(&mut self, now: Instant) {
        self.at = self.at.max(now);
        self.frequency = 0.0;
        self.target = 0.0;
    }

    /// Signed output frequency in 0.01 Hz as of the last [`Ramp::advance`].
    pub(crate) fn frequency(&self) -> i32 {
        rounded(self.frequency)
    }

    /// True once the output has reached its target.
    #[cfg(test)]
    fn settled(&self) -> bool {
        self.frequency == self.target
    }
}

// The ramp only moves between targets given as `i32`, so its rounded value is always one; the
// cast drops nothing but the fraction rounding has already removed.
#[allow(clippy::cast_possible_truncation)]
fn rounded(frequency: f64) -> i32 {
    frequency.round() as i32
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
}
