//! The simulated INVT Goodrive drives (GD20, GD300, GD10): their register map (2000H control and
//! setpoints, 2100H state, 3000H running values, 5000H fault), PXX.YY parameter addressing and the
//! manuals' exception codes, as a [`Model`] for the pipeline of [`super::Drive`]. Knows nothing of
//! the line's timing, the bus queue or TCP.
//!
//! Where the manuals are silent, contradict themselves or describe things a simulator has no use
//! for, the model decides:
//! - A value out of range is refused with 04, as in the manuals' worked example
//!   (01 06 00 01 00 03 -> 01 86 04), not 07 as their table suggests. 07 is kept for read-only
//!   registers and ● parameters, 08 for ◎ parameters while running, 01 for a run command while
//!   tripped, 02 for anything that is not there (including reads of write-only registers, of the
//!   RAM alias 8000H | PXX.YY and of the P29 factory group), 03 for a quantity outside 1..=16 and
//!   06 for a PDU whose length does not fit its function code.
//! - FC 10 is all or nothing: the words are carried out in order on a copy of the drive, so a
//!   later word sees an earlier one (P00.04 then P00.05), and a refusal anywhere changes nothing.
//! - 2000H commands act only while P00.01 selects communication (2). Otherwise they are answered
//!   and ignored, as real drives do. Jog runs at 5.00 Hz on the ordinary ramp; 8 (jog stop) stops
//!   a jog and leaves a run alone.
//! - Only the keypad (P00.06 = 0: P00.10) and Modbus (8: 2001H) references are wired; every other
//!   source reads 0 Hz. The reference is held within P00.05..=P00.04, also as 3001H reports it.
//! - P14.00-P14.02 report the line this drive hangs on (an unlisted baud or format reads the
//!   factory 4 / 1). Writing the value they hold is accepted; any other is refused with 07, since
//!   the simulated drive's address and format belong to the line's configuration.
//! - P14.04/P14.05 (communication timeout) are worked out at the next request, as of the moment
//!   the timeout expired, running or not. A drive already tripped keeps its first fault.
//! - P14.06 with the ones digit 1 carries out writes without answering them: a trap the gateway
//!   reports as 0x0B (target failed to respond). P14.03 and P14.06 act as they stand once the
//!   request is carried out, so the write that sets them is the first they govern.
//! - P00.18 = 1 restores the defaults but keeps the line's P14.00-P14.02 and the fault records,
//!   which P00.18 = 2 clears.
//! - 2100H reads 0002H for reverse running; the manuals misprint it as forward.

use super::{
    power_on_trip, Drive, DriveProtocol, DriveSettings, Exception, Model, Motor, ParamRefusal,
    Params, Ramp, Rates, SetupError,
};
use crate::pdu::ExceptionCode::{IllegalDataAddress, IllegalFunction, ServerDeviceFailure};
use std::time::Duration;
use tokio::time::Instant;

// The manuals' own meanings of the codes above 04 (their table of error codes).
/// 06H, data frame error: the length of the frame is wrong, or its CRC.
const FRAME_ERROR: Exception = Exception(0x06);
/// 07H, written not allowed: a read-only register or parameter.
const WRITE_NOT_ALLOWED: Exception = Exception(0x07);
/// 08H: the parameter cannot be modified during running.
const NOT_WHILE_RUNNING: Exception = Exception(0x08);

const REQUESTS: DriveProtocol = DriveProtocol {
    // The manuals' limit for one read or write.
    max_words: 16,
    diagnostics: true,
    write_multiple: true,
    malformed: FRAME_ERROR,
};

mod tables;

// The manuals' tables, by the manuals' names.
pub(crate) use tables::Variant;
use tables::*;

/// A run or jog command in force, as given (before P00.13 is applied).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Command {
    jog: bool,
    forward: bool,
}

/// A simulated Goodrive drive's state.
#[derive(Clone, Debug)]
pub(crate) struct Goodrive {
    variant: Variant,
    motor: Motor,
    params: Params,
    ramp: Ramp,
    command: Option<Command>,
    /// 2000H..=200EH as last written.
    control: [u16; CONTROL_REGISTERS.len()],
    /// Current fault code; 0 when healthy.
    fault: u16,
}

fn refusal_code(refusal: ParamRefusal) -> Exception {
    match refusal {
        ParamRefusal::NoSuchAddress => IllegalDataAddress.into(),
        ParamRefusal::ReadOnly => WRITE_NOT_ALLOWED,
        ParamRefusal::WhileRunning => NOT_WHILE_RUNNING,
        ParamRefusal::OutOfRange => ServerDeviceFailure.into(),
    }
}

fn saturate(value: u32) -> u16 {
    u16::try_from(value).unwrap_or(u16::MAX)
}

fn communication_processing_ok(value: u16) -> bool {
    matches!(value, 0x00 | 0x01 | 0x10 | 0x11)
}

fn setup_error(param: &str, reason: String) -> SetupError {
    SetupError {
        param: param.to_owned(),
        reason,
    }
}

impl Goodrive {
    /// Power on at `now` with `settings` (params applied via Params::apply, then trip).
    pub(crate) fn new(
        variant: Variant,
        settings: &DriveSettings,
        now: Instant,
    ) -> Result<Drive<Goodrive>, SetupError> {
        let mut params = Params::new(variant.table());
        params.apply(&settings.params)?;
        LINE.power_on(&mut params, settings)?;
        if params.value(P00_18) != 0 {
            return Err(setup_error(
                "P00.18",
                "is an action (restore or clear), not a setting".into(),
            ));
        }
        if !communication_processing_ok(params.value(P14_06)) {
            return Err(setup_error(
                "P14.06",
                "must be 0x00, 0x01, 0x10 or 0x11".into(),
            ));
        }
        let mut drive = Goodrive {
            variant,
            motor: variant.motor(),
            params,
            ramp: Ramp::new(now),
            command: None,
            control: [0; CONTROL_REGISTERS.len()],
            fault: 0,
        };
        if let Some(code) = power_on_trip(settings, LAST_FAULT_CODE)? {
            drive.trip(code, now);
        }
        Ok(Drive::new(drive, settings))
    }

    fn rates(&self) -> Rates {
        Rates {
            full_scale: u32::from(self.params.value(P00_03)),
            accel: TIME_UNIT * u32::from(self.params.value(P00_11)),
            decel: TIME_UNIT * u32::from(self.params.value(P00_12)),
        }
    }

    /// A run or jog command is in force, or the output has not yet come down to 0 Hz.
    fn running(&self) -> bool {
        self.command.is_some() || self.ramp.frequency() != 0
    }

    /// The frequency the drive runs at on a run command, held within the limits.
    fn reference(&self) -> u16 {
        let source = match self.params.value(P00_06) {
            KEYPAD_REFERENCE => self.params.value(P00_10),
            MODBUS_REFERENCE => self.control_value(SETPOINT_FREQUENCY),
            _ => 0,
        };
        source
            .max(self.params.value(P00_05))
            .min(self.params.value(P00_04))
    }

    /// The direction the output turns for `command`, P00.13 applied.
    fn turns_forward(&self, command: Command) -> bool {
        command.forward != (self.params.value(P00_13) == REVERSED)
    }

    /// Signed output frequency the ramp heads for.
    fn target(&self) -> i32 {
        let Some(command) = self.command else {
            return 0;
        };
        if !command.forward && self.params.value(P00_13) == REVERSE_FORBIDDEN {
            return 0;
        }
        let magnitude = if command.jog {
            JOG_FREQUENCY.min(i32::from(self.params.value(P00_03)))
        } else {
            i32::from(self.reference())
        };
        if self.turns_forward(command) {
            magnitude
        } else {
            -magnitude
        }
    }

    /// Follow the command and reference as they stand at `at`; the ramp must be advanced to `at`.
    fn retarget(&mut self, at: Instant) {
        let (target, rates) = (self.target(), self.rates());
        self.ramp.set_target(at, target, rates);
    }

    fn trip(&mut self, code: u16, at: Instant) {
        self.ramp.coast(at);
        self.command = None;
        self.fault = code;
        for newer in (0..FAULT_RECORDS.len() - 1).rev() {
            let record = self.params.value(FAULT_RECORDS[newer]);
            // Records hold 0..=100 and so does the next older one: this cannot be refused.
            let _ = self.params.force(FAULT_RECORDS[newer + 1], record);
        }
        let _ = self.params.force(FAULT_RECORDS[0], code);
    }

    fn control_value(&self, address: u16) -> u16 {
        self.control[usize::from(address - CONTROL)]
    }

    fn state_word(&self) -> u16 {
        if self.fault != 0 {
            return 4;
        }
        if !self.running() {
            return 3;
        }
        let frequency = self.ramp.frequency();
        let forward = if frequency != 0 {
            frequency > 0
        } else {
            self.command.is_none_or(|c| self.turns_forward(c))
        };
        if forward {
            1
        } else {
            2
        }
    }

    fn running_value(&self, address: u16) -> u16 {
        let Some(&(_, actual)) = RUNNING_VALUES.iter().find(|(a, _)| *a == address) else {
            return 0;
        };
        let frequency = self.ramp.frequency();
        let energised = self.running();
        match actual {
            Actual::OutputFrequency => saturate(frequency.unsigned_abs()),
            Actual::Reference => self.reference(),
            Actual::BusVoltage => self.motor.bus_voltage,
            Actual::OutputVoltage => self.motor.output_voltage(frequency),
            Actual::OutputCurrent => saturate(self.motor.output_current(frequency, energised) / 10),
            Actual::Speed => saturate(self.motor.speed(frequency)),
            Actual::Power => self.motor.power(frequency, energised),
            Actual::Torque => self.motor.torque(frequency, energised),
            Actual::PidReference => self.control_value(PID_REFERENCE),
            Actual::PidFeedback => self.control_value(PID_FEEDBACK),
            Actual::TorqueSetpoint => self.control_value(TORQUE_SETPOINT),
            Actual::Identifier => self.variant.identifier(),
        }
    }

    fn command(&mut self, value: u16, at: Instant) -> Result<(), Exception> {
        if !(1..=8).contains(&value) {
            return Err(ServerDeviceFailure.into());
        }
        if self.params.value(P00_01) != COMMUNICATION_CHANNEL {
            self.control[0] = value;
            return Ok(());
        }
        if self.fault != 0 && value <= 4 {
            // The manuals' "illegal command".
            return Err(IllegalFunction.into());
        }
        self.control[0] = value;
        match value {
            1..=4 => {
                self.command = Some(Command {
                    jog: value >= 3,
                    forward: value % 2 == 1,
                })
            }
            5 => self.command = None,
            6 => {
                self.command = None;
                self.ramp.coast(at);
            }
            7 => self.fault = 0,
            _ => {
                if self.command.is_some_and(|c| c.jog) {
                    self.command = None;
                }
            }
        }
        Ok(())
    }

    /// A write to the 2000H block: the command word, or a setpoint the table bounds.
    fn write_control(&mut self, address: u16, value: u16, at: Instant) -> Result<(), Exception> {
        let register = self
            .variant
            .control_register(address)
            .ok_or(IllegalDataAddress)?;
        let signed = i16::from_be_bytes(value.to_be_bytes());
        let allowed = match register.accepts {
            Accepts::Command => return self.command(value, at),
            Accepts::UpToMaxFrequency => value <= self.params.value(P00_03),
            Accepts::UpTo(max) => value <= max,
            Accepts::Signed(max) => (-max..=max).contains(&signed),
        };
        if !allowed {
            return Err(ServerDeviceFailure.into());
        }
        self.control[usize::from(address - CONTROL)] = value;
        Ok(())
    }

    fn write_parameter(&mut self, address: u16, value: u16) -> Result<(), Exception> {
        if address >> 8 == P29_GROUP {
            return Err(IllegalDataAddress.into());
        }
        let current = self.params.get(address).ok_or(IllegalDataAddress)?;
        if LINE.holds(address) {
            return if value == current {
                Ok(())
            } else {
                Err(WRITE_NOT_ALLOWED)
            };
        }
        if address == P14_06 && !communication_processing_ok(value) {
            return Err(ServerDeviceFailure.into());
        }
        let running = self.running();
        self.params
            .check(address, value, running)
            .map_err(refusal_code)?;
        match (address, value) {
            (P00_18, RESTORE_DEFAULTS) => self.restore_defaults(),
            (P00_18, CLEAR_FAULT_RECORDS) => {
                for record in FAULT_RECORDS {
                    let _ = self.params.force(record, 0);
                }
            }
            // P00.18 is an action and always reads 0.
            (P00_18, _) => {}
            _ => self
                .params
                .write(address, value, running)
                .map_err(refusal_code)?,
        }
        Ok(())
    }

    /// P00.18 = 1. The line's parameters stay, and so do the fault records, which have a clear
    /// of their own.
    fn restore_defaults(&mut self) {
        let kept: Vec<(u16, u16)> = [P14_00, P14_01, P14_02]
            .into_iter()
            .chain(FAULT_RECORDS)
            .map(|a| (a, self.params.value(a)))
            .collect();
        self.params.restore_defaults();
        for (a, value) in kept {
            // The values were in range before and these ranges are fixed.
            let _ = self.params.force(a, value);
        }
    }
}

impl Model for Goodrive {
    const PROTOCOL: DriveProtocol = REQUESTS;

    fn read(&self, address: u16) -> Result<u16, Exception> {
        match address {
            CONTROL..=CONTROL_LAST => match self.variant.control_register(address) {
                Some(_) if self.variant.control_readable() => Ok(self.control_value(address)),
                _ => Err(IllegalDataAddress.into()),
            },
            STATE_1 => Ok(self.state_word()),
            // Bit 0: bus voltage established; bits 5-6: the run command channel.
            STATE_2 => Ok(0x0001 | (self.params.value(P00_01) << 5)),
            FAULT_CODE | FAULT => Ok(self.fault),
            IDENTIFIER => Ok(self.variant.identifier()),
            RUNNING_FIRST..=RUNNING_LAST => Ok(self.running_value(address)),
            _ if address & RAM_ALIAS != 0 || address >> 8 == P29_GROUP => {
                Err(IllegalDataAddress.into())
            }
            _ => Ok(self.params.get(address).ok_or(IllegalDataAddress)?),
        }
    }

    fn write(&mut self, address: u16, value: u16, at: Instant) -> Result<(), Exception> {
        match address {
            CONTROL..=CONTROL_LAST => self.write_control(address, value, at)?,
            STATE_1..=IDENTIFIER | RUNNING_FIRST..=RUNNING_LAST | FAULT => {
                return Err(WRITE_NOT_ALLOWED)
            }
            _ => self.write_parameter(address & !RAM_ALIAS, value)?,
        }
        self.retarget(at);
        Ok(())
    }

    fn advance(&mut self, at: Instant) {
        self.ramp.advance(at, self.rates());
    }

    fn communication_timeout(&self) -> Duration {
        TIME_UNIT * u32::from(self.params.value(P14_04))
    }

    fn communication_lost(&mut self, expired: Instant) {
        self.ramp.advance(expired, self.rates());
        match self.params.value(P14_05) {
            TIMEOUT_TRIPS if self.fault == 0 => self.trip(COMMUNICATION_FAULT, expired),
            TIMEOUT_TRIPS | TIMEOUT_IGNORED => {}
            _ => {
                self.command = None;
                self.retarget(expired);
            }
        }
    }

    fn response_delay(&self) -> Duration {
        RESPONSE_DELAY_UNIT * u32::from(self.params.value(P14_03))
    }

    fn answers_writes(&self) -> bool {
        self.params.value(P14_06) & WRITES_UNANSWERED == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::rtu::{crc_ok, encode, pdu_of};
    use crate::line::{Parity, SerialFormat};
    use crate::sim::Simulated;

    fn line(baud: u32, parity: Parity, stop_bits: u8) -> SerialFormat {
        SerialFormat {
            baud,
            data_bits: 8,
            parity,
            stop_bits,
        }
    }

    fn settings(address: u8, params: &[(&str, u16)]) -> DriveSettings {
        let mut settings = DriveSettings::new(address, line(19200, Parity::Even, 1));
        settings.params = params.iter().map(|&(n, v)| (n.to_owned(), v)).collect();
        settings
    }

    fn power_on(
        variant: Variant,
        address: u8,
        params: &[(&str, u16)],
        t0: Instant,
    ) -> Drive<Goodrive> {
        Goodrive::new(variant, &settings(address, params), t0).unwrap()
    }

    /// Under communication control with the Modbus frequency reference.
    fn remote(variant: Variant, t0: Instant) -> Drive<Goodrive> {
        power_on(variant, 1, &[("P00.01", 2), ("P00.06", 8)], t0)
    }

    fn after(t0: Instant, secs: f64) -> Instant {
        t0 + Duration::from_secs_f64(secs)
    }

    /// Hand a manual's request frame to the drive; the frame it answers with.
    fn exchange(drive: &mut Drive<Goodrive>, request: &[u8], at: Instant) -> Vec<u8> {
        assert!(crc_ok(request), "the fixture's CRC is wrong");
        drive
            .handle(request[0], pdu_of(request), at)
            .expect("an answer")
            .bytes
    }

    /// The reply PDU to `request` sent to the drive's own address.
    fn ask(drive: &mut Drive<Goodrive>, request: &[u8], at: Instant) -> Vec<u8> {
        let answer = drive.handle(drive.address, request, at).expect("an answer");
        pdu_of(&answer.bytes).to_vec()
    }

    fn read(drive: &mut Drive<Goodrive>, address: u16, at: Instant) -> u16 {
        let [hi, lo] = address.to_be_bytes();
        let reply = ask(drive, &[0x03, hi, lo, 0x00, 0x01], at);
        assert_eq!(
            reply[..2],
            [0x03, 0x02],
            "reading {address:04X}H: {reply:02X?}"
        );
        u16::from_be_bytes([reply[2], reply[3]])
    }

    fn write(drive: &mut Drive<Goodrive>, address: u16, value: u16, at: Instant) -> Vec<u8> {
        let [a_hi, a_lo] = address.to_be_bytes();
        let [v_hi, v_lo] = value.to_be_bytes();
        ask(drive, &[0x06, a_hi, a_lo, v_hi, v_lo], at)
    }

    fn assert_written(drive: &mut Drive<Goodrive>, address: u16, value: u16, at: Instant) {
        let reply = write(drive, address, value, at);
        assert_eq!(
            reply[0], 0x06,
            "writing {value} to {address:04X}H: {reply:02X?}"
        );
    }

    fn refused(code: u8) -> Vec<u8> {
        vec![0x86, code]
    }

    /// The read, write and echo frames of the GD20 and GD300 manuals.
    #[test]
    fn the_gd20_and_gd300_manual_frames_come_out_byte_for_byte() {
        let t0 = Instant::now();
        for variant in [Variant::Gd20, Variant::Gd300] {
            let mut one = power_on(variant, 1, &[], t0);
            let mut two = power_on(variant, 2, &[], t0);
            // Read 2 words from 0004H: P00.04 = 50.00 Hz, P00.05 = 0 at the factory.
            assert_eq!(
                exchange(
                    &mut one,
                    &[0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA],
                    t0
                ),
                [0x01, 0x03, 0x04, 0x13, 0x88, 0x00, 0x00, 0x7E, 0x9D]
            );
            // Write 1388H to 0004H: echoed.
            let write_one = [0x02, 0x06, 0x00, 0x04, 0x13, 0x88, 0xC5, 0x6E];
            assert_eq!(exchange(&mut two, &write_one, t0), write_one);
            // Write 1388H, 0032H to 0004H-0005H. The manuals print C5 6E as this frame's CRC, a
            // copy of the FC 06 example's; F8 63 and 00 3A are the real ones.
            let write_two = [
                0x02, // slave address
                0x10, // write multiple registers
                0x00, 0x04, // from 0004H
                0x00, 0x02, // two words
                0x04, // four bytes
                0x13, 0x88, // P00.04 = 50.00 Hz
                0x00, 0x32, // P00.05 = 0.50 Hz
                0xF8, 0x63, // CRC
            ];
            assert_eq!(
                exchange(&mut two, &write_two, t0),
                [0x02, 0x10, 0x00, 0x04, 0x00, 0x02, 0x00, 0x3A]
            );
            assert_eq!(read(&mut two, 0x0005, t0), 50);
            // Diagnostics 0000 returns the query data.
            let echo = [0x01, 0x08, 0x00, 0x00, 0x12, 0xAB, 0xAD, 0x14];
            assert_eq!(exchange(&mut one, &echo, t0), echo);
        }
    }

    #[test]
    fn the_frames_of_the_gd10_manual_come_out_byte_for_byte() {
        let t0 = Instant::now();
        let mut one = power_on(Variant::Gd10, 1, &[], t0);
        // P01.20 = 5.0 s, then read back.
        let wake_up = [0x01, 0x06, 0x01, 0x14, 0x00, 0x32, 0x49, 0xE7];
        assert_eq!(exchange(&mut one, &wake_up, t0), wake_up);
        let read_back = encode(0x01, &[0x03, 0x01, 0x14, 0x00, 0x01]);
        assert_eq!(
            exchange(&mut one, &read_back, t0),
            [0x01, 0x03, 0x02, 0x00, 0x32, 0x39, 0x91]
        );
        // P00.01 = 3 is outside 0..=2: operation failed.
        assert_eq!(
            exchange(
                &mut one,
                &[0x01, 0x06, 0x00, 0x01, 0x00, 0x03, 0x98, 0x0B],
                t0
            ),
            [0x01, 0x86, 0x04, 0x43, 0xA3]
        );
        // State word 1: stopped.
        assert_eq!(
            exchange(
                &mut one,
                &[0x01, 0x03, 0x21, 0x00, 0x00, 0x01, 0x8E, 0x36],
                t0
            ),
            [0x01, 0x03, 0x02, 0x00, 0x03, 0xF8, 0x45]
        );

        let records = [
            ("P07.27", 35),
            ("P07.28", 35),
            ("P07.29", 35),
            ("P07.30", 35),
            ("P07.31", 35),
            ("P07.32", 35),
        ];
        let mut three = power_on(Variant::Gd10, 3, &records, t0);
        // The six fault records from 071BH, all 0023H (STo).
        let mut expected = vec![0x03, 0x03, 0x0C];
        expected.extend([0x00, 0x23].repeat(6));
        expected.extend([0x5F, 0xD2]);
        assert_eq!(
            exchange(
                &mut three,
                &[0x03, 0x03, 0x07, 0x1B, 0x00, 0x06, 0xB5, 0x59],
                t0
            ),
            expected
        );
        // Run forward: accepted (P00.01 is the keypad, so the drive stays stopped).
        let run = [0x03, 0x06, 0x20, 0x00, 0x00, 0x01, 0x42, 0x28];
        assert_eq!(exchange(&mut three, &run, t0), run);
        // P00.03 = 100.00 Hz on the stopped drive.
        let max_frequency = [0x03, 0x06, 0x00, 0x03, 0x27, 0x10, 0x62, 0x14];
        assert_eq!(exchange(&mut three, &max_frequency, t0), max_frequency);
        assert_eq!(read(&mut three, 0x0003, t0), 10000);
    }

    #[test]
    fn each_variant_reports_its_identifying_code_in_2103h_and_3016h() {
        let t0 = Instant::now();
        for (variant, code) in [
            (Variant::Gd20, 0x0106),
            (Variant::Gd300, 0x010A),
            (Variant::Gd10, 0x010D),
        ] {
            let mut drive = power_on(variant, 1, &[], t0);
            assert_eq!(read(&mut drive, 0x2103, t0), code);
            assert_eq!(read(&mut drive, 0x3016, t0), code);
        }
    }

    #[test]
    fn a_forward_run_takes_the_acceleration_time_and_a_stop_the_deceleration_time() {
        let t0 = Instant::now();
        let mut drive = remote(Variant::Gd20, t0);
        // GD20 ramps: 10.0 s from 0 to P00.03 and back.
        assert_eq!(read(&mut drive, 0x000B, t0), 100);
        assert_written(&mut drive, 0x2001, 5000, t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 5.0)), 2500);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 5.0)), 1);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 10.0)), 5000);
        assert_eq!(read(&mut drive, 0x3001, after(t0, 10.0)), 5000);

        assert_written(&mut drive, 0x2000, 5, after(t0, 10.0));
        assert_eq!(read(&mut drive, 0x3000, after(t0, 15.0)), 2500);
        // Still turning, so still running.
        assert_eq!(read(&mut drive, 0x2100, after(t0, 15.0)), 1);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 20.0)), 0);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 20.0)), 3);
        assert_eq!(read(&mut drive, 0x3004, after(t0, 20.0)), 0);
    }

    #[test]
    fn a_new_reference_while_running_moves_the_output_along_the_ramp() {
        let t0 = Instant::now();
        let mut drive = remote(Variant::Gd20, t0);
        assert_written(&mut drive, 0x2001, 5000, t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        // Down from 50 Hz at 5.00 Hz a second (P00.12 = 10.0 s for P00.03 = 50 Hz).
        assert_written(&mut drive, 0x2001, 2500, after(t0, 10.0));
        assert_eq!(read(&mut drive, 0x3000, after(t0, 12.5)), 3750);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 15.0)), 2500);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 15.0)), 1);
    }

    #[test]
    fn the_reference_is_held_between_the_lower_and_upper_limits() {
        let t0 = Instant::now();
        let params = [
            ("P00.01", 2),
            ("P00.06", 8),
            ("P00.04", 4000),
            ("P00.05", 1000),
        ];
        let mut drive = power_on(Variant::Gd20, 1, &params, t0);
        assert_eq!(read(&mut drive, 0x3001, t0), 1000);
        assert_written(&mut drive, 0x2001, 5000, t0);
        assert_eq!(read(&mut drive, 0x3001, t0), 4000);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 20.0)), 4000);
        // Sources the simulator does not wire (AI1) give 0 Hz, so the lower limit.
        assert_written(&mut drive, 0x0006, 1, after(t0, 20.0));
        assert_eq!(read(&mut drive, 0x3000, after(t0, 40.0)), 1000);
    }

    #[test]
    fn coast_to_stop_drops_the_output_at_once() {
        let t0 = Instant::now();
        let mut drive = remote(Variant::Gd300, t0);
        assert_written(&mut drive, 0x2001, 5000, t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert!(read(&mut drive, 0x3000, after(t0, 20.0)) > 0);
        assert_written(&mut drive, 0x2000, 6, after(t0, 20.0));
        assert_eq!(read(&mut drive, 0x3000, after(t0, 20.0)), 0);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 20.0)), 3);
    }

    #[test]
    fn jog_runs_at_five_hertz_and_jog_stop_ends_it() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd20, 1, &[("P00.01", 2), ("P00.11", 0)], t0);
        assert_written(&mut drive, 0x2000, 4, t0);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 1.0)), 500);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 1.0)), 2);
        assert_written(&mut drive, 0x2000, 8, after(t0, 1.0));
        assert_eq!(read(&mut drive, 0x3000, after(t0, 3.0)), 0);
        // Jog stop leaves an ordinary run alone.
        assert_written(&mut drive, 0x2000, 1, after(t0, 3.0));
        assert_written(&mut drive, 0x2000, 8, after(t0, 3.0));
        assert_eq!(read(&mut drive, 0x3000, after(t0, 4.0)), 5000);
    }

    #[test]
    fn the_running_direction_parameter_reverses_or_forbids_reverse() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd20, 1, &[("P00.01", 2), ("P00.13", 1)], t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 10.0)), 2);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 10.0)), 5000);

        let mut drive = power_on(Variant::Gd20, 1, &[("P00.01", 2), ("P00.13", 2)], t0);
        assert_written(&mut drive, 0x2000, 2, t0);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 10.0)), 0);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 10.0)), 2);
    }

    #[test]
    fn running_values_follow_the_motor_and_vanish_when_stopped() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd300, 1, &[("P00.01", 2)], t0);
        assert_eq!(read(&mut drive, 0x3002, t0), 5400);
        assert_eq!(read(&mut drive, 0x3004, t0), 0);
        assert_written(&mut drive, 0x2000, 1, t0);
        let at = after(t0, 15.0);
        assert_eq!(read(&mut drive, 0x3003, at), 380);
        let motor = Variant::Gd300.motor();
        assert_eq!(
            u32::from(read(&mut drive, 0x3004, at)),
            motor.output_current(5000, true) / 10
        );
        assert_eq!(read(&mut drive, 0x3005, at), 1440);
        assert_eq!(read(&mut drive, 0x3007, at), 800);
        assert_written(&mut drive, 0x2004, (-1500i16) as u16, at);
        assert_eq!(read(&mut drive, 0x3015, at), (-1500i16) as u16);
        assert_written(&mut drive, 0x2002, 456, at);
        assert_eq!(read(&mut drive, 0x3008, at), 456);
        assert_eq!(read(&mut drive, 0x300C, at), 0);
    }

    #[test]
    fn state_word_2_shows_the_run_command_channel() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd20, 1, &[], t0);
        assert_eq!(read(&mut drive, 0x2101, t0), 0x01);
        assert_written(&mut drive, 0x0001, 2, t0);
        assert_eq!(read(&mut drive, 0x2101, t0), 0x41);
    }

    #[test]
    fn commands_are_answered_but_ignored_unless_the_channel_is_communication() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd300, 1, &[], t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert_eq!(read(&mut drive, 0x2000, t0), 1);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 5.0)), 3);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 5.0)), 0);
    }

    #[test]
    fn a_read_of_more_than_16_words_or_of_none_is_an_illegal_value() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd20, 1, &[], t0);
        assert_eq!(
            ask(&mut drive, &[0x03, 0x30, 0x00, 0x00, 0x11], t0),
            [0x83, 0x03]
        );
        assert_eq!(
            ask(&mut drive, &[0x03, 0x30, 0x00, 0x00, 0x00], t0),
            [0x83, 0x03]
        );
        let sixteen = ask(&mut drive, &[0x03, 0x30, 0x00, 0x00, 0x10], t0);
        assert_eq!(sixteen[..2], [0x03, 0x20]);
        assert_eq!(sixteen.len(), 2 + 32);
        // A write of 17 words is refused the same way.
        let mut seventeen = vec![0x10, 0x20, 0x01, 0x00, 0x11, 0x22];
        seventeen.extend([0; 34]);
        assert_eq!(ask(&mut drive, &seventeen, t0), [0x90, 0x03]);
    }

    #[test]
    fn addresses_that_are_not_there_are_illegal_data_addresses() {
        let t0 = Instant::now();
        let mut gd20 = power_on(Variant::Gd20, 1, &[], t0);
        // The RAM alias of P00.07 cannot be read.
        assert_eq!(
            ask(&mut gd20, &[0x03, 0x80, 0x07, 0x00, 0x01], t0),
            [0x83, 0x02]
        );
        // The P29 factory group, read or written.
        assert_eq!(
            ask(&mut gd20, &[0x03, 0x1D, 0x00, 0x00, 0x01], t0),
            [0x83, 0x02]
        );
        assert_eq!(write(&mut gd20, 0x1D00, 0, t0), refused(0x02));
        assert_eq!(write(&mut gd20, 0x9D00, 0, t0), refused(0x02));
        // P00.17 is reserved, so a read across it fails as a whole.
        assert_eq!(
            ask(&mut gd20, &[0x03, 0x00, 0x10, 0x00, 0x01], t0)[..2],
            [0x03, 0x02]
        );
        assert_eq!(
            ask(&mut gd20, &[0x03, 0x00, 0x10, 0x00, 0x03], t0),
            [0x83, 0x02]
        );
        assert_eq!(write(&mut gd20, 0x0011, 0, t0), refused(0x02));
        // Past the register blocks and past the end of the address space.
        assert_eq!(
            ask(&mut gd20, &[0x03, 0x21, 0x04, 0x00, 0x01], t0),
            [0x83, 0x02]
        );
        assert_eq!(
            ask(&mut gd20, &[0x03, 0x30, 0x17, 0x00, 0x01], t0),
            [0x83, 0x02]
        );
        assert_eq!(
            ask(&mut gd20, &[0x03, 0xFF, 0xFF, 0x00, 0x02], t0),
            [0x83, 0x02]
        );
        // GD10 has only some of the setpoints.
        let mut gd10 = power_on(Variant::Gd10, 1, &[], t0);
        assert_eq!(write(&mut gd10, 0x2004, 0, t0), refused(0x02));
        assert_eq!(
            ask(&mut gd10, &[0x03, 0x20, 0x04, 0x00, 0x01], t0),
            [0x83, 0x02]
        );
        assert_written(&mut gd10, 0x200D, 0, t0);
    }

    #[test]
    fn gd20_control_registers_are_write_only_while_gd300_and_gd10_read_them_back() {
        let t0 = Instant::now();
        let mut gd20 = power_on(Variant::Gd20, 1, &[], t0);
        assert_written(&mut gd20, 0x2001, 1234, t0);
        assert_eq!(
            ask(&mut gd20, &[0x03, 0x20, 0x00, 0x00, 0x01], t0),
            [0x83, 0x02]
        );
        assert_eq!(
            ask(&mut gd20, &[0x03, 0x20, 0x01, 0x00, 0x01], t0),
            [0x83, 0x02]
        );
        for variant in [Variant::Gd300, Variant::Gd10] {
            let mut drive = power_on(variant, 1, &[], t0);
            assert_eq!(read(&mut drive, 0x2000, t0), 0);
            assert_written(&mut drive, 0x2000, 5, t0);
            assert_written(&mut drive, 0x2001, 1234, t0);
            assert_eq!(read(&mut drive, 0x2000, t0), 5);
            assert_eq!(read(&mut drive, 0x2001, t0), 1234);
        }
    }

    #[test]
    fn read_only_registers_and_records_refuse_writes_with_07() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd300, 1, &[], t0);
        for address in [0x2100, 0x2103, 0x3000, 0x3016, 0x5000, 0x071B] {
            assert_eq!(
                write(&mut drive, address, 1, t0),
                refused(0x07),
                "{address:04X}H"
            );
        }
    }

    #[test]
    fn values_out_of_range_are_refused_with_04() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd300, 1, &[], t0);
        for (address, value) in [
            (0x2000, 0),
            (0x2000, 9),
            (0x2001, 5001),
            (0x2002, 1001),
            (0x2004, (-3001i16) as u16),
            (0x200A, 0x200),
            (0x200E, 1001),
            (0x0004, 5001),
            (0x000E, 9),
            (0x0E06, 0x02),
        ] {
            assert_eq!(
                write(&mut drive, address, value, t0),
                refused(0x04),
                "{address:04X}H"
            );
        }
        assert_written(&mut drive, 0x2004, (-3000i16) as u16, t0);
        assert_written(&mut drive, 0x200E, (-1000i16) as u16, t0);
        assert_written(&mut drive, 0x0E06, 0x10, t0);
    }

    #[test]
    fn a_stopped_only_parameter_cannot_be_written_while_running_or_slowing_down() {
        let t0 = Instant::now();
        let mut drive = remote(Variant::Gd20, t0);
        assert_written(&mut drive, 0x2001, 5000, t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert_eq!(
            write(&mut drive, 0x0003, 6000, after(t0, 1.0)),
            refused(0x08)
        );
        assert_written(&mut drive, 0x2000, 5, after(t0, 1.0));
        assert_eq!(
            write(&mut drive, 0x0003, 6000, after(t0, 1.5)),
            refused(0x08)
        );
        // A ○ parameter may change at any time.
        assert_written(&mut drive, 0x000C, 50, after(t0, 1.5));
        assert_written(&mut drive, 0x0003, 6000, after(t0, 5.0));
    }

    #[test]
    fn the_ram_alias_writes_the_parameter_with_the_same_checks() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd20, 1, &[], t0);
        assert_written(&mut drive, 0x8007, 8, t0);
        assert_eq!(read(&mut drive, 0x0007, t0), 8);
        assert_eq!(write(&mut drive, 0x8007, 12, t0), refused(0x04));
        assert_eq!(write(&mut drive, 0x871B, 1, t0), refused(0x07));
        assert_eq!(write(&mut drive, 0x8011, 1, t0), refused(0x02));
    }

    #[test]
    fn a_tripped_drive_refuses_run_commands_until_a_fault_reset() {
        let t0 = Instant::now();
        let mut trip = settings(1, &[("P00.01", 2), ("P07.27", 5)]);
        trip.trip = Some(9);
        let mut drive = Goodrive::new(Variant::Gd20, &trip, t0).unwrap();
        assert_eq!(read(&mut drive, 0x2100, t0), 4);
        assert_eq!(read(&mut drive, 0x2102, t0), 9);
        assert_eq!(read(&mut drive, 0x5000, t0), 9);
        assert_eq!(read(&mut drive, 0x071B, t0), 9);
        assert_eq!(read(&mut drive, 0x071C, t0), 5);
        assert_eq!(write(&mut drive, 0x2000, 1, t0), refused(0x01));
        assert_eq!(write(&mut drive, 0x2000, 3, t0), refused(0x01));
        assert_written(&mut drive, 0x2000, 5, t0);
        assert_written(&mut drive, 0x2000, 7, t0);
        assert_eq!(read(&mut drive, 0x2100, t0), 3);
        assert_eq!(read(&mut drive, 0x2102, t0), 0);
        assert_eq!(read(&mut drive, 0x071B, t0), 9);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert_eq!(read(&mut drive, 0x2100, t0), 1);
    }

    #[test]
    fn a_power_on_trip_must_be_a_fault_code() {
        let t0 = Instant::now();
        for code in [0, 101] {
            let mut bad = settings(1, &[]);
            bad.trip = Some(code);
            assert_eq!(
                Goodrive::new(Variant::Gd10, &bad, t0).unwrap_err().param,
                "trip"
            );
        }
    }

    #[test]
    fn the_line_parameters_report_the_line_and_refuse_any_other_value() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd300, 7, &[], t0);
        assert_eq!(read(&mut drive, 0x0E00, t0), 7);
        assert_eq!(read(&mut drive, 0x0E01, t0), 4); // 19200
        assert_eq!(read(&mut drive, 0x0E02, t0), 1); // 8E1
        assert_written(&mut drive, 0x0E00, 7, t0);
        assert_eq!(write(&mut drive, 0x0E00, 8, t0), refused(0x07));
        assert_eq!(write(&mut drive, 0x0E01, 3, t0), refused(0x07));

        let slow = DriveSettings::new(7, line(9600, Parity::None, 2));
        let mut drive = Goodrive::new(Variant::Gd20, &slow, t0).unwrap();
        assert_eq!(read(&mut drive, 0x0E01, t0), 3);
        assert_eq!(read(&mut drive, 0x0E02, t0), 3);
        let odd = DriveSettings::new(7, line(14400, Parity::Odd, 2));
        let mut drive = Goodrive::new(Variant::Gd20, &odd, t0).unwrap();
        assert_eq!(read(&mut drive, 0x0E01, t0), 4);
        assert_eq!(read(&mut drive, 0x0E02, t0), 5);

        let clash = settings(7, &[("P14.00", 8)]);
        assert_eq!(
            Goodrive::new(Variant::Gd20, &clash, t0).unwrap_err().param,
            "P14.00"
        );
        assert!(Goodrive::new(Variant::Gd20, &settings(7, &[("P14.00", 7)]), t0).is_ok());
    }

    #[test]
    fn function_restore_resets_parameters_or_clears_the_fault_records() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd300, 9, &[("P07.30", 12)], t0);
        assert_written(&mut drive, 0x000B, 300, t0);
        assert_written(&mut drive, 0x0E03, 20, t0);
        assert_written(&mut drive, 0x0012, 1, t0);
        assert_eq!(read(&mut drive, 0x0012, t0), 0);
        assert_eq!(read(&mut drive, 0x000B, t0), 150);
        assert_eq!(read(&mut drive, 0x0E03, t0), 5);
        assert_eq!(read(&mut drive, 0x0E00, t0), 9);
        assert_eq!(read(&mut drive, 0x071E, t0), 12);
        assert_written(&mut drive, 0x0012, 2, t0);
        assert_eq!(read(&mut drive, 0x071E, t0), 0);
        assert_eq!(read(&mut drive, 0x0012, t0), 0);
    }

    #[test]
    fn the_response_delay_parameter_lengthens_the_reply_delay() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd20, 1, &[], t0);
        let delay = |drive: &mut Drive<Goodrive>| {
            drive
                .handle(1, &[0x03, 0x21, 0x00, 0x00, 0x01], t0)
                .unwrap()
                .delay
        };
        assert_eq!(delay(&mut drive), Duration::from_millis(5));
        assert_written(&mut drive, 0x0E03, 50, t0);
        assert_eq!(delay(&mut drive), Duration::from_millis(50));

        let mut slow = settings(1, &[]);
        slow.processing_delay = Duration::from_millis(80);
        let mut drive = Goodrive::new(Variant::Gd20, &slow, t0).unwrap();
        assert_eq!(delay(&mut drive), Duration::from_millis(80));
    }

    #[test]
    fn communication_processing_1_carries_out_writes_without_answering_them() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd300, 1, &[], t0);
        assert_eq!(drive.handle(1, &[0x06, 0x0E, 0x06, 0x00, 0x11], t0), None);
        assert_eq!(drive.handle(1, &[0x06, 0x00, 0x0A, 0x07, 0xD0], t0), None);
        let many = [0x10, 0x00, 0x0B, 0x00, 0x02, 0x04, 0x00, 0x64, 0x00, 0xC8];
        assert_eq!(drive.handle(1, &many, t0), None);
        // Reads are still answered and show the writes.
        assert_eq!(read(&mut drive, 0x000A, t0), 2000);
        assert_eq!(read(&mut drive, 0x000C, t0), 200);
        // Even a refused write goes unanswered.
        assert_eq!(drive.handle(1, &[0x06, 0x21, 0x00, 0x00, 0x01], t0), None);
        // The setting in force once a write is carried out decides: this one is answered.
        assert_written(&mut drive, 0x0E06, 0x10, t0);
    }

    #[test]
    fn a_communication_timeout_trips_with_ce_when_it_expires() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd20, 1, &[("P00.01", 2), ("P14.04", 20)], t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        // Polled within 2.0 s: no trip.
        assert_eq!(read(&mut drive, 0x2100, after(t0, 1.9)), 1);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 3.8)), 1);
        // 2.5 s of silence: tripped at 5.8 s, from 5800 * 0.5 = 2900 (held at P00.04 = 5000).
        assert_eq!(read(&mut drive, 0x2100, after(t0, 6.3)), 4);
        assert_eq!(read(&mut drive, 0x2102, after(t0, 6.3)), 18);
        assert_eq!(read(&mut drive, 0x071B, after(t0, 6.3)), 18);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 6.3)), 0);
        assert_eq!(write(&mut drive, 0x2000, 1, after(t0, 6.3)), refused(0x01));
    }

    #[test]
    fn a_communication_timeout_set_to_stop_decelerates_without_a_trip() {
        let t0 = Instant::now();
        let params = [("P00.01", 2), ("P14.04", 20), ("P14.05", 2)];
        let mut drive = power_on(Variant::Gd20, 1, &params, t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 1.0)), 500);
        // Silent from 1.0 s: the stop starts at 3.0 s from 1500 and loses 500 per second.
        assert_eq!(read(&mut drive, 0x3000, after(t0, 4.0)), 1000);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 4.0)), 1);
        assert_eq!(read(&mut drive, 0x2102, after(t0, 4.0)), 0);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 6.0)), 3);

        let params = [("P00.01", 2), ("P14.04", 20), ("P14.05", 1)];
        let mut drive = power_on(Variant::Gd20, 1, &params, t0);
        assert_written(&mut drive, 0x2000, 1, t0);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 10.0)), 5000);
    }

    #[test]
    fn a_refused_write_of_several_words_changes_nothing() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd300, 1, &[], t0);
        // P00.10 = 30.00 Hz, then P00.11 = 0.0 s, then P00.12 = 3600.1 s (out of range).
        let request = [
            0x10, 0x00, 0x0A, 0x00, 0x03, 0x06, 0x0B, 0xB8, 0x00, 0x00, 0x8C, 0xA1,
        ];
        assert_eq!(ask(&mut drive, &request, t0), [0x90, 0x04]);
        assert_eq!(read(&mut drive, 0x000A, t0), 5000);
        assert_eq!(read(&mut drive, 0x000B, t0), 150);
        // A later word sees an earlier one: P00.03 = 100 Hz makes P00.04 = 80 Hz legal.
        let request = [0x10, 0x00, 0x03, 0x00, 0x02, 0x04, 0x27, 0x10, 0x1F, 0x40];
        assert_eq!(
            ask(&mut drive, &request, t0),
            [0x10, 0x00, 0x03, 0x00, 0x02]
        );
        assert_eq!(read(&mut drive, 0x0004, t0), 8000);
    }

    #[test]
    fn malformed_requests_get_the_manuals_exceptions() {
        let t0 = Instant::now();
        let mut drive = power_on(Variant::Gd10, 1, &[], t0);
        assert_eq!(ask(&mut drive, &[0x06, 0x00, 0x0A, 0x07], t0), [0x86, 0x06]);
        assert_eq!(
            ask(&mut drive, &[0x06, 0x00, 0x0A, 0x07, 0xD0, 0x00], t0),
            [0x86, 0x06]
        );
        // Byte count 3 for one word; then two words announced and one sent.
        assert_eq!(
            ask(
                &mut drive,
                &[0x10, 0x00, 0x0A, 0x00, 0x01, 0x03, 0x07, 0xD0, 0x00],
                t0
            ),
            [0x90, 0x06]
        );
        assert_eq!(
            ask(
                &mut drive,
                &[0x10, 0x00, 0x0A, 0x00, 0x02, 0x04, 0x07, 0xD0],
                t0
            ),
            [0x90, 0x06]
        );
        assert_eq!(
            ask(&mut drive, &[0x10, 0x00, 0x0A, 0x00, 0x01], t0),
            [0x90, 0x06]
        );
        assert_eq!(ask(&mut drive, &[0x03, 0x00, 0x0A, 0x00], t0), [0x83, 0x06]);
        assert_eq!(
            ask(&mut drive, &[0x08, 0x00, 0x01, 0x00, 0x00], t0),
            [0x88, 0x01]
        );
        assert_eq!(
            ask(&mut drive, &[0x04, 0x00, 0x00, 0x00, 0x01], t0),
            [0x84, 0x01]
        );
        assert_eq!(ask(&mut drive, &[0x2B, 0x0E, 0x01, 0x00], t0), [0xAB, 0x01]);
        assert_eq!(read(&mut drive, 0x000A, t0), 5000);
    }

    #[test]
    fn a_broadcast_write_is_carried_out_and_never_answered() {
        let t0 = Instant::now();
        let params = [("P00.01", 2), ("P00.06", 8), ("P00.11", 0)];
        let mut drive = power_on(Variant::Gd20, 4, &params, t0);
        assert_eq!(drive.handle(0, &[0x06, 0x20, 0x00, 0x00, 0x01], t0), None);
        let setpoint = [0x10, 0x20, 0x01, 0x00, 0x01, 0x02, 0x0F, 0xA0];
        assert_eq!(drive.handle(0, &setpoint, t0), None);
        assert_eq!(drive.handle(0, &[0x03, 0x21, 0x00, 0x00, 0x01], t0), None);
        assert_eq!(drive.handle(0, &[0x06, 0x21, 0x00, 0x00, 0x01], t0), None);
        assert_eq!(read(&mut drive, 0x2100, after(t0, 1.0)), 1);
        assert_eq!(read(&mut drive, 0x3000, after(t0, 1.0)), 4000);
    }

    #[test]
    fn no_request_whatever_its_bytes_makes_the_drive_panic() {
        let t0 = Instant::now();
        let params = [("P00.01", 2), ("P00.06", 8), ("P14.04", 5)];
        let mut drives = [
            power_on(Variant::Gd20, 1, &params, t0),
            power_on(Variant::Gd300, 1, &params, t0),
            power_on(Variant::Gd10, 1, &params, t0),
        ];
        // Mostly the function codes the drive knows, at addresses in the blocks that exist.
        let functions = [0x03, 0x06, 0x08, 0x10];
        let addresses = [
            0x0001, 0x0003, 0x000B, 0x0012, 0x0114, 0x071B, 0x0E03, 0x0E06, 0x1D00, 0x2000, 0x2001,
            0x200E, 0x2100, 0x2103, 0x3000, 0x3016, 0x5000, 0x8007, 0x800B,
        ];
        let mut rng = fastrand::Rng::with_seed(1);
        let mut at = t0;
        for i in 0..60_000u32 {
            let pdu = crate::sim::random_pdu(&mut rng, 24, &functions, &addresses);
            at += Duration::from_millis(rng.u64(..700));
            let address = if i % 7 == 0 { 0 } else { 1 };
            let _ = drives[i as usize % 3].handle(address, &pdu, at);
        }
    }
}
