//! The master side of a line: one transaction at a time (`engine`) on whatever carries the bytes
//! (a serial port, a device server's or Modbus TCP device's socket, the simulated line, all behind
//! [`Transport`]), framed as the line is (`framing`: [`rtu`], `ascii`, or MBAP to a Modbus TCP
//! device), with the spec's timing (`timing`) and the PDU-level judgement of replies (`reply`);
//! several requests in flight on a Modbus TCP device (`pipeline`). Knows nothing of the masters'
//! side, queues or routing; what a frame looks like on the wire belongs to the framing alone.

pub(crate) mod ascii;
pub(crate) mod engine;
pub(crate) mod framing;
pub(crate) mod inbound;
pub(crate) mod listen;
pub(crate) mod pipeline;
pub(crate) mod reply;
pub mod rtu;
pub(crate) mod timing;

pub use engine::NoReply;
pub(crate) use engine::{Reply, TxError};

pub(crate) use engine::LineCounters;

pub(crate) use engine::{LineMaster, MasterTiming, Seen};
pub use framing::Framing;
pub(crate) use reply::ReplyForm;
#[cfg(test)]
pub(crate) use reply::Verdict;
pub use timing::{LineTiming, Parity, SerialFormat};

use std::future::Future;
use std::io;
use std::time::Duration;
use tokio::time::Instant;

/// The slave address that every slave obeys and none answers, in every serial framing.
pub(crate) const BROADCAST: u8 = 0;

/// The highest address of a slave on a serial line.
pub(crate) const MAX_SERIAL_ADDRESS: u8 = 247;

/// A byte pipe onto a line as a UART driver presents it, whatever carries it: a serial port, a
/// serial device server's socket or the simulated line. Which [`Framing`] may run over which kind of transport is the one
/// table behind `Framing::runs_over`.
pub trait Transport: Send {
    /// Hand a whole frame to the driver. Returns when the driver holds it, which is before the
    /// last byte has left the wire, unless the transport says otherwise in
    /// [`Transport::end_of_transmission`].
    fn send(&mut self, frame: &[u8]) -> impl Future<Output = io::Result<()>> + Send;

    /// When a frame whose `send` returned at `returned`, and which takes `frame_time` on the
    /// wire, is out and the line free for the reply: by default `frame_time` later. A port that
    /// switches the RS-485 transceiver itself returns once it has dropped its driver (then); the
    /// kernel's RS-485 mode adds its delays around the frame.
    fn end_of_transmission(&self, returned: Instant, frame_time: Duration) -> Instant {
        returned + frame_time
    }

    /// Wait for received bytes and append them to `buf`. `Ok(0)` means the port is gone (an
    /// unplugged adapter reads 0 bytes forever). Must be cancel-safe: a receive that is dropped
    /// before it completes loses no bytes.
    fn recv(&mut self, buf: &mut Vec<u8>) -> impl Future<Output = io::Result<usize>> + Send;

    /// Drop what the driver has received and not yet handed over, appending to `stale` what
    /// was dropped where the transport can know it (a socket; a serial port's flush cannot).
    fn clear_input(&mut self, stale: &mut Vec<u8>) -> io::Result<()>;
}
