//! The live trace of the lines: every frame a bus task sends or receives, with its bus, direction
//! and the outcome of its transaction, handed to whoever watches (`GET /trace` on the metrics
//! endpoint, read by `modbus-gateway trace`). Off the hot path: with nobody watching, a bus task
//! pays one atomic load per transaction and the line engine records nothing. Readers are
//! bounded in number, and each in what it may fall behind: a slow reader loses events (and is
//! told how many), it never slows the line. Knows nothing of HTTP or of framing.

use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::SystemTime;
use tokio::sync::broadcast;

/// Readers at once; more are refused (the metrics endpoint answers 503).
pub const MAX_READERS: usize = 8;
/// Events a reader may fall behind before it loses the oldest.
const BACKLOG: usize = 1024;

/// Which way a frame went on the line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    /// Gateway to slave.
    Tx,
    /// Slave (or anything else on the line) to gateway; on a listen line, what paired with
    /// nothing.
    Rx,
    /// On a listen-only line: the other master's request, heard.
    Request,
    /// On a listen-only line: a slave's reply to it, heard.
    Reply,
}

/// The `outcome` of a frame that answered no request of the gateway's: another slave's reply, a
/// late reply to an earlier try.
pub(crate) const FOREIGN: &str = "foreign";

/// The `outcome` of bytes that came while no reply was awaited (between transactions, in the gap
/// before a frame, or left in a device server's socket): discarded.
pub(crate) const STALE: &str = "stale";

/// One frame on one line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TraceEvent {
    /// When the frame was handed to the port (tx) or was complete (rx).
    pub time: SystemTime,
    pub bus: Arc<str>,
    pub direction: Direction,
    /// The address byte (0: broadcast).
    pub slave: u8,
    /// The function code byte as on the wire (an exception has the high bit set).
    pub function: u8,
    /// The whole frame as on the wire: address, PDU and CRC (RTU), the ASCII frame's bytes, or
    /// header and PDU (MBAP, to a Modbus TCP device).
    pub bytes: Vec<u8>,
    /// The line's framing: `rtu`, `ascii` or `tcp`, which says how to read `bytes`.
    pub framing: &'static str,
    /// What became of the try the frame belongs to, as the metrics' `outcome` label says it;
    /// `FOREIGN` for a frame that answered nothing, `STALE` for bytes no reply was awaited for.
    pub outcome: &'static str,
}

/// An event as `GET /trace` sends it: the `data` of an SSE `frame` event.
#[derive(Serialize)]
struct Wire<'a> {
    time: String,
    bus: &'a str,
    direction: Direction,
    slave: u8,
    function: u8,
    hex: String,
    framing: &'a str,
    outcome: &'a str,
}

/// `bytes` as lowercase hex pairs separated by spaces: `01 03 00 00`.
pub(crate) fn hex(bytes: &[u8]) -> String {
    let mut text = String::with_capacity(bytes.len() * 3);
    for (i, byte) in bytes.iter().enumerate() {
        if i > 0 {
            text.push(' ');
        }
        let _ = write!(text, "{byte:02x}");
    }
    text
}

impl TraceEvent {
    /// The event in Server-Sent Events form: `event: frame`, one `data` line of JSON, a blank
    /// line.
    pub(crate) fn to_sse(&self) -> String {
        let wire = Wire {
            time: humantime::format_rfc3339_micros(self.time).to_string(),
            bus: &self.bus,
            direction: self.direction,
            slave: self.slave,
            function: self.function,
            hex: hex(&self.bytes),
            framing: self.framing,
            outcome: self.outcome,
        };
        // Strings, numbers and a unit enum: serialising cannot fail.
        let data = serde_json::to_string(&wire).unwrap_or_default();
        format!("event: frame\ndata: {data}\n\n")
    }
}

/// The SSE event that tells a reader it missed `lost` events.
pub(crate) fn lost_sse(lost: u64) -> String {
    format!("event: lost\ndata: {{\"lost\":{lost}}}\n\n")
}

/// Where the bus tasks publish their frames and the readers subscribe.
pub struct TraceHub {
    readers: AtomicUsize,
    sender: broadcast::Sender<Arc<TraceEvent>>,
    /// The buses that may publish, with how many tasks of each name run (a reload starts the new
    /// task of a bus before the old one has ended).
    buses: Mutex<BTreeMap<Arc<str>, usize>>,
    published: AtomicU64,
}

impl Default for TraceHub {
    fn default() -> Self {
        Self::new()
    }
}

impl TraceHub {
    pub fn new() -> Self {
        TraceHub {
            readers: AtomicUsize::new(0),
            sender: broadcast::channel(BACKLOG).0,
            buses: Mutex::new(BTreeMap::new()),
            published: AtomicU64::new(0),
        }
    }

    /// Whether anyone is watching: the one check a bus task makes per transaction.
    #[inline]
    pub(crate) fn active(&self) -> bool {
        self.readers.load(Ordering::Relaxed) != 0
    }

    /// Hand `event` to the readers, if there are any.
    pub(crate) fn publish(&self, event: TraceEvent) {
        if !self.active() {
            return;
        }
        self.published.fetch_add(1, Ordering::Relaxed);
        // No receiver left (the last reader went meanwhile): nobody misses it.
        let _ = self.sender.send(Arc::new(event));
    }

    #[cfg(any(test, feature = "test-util"))]
    /// Events published so far.
    pub fn published(&self) -> u64 {
        self.published.load(Ordering::Relaxed)
    }

    /// A new reader of the events published from now on, unless [`MAX_READERS`] are reading.
    pub fn subscribe(self: &Arc<Self>) -> Option<TraceReader> {
        self.readers
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < MAX_READERS).then_some(n + 1)
            })
            .ok()?;
        Some(TraceReader {
            receiver: self.sender.subscribe(),
            hub: self.clone(),
        })
    }

    /// Bus `name` publishes here while the returned tap lives.
    pub fn register(self: &Arc<Self>, name: Arc<str>) -> BusTap {
        *self
            .buses
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(name.clone())
            .or_default() += 1;
        BusTap {
            hub: self.clone(),
            bus: name,
        }
    }

    /// The names of the buses that publish here, sorted.
    pub fn buses(&self) -> Vec<String> {
        let buses = self.buses.lock().unwrap_or_else(PoisonError::into_inner);
        buses.keys().map(ToString::to_string).collect()
    }
}

/// A bus's place in the hub: publishes its frames, and keeps its name known while it lives.
pub struct BusTap {
    hub: Arc<TraceHub>,
    bus: Arc<str>,
}

impl BusTap {
    pub fn hub(&self) -> &TraceHub {
        &self.hub
    }

    pub fn bus(&self) -> &Arc<str> {
        &self.bus
    }
}

impl Drop for BusTap {
    fn drop(&mut self) {
        let mut buses = self
            .hub
            .buses
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if let Some(count) = buses.get_mut(&self.bus) {
            *count -= 1;
            if *count == 0 {
                buses.remove(&self.bus);
            }
        }
    }
}

/// What a reader gets next.
#[derive(Debug)]
pub enum Traced {
    Frame(Arc<TraceEvent>),
    /// The reader fell behind: this many events are lost to it.
    Lost(u64),
}

/// One reader of the trace; counted by the hub until dropped.
pub struct TraceReader {
    hub: Arc<TraceHub>,
    receiver: broadcast::Receiver<Arc<TraceEvent>>,
}

impl TraceReader {
    /// The next event, or how many were lost before it. Cancel-safe.
    pub async fn next(&mut self) -> Traced {
        match self.receiver.recv().await {
            Ok(event) => Traced::Frame(event),
            Err(broadcast::error::RecvError::Lagged(lost)) => Traced::Lost(lost),
            // The hub holds the sender for as long as any reader holds the hub.
            Err(broadcast::error::RecvError::Closed) => std::future::pending().await,
        }
    }
}

impl Drop for TraceReader {
    fn drop(&mut self) {
        self.hub.readers.fetch_sub(1, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn event(bus: &Arc<str>, slave: u8) -> TraceEvent {
        TraceEvent {
            // 2026-11-23T14:00:00.123456Z
            time: SystemTime::UNIX_EPOCH + Duration::from_micros(1_795_442_400_123_456),
            bus: bus.clone(),
            direction: Direction::Tx,
            slave,
            function: 3,
            bytes: vec![0x01, 0x03, 0x00, 0x00, 0x00, 0x02, 0xc4, 0x0b],
            framing: "rtu",
            outcome: "ok",
        }
    }

    #[test]
    fn a_frame_is_one_sse_event_of_json_with_the_wire_bytes_in_lowercase_hex() {
        let bus: Arc<str> = "line1".into();
        assert_eq!(
            event(&bus, 1).to_sse(),
            "event: frame\ndata: {\"time\":\"2026-11-23T14:00:00.123456Z\",\"bus\":\"line1\",\
             \"direction\":\"tx\",\"slave\":1,\"function\":3,\
             \"hex\":\"01 03 00 00 00 02 c4 0b\",\"framing\":\"rtu\",\"outcome\":\"ok\"}\n\n"
        );
        assert_eq!(lost_sse(17), "event: lost\ndata: {\"lost\":17}\n\n");
    }

    #[test]
    fn with_no_reader_nothing_is_published() {
        let hub = Arc::new(TraceHub::new());
        let bus: Arc<str> = "line1".into();
        assert!(!hub.active());
        hub.publish(event(&bus, 1));
        assert_eq!(hub.published(), 0);
        let reader = hub.subscribe().unwrap();
        assert!(hub.active());
        hub.publish(event(&bus, 1));
        assert_eq!(hub.published(), 1);
        drop(reader);
        assert!(!hub.active(), "a reader that goes is no longer counted");
    }

    #[test]
    fn readers_beyond_the_limit_are_refused() {
        let hub = Arc::new(TraceHub::new());
        let readers: Vec<_> = (0..MAX_READERS).map(|_| hub.subscribe().unwrap()).collect();
        assert!(hub.subscribe().is_none());
        drop(readers);
        assert!(hub.subscribe().is_some());
    }

    #[tokio::test]
    async fn a_reader_that_fell_behind_is_told_how_many_events_it_lost() {
        let hub = Arc::new(TraceHub::new());
        let bus: Arc<str> = "line1".into();
        let mut reader = hub.subscribe().unwrap();
        for _ in 0..BACKLOG + 17 {
            hub.publish(event(&bus, 1));
        }
        assert!(matches!(reader.next().await, Traced::Lost(17)));
        assert!(matches!(reader.next().await, Traced::Frame(_)));
    }

    #[test]
    fn a_bus_is_known_while_one_of_its_taps_lives() {
        let hub = Arc::new(TraceHub::new());
        let old = hub.register("line1".into());
        let new = hub.register("line1".into());
        let _other = hub.register("line0".into());
        assert_eq!(hub.buses(), ["line0", "line1"]);
        drop(old);
        assert_eq!(hub.buses(), ["line0", "line1"]);
        drop(new);
        assert_eq!(hub.buses(), ["line0"]);
    }
}
