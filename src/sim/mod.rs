//! The simulated RS-485 line (`device = "sim"`) and the slaves on it, so the whole gateway runs and
//! is tested with no hardware: [`line`] times every frame at the configured baud and checks the
//! gaps; [`registers`] holds plain register-bank slaves; [`scripted`] plays a script for tests. Knows nothing of TCP or the bus queue;
//! the bus opens it like any port.

pub mod drive;
pub mod goodrive;
pub mod line;
pub mod pd_inverter;
pub mod registers;
pub mod scripted;

pub use line::{LineStats, SimLine, SimPort, Source, WireFrame};
pub use registers::RegisterBank;
pub use scripted::Scripted;

use crate::rtu::frame;
use std::time::Duration;
use tokio::time::Instant;

/// What a simulated slave puts on the wire in answer to a request.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Transmission {
    /// The whole frame as it goes on the wire: address, PDU, CRC (or whatever a faulty slave sends).
    pub bytes: Vec<u8>,
    /// Processing time after the slave has recognised the end of the request (t3.5 of silence).
    pub delay: Duration,
}

impl Transmission {
    /// A well-formed frame for `pdu` from `address`, sent after `delay`.
    pub fn frame(address: u8, pdu: &[u8], delay: Duration) -> Self {
        Transmission {
            bytes: frame::encode(address, pdu),
            delay,
        }
    }
}

/// A device on the simulated line. It sees every intact request frame addressed to it, and every
/// broadcast.
pub trait SimSlave: Send {
    /// Act on `request` (a PDU) that ended on the wire at `at`. `address` is the frame's address:
    /// the slave's own, or 0 for a broadcast, whose answer the line never sends.
    fn handle(&mut self, address: u8, request: &[u8], at: Instant) -> Option<Transmission>;
}
