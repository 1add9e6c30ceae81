//! The second inverter of shared/reference (manual 003: P0..PF parameter groups, Pd group for
//! communication) as a simulated drive on the line. Owns its register map, exception codes and
//! the manual's quirks, as a [`Model`] for the pipeline of [`super::Drive`]; the ramp, motor values
//! and parameter table come from [`super`]. Knows nothing of the line's timing or of TCP.
//!
//! Where the manual is silent, missing or wrong, this model decides:
//! - Its error-response table did not survive, so exceptions are the standard Modbus codes:
//!   01 a function other than 03 and 06; 02 an address that cannot be used that way (nothing
//!   there, reading a write-only register or the RAM alias, writing a read-only one, the PF
//!   group); 03 a malformed PDU or a read of other than 1..=12 words; 04 the drive refuses the
//!   value (out of range, a stopped-only parameter while running, a run command while tripped).
//! - Modelled: groups P0 (P0-00..P0-19) and Pd (Pd-00..Pd-06), 1000H..1020H, 1F00H,
//!   2000H..2004H, 3000H, 8000H. The other P groups, the A and U groups are not (02). A read
//!   running past a group's last modelled parameter is refused (02): the manual's "cannot skip
//!   the last function code in this group".
//! - Pd-05 = 0, the factory default "non-standard protocol", sends read replies one byte longer:
//!   the byte count as two bytes, big-endian. Exceptions and write echoes are unchanged.
//! - Pd-00..Pd-02 read the line's baud, format and the drive's address (a baud or format with no
//!   index reads the factory 5 or 0). Writing the value they hold is accepted, another is refused
//!   (04): the line's configuration owns them. Configuring a different one is a setup error.
//! - Pd-04's factory default "2ms" is a misprint for 0 (off). When more than Pd-04 passes between
//!   two requests to the drive (its own or broadcast), it trips with fault 10H and coasts at the
//!   moment the timeout ran out; this is worked out when the next request arrives.
//! - 2000H commands are answered whatever P0-02 says but carried out only when it is 2
//!   (communication). Jogs run at 2.00 Hz on the P0-17/P0-18 ramp.
//! - The reference is P0-08 (P0-03 = 0) or 1000H's magnitude (P0-03 = 9), 0 for the other
//!   sources, held within P0-14..=P0-12 (the digital upper limit whatever P0-11 says) and P0-10.
//!   The command and P0-09 give the direction.
//! - 1F00H: no password is set, so any write passes and a read returns 0888H ("check passed").
//! - 101BH counts the minutes a run or jog command has been in force.

use super::Limit::{Param, Value};
use super::Modify::{Always, Never, Stopped};
use super::{
    power_on_trip, Drive, DriveProtocol, DriveSettings, Exception, Limit, LineIndices, LineParams,
    Model, Modify, Motor, ParamRefusal, ParamSpec, Params, Ramp, Rates, SetupError,
};
use crate::line::Parity;
use crate::pdu::ExceptionCode::{self, IllegalDataAddress, ServerDeviceFailure};
use std::time::Duration;
use tokio::time::Instant;

/// Only FC 03 and 06; a malformed request is an illegal data value.
const REQUESTS: DriveProtocol = DriveProtocol {
    // The manual's limit on one read.
    max_words: 12,
    diagnostics: false,
    write_multiple: false,
    malformed: Exception::standard(ExceptionCode::IllegalDataValue),
};

/// P0..PE parameters at F000H | group << 8 | index; PF (FF00H..) is closed to communication.
const PARAMETERS_FIRST: u16 = 0xF000;
const PARAMETERS_LAST: u16 = 0xFEFF;
/// The same parameters with the high nibble cleared: written to RAM only, never read.
const RAM_ALIAS_LAST: u16 = 0x0EFF;
const RAM_ALIAS_TO_PARAMETER: u16 = 0xF000;
const COMM_SETTING: u16 = 0x1000;
const RUNNING_VALUES_LAST: u16 = 0x1020;
const PASSWORD: u16 = 0x1F00;
const CONTROL: u16 = 0x2000;
const DO_CONTROL: u16 = 0x2001;
const OUTPUTS_LAST: u16 = 0x2004;
const STATE: u16 = 0x3000;
const FAULT: u16 = 0x8000;

const PASSWORD_PASSED: u16 = 0x0888;
const DO_MASK: u16 = 0x7F;
const ANALOG_OUTPUT_MAX: u16 = 0x7FFF;
/// 1000H: 10000 is 100.00 % of P0-10.
const COMM_SETTING_FULL_SCALE: u16 = 10000;

const STATE_FORWARD: u16 = 1;
const STATE_REVERSE: u16 = 2;
const STATE_STOPPED: u16 = 3;

const COMMUNICATION_FAULT: u16 = 0x0010;
const LAST_FAULT_CODE: u16 = 0x5E;

const P0_00: u16 = 0xF000;
const MOTOR_CONTROL: u16 = 0xF001;
const COMMAND_SOURCE: u16 = 0xF002;
const MAIN_SOURCE: u16 = 0xF003;
const AUX_SOURCE: u16 = 0xF004;
const PRESET_FREQUENCY: u16 = 0xF008;
const DIRECTION: u16 = 0xF009;
const MAX_FREQUENCY: u16 = 0xF00A;
const UPPER_LIMIT_SOURCE: u16 = 0xF00B;
const UPPER_LIMIT: u16 = 0xF00C;
const UPPER_LIMIT_OFFSET: u16 = 0xF00D;
const LOWER_LIMIT: u16 = 0xF00E;
const CARRIER: u16 = 0xF00F;
const ACCEL_TIME: u16 = 0xF011;
const DECEL_TIME: u16 = 0xF012;
const RAMP_TIME_UNIT_PARAM: u16 = 0xF013;
const BAUD: u16 = 0xFD00;
const FORMAT: u16 = 0xFD01;
const ADDRESS: u16 = 0xFD02;
const RESPONSE_DELAY: u16 = 0xFD03;
const TIMEOUT: u16 = 0xFD04;
const PROTOCOL: u16 = 0xFD05;
const CURRENT_RESOLUTION: u16 = 0xFD06;

const COMMAND_FROM_COMMUNICATION: u16 = 2;
const SOURCE_DIGITAL: u16 = 0;
const SOURCE_COMMUNICATION: u16 = 9;
const DIRECTION_REVERSED: u16 = 1;
const PROTOCOL_STANDARD: u16 = 1;
const CURRENT_IN_TENTHS: u16 = 1;

/// P0-17/P0-18 count in 0.1 s (P0-19 = 1, the only unit modelled).
const RAMP_TIME_UNIT: Duration = Duration::from_millis(100);
const TIMEOUT_UNIT: Duration = Duration::from_millis(100);
const RESPONSE_DELAY_UNIT: Duration = Duration::from_millis(1);
const MINUTE: Duration = Duration::from_secs(60);

/// 0.01 Hz.
const JOG_FREQUENCY: u16 = 200;
/// Rated output power, 0.1 kW.
const RATED_POWER: u32 = 22;
const MOTOR: Motor = Motor {
    voltage: 380,
    current: 510,
    frequency: 5000,
    speed: 1430,
    poles: 4,
    bus_voltage: 5400,
};

/// Pd-00..Pd-02: Pd-00's baud rates and Pd-01's formats (8 data bits) by index.
const LINE: LineParams = LineParams {
    address: ADDRESS,
    baud: BAUD,
    format: FORMAT,
    indices: LineIndices {
        bauds: &[
            300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200,
        ],
        factory_baud: FACTORY_BAUD_INDEX,
        formats: &[(Parity::None, 2), (Parity::Even, 1), (Parity::Odd, 1)],
        factory_format: FACTORY_FORMAT_INDEX,
    },
    differs: |value, configured| {
        format!(
            "{configured} differs from the line's {value}: set the slave's address and the line's format instead"
        )
    },
    outside: |value| format!("the line's {value} is outside its range"),
};
const FACTORY_BAUD_INDEX: u16 = 5;
const FACTORY_FORMAT_INDEX: u16 = 0;

const fn param(
    address: u16,
    name: &'static str,
    default: u16,
    min: Limit,
    max: Limit,
    modify: Modify,
) -> ParamSpec {
    ParamSpec {
        address,
        name,
        default,
        min,
        max,
        modify,
    }
}

/// Fieldbus values: 50.00 Hz is 5000, 20.0 s is 200.
const TABLE: &[ParamSpec] = &[
    param(P0_00, "P0-00", 1, Value(1), Value(2), Never),
    param(MOTOR_CONTROL, "P0-01", 2, Value(0), Value(2), Stopped),
    param(COMMAND_SOURCE, "P0-02", 0, Value(0), Value(2), Always),
    param(MAIN_SOURCE, "P0-03", 0, Value(0), Value(9), Stopped),
    param(AUX_SOURCE, "P0-04", 0, Value(0), Value(9), Stopped),
    param(0xF005, "P0-05", 0, Value(0), Value(1), Always),
    param(0xF006, "P0-06", 100, Value(0), Value(150), Always),
    param(0xF007, "P0-07", 0, Value(0), Value(0x99), Always),
    param(
        PRESET_FREQUENCY,
        "P0-08",
        5000,
        Value(0),
        Param(MAX_FREQUENCY),
        Always,
    ),
    param(DIRECTION, "P0-09", 0, Value(0), Value(1), Always),
    param(
        MAX_FREQUENCY,
        "P0-10",
        5000,
        Value(5000),
        Value(50000),
        Stopped,
    ),
    param(UPPER_LIMIT_SOURCE, "P0-11", 0, Value(0), Value(5), Stopped),
    param(
        UPPER_LIMIT,
        "P0-12",
        5000,
        Param(LOWER_LIMIT),
        Param(MAX_FREQUENCY),
        Always,
    ),
    param(
        UPPER_LIMIT_OFFSET,
        "P0-13",
        0,
        Value(0),
        Param(MAX_FREQUENCY),
        Always,
    ),
    param(
        LOWER_LIMIT,
        "P0-14",
        0,
        Value(0),
        Param(UPPER_LIMIT),
        Always,
    ),
    param(CARRIER, "P0-15", 60, Value(5), Value(160), Always),
    param(0xF010, "P0-16", 1, Value(0), Value(1), Always),
    param(ACCEL_TIME, "P0-17", 200, Value(0), Value(65000), Always),
    param(DECEL_TIME, "P0-18", 200, Value(0), Value(65000), Always),
    param(
        RAMP_TIME_UNIT_PARAM,
        "P0-19",
        1,
        Value(1),
        Value(1),
        Stopped,
    ),
    param(
        BAUD,
        "Pd-00",
        FACTORY_BAUD_INDEX,
        Value(0),
        Value(9),
        Always,
    ),
    param(
        FORMAT,
        "Pd-01",
        FACTORY_FORMAT_INDEX,
        Value(0),
        Value(2),
        Always,
    ),
    param(ADDRESS, "Pd-02", 1, Value(1), Value(247), Always),
    param(RESPONSE_DELAY, "Pd-03", 2, Value(0), Value(20), Always),
    param(TIMEOUT, "Pd-04", 0, Value(0), Value(600), Always),
    param(PROTOCOL, "Pd-05", 0, Value(0), Value(1), Always),
    param(CURRENT_RESOLUTION, "Pd-06", 0, Value(0), Value(1), Always),
];

/// A running value the drive works out (1000H..1020H).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Actual {
    CommSetting,
    OperatingFrequency,
    BusVoltage,
    OutputVoltage,
    OutputCurrent,
    OutputPower,
    OutputTorque,
    Speed,
    DoFlags,
    /// 0.1 Hz.
    FeedbackSpeed,
    PowerOnTime,
    RunningTime,
    MainFrequency,
}

/// The manual's shutdown/running parameters that read other than 0.
static RUNNING_VALUES: [(u16, Actual); 16] = [
    (COMM_SETTING, Actual::CommSetting),
    (0x1001, Actual::OperatingFrequency),
    (0x1002, Actual::BusVoltage),
    (0x1003, Actual::OutputVoltage),
    (0x1004, Actual::OutputCurrent),
    (0x1005, Actual::OutputPower),
    (0x1006, Actual::OutputTorque),
    // Operating speed.
    (0x1007, Actual::Speed),
    (0x1009, Actual::DoFlags),
    // Load speed.
    (0x100F, Actual::Speed),
    (0x1014, Actual::FeedbackSpeed),
    (0x101A, Actual::PowerOnTime),
    (0x101B, Actual::RunningTime),
    // The communication setting value's copy.
    (0x101D, Actual::CommSetting),
    // Actual feedback speed.
    (0x101E, Actual::FeedbackSpeed),
    (0x101F, Actual::MainFrequency),
];

fn refusal_code(refusal: ParamRefusal) -> ExceptionCode {
    match refusal {
        ParamRefusal::NoSuchAddress | ParamRefusal::ReadOnly => IllegalDataAddress,
        ParamRefusal::OutOfRange | ParamRefusal::WhileRunning => ServerDeviceFailure,
    }
}

fn minutes(time: Duration) -> u16 {
    u16::try_from(time.as_secs() / MINUTE.as_secs()).unwrap_or(u16::MAX)
}

/// A run or jog command in force.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Run {
    reverse: bool,
    jog: bool,
}

/// What 2000H orders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Command {
    Run(Run),
    Coast,
    Decelerate,
    ResetFault,
}

impl Command {
    fn from_word(value: u16) -> Option<Command> {
        let run = |reverse, jog| Command::Run(Run { reverse, jog });
        Some(match value {
            1 => run(false, false),
            2 => run(true, false),
            3 => run(false, true),
            4 => run(true, true),
            5 => Command::Coast,
            6 => Command::Decelerate,
            7 => Command::ResetFault,
            _ => return None,
        })
    }
}

/// The drive's state.
#[derive(Clone, Debug)]
pub(crate) struct PdInverter {
    params: Params,
    ramp: Ramp,
    /// None once stopped, though the output may still be ramping down.
    run: Option<Run>,
    /// The manual's fault code; 0 when healthy.
    fault: u16,
    /// 1000H, signed.
    comm_setting: i16,
    /// 2001H..2004H as last written.
    outputs: [u16; 4],
    powered_on: Instant,
    run_time: Duration,
    run_since: Option<Instant>,
    /// The time of the request being handled.
    now: Instant,
}

impl PdInverter {
    /// Power on at `now` with `settings` (params applied with Params::apply, then trip).
    pub(crate) fn new(
        settings: &DriveSettings,
        now: Instant,
    ) -> Result<Drive<PdInverter>, SetupError> {
        let mut params = Params::new(TABLE);
        params.apply(&settings.params)?;
        LINE.power_on(&mut params, settings)?;
        let fault = power_on_trip(settings, LAST_FAULT_CODE)?.unwrap_or(0);
        let drive = PdInverter {
            params,
            ramp: Ramp::new(now),
            run: None,
            fault,
            comm_setting: 0,
            outputs: [0; 4],
            powered_on: now,
            run_time: Duration::ZERO,
            run_since: None,
            now,
        };
        Ok(Drive::new(drive, settings))
    }

    fn rates(&self) -> Rates {
        Rates {
            full_scale: u32::from(self.params.value(MAX_FREQUENCY)),
            accel: RAMP_TIME_UNIT * u32::from(self.params.value(ACCEL_TIME)),
            decel: RAMP_TIME_UNIT * u32::from(self.params.value(DECEL_TIME)),
        }
    }

    /// A command in force, or an output still ramping down.
    fn running(&self) -> bool {
        self.run.is_some() || self.ramp.frequency() != 0
    }

    fn direction_reversed(&self) -> bool {
        self.params.value(DIRECTION) == DIRECTION_REVERSED
    }

    /// Main frequency X, 0.01 Hz, before the limits.
    fn main_reference(&self) -> u16 {
        match self.params.value(MAIN_SOURCE) {
            SOURCE_DIGITAL => self.params.value(PRESET_FREQUENCY),
            SOURCE_COMMUNICATION => {
                let share = u32::from(self.comm_setting.unsigned_abs());
                let max = u32::from(self.params.value(MAX_FREQUENCY));
                let reference = share * max / u32::from(COMM_SETTING_FULL_SCALE);
                u16::try_from(reference).unwrap_or(u16::MAX)
            }
            _ => 0,
        }
    }

    /// Signed output the drive heads for, 0.01 Hz.
    fn target(&self) -> i32 {
        let Some(run) = self.run else {
            return 0;
        };
        let magnitude = if run.jog {
            JOG_FREQUENCY
        } else {
            let upper = self
                .params
                .value(UPPER_LIMIT)
                .min(self.params.value(MAX_FREQUENCY));
            // Not `clamp`: a lowered P0-10 may leave the bounds crossed.
            self.main_reference()
                .max(self.params.value(LOWER_LIMIT))
                .min(upper)
        };
        let magnitude = i32::from(magnitude);
        if run.reverse != self.direction_reversed() {
            -magnitude
        } else {
            magnitude
        }
    }

    fn retarget(&mut self) {
        let (target, rates) = (self.target(), self.rates());
        self.ramp.set_target(self.now, target, rates);
    }

    fn start(&mut self, run: Run) {
        if self.run.is_none() {
            self.run_since = Some(self.now);
        }
        self.run = Some(run);
        self.retarget();
    }

    /// Drop the command; the ramp is the caller's business.
    fn end_run(&mut self) {
        if let Some(since) = self.run_since.take() {
            self.run_time += self.now.saturating_duration_since(since);
        }
        self.run = None;
    }

    fn trip(&mut self, code: u16) {
        self.ramp.coast(self.now);
        self.end_run();
        if self.fault == 0 {
            self.fault = code;
        }
    }

    fn state(&self) -> u16 {
        if !self.running() {
            return STATE_STOPPED;
        }
        let reverse = match self.ramp.frequency() {
            0 => self
                .run
                .is_some_and(|run| run.reverse != self.direction_reversed()),
            frequency => frequency < 0,
        };
        if reverse {
            STATE_REVERSE
        } else {
            STATE_FORWARD
        }
    }

    fn running_time(&self) -> Duration {
        let current = self.run_since.map_or(Duration::ZERO, |since| {
            self.now.saturating_duration_since(since)
        });
        self.run_time + current
    }

    /// 1000H..1020H.
    fn running_value(&self, address: u16) -> u16 {
        let Some(&(_, actual)) = RUNNING_VALUES.iter().find(|(a, _)| *a == address) else {
            // Inputs, counters, PID, PLC, calibration: nothing connected.
            return 0;
        };
        let frequency = self.ramp.frequency();
        let hz = u16::try_from(frequency.unsigned_abs()).unwrap_or(u16::MAX);
        let energised = self.running();
        match actual {
            // Two's complement on the wire.
            Actual::CommSetting => u16::from_be_bytes(self.comm_setting.to_be_bytes()),
            Actual::OperatingFrequency => hz,
            Actual::BusVoltage => MOTOR.bus_voltage,
            Actual::OutputVoltage => MOTOR.output_voltage(frequency),
            Actual::OutputCurrent => {
                let current = MOTOR.output_current(frequency, energised);
                let current = if self.params.value(CURRENT_RESOLUTION) == CURRENT_IN_TENTHS {
                    (current + 5) / 10
                } else {
                    current
                };
                u16::try_from(current).unwrap_or(u16::MAX)
            }
            Actual::OutputPower => {
                // 0.1 kW from 0.1 % of rated.
                let power = RATED_POWER * u32::from(MOTOR.power(frequency, energised));
                u16::try_from((power + 500) / 1000).unwrap_or(u16::MAX)
            }
            Actual::OutputTorque => MOTOR.torque(frequency, energised),
            Actual::Speed => u16::try_from(MOTOR.speed(frequency)).unwrap_or(u16::MAX),
            Actual::DoFlags => self.outputs[0],
            Actual::FeedbackSpeed => hz / 10,
            Actual::PowerOnTime => minutes(self.now.saturating_duration_since(self.powered_on)),
            Actual::RunningTime => minutes(self.running_time()),
            Actual::MainFrequency => self.main_reference(),
        }
    }

    fn read_word(&self, address: u16) -> Result<u16, ExceptionCode> {
        match address {
            PARAMETERS_FIRST..=PARAMETERS_LAST => {
                self.params.get(address).ok_or(IllegalDataAddress)
            }
            COMM_SETTING..=RUNNING_VALUES_LAST => Ok(self.running_value(address)),
            PASSWORD => Ok(PASSWORD_PASSED),
            STATE => Ok(self.state()),
            FAULT => Ok(self.fault),
            _ => Err(IllegalDataAddress),
        }
    }

    fn write_param(&mut self, address: u16, value: u16) -> Result<(), ExceptionCode> {
        if matches!(address, BAUD | FORMAT | ADDRESS) {
            return match self.params.get(address) {
                Some(current) if current == value => Ok(()),
                _ => Err(ServerDeviceFailure),
            };
        }
        self.params
            .write(address, value, self.running())
            .map_err(refusal_code)?;
        self.retarget();
        Ok(())
    }

    fn command(&mut self, value: u16) -> Result<(), ExceptionCode> {
        let command = Command::from_word(value).ok_or(ServerDeviceFailure)?;
        if self.params.value(COMMAND_SOURCE) != COMMAND_FROM_COMMUNICATION {
            return Ok(());
        }
        match command {
            Command::Run(_) if self.fault != 0 => return Err(ServerDeviceFailure),
            Command::Run(run) => self.start(run),
            Command::Coast => {
                self.ramp.coast(self.now);
                self.end_run();
            }
            Command::Decelerate => {
                self.end_run();
                self.retarget();
            }
            Command::ResetFault => self.fault = 0,
        }
        Ok(())
    }

    fn write_word(&mut self, address: u16, value: u16) -> Result<(), ExceptionCode> {
        match address {
            0..=RAM_ALIAS_LAST => self.write_param(address | RAM_ALIAS_TO_PARAMETER, value),
            PARAMETERS_FIRST..=PARAMETERS_LAST => self.write_param(address, value),
            COMM_SETTING => {
                // Two's complement on the wire.
                let setting = i16::from_be_bytes(value.to_be_bytes());
                if setting.unsigned_abs() > COMM_SETTING_FULL_SCALE {
                    return Err(ServerDeviceFailure);
                }
                self.comm_setting = setting;
                self.retarget();
                Ok(())
            }
            PASSWORD => Ok(()),
            CONTROL => self.command(value),
            DO_CONTROL..=OUTPUTS_LAST => {
                let max = if address == DO_CONTROL {
                    DO_MASK
                } else {
                    ANALOG_OUTPUT_MAX
                };
                if value > max {
                    return Err(ServerDeviceFailure);
                }
                self.outputs[usize::from(address - DO_CONTROL)] = value;
                Ok(())
            }
            _ => Err(IllegalDataAddress),
        }
    }
}

impl Model for PdInverter {
    const PROTOCOL: DriveProtocol = REQUESTS;

    fn read(&self, address: u16) -> Result<u16, Exception> {
        Ok(self.read_word(address)?)
    }

    /// Acts as of the drive's clock, which `advance` has brought up to `at`.
    fn write(&mut self, address: u16, value: u16, _at: Instant) -> Result<(), Exception> {
        Ok(self.write_word(address, value)?)
    }

    fn advance(&mut self, at: Instant) {
        self.now = self.now.max(at);
        self.ramp.advance(self.now, self.rates());
    }

    fn communication_timeout(&self) -> Duration {
        TIMEOUT_UNIT * u32::from(self.params.value(TIMEOUT))
    }

    /// Trip at the moment Pd-04 ran out.
    fn communication_lost(&mut self, expired: Instant) {
        self.now = self.now.max(expired);
        self.ramp.advance(self.now, self.rates());
        self.trip(COMMUNICATION_FAULT);
    }

    fn response_delay(&self) -> Duration {
        RESPONSE_DELAY_UNIT * u32::from(self.params.value(RESPONSE_DELAY))
    }

    /// Pd-05 = 0, the factory "non-standard protocol".
    fn wide_byte_count(&self) -> bool {
        self.params.value(PROTOCOL) != PROTOCOL_STANDARD
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::rtu;
    use crate::line::SerialFormat;
    use crate::pdu::code::{READ_HOLDING_REGISTERS, WRITE_SINGLE_REGISTER};
    use crate::pdu::ExceptionCode::{IllegalDataValue, IllegalFunction};
    use crate::sim::Simulated;

    const LINE: SerialFormat = SerialFormat {
        baud: 9600,
        data_bits: 8,
        parity: Parity::None,
        stop_bits: 2,
    };

    fn settings(params: &[(&str, u16)]) -> DriveSettings {
        DriveSettings {
            params: params.iter().map(|&(n, v)| (n.to_owned(), v)).collect(),
            ..DriveSettings::new(1, LINE)
        }
    }

    /// A drive at address 1 powered on at the returned instant.
    fn power_on(params: &[(&str, u16)]) -> (Drive<PdInverter>, Instant) {
        let t0 = Instant::now();
        (PdInverter::new(&settings(params), t0).unwrap(), t0)
    }

    /// A drive taking its commands and reference from the bus.
    fn on_the_bus(params: &[(&str, u16)]) -> (Drive<PdInverter>, Instant) {
        let mut all = vec![("P0-02", 2), ("P0-03", 9)];
        all.extend_from_slice(params);
        power_on(&all)
    }

    fn after(t0: Instant, secs: f64) -> Instant {
        t0 + Duration::from_secs_f64(secs)
    }

    /// The reply PDU to a request to address 1.
    fn ask(drive: &mut Drive<PdInverter>, pdu: &[u8], at: Instant) -> Vec<u8> {
        let reply = drive
            .handle(1, pdu, at)
            .expect("a request to 1 is answered");
        assert!(rtu::crc_ok(&reply.bytes));
        assert_eq!(reply.bytes[0], 1);
        rtu::pdu_of(&reply.bytes).to_vec()
    }

    /// Words read in the factory (two-byte count) form, or the exception code.
    fn read(
        drive: &mut Drive<PdInverter>,
        start: u16,
        quantity: u16,
        at: Instant,
    ) -> Result<Vec<u16>, u8> {
        let [a_hi, a_lo] = start.to_be_bytes();
        let [q_hi, q_lo] = quantity.to_be_bytes();
        match ask(drive, &[READ_HOLDING_REGISTERS, a_hi, a_lo, q_hi, q_lo], at).as_slice() {
            [0x83, code] => Err(*code),
            [READ_HOLDING_REGISTERS, c_hi, c_lo, data @ ..] => {
                assert_eq!(usize::from(u16::from_be_bytes([*c_hi, *c_lo])), data.len());
                Ok(data
                    .chunks_exact(2)
                    .map(|w| u16::from_be_bytes([w[0], w[1]]))
                    .collect())
            }
            other => panic!("not a read reply: {other:02X?}"),
        }
    }

    fn read_one(drive: &mut Drive<PdInverter>, address: u16, at: Instant) -> Result<u16, u8> {
        read(drive, address, 1, at).map(|words| words[0])
    }

    fn write(
        drive: &mut Drive<PdInverter>,
        address: u16,
        value: u16,
        at: Instant,
    ) -> Result<(), u8> {
        let [a_hi, a_lo] = address.to_be_bytes();
        let [v_hi, v_lo] = value.to_be_bytes();
        let request = [WRITE_SINGLE_REGISTER, a_hi, a_lo, v_hi, v_lo];
        match ask(drive, &request, at).as_slice() {
            echo if echo == request => Ok(()),
            [0x86, code] => Err(*code),
            other => panic!("not a write reply: {other:02X?}"),
        }
    }

    #[test]
    fn factory_read_replies_carry_a_two_byte_count_and_pd_05_one_makes_them_standard() {
        let (mut drive, t0) = power_on(&[]);
        // 01 address, 03 read, 3000H state, 1 word, CRC.
        let request = [0x01, 0x03, 0x30, 0x00, 0x00, 0x01, 0x8B, 0x0A];
        let reply = drive.handle(1, rtu::pdu_of(&request), t0).unwrap();
        // 01 address, 03 read, 00 02 byte count (two bytes), 00 03 stopped, CRC.
        assert_eq!(
            reply.bytes,
            [0x01, 0x03, 0x00, 0x02, 0x00, 0x03, 0xA4, 0x0B]
        );
        // 01 address, 03 read, 83 exception to a read of 2000H: 02, CRC; the same in both forms.
        let exception = [0x01, 0x83, 0x02, 0xC0, 0xF1];
        let bad = drive
            .handle(1, &[0x03, 0x20, 0x00, 0x00, 0x01], t0)
            .unwrap();
        assert_eq!(bad.bytes, exception);
        // 01 address, 06 write, FD05H Pd-05, 0001 standard, CRC: echoed as is.
        let standard = [0x01, 0x06, 0xFD, 0x05, 0x00, 0x01, 0x69, 0xA7];
        let echo = drive.handle(1, rtu::pdu_of(&standard), t0).unwrap();
        assert_eq!(echo.bytes, standard);
        let reply = drive.handle(1, rtu::pdu_of(&request), t0).unwrap();
        // 01 address, 03 read, 02 byte count, 00 03 stopped, CRC.
        assert_eq!(reply.bytes, [0x01, 0x03, 0x02, 0x00, 0x03, 0xF8, 0x45]);
        let bad = drive
            .handle(1, &[0x03, 0x20, 0x00, 0x00, 0x01], t0)
            .unwrap();
        assert_eq!(bad.bytes, exception);
    }

    #[test]
    fn a_read_takes_one_to_twelve_words() {
        let (mut drive, t0) = power_on(&[]);
        assert_eq!(
            read(&mut drive, 0x1000, 13, t0),
            Err(IllegalDataValue as u8)
        );
        assert_eq!(read(&mut drive, 0x1000, 0, t0), Err(IllegalDataValue as u8));
        let words = read(&mut drive, 0x1000, 12, t0).unwrap();
        assert_eq!(words.len(), 12);
        // Bus voltage 540.0 V at 1002H.
        assert_eq!(words[2], 5400);
        assert_eq!(
            read(&mut drive, 0xFFFF, 2, t0),
            Err(IllegalDataAddress as u8)
        );
    }

    #[test]
    fn malformed_requests_are_illegal_data_values() {
        let (mut drive, t0) = power_on(&[]);
        for pdu in [
            &[0x03][..],
            &[0x03, 0x10, 0x00, 0x00],
            &[0x03, 0x10, 0x00, 0x00, 0x01, 0x00],
            &[0x06, 0xF0, 0x08],
            &[0x06, 0xF0, 0x08, 0x00, 0x01, 0xFF],
        ] {
            assert_eq!(
                ask(&mut drive, pdu, t0),
                [pdu[0] | 0x80, IllegalDataValue as u8]
            );
        }
    }

    #[test]
    fn function_codes_other_than_03_and_06_are_illegal_functions() {
        let (mut drive, t0) = power_on(&[]);
        // FC 10 writing P0-08, FC 08 echo, FC 04, FC 01, FC 07, a user code.
        assert_eq!(
            ask(
                &mut drive,
                &[0x10, 0xF0, 0x08, 0x00, 0x01, 0x02, 0x0F, 0xA0],
                t0
            ),
            [0x90, IllegalFunction as u8]
        );
        assert_eq!(read_one(&mut drive, PRESET_FREQUENCY, t0), Ok(5000));
        assert_eq!(
            ask(&mut drive, &[0x08, 0x00, 0x00, 0x12, 0x34], t0),
            [0x88, IllegalFunction as u8]
        );
        for function in [0x01, 0x04, 0x07, 0x41] {
            assert_eq!(
                ask(&mut drive, &[function, 0x10, 0x00, 0x00, 0x01], t0),
                [function | 0x80, IllegalFunction as u8]
            );
        }
    }

    #[test]
    fn the_ram_alias_takes_writes_with_the_same_checks_but_cannot_be_read() {
        let (mut drive, t0) = power_on(&[]);
        // 0008H is P0-08 in RAM.
        assert_eq!(write(&mut drive, 0x0008, 4000, t0), Ok(()));
        assert_eq!(read_one(&mut drive, 0xF008, t0), Ok(4000));
        assert_eq!(
            read_one(&mut drive, 0x0008, t0),
            Err(IllegalDataAddress as u8)
        );
        assert_eq!(
            read_one(&mut drive, 0x0D05, t0),
            Err(IllegalDataAddress as u8)
        );
        assert_eq!(
            write(&mut drive, 0x0008, 5001, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, 0x0000, 2, t0),
            Err(IllegalDataAddress as u8)
        );
        assert_eq!(write(&mut drive, 0x0D05, 1, t0), Ok(()));
        // Pd-05 = 1 took: the reply is in the standard form.
        assert_eq!(
            ask(
                &mut drive,
                &[READ_HOLDING_REGISTERS, 0xFD, 0x05, 0x00, 0x01],
                t0
            ),
            [READ_HOLDING_REGISTERS, 0x02, 0x00, 0x01]
        );
    }

    #[test]
    fn registers_refuse_the_direction_they_do_not_have() {
        let (mut drive, t0) = power_on(&[]);
        for write_only in [CONTROL, DO_CONTROL, 0x2002, 0x2003, 0x2004] {
            assert_eq!(
                read_one(&mut drive, write_only, t0),
                Err(IllegalDataAddress as u8)
            );
        }
        for read_only in [STATE, FAULT, 0x1001, 0x101D, 0x1020] {
            assert_eq!(
                write(&mut drive, read_only, 1, t0),
                Err(IllegalDataAddress as u8)
            );
        }
        // P0-00 is marked read-only.
        assert_eq!(read_one(&mut drive, P0_00, t0), Ok(1));
        assert_eq!(
            write(&mut drive, P0_00, 2, t0),
            Err(IllegalDataAddress as u8)
        );
    }

    #[test]
    fn the_pf_group_and_unmodelled_groups_are_illegal_addresses() {
        let (mut drive, t0) = power_on(&[]);
        for address in [0xFF00, 0xFF10, 0xF100, 0xFE00, 0xA000, 0x7000, 0x4000] {
            assert_eq!(
                read_one(&mut drive, address, t0),
                Err(IllegalDataAddress as u8)
            );
            assert_eq!(
                write(&mut drive, address, 0, t0),
                Err(IllegalDataAddress as u8)
            );
        }
        // PF through the RAM alias.
        assert_eq!(
            write(&mut drive, 0x0F00, 0, t0),
            Err(IllegalDataAddress as u8)
        );
    }

    #[test]
    fn a_read_cannot_run_past_the_last_parameter_of_a_group() {
        let (mut drive, t0) = power_on(&[]);
        assert_eq!(read(&mut drive, 0xF012, 2, t0), Ok(vec![200, 1]));
        assert_eq!(
            read(&mut drive, 0xF012, 3, t0),
            Err(IllegalDataAddress as u8)
        );
        assert_eq!(
            read(&mut drive, 0xFD05, 3, t0),
            Err(IllegalDataAddress as u8)
        );
        assert_eq!(
            read(&mut drive, 0xF000, 12, t0),
            Ok(vec![1, 2, 0, 0, 0, 0, 100, 0, 5000, 0, 5000, 0])
        );
    }

    #[test]
    fn values_the_drive_refuses_are_exception_04() {
        let (mut drive, t0) = power_on(&[]);
        assert_eq!(
            write(&mut drive, PRESET_FREQUENCY, 5001, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, RAMP_TIME_UNIT_PARAM, 0, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, CARRIER, 4, t0),
            Err(ServerDeviceFailure as u8)
        );
        // 1000H: 10001 and -10001 are out, -10000 is in.
        assert_eq!(
            write(&mut drive, COMM_SETTING, 10001, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, COMM_SETTING, 0xD8EF, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(write(&mut drive, COMM_SETTING, 0xD8F0, t0), Ok(()));
        assert_eq!(read_one(&mut drive, COMM_SETTING, t0), Ok(0xD8F0));
        assert_eq!(
            write(&mut drive, DO_CONTROL, 0x80, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(write(&mut drive, DO_CONTROL, 0x7F, t0), Ok(()));
        assert_eq!(read_one(&mut drive, 0x1009, t0), Ok(0x7F));
        assert_eq!(
            write(&mut drive, 0x2004, 0x8000, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(write(&mut drive, 0x2004, 0x7FFF, t0), Ok(()));
        assert_eq!(
            write(&mut drive, CONTROL, 0, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, CONTROL, 8, t0),
            Err(ServerDeviceFailure as u8)
        );
    }

    #[test]
    fn the_password_register_accepts_anything_and_reads_check_passed() {
        let (mut drive, t0) = power_on(&[]);
        assert_eq!(write(&mut drive, PASSWORD, 12345, t0), Ok(()));
        assert_eq!(read_one(&mut drive, PASSWORD, t0), Ok(0x0888));
    }

    #[test]
    fn the_reply_waits_for_pd_03_unless_processing_takes_longer() {
        let (mut drive, t0) = power_on(&[]);
        let read_state = [READ_HOLDING_REGISTERS, 0x30, 0x00, 0x00, 0x01];
        let delay = |drive: &mut Drive<PdInverter>| drive.handle(1, &read_state, t0).unwrap().delay;
        assert_eq!(delay(&mut drive), Duration::from_millis(2));
        assert_eq!(
            write(&mut drive, RESPONSE_DELAY, 21, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(write(&mut drive, RESPONSE_DELAY, 20, t0), Ok(()));
        assert_eq!(delay(&mut drive), Duration::from_millis(20));

        let slow = DriveSettings {
            processing_delay: Duration::from_millis(30),
            ..settings(&[("Pd-03", 20)])
        };
        let mut drive = PdInverter::new(&slow, t0).unwrap();
        assert_eq!(delay(&mut drive), Duration::from_millis(30));
    }

    /// A run started over communication.
    #[test]
    fn a_run_reaches_full_reference_in_the_acceleration_time_and_no_sooner() {
        let (mut drive, t0) = on_the_bus(&[]);
        assert_eq!(write(&mut drive, COMM_SETTING, 10000, t0), Ok(()));
        assert_eq!(write(&mut drive, CONTROL, 1, t0), Ok(()));
        // P0-17 = 20.0 s for 0 to P0-10.
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 10.0)), Ok(2500));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 10.0)),
            Ok(STATE_FORWARD)
        );
        assert!(read_one(&mut drive, 0x1001, after(t0, 19.9)).unwrap() < 5000);
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 20.0)), Ok(5000));
        assert_eq!(read_one(&mut drive, 0x101F, after(t0, 20.0)), Ok(5000));
        // Half the setting, half the reference.
        assert_eq!(
            write(&mut drive, COMM_SETTING, 5000, after(t0, 20.0)),
            Ok(())
        );
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 30.0)), Ok(2500));
    }

    #[test]
    fn a_deceleration_stop_ramps_down_over_the_deceleration_time() {
        let (mut drive, t0) = on_the_bus(&[("P0-18", 100)]);
        write(&mut drive, COMM_SETTING, 10000, t0).unwrap();
        write(&mut drive, CONTROL, 1, t0).unwrap();
        assert_eq!(write(&mut drive, CONTROL, 6, after(t0, 20.0)), Ok(()));
        // P0-18 = 10.0 s from P0-10 to 0; running until the output is 0.
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 25.0)), Ok(2500));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 29.9)),
            Ok(STATE_FORWARD)
        );
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 30.0)), Ok(0));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 30.0)),
            Ok(STATE_STOPPED)
        );
    }

    #[test]
    fn a_freewheel_stop_drops_the_output_at_once() {
        let (mut drive, t0) = on_the_bus(&[]);
        write(&mut drive, COMM_SETTING, 10000, t0).unwrap();
        write(&mut drive, CONTROL, 2, t0).unwrap();
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 20.0)),
            Ok(STATE_REVERSE)
        );
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 20.0)), Ok(5000));
        assert_eq!(write(&mut drive, CONTROL, 5, after(t0, 20.0)), Ok(()));
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 20.0)), Ok(0));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 20.0)),
            Ok(STATE_STOPPED)
        );
    }

    #[test]
    fn stopped_only_parameters_are_refused_until_the_output_reaches_zero() {
        let (mut drive, t0) = on_the_bus(&[]);
        write(&mut drive, COMM_SETTING, 10000, t0).unwrap();
        write(&mut drive, CONTROL, 1, t0).unwrap();
        assert_eq!(
            write(&mut drive, MAX_FREQUENCY, 10000, after(t0, 1.0)),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, MAIN_SOURCE, 0, after(t0, 1.0)),
            Err(ServerDeviceFailure as u8)
        );
        // Always-writable ones still go in.
        assert_eq!(write(&mut drive, ACCEL_TIME, 100, after(t0, 1.0)), Ok(()));
        write(&mut drive, CONTROL, 6, after(t0, 1.0)).unwrap();
        assert_eq!(
            write(&mut drive, MAX_FREQUENCY, 10000, after(t0, 1.1)),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, MAX_FREQUENCY, 10000, after(t0, 2.0)),
            Ok(())
        );
        assert_eq!(
            read_one(&mut drive, MAX_FREQUENCY, after(t0, 2.0)),
            Ok(10000)
        );
    }

    #[test]
    fn a_silence_longer_than_pd_04_trips_the_drive_when_it_ran_out() {
        // Pd-04 = 60.0 s.
        let (mut drive, t0) = on_the_bus(&[("Pd-04", 600), ("P0-17", 0)]);
        write(&mut drive, COMM_SETTING, 10000, t0).unwrap();
        write(&mut drive, CONTROL, 1, t0).unwrap();
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 30.0)), Ok(5000));
        // 60.0 s of silence exactly is still within the timeout.
        assert_eq!(read_one(&mut drive, FAULT, after(t0, 90.0)), Ok(0));
        // The next request comes 120 s later: the trip happened at 150 s.
        assert_eq!(read_one(&mut drive, FAULT, after(t0, 210.0)), Ok(0x0010));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 210.0)),
            Ok(STATE_STOPPED)
        );
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 210.0)), Ok(0));
        // Ran 150 s (2 minutes) of 210 s (3 minutes) powered.
        assert_eq!(
            read(&mut drive, 0x101A, 2, after(t0, 210.0)),
            Ok(vec![3, 2])
        );
        assert_eq!(
            write(&mut drive, CONTROL, 1, after(t0, 211.0)),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(write(&mut drive, CONTROL, 7, after(t0, 212.0)), Ok(()));
        assert_eq!(read_one(&mut drive, FAULT, after(t0, 213.0)), Ok(0));
        assert_eq!(write(&mut drive, CONTROL, 1, after(t0, 214.0)), Ok(()));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 215.0)),
            Ok(STATE_FORWARD)
        );
    }

    #[test]
    fn a_drive_powered_on_tripped_refuses_to_run_until_reset() {
        let tripped = DriveSettings {
            trip: Some(0x000F),
            ..settings(&[("P0-02", 2)])
        };
        let t0 = Instant::now();
        let mut drive = PdInverter::new(&tripped, t0).unwrap();
        assert_eq!(read_one(&mut drive, FAULT, t0), Ok(0x000F));
        assert_eq!(
            write(&mut drive, CONTROL, 1, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, CONTROL, 4, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(write(&mut drive, CONTROL, 6, t0), Ok(()));
        assert_eq!(write(&mut drive, CONTROL, 7, t0), Ok(()));
        assert_eq!(read_one(&mut drive, FAULT, t0), Ok(0));
        assert_eq!(write(&mut drive, CONTROL, 1, t0), Ok(()));
        // P0-03 = 0: the preset P0-08 (50.00 Hz) in P0-17 (20.0 s).
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 20.0)), Ok(5000));
    }

    #[test]
    fn commands_are_answered_but_ignored_unless_the_command_source_is_communication() {
        let (mut drive, t0) = power_on(&[("P0-03", 9)]);
        write(&mut drive, COMM_SETTING, 10000, t0).unwrap();
        assert_eq!(write(&mut drive, CONTROL, 1, t0), Ok(()));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 5.0)),
            Ok(STATE_STOPPED)
        );
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 5.0)), Ok(0));
        assert_eq!(write(&mut drive, COMMAND_SOURCE, 2, after(t0, 5.0)), Ok(()));
        assert_eq!(write(&mut drive, CONTROL, 1, after(t0, 5.0)), Ok(()));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 6.0)),
            Ok(STATE_FORWARD)
        );
    }

    #[test]
    fn the_reference_follows_the_preset_the_limits_and_the_direction_parameter() {
        let (mut drive, t0) = power_on(&[
            ("P0-02", 2),
            ("P0-08", 3000),
            ("P0-09", 1),
            ("P0-12", 2500),
            ("P0-17", 0),
            ("P0-18", 0),
        ]);
        write(&mut drive, CONTROL, 1, t0).unwrap();
        // Forward reversed by P0-09, held at the upper limit; X shows the preset.
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 0.001)), Ok(2500));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 0.001)),
            Ok(STATE_REVERSE)
        );
        assert_eq!(read_one(&mut drive, 0x101F, after(t0, 0.001)), Ok(3000));
        write(&mut drive, LOWER_LIMIT, 2000, after(t0, 0.001)).unwrap();
        write(&mut drive, PRESET_FREQUENCY, 1000, after(t0, 0.001)).unwrap();
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 0.002)), Ok(2000));
        // Other sources give no reference.
        write(&mut drive, CONTROL, 5, after(t0, 0.002)).unwrap();
        write(&mut drive, MAIN_SOURCE, 1, after(t0, 0.002)).unwrap();
        write(&mut drive, LOWER_LIMIT, 0, after(t0, 0.002)).unwrap();
        write(&mut drive, CONTROL, 1, after(t0, 0.002)).unwrap();
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 0.003)), Ok(0));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 0.003)),
            Ok(STATE_REVERSE)
        );
    }

    #[test]
    fn a_jog_runs_at_two_hertz_either_way() {
        let (mut drive, t0) = on_the_bus(&[("P0-17", 0), ("P0-18", 0)]);
        write(&mut drive, COMM_SETTING, 10000, t0).unwrap();
        write(&mut drive, CONTROL, 3, t0).unwrap();
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 0.001)), Ok(200));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 0.001)),
            Ok(STATE_FORWARD)
        );
        write(&mut drive, CONTROL, 4, after(t0, 0.001)).unwrap();
        assert_eq!(read_one(&mut drive, 0x1001, after(t0, 0.002)), Ok(200));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 0.002)),
            Ok(STATE_REVERSE)
        );
    }

    #[test]
    fn actual_values_follow_the_output_and_pd_06_sets_the_current_unit() {
        let (mut drive, t0) = on_the_bus(&[("P0-17", 0)]);
        write(&mut drive, COMM_SETTING, 10000, t0).unwrap();
        write(&mut drive, CONTROL, 1, t0).unwrap();
        let at = after(t0, 0.001);
        let values = read(&mut drive, 0x1000, 8, at).unwrap();
        // Setting, 50.00 Hz, 540.0 V bus, 380 V, 4.39 A, 1.8 kW, 80.0 % torque, 1430 rpm.
        assert_eq!(values, [10000, 5000, 5400, 380, 439, 18, 800, 1430]);
        // Load speed; feedback speed 50.0 Hz; the setting's copy; actual feedback speed; X.
        assert_eq!(read_one(&mut drive, 0x100F, at), Ok(1430));
        assert_eq!(read_one(&mut drive, 0x1014, at), Ok(500));
        assert_eq!(read(&mut drive, 0x101D, 3, at), Ok(vec![10000, 500, 5000]));
        write(&mut drive, CURRENT_RESOLUTION, 1, at).unwrap();
        assert_eq!(read_one(&mut drive, 0x1004, at), Ok(44));
    }

    #[test]
    fn running_time_counts_only_while_a_command_is_in_force() {
        let (mut drive, t0) = on_the_bus(&[]);
        write(&mut drive, CONTROL, 1, after(t0, 30.0)).unwrap();
        assert_eq!(read_one(&mut drive, 0x101B, after(t0, 89.0)), Ok(0));
        assert_eq!(read_one(&mut drive, 0x101B, after(t0, 90.0)), Ok(1));
        write(&mut drive, CONTROL, 5, after(t0, 180.0)).unwrap();
        // 150 s run, 600 s powered.
        assert_eq!(
            read(&mut drive, 0x101A, 2, after(t0, 600.0)),
            Ok(vec![10, 2])
        );
    }

    #[test]
    fn the_communication_parameters_read_the_line_and_refuse_other_values() {
        let format = SerialFormat {
            baud: 19200,
            parity: Parity::Even,
            stop_bits: 1,
            ..LINE
        };
        let t0 = Instant::now();
        let mut drive = PdInverter::new(&DriveSettings::new(1, format), t0).unwrap();
        assert_eq!(read(&mut drive, BAUD, 3, t0), Ok(vec![6, 1, 1]));
        assert_eq!(write(&mut drive, BAUD, 6, t0), Ok(()));
        assert_eq!(
            write(&mut drive, BAUD, 5, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, FORMAT, 0, t0),
            Err(ServerDeviceFailure as u8)
        );
        assert_eq!(
            write(&mut drive, 0x0D02, 2, t0),
            Err(ServerDeviceFailure as u8)
        );

        let odd = SerialFormat {
            baud: 14400,
            parity: Parity::Odd,
            ..format
        };
        let mut drive = PdInverter::new(&DriveSettings::new(7, odd), t0).unwrap();
        let reply = drive
            .handle(7, &[READ_HOLDING_REGISTERS, 0xFD, 0x00, 0x00, 0x03], t0)
            .unwrap();
        // 07 address, 03 read, 00 06 count, 5 (no index for 14400), 2 (8O1), 7, CRC.
        assert_eq!(
            rtu::pdu_of(&reply.bytes),
            [
                READ_HOLDING_REGISTERS,
                0x00,
                0x06,
                0x00,
                0x05,
                0x00,
                0x02,
                0x00,
                0x07
            ]
        );
        assert_eq!(reply.bytes[0], 7);
    }

    #[test]
    fn power_on_settings_are_checked_and_name_the_bad_one() {
        let t0 = Instant::now();
        let reject = |settings: DriveSettings| PdInverter::new(&settings, t0).unwrap_err().param;
        assert_eq!(reject(settings(&[("Pd-02", 2)])), "Pd-02");
        assert_eq!(reject(settings(&[("Pd-00", 6)])), "Pd-00");
        assert_eq!(reject(settings(&[("P0-99", 1)])), "P0-99");
        assert_eq!(reject(settings(&[("P0-08", 6000)])), "P0-08");
        let tripped = |trip| DriveSettings {
            trip: Some(trip),
            ..settings(&[])
        };
        assert_eq!(reject(tripped(0)), "trip");
        assert_eq!(reject(tripped(0x5F)), "trip");
        // The line's own values and a raised maximum that makes room for the preset are fine.
        let fine = settings(&[("Pd-02", 1), ("P0-08", 6000), ("P0-10", 6000)]);
        let mut drive = PdInverter::new(&fine, t0).unwrap();
        assert_eq!(read_one(&mut drive, PRESET_FREQUENCY, t0), Ok(6000));
        assert!(PdInverter::new(&tripped(0x5E), t0).is_ok());
        assert_eq!(reject(DriveSettings::new(0, LINE)), "Pd-02");
    }

    #[test]
    fn a_broadcast_write_is_carried_out_and_never_answered() {
        let (mut drive, t0) = on_the_bus(&[]);
        assert_eq!(
            drive.handle(0, &[WRITE_SINGLE_REGISTER, 0xF0, 0x08, 0x0F, 0xA0], t0),
            None
        );
        assert_eq!(
            drive.handle(0, &[WRITE_SINGLE_REGISTER, 0x10, 0x00, 0x27, 0x10], t0),
            None
        );
        assert_eq!(
            drive.handle(0, &[WRITE_SINGLE_REGISTER, 0x20, 0x00, 0x00, 0x01], t0),
            None
        );
        assert_eq!(
            drive.handle(0, &[READ_HOLDING_REGISTERS, 0x30, 0x00, 0x00, 0x01], t0),
            None
        );
        assert_eq!(
            drive.handle(0, &[WRITE_SINGLE_REGISTER, 0x30, 0x00, 0x00, 0x01], t0),
            None
        );
        assert_eq!(read_one(&mut drive, PRESET_FREQUENCY, t0), Ok(4000));
        assert_eq!(
            read_one(&mut drive, STATE, after(t0, 1.0)),
            Ok(STATE_FORWARD)
        );
    }

    #[test]
    fn a_broadcast_keeps_the_communication_timeout_from_running_out() {
        let (mut drive, t0) = power_on(&[("Pd-04", 10)]);
        assert_eq!(read_one(&mut drive, FAULT, t0), Ok(0));
        assert_eq!(
            drive.handle(
                0,
                &[READ_HOLDING_REGISTERS, 0x30, 0x00, 0x00, 0x01],
                after(t0, 0.9)
            ),
            None
        );
        assert_eq!(read_one(&mut drive, FAULT, after(t0, 1.8)), Ok(0));
        assert_eq!(read_one(&mut drive, FAULT, after(t0, 2.9)), Ok(0x0010));
    }

    #[test]
    fn no_request_whatever_its_bytes_makes_the_drive_panic() {
        let (mut drive, t0) = on_the_bus(&[("Pd-04", 5)]);
        let interesting = [
            0x0000, 0x0D05, 0x0EFF, 0x0F00, 0x1000, 0x1001, 0x101B, 0x1020, 0x1F00, 0x2000, 0x2001,
            0x2004, 0x3000, 0x8000, 0xF000, 0xF00A, 0xF011, 0xF013, 0xFD00, 0xFD03, 0xFD05, 0xFF00,
            0xFFFF,
        ];
        let mut rng = fastrand::Rng::with_seed(1);
        for step in 0..50_000u64 {
            let mut pdu = crate::sim::random_pdu(
                &mut rng,
                9,
                &[
                    READ_HOLDING_REGISTERS,
                    WRITE_SINGLE_REGISTER,
                    WRITE_SINGLE_REGISTER,
                ],
                &interesting,
            );
            if pdu.len() >= 5 && rng.bool() {
                // Small values, so commands and in-range writes happen too.
                pdu[3] = 0;
                pdu[4] %= 16;
            }
            let address = if rng.bool() { 0 } else { 1 };
            // Mostly forward in time, sometimes past the timeout, now and then backwards.
            let at = t0 + Duration::from_millis(step * 20 + rng.u64(..700));
            let _ = drive.handle(address, &pdu, at);
        }
    }
}
