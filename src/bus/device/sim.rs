//! The simulated line as a bus's transport: what the bus's [`Device`](super::Device) asks of it.
//! The line, its slaves and its master port ([`SimPort`](crate::sim::SimPort), which is the
//! [`Transport`](crate::line::Transport)) are the simulator's; this knows nothing of them but
//! that a line opens like a serial device, or to listen (a port that only hears), and is one line
//! however many handles name it.

use super::Port;
use crate::sim::SimLine;
use std::io;

/// Open the master's port on `line`; an older port on it goes dead, as on a reopened adapter.
pub(super) fn open(line: &SimLine) -> io::Result<Port> {
    line.open().map(Port::Sim)
}

/// Open `line`'s adapter to listen: a port that hears every frame and never sends.
pub(super) fn open_listening(line: &SimLine) -> io::Result<Port> {
    line.open_listening().map(Port::Sim)
}

/// Whether `line` and `other` are handles on one simulated line.
pub(super) fn same_as(line: &SimLine, other: &SimLine) -> bool {
    line.same_line(other)
}
