//! The simulated Eastron SDM120-Modbus single-phase energy meter (`model = "sdm120"`): its input
//! registers, each measurement an IEEE 754 single-precision float in two registers, high word
//! first (ABCD), read with FC 04, and the exceptions Eastron's protocol documents give for the
//! rest. What it measures is a pure function of the time since power-on, so a test knows what
//! it reads. Knows nothing of the line's timing, the bus queue or TCP.
//!
//! Where the meter's documents are silent, or a simulator has no use for a part, the model
//! decides:
//! - A read must start on a parameter the table lists and cover whole parameters, each one
//!   listed: half a float, or an address between parameters, is 02 ("an attempt to read part
//!   of a floating point value", "an invalid address"). 0 registers, or more than 40 parameters
//!   in one request, is 03.
//! - The demand registers (0x0054-0x005E, 0x0102, 0x0108) are not modelled (02), nor are the
//!   holding registers, the set-up: FC 03 and FC 10 are answered 02 whatever they ask. Every
//!   other function code is 01.
//! - The load imports throughout and is inductive: active power swings 1000-1300 W, reactive
//!   power 0-200 var, voltage 228-232 V, frequency 49.95-50.05 Hz, each on its own slow period,
//!   and all of them start at their power-on value: 230 V, 5 A, 1150 W, power factor 1, 50 Hz,
//!   no energy. Export energies stay 0; the totals are import plus export.

use super::{Simulated, Transmission};
use crate::pdu::code;
use crate::pdu::exception_pdu;
use crate::pdu::ExceptionCode::{self, IllegalDataAddress, IllegalDataValue, IllegalFunction};
use std::f64::consts::{FRAC_PI_2, TAU};
use std::time::Duration;
use tokio::time::Instant;

/// The length of an FC 04 request: function code, start address, quantity.
const READ_REQUEST_LEN: usize = 5;
/// Registers one parameter takes: an f32.
const PARAMETER_WORDS: u16 = 2;
/// Eastron's documents limit one read to a number of parameters; the SDM630's figure.
const MAX_READ_PARAMETERS: u16 = 40;
/// A kWh in joules, and a kvarh in var s: the meter counts energy in those.
const JOULES_PER_KILOWATT_HOUR: f64 = 3_600_000.0;

/// What a parameter's register pair holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Parameter {
    Voltage,
    Current,
    ActivePower,
    ApparentPower,
    ReactivePower,
    PowerFactor,
    PhaseAngle,
    Frequency,
    ImportActiveEnergy,
    ExportActiveEnergy,
    ImportReactiveEnergy,
    ExportReactiveEnergy,
    TotalActiveEnergy,
    TotalReactiveEnergy,
}

/// The modelled input registers: each parameter's first register, as Eastron's table lists them.
const INPUT_REGISTERS: [(u16, Parameter); 14] = [
    (0x0000, Parameter::Voltage),
    (0x0006, Parameter::Current),
    (0x000C, Parameter::ActivePower),
    (0x0012, Parameter::ApparentPower),
    (0x0018, Parameter::ReactivePower),
    (0x001E, Parameter::PowerFactor),
    (0x0024, Parameter::PhaseAngle),
    (0x0046, Parameter::Frequency),
    (0x0048, Parameter::ImportActiveEnergy),
    (0x004A, Parameter::ExportActiveEnergy),
    (0x004C, Parameter::ImportReactiveEnergy),
    (0x004E, Parameter::ExportReactiveEnergy),
    (0x0156, Parameter::TotalActiveEnergy),
    (0x0158, Parameter::TotalReactiveEnergy),
];

fn parameter_at(address: u16) -> Option<Parameter> {
    INPUT_REGISTERS
        .iter()
        .find(|(first, _)| *first == address)
        .map(|&(_, parameter)| parameter)
}

/// A quantity that swings around `mean` by `amplitude` with `period` (seconds), starting at
/// `phase` (radians) at power-on.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Swing {
    mean: f64,
    amplitude: f64,
    period: f64,
    phase: f64,
}

impl Swing {
    fn angular(&self) -> f64 {
        TAU / self.period
    }

    /// The value `t` seconds after power-on.
    fn at(&self, t: f64) -> f64 {
        self.mean + self.amplitude * (self.angular() * t + self.phase).sin()
    }

    /// Its integral from power-on to `t` seconds: what a meter accumulates of it.
    fn integral(&self, t: f64) -> f64 {
        let w = self.angular();
        self.mean * t + self.amplitude / w * (self.phase.cos() - (w * t + self.phase).cos())
    }
}

const VOLTAGE: Swing = Swing {
    mean: 230.0,
    amplitude: 2.0,
    period: 450.0,
    phase: 0.0,
};
const ACTIVE_POWER: Swing = Swing {
    mean: 1150.0,
    amplitude: 150.0,
    period: 600.0,
    phase: 0.0,
};
/// 0 var at power-on, up to 200 var half a period later: a motor starting up somewhere.
const REACTIVE_POWER: Swing = Swing {
    mean: 100.0,
    amplitude: 100.0,
    period: 780.0,
    phase: -FRAC_PI_2,
};
const FREQUENCY: Swing = Swing {
    mean: 50.0,
    amplitude: 0.05,
    period: 180.0,
    phase: 0.0,
};

/// What the meter has counted of `power` (W or var, never negative) `t` seconds after power-on,
/// in kWh or kvarh. Just after power-on the integral's two terms nearly cancel and rounding may
/// leave it a hair below 0, which a meter's count never is.
fn energy(power: Swing, t: f64) -> f64 {
    (power.integral(t) / JOULES_PER_KILOWATT_HOUR).max(0.0)
}

/// What the meter measures at one moment, in its own units (V, A, W, VA, var, degrees, Hz,
/// kWh, kvarh).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Readings {
    voltage: f64,
    active_power: f64,
    reactive_power: f64,
    frequency: f64,
    import_active_energy: f64,
    import_reactive_energy: f64,
}

impl Readings {
    /// `t` seconds after power-on.
    fn at(t: f64) -> Self {
        Readings {
            voltage: VOLTAGE.at(t),
            active_power: ACTIVE_POWER.at(t),
            reactive_power: REACTIVE_POWER.at(t),
            frequency: FREQUENCY.at(t),
            import_active_energy: energy(ACTIVE_POWER, t),
            import_reactive_energy: energy(REACTIVE_POWER, t),
        }
    }

    fn apparent_power(&self) -> f64 {
        self.active_power.hypot(self.reactive_power)
    }

    fn value(&self, parameter: Parameter) -> f64 {
        // The load never exports.
        let (export_active_energy, export_reactive_energy) = (0.0, 0.0);
        match parameter {
            Parameter::Voltage => self.voltage,
            Parameter::Current => self.apparent_power() / self.voltage,
            Parameter::ActivePower => self.active_power,
            Parameter::ApparentPower => self.apparent_power(),
            Parameter::ReactivePower => self.reactive_power,
            Parameter::PowerFactor => self.active_power / self.apparent_power(),
            Parameter::PhaseAngle => self.reactive_power.atan2(self.active_power).to_degrees(),
            Parameter::Frequency => self.frequency,
            Parameter::ImportActiveEnergy => self.import_active_energy,
            Parameter::ExportActiveEnergy => export_active_energy,
            Parameter::ImportReactiveEnergy => self.import_reactive_energy,
            Parameter::ExportReactiveEnergy => export_reactive_energy,
            Parameter::TotalActiveEnergy => self.import_active_energy + export_active_energy,
            Parameter::TotalReactiveEnergy => self.import_reactive_energy + export_reactive_energy,
        }
    }
}

// The meter's registers hold IEEE 754 single precision: rounding to it is what the meter does.
#[allow(clippy::cast_possible_truncation)]
fn single(value: f64) -> f32 {
    value as f32
}

type Reply = Result<Vec<u8>, ExceptionCode>;

fn word(pdu: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]))
}

/// A simulated SDM120 on the line.
#[derive(Clone, Debug)]
pub(crate) struct Sdm120 {
    powered_on: Instant,
    processing_delay: Duration,
}

impl Sdm120 {
    /// Powered on at `now`, answering `processing_delay` after each request.
    pub(crate) fn new(processing_delay: Duration, now: Instant) -> Self {
        Sdm120 {
            powered_on: now,
            processing_delay,
        }
    }

    fn readings(&self, at: Instant) -> Readings {
        Readings::at(at.saturating_duration_since(self.powered_on).as_secs_f64())
    }

    /// FC 04: whole parameters from a listed one, every one of them listed.
    fn read_input_registers(&self, request: &[u8], at: Instant) -> Reply {
        let (READ_REQUEST_LEN, Some(start), Some(quantity)) =
            (request.len(), word(request, 1), word(request, 3))
        else {
            return Err(IllegalDataValue);
        };
        if quantity == 0 || quantity > MAX_READ_PARAMETERS * PARAMETER_WORDS {
            return Err(IllegalDataValue);
        }
        if quantity % PARAMETER_WORDS != 0 {
            return Err(IllegalDataAddress);
        }
        let readings = self.readings(at);
        let mut reply = vec![code::READ_INPUT_REGISTERS];
        // At most 40 parameters: 160 bytes.
        reply.push(u8::try_from(2 * quantity).map_err(|_| IllegalDataValue)?);
        for offset in (0..quantity).step_by(usize::from(PARAMETER_WORDS)) {
            let parameter = start
                .checked_add(offset)
                .and_then(parameter_at)
                .ok_or(IllegalDataAddress)?;
            reply.extend(single(readings.value(parameter)).to_be_bytes());
        }
        Ok(reply)
    }

    fn respond(&self, request: &[u8], at: Instant) -> Reply {
        match request.first().copied() {
            Some(code::READ_INPUT_REGISTERS) => self.read_input_registers(request, at),
            // The set-up lives in holding registers, which this model does not have.
            Some(code::READ_HOLDING_REGISTERS | code::WRITE_MULTIPLE_REGISTERS) => {
                Err(IllegalDataAddress)
            }
            _ => Err(IllegalFunction),
        }
    }
}

impl Simulated for Sdm120 {
    fn handle(&mut self, address: u8, request: &[u8], at: Instant) -> Option<Transmission> {
        if address == crate::line::BROADCAST {
            // Nothing the model serves is a write: a broadcast changes nothing.
            return None;
        }
        let function = request.first().copied().unwrap_or(0);
        let pdu = self
            .respond(request, at)
            .unwrap_or_else(|e| exception_pdu(function, e).to_vec());
        Some(Transmission::frame(address, &pdu, self.processing_delay))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::rtu;

    const ADDRESS: u8 = 5;

    fn after(t0: Instant, secs: f64) -> Instant {
        t0 + Duration::from_secs_f64(secs)
    }

    /// The reply PDU to `request` at `at`.
    fn ask(meter: &mut Sdm120, request: &[u8], at: Instant) -> Vec<u8> {
        let answer = meter.handle(ADDRESS, request, at).expect("an answer");
        rtu::pdu_of(&answer.bytes).to_vec()
    }

    /// The floats of an FC 04 read of `count` parameters from `start`.
    fn read(meter: &mut Sdm120, start: u16, count: u16, at: Instant) -> Vec<f32> {
        let [s_hi, s_lo] = start.to_be_bytes();
        let [q_hi, q_lo] = (2 * count).to_be_bytes();
        let reply = ask(meter, &[0x04, s_hi, s_lo, q_hi, q_lo], at);
        assert_eq!(
            reply[..2],
            [0x04, u8::try_from(4 * count).unwrap()],
            "{reply:02X?}"
        );
        reply[2..]
            .chunks_exact(4)
            .map(|b| f32::from_be_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    }

    fn one(meter: &mut Sdm120, start: u16, at: Instant) -> f32 {
        read(meter, start, 1, at)[0]
    }

    /// 230 volts, 5 amperes, 1150 watts at power factor 1, and 50 hertz.
    #[test]
    fn at_power_on_the_meter_reads_230_v_5_a_1150_w_power_factor_1_and_50_hz() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        let expected = [
            (0x0000, 230.0),
            (0x0006, 5.0),
            (0x000C, 1150.0),
            (0x0012, 1150.0),
            (0x0018, 0.0),
            (0x001E, 1.0),
            (0x0024, 0.0),
            (0x0046, 50.0),
            (0x0048, 0.0),
            (0x004A, 0.0),
            (0x004C, 0.0),
            (0x004E, 0.0),
            (0x0156, 0.0),
            (0x0158, 0.0),
        ];
        for (address, value) in expected {
            assert_eq!(one(&mut meter, address, t0), value, "{address:04X}");
        }
    }

    #[test]
    fn each_value_is_a_float_high_word_first() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        // 230.0 = 0x43660000, 5.0 = 0x40A00000.
        assert_eq!(
            ask(&mut meter, &[0x04, 0x00, 0x00, 0x00, 0x02], t0),
            [0x04, 0x04, 0x43, 0x66, 0x00, 0x00]
        );
        assert_eq!(
            ask(&mut meter, &[0x04, 0x00, 0x06, 0x00, 0x02], t0),
            [0x04, 0x04, 0x40, 0xA0, 0x00, 0x00]
        );
    }

    /// After whole periods of the load, the import energy is the mean power times the time.
    #[test]
    fn over_whole_load_periods_import_energy_is_mean_power_times_time() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        // One hour is six periods of the active power and a whole number of the other swings but
        // the reactive power's: 1150 W for an hour.
        let hour = after(t0, 3600.0);
        let [frequency, import, export] = read(&mut meter, 0x0046, 3, hour)[..] else {
            unreachable!()
        };
        assert_eq!(frequency, 50.0);
        assert!((import - 1.15).abs() < 1e-6, "{import} kWh");
        assert_eq!(export, 0.0);
        assert_eq!(one(&mut meter, 0x0156, hour), import);
        assert_eq!(one(&mut meter, 0x0000, hour), 230.0);
    }

    #[test]
    fn just_after_power_on_no_energy_reads_below_zero() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        for micros in 0..2000 {
            let at = t0 + Duration::from_micros(micros * 7);
            for energy in read(&mut meter, 0x0048, 4, at) {
                assert!(energy >= 0.0, "{micros}: {energy}");
            }
        }
    }

    #[test]
    fn energy_counts_up_with_the_power_and_never_back() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        let mut last = (0.0, 0.0);
        for step in 1..=200 {
            let at = after(t0, f64::from(step) * 37.0);
            let imported = (one(&mut meter, 0x0048, at), one(&mut meter, 0x004C, at));
            assert!(imported.0 > last.0 && imported.1 >= last.1, "{step}");
            last = imported;
        }
        // 7400 s at 1150 W on average, give or take part of a swing.
        let expected = 1150.0 * 7400.0 / 3_600_000.0;
        assert!((f64::from(last.0) - expected).abs() < 0.03, "{}", last.0);
    }

    #[test]
    fn the_values_vary_slowly_within_their_swings_and_agree_with_each_other() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        let mut previous: Option<Vec<f32>> = None;
        for second in 0..1800 {
            let at = after(t0, f64::from(second));
            let mut v = read(&mut meter, 0x0000, 1, at);
            v.extend(read(&mut meter, 0x0006, 1, at));
            v.extend(read(&mut meter, 0x000C, 1, at));
            v.extend(read(&mut meter, 0x0012, 1, at));
            v.extend(read(&mut meter, 0x0018, 1, at));
            v.extend(read(&mut meter, 0x001E, 1, at));
            let [voltage, current, p, s, q, pf] = v[..] else {
                unreachable!()
            };
            assert!((228.0..=232.0).contains(&voltage), "{second}: {voltage}");
            assert!((1000.0..=1300.0).contains(&p), "{second}: {p}");
            assert!((0.0..=200.0).contains(&q), "{second}: {q}");
            assert!((s * s - p * p - q * q).abs() / (s * s) < 1e-5, "{second}");
            assert!((current * voltage - s).abs() / s < 1e-5, "{second}");
            assert!((pf * s - p).abs() / s < 1e-5, "{second}");
            if let Some(previous) = &previous {
                // Most each can move in a second: V, A, W, VA, var, power factor.
                let limits = [0.03, 0.02, 1.6, 2.4, 0.81, 0.001];
                for ((now, before), limit) in v.iter().zip(previous).zip(limits) {
                    assert!((now - before).abs() <= limit, "{second}: {before} -> {now}");
                }
            }
            previous = Some(v);
        }
    }

    #[test]
    fn the_same_moment_reads_the_same_whatever_was_read_before() {
        let t0 = Instant::now();
        let mut polled = Sdm120::new(Duration::ZERO, t0);
        let mut fresh = Sdm120::new(Duration::ZERO, t0);
        for step in 0..100 {
            one(&mut polled, 0x0048, after(t0, f64::from(step) * 11.0));
        }
        let at = after(t0, 1234.5);
        assert_eq!(
            read(&mut polled, 0x0046, 5, at),
            read(&mut fresh, 0x0046, 5, at)
        );
    }

    #[test]
    fn half_a_float_or_a_register_the_table_does_not_list_is_an_illegal_data_address() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        for request in [
            // The low half of the voltage.
            [0x04, 0x00, 0x01, 0x00, 0x02],
            // The voltage and half the next.
            [0x04, 0x00, 0x00, 0x00, 0x03],
            // Between the voltage and the current.
            [0x04, 0x00, 0x02, 0x00, 0x02],
            // From the voltage across that gap to the current.
            [0x04, 0x00, 0x00, 0x00, 0x08],
            // A demand register, not modelled.
            [0x04, 0x00, 0x54, 0x00, 0x02],
            // Past the last parameter.
            [0x04, 0x01, 0x56, 0x00, 0x06],
            [0x04, 0xFF, 0xFE, 0x00, 0x04],
        ] {
            assert_eq!(
                ask(&mut meter, &request, t0),
                [0x84, 0x02],
                "{request:02X?}"
            );
        }
    }

    /// No registers, more than 40 parameters, or a malformed read.
    #[test]
    fn an_empty_oversized_or_malformed_read_is_an_illegal_data_value() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        for request in [
            &[0x04, 0x00, 0x00, 0x00, 0x00][..],
            &[0x04, 0x00, 0x00, 0x00, 0x52],
            &[0x04, 0x00, 0x00, 0x00],
            &[0x04, 0x00, 0x00, 0x00, 0x02, 0x00],
        ] {
            assert_eq!(ask(&mut meter, request, t0), [0x84, 0x03], "{request:02X?}");
        }
    }

    #[test]
    fn holding_register_functions_find_no_register_and_the_others_are_illegal() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        assert_eq!(
            ask(&mut meter, &[0x03, 0x00, 0x14, 0x00, 0x02], t0),
            [0x83, 0x02]
        );
        assert_eq!(
            ask(
                &mut meter,
                &[0x10, 0x00, 0x14, 0x00, 0x02, 0x04, 0x40, 0x00, 0x00, 0x00],
                t0
            ),
            [0x90, 0x02]
        );
        for function in [0x01, 0x02, 0x05, 0x06, 0x08, 0x0F, 0x11, 0x2B, 0x41] {
            assert_eq!(
                ask(&mut meter, &[function, 0x00, 0x00, 0x00, 0x02], t0),
                [function | 0x80, 0x01]
            );
        }
    }

    #[test]
    fn the_answer_is_a_frame_from_the_meter_after_its_processing_delay() {
        let t0 = Instant::now();
        let delay = Duration::from_millis(30);
        let mut meter = Sdm120::new(delay, t0);
        let request = [0x04, 0x00, 0x00, 0x00, 0x02];
        let answer = meter.handle(ADDRESS, &request, t0).expect("an answer");
        assert_eq!(
            answer,
            Transmission::frame(ADDRESS, &[0x04, 0x04, 0x43, 0x66, 0x00, 0x00], delay)
        );
        assert_eq!(
            rtu::check_reply(&answer.bytes, ADDRESS, &request),
            crate::line::Verdict::Answer
        );
    }

    #[test]
    fn a_broadcast_is_never_answered() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        assert_eq!(
            meter.handle(crate::line::BROADCAST, &[0x04, 0x00, 0x00, 0x00, 0x02], t0),
            None
        );
        assert_eq!(
            meter.handle(
                crate::line::BROADCAST,
                &[0x10, 0x00, 0x14, 0x00, 0x02, 0x04, 0x40, 0x00, 0x00, 0x00],
                t0
            ),
            None
        );
    }

    #[test]
    fn every_answer_to_any_request_is_a_frame_the_master_reads_whole_and_accepts() {
        let t0 = Instant::now();
        let mut meter = Sdm120::new(Duration::ZERO, t0);
        let addresses: Vec<u16> = INPUT_REGISTERS
            .iter()
            .flat_map(|&(a, _)| [a, a + 1])
            .chain([0x0054, 0xFFFE, 0xFFFF])
            .collect();
        let mut rng = fastrand::Rng::with_seed(1);
        for step in 0..20_000u64 {
            let mut pdu =
                crate::sim::random_pdu(&mut rng, 12, &[0x04, 0x04, 0x03, 0x10, 0x06], &addresses);
            if pdu.len() >= 5 && rng.bool() {
                // Small quantities, so whole reads happen too.
                pdu[3] = 0;
                pdu[4] %= 24;
            }
            let at = t0 + Duration::from_millis(step * 50);
            let Some(answer) = meter.handle(ADDRESS, &pdu, at) else {
                panic!("{pdu:02X?} unanswered");
            };
            // Function 0 and codes with the exception bit are no requests (the gateway never
            // sends them), so nothing is their answer.
            if !pdu
                .first()
                .copied()
                .is_some_and(crate::pdu::is_valid_request_function)
            {
                continue;
            }
            assert_eq!(
                rtu::reply_len(&answer.bytes, ADDRESS, &pdu),
                rtu::FrameLen::Exact(answer.bytes.len()),
                "{pdu:02X?} -> {:02X?}",
                answer.bytes
            );
            assert_eq!(
                rtu::check_reply(&answer.bytes, ADDRESS, &pdu),
                crate::line::Verdict::Answer,
                "{pdu:02X?} -> {:02X?}",
                answer.bytes
            );
        }
    }
}
