//! The Goodrive manuals' tables as data: the 2000H control registers and what each accepts, the
//! 3000H running values, the modelled parameters with their ranges and modify marks, the line's
//! parameters and indices, and what sets the variants apart. The behaviour that reads them is in
//! [`super`]; this module knows nothing of requests or time.

use crate::line::Parity;
use crate::sim::drive::{Limit, LineIndices, LineParams, Modify, Motor, ParamSpec};
use std::time::Duration;

pub(super) const CONTROL: u16 = 0x2000;
pub(super) const SETPOINT_FREQUENCY: u16 = 0x2001;
pub(super) const PID_REFERENCE: u16 = 0x2002;
pub(super) const PID_FEEDBACK: u16 = 0x2003;
pub(super) const TORQUE_SETPOINT: u16 = 0x2004;
pub(super) const CONTROL_LAST: u16 = 0x200E;
pub(super) const STATE_1: u16 = 0x2100;
pub(super) const STATE_2: u16 = 0x2101;
pub(super) const FAULT_CODE: u16 = 0x2102;
pub(super) const IDENTIFIER: u16 = 0x2103;
pub(super) const RUNNING_FIRST: u16 = 0x3000;
pub(super) const RUNNING_LAST: u16 = 0x3016;
pub(super) const FAULT: u16 = 0x5000;
/// Set on a parameter's address, it writes RAM only; such an address cannot be read.
pub(super) const RAM_ALIAS: u16 = 0x8000;
/// Factory parameters: neither readable nor writable.
pub(super) const P29_GROUP: u16 = 0x1D;

/// What a 2000H register accepts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Accepts {
    /// The command word: run, jog, stop, fault reset.
    Command,
    /// 0 to the maximum frequency (P00.03).
    UpToMaxFrequency,
    UpTo(u16),
    /// -n..=n, two's complement on the wire.
    Signed(i16),
}

/// A 2000H register: what it accepts and whether the GD10 has it (the GD20 and GD300 have all).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct ControlRegister {
    pub(super) address: u16,
    pub(super) accepts: Accepts,
    pub(super) on_gd10: bool,
}

pub(super) const fn control(address: u16, accepts: Accepts, on_gd10: bool) -> ControlRegister {
    ControlRegister {
        address,
        accepts,
        on_gd10,
    }
}

/// 2000H..=200EH, as the manuals list them.
pub(super) const CONTROL_REGISTERS: [ControlRegister; 15] = {
    use Accepts::{Command, Signed, UpTo, UpToMaxFrequency};
    [
        control(CONTROL, Command, true),
        control(SETPOINT_FREQUENCY, UpToMaxFrequency, true),
        control(PID_REFERENCE, UpTo(1000), true),
        control(PID_FEEDBACK, UpTo(1000), true),
        control(TORQUE_SETPOINT, Signed(3000), false),
        // Upper limit frequencies, forward and reverse.
        control(0x2005, UpToMaxFrequency, false),
        control(0x2006, UpToMaxFrequency, false),
        // Upper limits of the electromotive and the braking torque.
        control(0x2007, UpTo(3000), false),
        control(0x2008, UpTo(3000), false),
        // Special control command word.
        control(0x2009, UpTo(0x3F), false),
        // Virtual input terminal commands.
        control(0x200A, UpTo(0x1FF), true),
        control(0x200B, UpTo(0x0F), true),
        // Voltage setting for V/F separation.
        control(0x200C, UpTo(1000), false),
        // AO output settings 1 and 2.
        control(0x200D, Signed(1000), true),
        control(CONTROL_LAST, Signed(1000), false),
    ]
};

/// A running value the drive works out; 3000H..=3016H addresses not in [`RUNNING_VALUES`]
/// (terminals, analog and pulse inputs, counters) read 0: nothing is wired to them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Actual {
    OutputFrequency,
    Reference,
    BusVoltage,
    OutputVoltage,
    OutputCurrent,
    Speed,
    Power,
    Torque,
    PidReference,
    PidFeedback,
    TorqueSetpoint,
    Identifier,
}

pub(super) static RUNNING_VALUES: [(u16, Actual); 12] = [
    (RUNNING_FIRST, Actual::OutputFrequency),
    (0x3001, Actual::Reference),
    (0x3002, Actual::BusVoltage),
    (0x3003, Actual::OutputVoltage),
    (0x3004, Actual::OutputCurrent),
    (0x3005, Actual::Speed),
    (0x3006, Actual::Power),
    (0x3007, Actual::Torque),
    (0x3008, Actual::PidReference),
    (0x3009, Actual::PidFeedback),
    (0x3015, Actual::TorqueSetpoint),
    (RUNNING_LAST, Actual::Identifier),
];

pub(super) const P00_01: u16 = 0x0001;
pub(super) const P00_03: u16 = 0x0003;
pub(super) const P00_04: u16 = 0x0004;
pub(super) const P00_05: u16 = 0x0005;
pub(super) const P00_06: u16 = 0x0006;
pub(super) const P00_10: u16 = 0x000A;
pub(super) const P00_11: u16 = 0x000B;
pub(super) const P00_12: u16 = 0x000C;
pub(super) const P00_13: u16 = 0x000D;
pub(super) const P00_18: u16 = 0x0012;
/// P07.27 (current fault) to P07.32 (the fifth before it).
pub(super) const FAULT_RECORDS: [u16; 6] = [0x071B, 0x071C, 0x071D, 0x071E, 0x071F, 0x0720];
pub(super) const P14_00: u16 = 0x0E00;
pub(super) const P14_01: u16 = 0x0E01;
pub(super) const P14_02: u16 = 0x0E02;
pub(super) const P14_03: u16 = 0x0E03;
pub(super) const P14_04: u16 = 0x0E04;
pub(super) const P14_05: u16 = 0x0E05;
pub(super) const P14_06: u16 = 0x0E06;

/// P00.01: commands come from the communication channel.
pub(super) const COMMUNICATION_CHANNEL: u16 = 2;
/// P00.06: frequency sources the simulator wires.
pub(super) const KEYPAD_REFERENCE: u16 = 0;
pub(super) const MODBUS_REFERENCE: u16 = 8;
/// P00.13.
pub(super) const REVERSED: u16 = 1;
pub(super) const REVERSE_FORBIDDEN: u16 = 2;
/// P00.18.
pub(super) const RESTORE_DEFAULTS: u16 = 1;
pub(super) const CLEAR_FAULT_RECORDS: u16 = 2;
/// P14.05: trip on a communication timeout; 1 carries on, 2 and 3 stop.
pub(super) const TIMEOUT_TRIPS: u16 = 0;
pub(super) const TIMEOUT_IGNORED: u16 = 1;
/// P14.06's ones digit: writes are carried out but not answered.
pub(super) const WRITES_UNANSWERED: u16 = 0x01;
/// Fault code CE, the communication timeout.
pub(super) const COMMUNICATION_FAULT: u16 = 18;
/// The highest fault code.
pub(super) const LAST_FAULT_CODE: u16 = 100;
/// The jog frequency's factory default (P08.06 is not modelled).
pub(super) const JOG_FREQUENCY: i32 = 500;
/// P00.11, P00.12, P14.04 count in 0.1 s; P14.03 in ms.
pub(super) const TIME_UNIT: Duration = Duration::from_millis(100);
pub(super) const RESPONSE_DELAY_UNIT: Duration = Duration::from_millis(1);

/// P14.00-P14.02. P14.01 index to baud rate, and P14.02 index to (parity, stop bits) with 8 data
/// bits.
pub(super) const LINE: LineParams = LineParams {
    address: P14_00,
    baud: P14_01,
    format: P14_02,
    indices: LineIndices {
        bauds: &[1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200],
        factory_baud: FACTORY_BAUD_INDEX,
        formats: &[
            (Parity::None, 1),
            (Parity::Even, 1),
            (Parity::Odd, 1),
            (Parity::None, 2),
            (Parity::Even, 2),
            (Parity::Odd, 2),
        ],
        factory_format: FACTORY_FORMAT_INDEX,
    },
    differs: |value, configured| {
        format!(
            "is {value} on this line; the simulated drive takes it from the line's \
             configuration, not {configured}"
        )
    },
    outside: |value| format!("{value} is outside its range"),
};
pub(super) const FACTORY_BAUD_INDEX: u16 = 4;
pub(super) const FACTORY_FORMAT_INDEX: u16 = 1;

pub(super) const TABLE_LEN: usize = 33;

pub(super) const fn fixed(
    address: u16,
    name: &'static str,
    default: u16,
    min: u16,
    max: u16,
    modify: Modify,
) -> ParamSpec {
    ParamSpec {
        address,
        name,
        default,
        min: Limit::Value(min),
        max: Limit::Value(max),
        modify,
    }
}

/// The modelled parameters; the variants differ in the highest maximum frequency and the
/// factory ramp times.
pub(super) const fn table(max_frequency: u16, ramp_time: u16) -> [ParamSpec; TABLE_LEN] {
    use Modify::{Always, Never, Stopped};
    [
        fixed(0x0000, "P00.00", 2, 0, 2, Stopped),
        fixed(P00_01, "P00.01", 0, 0, 2, Always),
        fixed(0x0002, "P00.02", 0, 0, 3, Always),
        ParamSpec {
            address: P00_03,
            name: "P00.03",
            default: 5000,
            min: Limit::Param(P00_04),
            max: Limit::Value(max_frequency),
            modify: Stopped,
        },
        ParamSpec {
            address: P00_04,
            name: "P00.04",
            default: 5000,
            min: Limit::Param(P00_05),
            max: Limit::Param(P00_03),
            modify: Stopped,
        },
        ParamSpec {
            address: P00_05,
            name: "P00.05",
            default: 0,
            min: Limit::Value(0),
            max: Limit::Param(P00_04),
            modify: Stopped,
        },
        fixed(P00_06, "P00.06", 0, 0, 11, Always),
        fixed(0x0007, "P00.07", 2, 0, 11, Always),
        fixed(0x0008, "P00.08", 0, 0, 1, Always),
        fixed(0x0009, "P00.09", 0, 0, 5, Always),
        ParamSpec {
            address: P00_10,
            name: "P00.10",
            default: 5000,
            min: Limit::Value(0),
            max: Limit::Param(P00_03),
            modify: Always,
        },
        fixed(P00_11, "P00.11", ramp_time, 0, 36000, Always),
        fixed(P00_12, "P00.12", ramp_time, 0, 36000, Always),
        fixed(P00_13, "P00.13", 0, 0, 2, Always),
        fixed(0x000E, "P00.14", 40, 10, 150, Always),
        fixed(0x000F, "P00.15", 0, 0, 3, Stopped),
        fixed(0x0010, "P00.16", 1, 0, 1, Always),
        fixed(P00_18, "P00.18", 0, 0, 2, Stopped),
        fixed(0x0114, "P01.20", 0, 0, 36000, Always),
        fixed(0x0115, "P01.21", 0, 0, 1, Always),
        fixed(FAULT_RECORDS[0], "P07.27", 0, 0, LAST_FAULT_CODE, Never),
        fixed(FAULT_RECORDS[1], "P07.28", 0, 0, LAST_FAULT_CODE, Never),
        fixed(FAULT_RECORDS[2], "P07.29", 0, 0, LAST_FAULT_CODE, Never),
        fixed(FAULT_RECORDS[3], "P07.30", 0, 0, LAST_FAULT_CODE, Never),
        fixed(FAULT_RECORDS[4], "P07.31", 0, 0, LAST_FAULT_CODE, Never),
        fixed(FAULT_RECORDS[5], "P07.32", 0, 0, LAST_FAULT_CODE, Never),
        // The line's address and format: set from the configuration, never by a write.
        fixed(P14_00, "P14.00", 1, 1, 247, Never),
        fixed(P14_01, "P14.01", FACTORY_BAUD_INDEX, 0, 7, Never),
        fixed(P14_02, "P14.02", FACTORY_FORMAT_INDEX, 0, 5, Never),
        fixed(P14_03, "P14.03", 5, 0, 200, Always),
        fixed(P14_04, "P14.04", 0, 0, 600, Always),
        fixed(P14_05, "P14.05", 0, 0, 3, Always),
        // Only 0x00, 0x01, 0x10 and 0x11 are settings; see `communication_processing_ok`.
        fixed(P14_06, "P14.06", 0, 0, 0x11, Always),
    ]
}

pub(super) static GD20_TABLE: [ParamSpec; TABLE_LEN] = table(40000, 100);
pub(super) static GD300_TABLE: [ParamSpec; TABLE_LEN] = table(60000, 150);
pub(super) static GD10_TABLE: [ParamSpec; TABLE_LEN] = table(40000, 50);

/// Which Goodrive: they share the protocol and differ in identifying code, motor, factory ramp
/// times and which control registers exist and can be read back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Variant {
    Gd20,
    Gd300,
    Gd10,
}

impl Variant {
    pub(super) fn identifier(self) -> u16 {
        match self {
            Variant::Gd20 => 0x0106,
            Variant::Gd300 => 0x010A,
            Variant::Gd10 => 0x010D,
        }
    }

    pub(super) fn table(self) -> &'static [ParamSpec] {
        match self {
            Variant::Gd20 => &GD20_TABLE,
            Variant::Gd300 => &GD300_TABLE,
            Variant::Gd10 => &GD10_TABLE,
        }
    }

    pub(super) fn motor(self) -> Motor {
        let (voltage, current, speed, bus_voltage) = match self {
            Variant::Gd20 => (220, 340, 1400, 3110),
            Variant::Gd300 => (380, 1300, 1440, 5400),
            Variant::Gd10 => (220, 230, 1390, 3110),
        };
        Motor {
            voltage,
            current,
            frequency: 5000,
            speed,
            poles: 4,
            bus_voltage,
        }
    }

    /// GD20's manual marks the 2000H block write-only; the later manuals make it R/W.
    pub(super) fn control_readable(self) -> bool {
        self != Variant::Gd20
    }

    /// The 2000H register at `address`, if this variant has it.
    pub(super) fn control_register(self, address: u16) -> Option<&'static ControlRegister> {
        CONTROL_REGISTERS
            .iter()
            .find(|r| r.address == address && (self != Variant::Gd10 || r.on_gd10))
    }
}
