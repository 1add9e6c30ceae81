//! What the line master counts and records of the line for metrics and the trace: its byte and
//! frame counters, and the frames it saw with what each was to it.

use std::time::SystemTime;

/// What went over the line, and what the master saw there that was not an answer; cumulative,
/// for metrics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LineCounters {
    /// Bytes of every frame the master sent.
    pub(crate) sent_bytes: u64,
    /// Every byte read from the line: replies, other frames, noise.
    pub(crate) received_bytes: u64,
    /// Intact frames that answered nothing: other slaves' replies, late replies.
    pub(crate) foreign_frames: u64,
    /// Bytes received while no reply was awaited.
    pub(crate) stray_bytes: u64,
}

impl LineCounters {
    /// What was counted after `earlier`.
    pub fn since(&self, earlier: &LineCounters) -> LineCounters {
        LineCounters {
            sent_bytes: self.sent_bytes - earlier.sent_bytes,
            received_bytes: self.received_bytes - earlier.received_bytes,
            foreign_frames: self.foreign_frames - earlier.foreign_frames,
            stray_bytes: self.stray_bytes - earlier.stray_bytes,
        }
    }
}

/// What a frame recorded for the trace was to the master.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Seen {
    /// A request (or broadcast) the master sent.
    Sent,
    /// The frame that ended a try: its answer, a malformed reply, a frame that failed its check
    /// or was incomplete.
    Reply,
    /// A whole frame that answered nothing: another slave's, a late reply to an earlier try.
    Foreign,
    /// Bytes that came while no reply was awaited (between transactions, in the gap before a
    /// frame, or left in a socket), discarded as they came.
    Stale,
}

/// A frame on the wire, as recorded while [`LineMaster::record_frames`] is on.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct RecordedFrame {
    /// When it was handed to the port, or was complete.
    pub at: SystemTime,
    pub seen: Seen,
    /// The address and function code it carries (0 where its bytes do not reach them).
    pub address: u8,
    pub function: u8,
    /// The whole frame as on the wire.
    pub bytes: Vec<u8>,
}

impl RecordedFrame {
    pub(super) fn new(seen: Seen, address: u8, function: u8, bytes: &[u8]) -> Self {
        RecordedFrame {
            at: SystemTime::now(),
            seen,
            address,
            function,
            bytes: bytes.to_vec(),
        }
    }
}
