//! The RTU master of one serial line: CRC and frames ([`frame`]), the spec's timing ([`timing`]),
//! and one transaction at a time on whatever carries the bytes ([`master`]), a serial port or the
//! simulated line, both behind [`Transport`]. Knows nothing of TCP, masters, queues or routing.

pub mod frame;
pub mod master;
pub mod timing;

pub use master::{LineCounters, MasterTiming, Reply, RtuMaster, TxError};
pub use timing::{LineTiming, Parity, SerialFormat};

use std::future::Future;
use std::io;

/// A byte pipe onto an RS-485 line as a UART driver presents it.
pub trait Transport: Send {
    /// Hand a whole frame to the driver. Returns when the driver holds it, which is before the
    /// last byte has left the wire.
    fn send(&mut self, frame: &[u8]) -> impl Future<Output = io::Result<()>> + Send;

    /// Wait for received bytes and append them to `buf`. `Ok(0)` means the port is gone (an
    /// unplugged adapter reads 0 bytes forever). Must be cancel-safe: a receive that is dropped
    /// before it completes loses no bytes.
    fn recv(&mut self, buf: &mut Vec<u8>) -> impl Future<Output = io::Result<usize>> + Send;

    /// Drop what the driver has received and not yet handed over.
    fn clear_input(&mut self) -> io::Result<()>;
}
