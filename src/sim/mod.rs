//! The simulated RS-485 line (`device = "sim"`) and the slaves on it, so the whole gateway runs and
//! is tested with no hardware: `line` times every frame at the configured baud and checks the gaps;
//! `slaves` is where a request frame reaches the slave at its address, each a [`Simulated`];
//! `registers` holds plain register-bank slaves; `drive` models the drives of the reference manuals
//! on one shared request pipeline; `meter` an Eastron SDM120 energy meter; [`faults`] bends any
//! slave's replies; `scripted` plays a script for tests; `master` is a listen line's other
//! master (`[bus.sim_master]`); [`responder`] serves the slaves on a real serial port
//! (`modbus-gateway simulate`) and `device_server` the line on a byte stream, as a serial device
//! server does (`simulate --listen`). Knows nothing of TCP or the bus queue; the bus opens the
//! line like any port, or to listen.

pub(crate) mod device_server;
pub(crate) mod drive;
pub mod faults;
pub(crate) mod line;
pub(crate) mod master;
pub(crate) mod meter;
pub(crate) mod registers;
pub mod responder;
#[cfg(any(test, feature = "test-util"))]
pub(crate) mod scripted;
pub(crate) mod slaves;

pub use line::SimLine;
#[cfg(any(test, feature = "test-util"))]
pub use line::Source;

pub(crate) use line::SimPort;
pub use registers::RegisterBank;
#[cfg(any(test, feature = "test-util"))]
pub use scripted::Scripted;

use crate::config::{self, SimModel};
use crate::line::rtu;
use crate::line::{Framing, SerialFormat};
use drive::goodrive::{Goodrive, Variant};
use drive::pd_inverter::PdInverter;
use drive::{DriveSettings, SetupError};
use faults::{Faults, Faulty};
use meter::Sdm120;
use std::time::Duration;
use tokio::time::Instant;

/// Power on the slave `spec` describes, at `address` on a line of `format`, with its fault knobs.
/// Fails if the drive model refuses a configured parameter or trip.
pub(crate) fn build(
    spec: &config::SimSlave,
    address: u8,
    format: SerialFormat,
    framing: Framing,
) -> Result<Box<dyn Simulated>, SetupError> {
    let now = Instant::now();
    let settings = DriveSettings {
        address,
        format,
        processing_delay: spec.processing_delay,
        params: spec.params.clone(),
        trip: spec.trip,
    };
    let faults = Faults::from(spec);
    Ok(match spec.model {
        SimModel::Registers => with_faults(
            RegisterBank::new(spec.processing_delay),
            faults,
            address,
            framing,
        ),
        SimModel::Gd20 => with_faults(
            Goodrive::new(Variant::Gd20, &settings, now)?,
            faults,
            address,
            framing,
        ),
        SimModel::Gd300 => with_faults(
            Goodrive::new(Variant::Gd300, &settings, now)?,
            faults,
            address,
            framing,
        ),
        SimModel::Gd10 => with_faults(
            Goodrive::new(Variant::Gd10, &settings, now)?,
            faults,
            address,
            framing,
        ),
        SimModel::PdInverter => {
            with_faults(PdInverter::new(&settings, now)?, faults, address, framing)
        }
        SimModel::Sdm120 => with_faults(
            Sdm120::new(spec.processing_delay, now),
            faults,
            address,
            framing,
        ),
    })
}

/// The configuration's check asks the simulator whether each drive accepts its parameters.
pub(crate) struct Drives;

impl config::DriveCheck for Drives {
    fn power_on(
        &self,
        slave: &config::SimSlave,
        address: u8,
        format: SerialFormat,
    ) -> Result<(), config::DriveRefusal> {
        // The parameters are the same whatever the line's framing.
        build(slave, address, format, Framing::Rtu)
            .map(drop)
            .map_err(|e| config::DriveRefusal {
                param: e.param,
                reason: e.reason,
            })
    }
}

/// `slave` as it answers on a line of `framing` with `faults`: as it is on an RTU line without
/// faults, framed and bent by [`Faulty`] otherwise.
fn with_faults<S: Simulated + 'static>(
    slave: S,
    faults: Faults,
    address: u8,
    framing: Framing,
) -> Box<dyn Simulated> {
    if faults.is_none() && framing == Framing::Rtu {
        Box::new(slave)
    } else {
        Box::new(Faulty::framed(slave, faults, address, framing))
    }
}

/// What a simulated slave puts on the wire in answer to a request.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Transmission {
    /// The whole frame as it goes on the wire: address, PDU, CRC (or whatever a faulty slave sends).
    pub bytes: Vec<u8>,
    /// Processing time after the slave has recognised the end of the request (t3.5 of silence).
    pub delay: Duration,
    /// A silence in the middle: the slave stops talking for a while (and lets go of the line),
    /// then sends the rest.
    pub pause: Option<Pause>,
}

/// After the first `after` bytes of a transmission, `gap` of silence before the rest.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pause {
    pub after: usize,
    pub gap: Duration,
}

impl Transmission {
    /// A well-formed frame for `pdu` from `address`, sent after `delay`.
    pub fn frame(address: u8, pdu: &[u8], delay: Duration) -> Self {
        Transmission {
            bytes: rtu::encode(address, pdu),
            delay,
            pause: None,
        }
    }
}

/// A device on the simulated line. It sees every intact request frame addressed to it, and every
/// broadcast.
pub trait Simulated: Send {
    /// Act on `request` (a PDU) that ended on the wire at `at`. `address` is the frame's address:
    /// the slave's own, or 0 for a broadcast, whose answer the line never sends.
    fn handle(&mut self, address: u8, request: &[u8], at: Instant) -> Option<Transmission>;
}

impl<S: Simulated + ?Sized> Simulated for Box<S> {
    fn handle(&mut self, address: u8, request: &[u8], at: Instant) -> Option<Transmission> {
        (**self).handle(address, request, at)
    }
}

/// Input for the slaves' no-panic tests: a PDU of fewer than `max_len` random bytes whose function
/// code is mostly one of `functions` and whose first word (a register address) is mostly one of
/// `addresses`, so the handlers behind them run, not just the first check.
#[cfg(test)]
pub(crate) fn random_pdu(
    rng: &mut fastrand::Rng,
    max_len: usize,
    functions: &[u8],
    addresses: &[u16],
) -> Vec<u8> {
    let mut pdu: Vec<u8> = (0..rng.usize(..max_len)).map(|_| rng.u8(..)).collect();
    if let (Some(first), Some(&function)) = (
        pdu.first_mut(),
        functions.get(rng.usize(..=functions.len())),
    ) {
        *first = function;
    }
    if let (Some(word), Some(address)) = (
        pdu.get_mut(1..3),
        addresses.get(rng.usize(..=addresses.len())),
    ) {
        word.copy_from_slice(&address.to_be_bytes());
    }
    pdu
}
