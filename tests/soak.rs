//! The soak test: 100 masters over real TCP on one simulated line with healthy and faulty slaves,
//! for `MBGW_SOAK_SECONDS` (default 100) after a warm-up, while the line's adapter vanishes twice
//! and masters disconnect with requests in flight. Afterwards: every request got exactly one reply
//! (data or exception) or its connection was closed; no reply crossed masters or transaction ids;
//! no write went out on the wire twice; the heap is back at its warm level; `/metrics` agrees with
//! what the masters saw; nothing panicked.
//!
//! Ignored by plain `cargo test` (it takes minutes); `.ci/run` runs it in release with
//! `cargo test --release --test soak -- --ignored --nocapture`.
//!
//! How a crossed reply shows: each master owns registers `128 m ..= 128 m + 3` on every slave.
//! Register 0 holds the count of its single-register writes (FC 06) to that slave, registers 1-3
//! the last multiple-register write (FC 10): its tag `0x8000 | m`, its count, and the count
//! XOR 0x5A5A. A read of them must show this master's tag and counts no older than its last
//! acknowledged write and no newer than its last one sent. Reads of the late-replying slave ask
//! for `4 + m` registers, so a late reply to one master's read never fits another master's.

// Test code may be long and cast freely; the workspace lint table is for the product.
#![allow(
    unreachable_pub,
    // The counting allocator is an `unsafe impl GlobalAlloc` (each fn with its SAFETY comment).
    unsafe_code,
    clippy::too_many_lines,
    clippy::cast_possible_truncation,
    // Deadlines on daemons run as processes, which no paused clock reaches, and tokio's own
    // sleeps: src/timer.rs's choice of precision is the product's.
    clippy::disallowed_types,
    clippy::disallowed_methods
)]

use modbus_gateway::testing::sim::{SimLine, Source};
use modbus_gateway::Gateway;
use std::alloc::{GlobalAlloc, Layout, System};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Once, PoisonError};
use std::time::Duration;
use test_support::{wait_for_bus, Bus, GatewayConfig, Scrape};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::{timeout, Instant};

/// Bytes allocated and not yet freed, over the whole process.
static LIVE_BYTES: AtomicUsize = AtomicUsize::new(0);

/// The system allocator, counting live bytes.
struct Counting;

// SAFETY: every call is passed on to `System` unchanged; only a counter is kept beside it.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let ptr = System.alloc(layout);
        if !ptr.is_null() {
            LIVE_BYTES.fetch_add(layout.size(), Ordering::Relaxed);
        }
        ptr
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let ptr = System.alloc_zeroed(layout);
        if !ptr.is_null() {
            LIVE_BYTES.fetch_add(layout.size(), Ordering::Relaxed);
        }
        ptr
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        LIVE_BYTES.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let moved = System.realloc(ptr, layout, new_size);
        if !moved.is_null() {
            LIVE_BYTES.fetch_add(new_size, Ordering::Relaxed);
            LIVE_BYTES.fetch_sub(layout.size(), Ordering::Relaxed);
        }
        moved
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

static PANICS: AtomicUsize = AtomicUsize::new(0);
static COUNT_PANICS: Once = Once::new();

/// Count every panic on any thread: tokio turns a panicking task into a closed connection, which
/// this test would otherwise take for a master's own disconnect.
fn count_panics() {
    COUNT_PANICS.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            PANICS.fetch_add(1, Ordering::Relaxed);
            previous(info);
        }));
    });
}

const MASTERS: usize = 100;
/// Soak length without `MBGW_SOAK_SECONDS`: a little over two minutes in all, in release.
const DEFAULT_SOAK: Duration = Duration::from_secs(100);
/// The mixed round of the warm-up, after every master has written all its registers.
const WARM_MIXED: Duration = Duration::from_secs(8);
/// How long the adapter stays unplugged, each of the two times.
const UNPLUGGED_FOR: Duration = Duration::from_secs(3);
/// A request must be answered within this; far beyond the queue timeout plus a transaction.
const REPLY_PATIENCE: Duration = Duration::from_secs(15);
/// Anything else the test waits for (connect, the gateway noticing a close, the bus idling).
const PATIENCE: Duration = Duration::from_secs(20);
/// Wire frames are collected this often; the line remembers its last 4096, over 10 s of traffic.
const WIRE_POLL: Duration = Duration::from_millis(100);
/// The heap may end this far above its warm level, plus [`HEAP_PER_SERIES`] for each metric
/// series first made during the soak. See `heap_is_back_at_its_warm_level`. Measured in release
/// on 2 cores (issue 27), before and after that changes alike: after 100 s the heap had
/// grown 21-51 kB (seven runs, 24-33 new series each), after 200 s 36 kB: the growth does not
/// scale with the soak's length, so it is pools sized by the peak number of connections and
/// requests at once (the runtime's slab pages, hash tables), which never shrink and which a
/// longer soak reaches more often than the warm-up; 16 KiB of slack failed one run in three.
const HEAP_SLACK: usize = 64 * 1024;
/// A new metric series costs about 600 bytes (measured: 30 new series, 18 kB).
const HEAP_PER_SERIES: usize = 1024;
const PIPELINE_DEPTH: usize = 4;

const HEALTHY: [u8; 3] = [1, 2, 3];
const OFFLINE: u8 = 10;
const CRC_ERRORS: u8 = 11;
const GARBAGE_BEFORE: u8 = 12;
const GARBAGE_AFTER: u8 = 13;
const LATE: u8 = 14;
const WRONG_ADDRESS: u8 = 15;
const SLOW: u8 = 16;
const FAULTY: [u8; 7] = [
    OFFLINE,
    CRC_ERRORS,
    GARBAGE_BEFORE,
    GARBAGE_AFTER,
    LATE,
    WRONG_ADDRESS,
    SLOW,
];
/// Every slave, in the order of the per-slave tables below.
const SLAVES: [u8; 10] = [1, 2, 3, 10, 11, 12, 13, 14, 15, 16];
/// Slaves that carry out writes, so the warm-up can create every register. Writes also go to the
/// offline slave (whose timeout must not make the gateway send them again), to the slaves with
/// unreadable replies, and to the late one: its late echo of one master's write must never pass
/// for the answer to another's (the gateway's late-reply window).
const WRITTEN: [u8; 9] = [
    1,
    2,
    3,
    OFFLINE,
    CRC_ERRORS,
    GARBAGE_BEFORE,
    GARBAGE_AFTER,
    LATE,
    SLOW,
];

fn config() -> GatewayConfig {
    let mut soak = Bus::sim("soak")
        .baud(115_200)
        .parity("none")
        .key("stop_bits", 1)
        .response_timeout("50ms")
        .retries(1)
        .queue_depth(512)
        .queue_timeout("3s")
        .key("reopen_delay", "100ms")
        .key("reopen_delay_max", "400ms")
        .sim_slaves("1-3");
    for (address, knob) in [
        (OFFLINE, ("offline", true.into())),
        (CRC_ERRORS, ("crc_error_rate", 0.3.into())),
        (GARBAGE_BEFORE, ("garbage_before", 3.into())),
        (GARBAGE_AFTER, ("garbage_after", 5.into())),
        (LATE, ("late_reply", "80ms".into())),
        (WRONG_ADDRESS, ("reply_address", 1.into())),
        (SLOW, ("extra_delay", "20ms".into())),
    ] {
        soak = soak.sim_slave(&address.to_string(), &[knob]);
    }
    GatewayConfig::new()
        .pipeline_depth(PIPELINE_DEPTH)
        .bus(soak)
}

fn slave_index(slave: u8) -> usize {
    SLAVES
        .iter()
        .position(|&s| s == slave)
        .expect("a soak slave")
}

fn base(master: usize) -> u16 {
    (master * 128) as u16
}

fn tag(master: usize) -> u16 {
    0x8000 | master as u16
}

/// What the masters saw, all together.
#[derive(Default)]
struct Tally {
    sent: AtomicU64,
    /// Normal replies, each checked.
    data: AtomicU64,
    /// Exceptions the slaves made (to the deliberately illegal reads).
    slave_exceptions: AtomicU64,
    port_down_0a: AtomicU64,
    no_response_0b: AtomicU64,
    busy_06: AtomicU64,
    /// Requests still unanswered when their master closed the connection.
    closed_pending: AtomicU64,
    connections: AtomicU64,
    abrupt_closes: AtomicU64,
    orderly_closes: AtomicU64,
    /// Connections the gateway closed while requests were outstanding: never expected here.
    closed_by_gateway: AtomicU64,
    writes_acknowledged: AtomicU64,
    failures: Mutex<Vec<String>>,
}

impl Tally {
    fn add(counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Ordering::Relaxed);
    }

    fn get(counter: &AtomicU64) -> u64 {
        counter.load(Ordering::Relaxed)
    }

    fn replies(&self) -> u64 {
        Self::get(&self.data)
            + Self::get(&self.slave_exceptions)
            + Self::get(&self.port_down_0a)
            + Self::get(&self.no_response_0b)
            + Self::get(&self.busy_06)
    }

    fn fail(&self, what: String) {
        let mut failures = self.failures.lock().unwrap_or_else(PoisonError::into_inner);
        if failures.len() < 20 {
            failures.push(what);
        }
    }

    fn failures(&self) -> Vec<String> {
        self.failures
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

/// One master's knowledge of its registers on one slave.
#[derive(Clone, Copy, Default)]
struct Registers {
    /// Writes sent (FC 06, FC 10); each write carries its count.
    sent_06: u16,
    sent_10: u16,
    /// Highest count acknowledged by the slave's echo.
    acked_06: u16,
    acked_10: u16,
    /// Lowest count of a write left in flight by an abrupt close: the gateway may still carry it
    /// out after later ones, from the closed connection's queue, until it notices the close.
    limbo_06: Option<u16>,
    limbo_10: Option<u16>,
}

impl Registers {
    fn floor_06(&self) -> u16 {
        self.limbo_06
            .map_or(self.acked_06, |l| l.min(self.acked_06))
    }

    fn floor_10(&self) -> u16 {
        self.limbo_10
            .map_or(self.acked_10, |l| l.min(self.acked_10))
    }
}

#[derive(Clone, Copy, Debug)]
enum Ask {
    /// Read `quantity` registers from the master's base; the counts it may show.
    Read {
        quantity: u16,
        range_06: (u16, u16),
        range_10: (u16, u16),
    },
    /// 126 registers: more than a read may ask for, so the slave answers exception 03.
    IllegalRead,
    Write06 {
        count: u16,
    },
    Write10 {
        count: u16,
    },
}

#[derive(Clone, Copy, Debug)]
struct Pending {
    transaction: u16,
    slave: u8,
    ask: Ask,
}

impl Pending {
    fn pdu(&self, master: usize, out: &mut Vec<u8>) {
        let start = base(master);
        out.clear();
        match self.ask {
            Ask::Read { quantity, .. } => {
                out.push(0x03);
                out.extend_from_slice(&start.to_be_bytes());
                out.extend_from_slice(&quantity.to_be_bytes());
            }
            Ask::IllegalRead => {
                out.push(0x03);
                out.extend_from_slice(&start.to_be_bytes());
                out.extend_from_slice(&126u16.to_be_bytes());
            }
            Ask::Write06 { count } => {
                out.push(0x06);
                out.extend_from_slice(&start.to_be_bytes());
                out.extend_from_slice(&count.to_be_bytes());
            }
            Ask::Write10 { count } => {
                out.push(0x10);
                out.extend_from_slice(&(start + 1).to_be_bytes());
                out.extend_from_slice(&[0, 3, 6]);
                for word in [tag(master), count, count ^ 0x5A5A] {
                    out.extend_from_slice(&word.to_be_bytes());
                }
            }
        }
    }

    fn function(&self) -> u8 {
        match self.ask {
            Ask::Read { .. } | Ask::IllegalRead => 0x03,
            Ask::Write06 { .. } => 0x06,
            Ask::Write10 { .. } => 0x10,
        }
    }
}

/// How a master leaves a connection.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Leave {
    /// Half-close, take the replies that still come, wait for the gateway to close: its session
    /// has then forgotten whatever was still queued.
    Orderly,
    /// Drop the socket with requests in flight.
    Abrupt,
}

/// A master's side of the test: its registers, its random choices, its expectations.
struct Master {
    id: usize,
    rng: fastrand::Rng,
    registers: [Registers; SLAVES.len()],
    /// A 0x0A came since the last pause.
    port_down: bool,
    tally: Arc<Tally>,
}

/// Read one MBAP reply into `pdu`: `Ok(None)` if the gateway closed the connection.
async fn read_reply(
    stream: &mut TcpStream,
    pdu: &mut [u8; 256],
) -> Result<Option<(u16, u8, usize)>, String> {
    let mut header = [0u8; 7];
    match timeout(REPLY_PATIENCE, stream.read_exact(&mut header)).await {
        Err(_) => return Err(format!("no reply within {REPLY_PATIENCE:?}")),
        Ok(Err(_)) => return Ok(None),
        Ok(Ok(_)) => {}
    }
    let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
    if header[2..4] != [0, 0] || !(2..=254).contains(&length) {
        return Err(format!("bad MBAP header {header:02X?}"));
    }
    let body = &mut pdu[..length - 1];
    match timeout(REPLY_PATIENCE, stream.read_exact(body)).await {
        Err(_) => Err("reply body never came".to_owned()),
        Ok(Err(_)) => Ok(None),
        Ok(Ok(_)) => Ok(Some((
            u16::from_be_bytes([header[0], header[1]]),
            header[6],
            length - 1,
        ))),
    }
}

fn word(pdu: &[u8], index: usize) -> u16 {
    u16::from_be_bytes([pdu[2 + 2 * index], pdu[3 + 2 * index]])
}

impl Master {
    fn new(id: usize, tally: Arc<Tally>) -> Self {
        Master {
            id,
            rng: fastrand::Rng::with_seed(id as u64),
            registers: [Registers::default(); SLAVES.len()],
            port_down: false,
            tally,
        }
    }

    fn read(&self, slave: u8) -> Ask {
        let r = &self.registers[slave_index(slave)];
        // The same form from every master, the late slave included: a late reply to one master's
        // read would fit another's.
        Ask::Read {
            quantity: 4,
            range_06: (r.floor_06(), r.sent_06),
            range_10: (r.floor_10(), r.sent_10),
        }
    }

    fn write06(&mut self, slave: u8) -> Ask {
        let r = &mut self.registers[slave_index(slave)];
        r.sent_06 = r.sent_06.checked_add(1).expect("fewer than 65536 writes");
        Ask::Write06 { count: r.sent_06 }
    }

    fn write10(&mut self, slave: u8) -> Ask {
        let r = &mut self.registers[slave_index(slave)];
        r.sent_10 = r.sent_10.checked_add(1).expect("fewer than 65536 writes");
        Ask::Write10 { count: r.sent_10 }
    }

    /// The soak's mix: mostly healthy slaves, one request in eight to a faulty one; half reads.
    fn next_request(&mut self) -> (u8, Ask) {
        let slave = if self.rng.u8(..100) < 88 {
            HEALTHY[self.rng.usize(..HEALTHY.len())]
        } else {
            FAULTY[self.rng.usize(..FAULTY.len())]
        };
        let roll = self.rng.u8(..100);
        let ask = match roll {
            _ if !WRITTEN.contains(&slave) => self.read(slave),
            0..50 => self.read(slave),
            50..70 => self.write06(slave),
            70..97 => self.write10(slave),
            _ => Ask::IllegalRead,
        };
        (slave, ask)
    }

    /// Check `reply` against the request it must answer; a mismatch is a crossed reply.
    fn check(&mut self, pending: &Pending, transaction: u16, unit: u8, pdu: &[u8]) -> bool {
        let m = self.id;
        let tally = self.tally.clone();
        let fail = |what: String| {
            tally.fail(format!(
                "master {m}, slave {}, {:?}: {what}",
                pending.slave, pending.ask
            ));
            false
        };
        if (transaction, unit) != (pending.transaction, pending.slave) {
            return fail(format!(
                "reply for transaction {transaction} unit {unit}, expected {} unit {}",
                pending.transaction, pending.slave
            ));
        }
        let function = pending.function();
        if pdu.len() == 2 && pdu[0] == function | 0x80 {
            let counter = match (pdu[1], pending.ask) {
                (0x0A, _) => {
                    self.port_down = true;
                    &self.tally.port_down_0a
                }
                (0x0B, _) => &self.tally.no_response_0b,
                (0x06, _) => &self.tally.busy_06,
                (0x03, Ask::IllegalRead) => &self.tally.slave_exceptions,
                (code, _) => return fail(format!("unexpected exception {code:#04X}")),
            };
            Tally::add(counter, 1);
            return true;
        }
        let mut expected = Vec::new();
        pending.pdu(m, &mut expected);
        let ok = match pending.ask {
            Ask::IllegalRead => return fail(format!("data {pdu:02X?} to an illegal read")),
            Ask::Write06 { count } => {
                let ok = pdu == expected.as_slice();
                let r = &mut self.registers[slave_index(pending.slave)];
                r.acked_06 = r.acked_06.max(count);
                ok
            }
            Ask::Write10 { count } => {
                let ok = pdu == &expected[..5];
                let r = &mut self.registers[slave_index(pending.slave)];
                r.acked_10 = r.acked_10.max(count);
                ok
            }
            Ask::Read {
                quantity,
                range_06,
                range_10,
            } => {
                let bytes = usize::from(quantity) * 2;
                if pdu.len() != 2 + bytes || pdu[..2] != [0x03, bytes as u8] {
                    false
                } else {
                    let in_range = |v: u16, (low, high): (u16, u16)| low <= v && v <= high;
                    let (r0, r1, r2, r3) = (word(pdu, 0), word(pdu, 1), word(pdu, 2), word(pdu, 3));
                    let tenth_unwritten = (r1, r2, r3) == (0, 0, 0) && range_10.0 == 0;
                    let tenth = tenth_unwritten
                        || (r1 == tag(m) && r3 == r2 ^ 0x5A5A && in_range(r2, range_10));
                    let rest_zero = (4..usize::from(quantity)).all(|i| word(pdu, i) == 0);
                    in_range(r0, range_06) && tenth && rest_zero
                }
            }
        };
        if !ok {
            let shown = &pdu[..pdu.len().min(12)];
            return fail(format!(
                "reply of {} bytes {shown:02X?} does not answer {expected:02X?}",
                pdu.len()
            ));
        }
        if matches!(pending.ask, Ask::Write06 { .. } | Ask::Write10 { .. }) {
            Tally::add(&self.tally.writes_acknowledged, 1);
        }
        Tally::add(&self.tally.data, 1);
        true
    }

    async fn connect(&self, at: SocketAddr) -> Option<TcpStream> {
        match timeout(PATIENCE, TcpStream::connect(at)).await {
            Ok(Ok(stream)) => {
                Tally::add(&self.tally.connections, 1);
                Some(stream)
            }
            _ => {
                self.tally
                    .fail(format!("master {}: cannot connect", self.id));
                None
            }
        }
    }

    /// Send `asks` pipelined on `stream`; the requests now outstanding.
    async fn send(
        &self,
        stream: &mut TcpStream,
        transaction: &mut u16,
        asks: &[(u8, Ask)],
        pending: &mut Vec<Pending>,
    ) -> bool {
        let mut bytes = Vec::with_capacity(64 * asks.len());
        let mut pdu = Vec::with_capacity(16);
        for &(slave, ask) in asks {
            *transaction = transaction.wrapping_add(1);
            let request = Pending {
                transaction: *transaction,
                slave,
                ask,
            };
            request.pdu(self.id, &mut pdu);
            bytes.extend_from_slice(&transaction.to_be_bytes());
            bytes.extend_from_slice(&[0, 0]);
            bytes.extend_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
            bytes.push(slave);
            bytes.extend_from_slice(&pdu);
            pending.push(request);
        }
        Tally::add(&self.tally.sent, asks.len() as u64);
        if stream.write_all(&bytes).await.is_err() {
            self.tally
                .fail(format!("master {}: the gateway refused a request", self.id));
            return false;
        }
        true
    }

    /// Take one reply for every request in `pending`, in order.
    async fn answers(&mut self, stream: &mut TcpStream, pending: &mut Vec<Pending>) -> bool {
        let mut pdu = [0u8; 256];
        for i in 0..pending.len() {
            match read_reply(stream, &mut pdu).await {
                Ok(Some((transaction, unit, len))) => {
                    if !self.check(&pending[i], transaction, unit, &pdu[..len]) {
                        return false;
                    }
                }
                Ok(None) => {
                    Tally::add(&self.tally.closed_by_gateway, 1);
                    self.tally.fail(format!(
                        "master {}: the gateway closed the connection with {} requests unanswered",
                        self.id,
                        pending.len() - i
                    ));
                    return false;
                }
                Err(what) => {
                    self.tally.fail(format!("master {}: {what}", self.id));
                    return false;
                }
            }
        }
        pending.clear();
        true
    }

    /// Leave the connection with `pending` requests unanswered, one way or the other.
    async fn leave(&mut self, mut stream: TcpStream, pending: &mut Vec<Pending>, how: Leave) {
        if how == Leave::Abrupt {
            for request in pending.iter() {
                let r = &mut self.registers[slave_index(request.slave)];
                match request.ask {
                    Ask::Write06 { count } => {
                        r.limbo_06 = Some(r.limbo_06.map_or(count, |l| l.min(count)))
                    }
                    Ask::Write10 { count } => {
                        r.limbo_10 = Some(r.limbo_10.map_or(count, |l| l.min(count)))
                    }
                    _ => {}
                }
            }
            Tally::add(&self.tally.abrupt_closes, 1);
            Tally::add(&self.tally.closed_pending, pending.len() as u64);
            pending.clear();
            return;
        }
        Tally::add(&self.tally.orderly_closes, 1);
        if stream.shutdown().await.is_err() {
            self.tally
                .fail(format!("master {}: cannot half-close", self.id));
            return;
        }
        // Replies written before the gateway saw the close still come; then nothing more.
        let mut pdu = [0u8; 256];
        let mut answered = 0;
        loop {
            match read_reply(&mut stream, &mut pdu).await {
                Ok(Some((transaction, unit, len))) => {
                    let Some(request) = pending.get(answered).copied() else {
                        self.tally.fail(format!(
                            "master {}: a reply (transaction {transaction}) with nothing outstanding",
                            self.id
                        ));
                        return;
                    };
                    if !self.check(&request, transaction, unit, &pdu[..len]) {
                        return;
                    }
                    answered += 1;
                }
                Ok(None) => break,
                Err(what) => {
                    self.tally
                        .fail(format!("master {}: after half-close: {what}", self.id));
                    return;
                }
            }
        }
        Tally::add(
            &self.tally.closed_pending,
            (pending.len() - answered) as u64,
        );
        pending.clear();
    }

    /// Write every register this master owns on the slaves that carry writes out, so the slaves'
    /// register maps are complete before the heap is measured.
    async fn write_everything(&mut self, at: SocketAddr) {
        let Some(mut stream) = self.connect(at).await else {
            return;
        };
        let mut transaction = self.rng.u16(..);
        let mut pending = Vec::with_capacity(PIPELINE_DEPTH);
        let carried_out: Vec<u8> = WRITTEN.into_iter().filter(|&s| s != OFFLINE).collect();
        for pair in carried_out.chunks(PIPELINE_DEPTH / 2) {
            let mut asks = Vec::with_capacity(PIPELINE_DEPTH);
            for &slave in pair {
                asks.push((slave, self.write10(slave)));
                asks.push((slave, self.write06(slave)));
            }
            if !self
                .send(&mut stream, &mut transaction, &asks, &mut pending)
                .await
                || !self.answers(&mut stream, &mut pending).await
            {
                return;
            }
        }
        self.leave(stream, &mut pending, Leave::Orderly).await;
    }

    /// The mix until `until`: batches of up to the pipeline depth, a short pause between them,
    /// and now and then a close with requests in flight and a new connection.
    async fn run(&mut self, at: SocketAddr, until: Instant) {
        let mut pending = Vec::with_capacity(PIPELINE_DEPTH);
        let mut asks = Vec::with_capacity(PIPELINE_DEPTH);
        while Instant::now() < until {
            let Some(mut stream) = self.connect(at).await else {
                return;
            };
            let mut transaction = self.rng.u16(..);
            loop {
                asks.clear();
                for _ in 0..self.rng.usize(1..=PIPELINE_DEPTH) {
                    let ask = self.next_request();
                    asks.push(ask);
                }
                if !self
                    .send(&mut stream, &mut transaction, &asks, &mut pending)
                    .await
                {
                    return;
                }
                let leave = match self.rng.u8(..200) {
                    0 => Some(Leave::Abrupt),
                    1 => Some(Leave::Orderly),
                    _ => None,
                };
                if let Some(how) = leave {
                    self.leave(stream, &mut pending, how).await;
                    break;
                }
                if !self.answers(&mut stream, &mut pending).await {
                    return;
                }
                if Instant::now() >= until {
                    self.leave(stream, &mut pending, Leave::Orderly).await;
                    return;
                }
                // Like a SCADA poll cycle: a short pause, a longer one while the port is down.
                let pause = if std::mem::take(&mut self.port_down) {
                    self.rng.u64(100..200)
                } else {
                    self.rng.u64(0..50)
                };
                tokio::time::sleep(Duration::from_millis(pause)).await;
            }
        }
    }
}

/// The write frames the gateway put on the wire, each counted once: a frame seen twice is a write
/// that went out twice.
struct WireWrites {
    /// One bit per (master, slave, function, count).
    seen: Vec<u64>,
    /// Start of the last master frame taken in; frames start strictly later one after another.
    last_start: Option<Instant>,
    master_frames: u64,
    writes: u64,
    duplicates: Vec<String>,
    strangers: Vec<String>,
}

impl WireWrites {
    fn new() -> Self {
        WireWrites {
            seen: vec![0; MASTERS * SLAVES.len() * 2 * 65536 / 64],
            last_start: None,
            master_frames: 0,
            writes: 0,
            duplicates: Vec::new(),
            strangers: Vec::new(),
        }
    }

    fn take(&mut self, line: &SimLine) {
        let frames = line.frames();
        for frame in frames.iter().filter(|f| f.from == Source::Master) {
            if self.last_start.is_some_and(|last| frame.start <= last) {
                continue;
            }
            self.last_start = Some(frame.start);
            self.master_frames += 1;
            let bytes = &frame.bytes;
            let function = bytes[1];
            if function != 0x06 && function != 0x10 {
                continue;
            }
            self.writes += 1;
            let register = u16::from_be_bytes([bytes[2], bytes[3]]);
            let (master, offset) = (usize::from(register / 128), register % 128);
            let (kind, count) = match function {
                0x06 if offset == 0 && bytes.len() == 8 => {
                    (0, u16::from_be_bytes([bytes[4], bytes[5]]))
                }
                0x10 if offset == 1 && bytes.len() == 15 => {
                    (1, u16::from_be_bytes([bytes[9], bytes[10]]))
                }
                _ => {
                    self.strangers.push(format!("{bytes:02X?}"));
                    continue;
                }
            };
            let Some(slave) = SLAVES.iter().position(|&s| s == bytes[0]) else {
                self.strangers.push(format!("{bytes:02X?}"));
                continue;
            };
            if master >= MASTERS {
                self.strangers.push(format!("{bytes:02X?}"));
                continue;
            }
            let bit = ((master * SLAVES.len() + slave) * 2 + kind) * 65536 + usize::from(count);
            let (word, mask) = (bit / 64, 1u64 << (bit % 64));
            if self.seen[word] & mask != 0 {
                if self.duplicates.len() < 20 {
                    self.duplicates.push(format!("{bytes:02X?}"));
                }
            } else {
                self.seen[word] |= mask;
            }
        }
    }
}

/// Collect wire frames every [`WIRE_POLL`] until aborted.
fn watch_wire(line: SimLine, wire: Arc<Mutex<WireWrites>>) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        loop {
            wire.lock()
                .unwrap_or_else(PoisonError::into_inner)
                .take(&line);
            tokio::time::sleep(WIRE_POLL).await;
        }
    })
}

async fn stop_watching(watcher: tokio::task::JoinHandle<()>) {
    watcher.abort();
    let _ = watcher.await;
}

/// Run every master to `until`, or through the register-writing round if `until` is `None`.
async fn run_masters(at: SocketAddr, masters: &mut Vec<Master>, until: Option<Instant>) {
    let mut running = tokio::task::JoinSet::new();
    for mut master in masters.drain(..) {
        running.spawn(async move {
            match until {
                Some(until) => master.run(at, until).await,
                None => master.write_everything(at).await,
            }
            master
        });
    }
    while let Some(done) = running.join_next().await {
        masters.push(done.expect("a master task ends without panicking"));
    }
    masters.sort_by_key(|m| m.id);
}

/// Wait until no master is connected and the line has been quiet for a while.
async fn idle(gateway: &Gateway, line: &SimLine) {
    let waited = timeout(PATIENCE, async {
        loop {
            let frames = line.stats().master_frames;
            tokio::time::sleep(Duration::from_millis(300)).await;
            let quiet = line.stats().master_frames == frames;
            if quiet && gateway.status().starts_with("0 masters connected") {
                return;
            }
        }
    })
    .await;
    assert!(
        waited.is_ok(),
        "the gateway never went idle: {}",
        gateway.status()
    );
}

/// Pull the line's adapter, and plug it back `unplugged_for` after the bus noticed.
async fn vanish(gateway: &Gateway, line: &SimLine, unplugged_for: Duration) {
    line.unplug();
    wait_for_bus(gateway, "soak", false).await;
    tokio::time::sleep(unplugged_for).await;
    line.plug();
    wait_for_bus(gateway, "soak", true).await;
}

fn series(scrape: &Scrape) -> usize {
    let samples = scrape.text.lines();
    samples
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .count()
}

fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|status| {
            let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
            line.split_whitespace().nth(1)?.parse().ok()
        })
        .unwrap_or(0)
}

/// Live heap bytes, less what the line's monitor holds in frame bytes: its last 4096 frames
/// differ in length from one moment to the next, and it is the test's instrument, not the
/// gateway's state. Taken while nothing runs.
fn heap(line: &SimLine) -> (usize, usize) {
    let live = LIVE_BYTES.load(Ordering::Relaxed);
    let monitor: usize = line.frames().iter().map(|f| f.bytes.len()).sum();
    (live, live.saturating_sub(monitor))
}

/// The sum of every series of `name` whose labels contain all of `labels`, grown since `before`.
fn grown(after: &Scrape, before: &Scrape, name: &str, labels: &[&str]) -> u64 {
    after
        .series_of(name)
        .into_iter()
        .filter(|(series, _)| labels.iter().all(|l| series.contains(l)))
        .map(|(series, _)| after.delta(before, series))
        .sum::<f64>() as u64
}

fn soak_length() -> Duration {
    std::env::var("MBGW_SOAK_SECONDS")
        .ok()
        .map(|s| {
            let secs: u64 = s
                .parse()
                .unwrap_or_else(|_| panic!("MBGW_SOAK_SECONDS={s:?} is not a whole number"));
            Duration::from_secs(secs)
        })
        .unwrap_or(DEFAULT_SOAK)
}

/// Faulty slaves and a vanishing port.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a soak of minutes: cargo test --release --test soak -- --ignored --nocapture"]
async fn a_hundred_masters_on_faulty_slaves_get_one_answer_each_and_leak_nothing() {
    count_panics();
    let soak = soak_length();
    let began = std::time::Instant::now();
    println!("soak: {MASTERS} masters, {soak:?} after the warm-up");
    // As the daemon does: the line keeps its timing to well under a millisecond.
    modbus_gateway::testing::timer::use_precise_timer();
    let gateway = config().start().await;
    let at = test_support::addr(&gateway);
    let line = gateway.sim_line("soak").expect("a simulated line");
    let wire = Arc::new(Mutex::new(WireWrites::new()));
    let watcher = watch_wire(line.clone(), wire.clone());

    // Warm-up: every register written, then the mix with a short outage of the port, so every
    // pool and metric series the soak needs exists before the heap is measured.
    let warm_tally = Arc::new(Tally::default());
    let mut masters: Vec<Master> = (0..MASTERS)
        .map(|id| Master::new(id, warm_tally.clone()))
        .collect();
    run_masters(at, &mut masters, None).await;
    let warm_vanish = async {
        tokio::time::sleep(WARM_MIXED / 3).await;
        vanish(&gateway, &line, WARM_MIXED / 8).await;
    };
    let ((), ()) = tokio::join!(
        run_masters(at, &mut masters, Some(Instant::now() + WARM_MIXED)),
        warm_vanish
    );
    assert_eq!(
        warm_tally.failures(),
        Vec::<String>::new(),
        "in the warm-up"
    );
    idle(&gateway, &line).await;
    let before = Scrape::of(&gateway).await;
    // Whatever the soak keeps until the end is made before the heap is measured.
    let tally = Arc::new(Tally::default());
    let unplugs = Arc::new(AtomicUsize::new(0));
    stop_watching(watcher).await;
    let (warm_live, warm_heap) = heap(&line);
    let warm_rss = rss_kib();
    let warmed_in = began.elapsed();
    let warm_frames = line.stats().master_frames;

    // The soak.
    for master in &mut masters {
        master.tally = tally.clone();
    }
    let watcher = watch_wire(line.clone(), wire.clone());
    let soak_start = Instant::now();
    let until = soak_start + soak;
    let chaos = {
        let (line, unplugs) = (line.clone(), unplugs.clone());
        let gateway = &gateway;
        async move {
            for at in [soak * 3 / 10, soak * 13 / 20] {
                tokio::time::sleep_until(soak_start + at).await;
                unplugs.fetch_add(1, Ordering::Relaxed);
                vanish(gateway, &line, UNPLUGGED_FOR).await;
            }
        }
    };
    let ((), ()) = tokio::join!(run_masters(at, &mut masters, Some(until)), chaos);
    let soaked_for = soak_start.elapsed();
    idle(&gateway, &line).await;
    stop_watching(watcher).await;
    let (end_live, end_heap) = heap(&line);
    let end_rss = rss_kib();
    println!(
        "soak: warm after {warmed_in:.0?}: {warm_frames} master frames, heap {warm_live} B \
         ({warm_heap} B without the line monitor's frames), RSS {warm_rss} KiB"
    );
    let after = Scrape::of(&gateway).await;
    let mut wire = wire.lock().unwrap_or_else(PoisonError::into_inner);
    wire.take(&line);
    let stats = line.stats();

    let requests = grown(&after, &before, "modbus_gateway_requests_total", &[]);
    let gateway_exceptions = |code: &str| {
        let code = format!("code=\"{code}\"");
        grown(
            &after,
            &before,
            "modbus_gateway_exceptions_total",
            &[&code, "source=\"gateway\""],
        )
    };
    let outcome = |fate: &str| {
        let fate = format!("outcome=\"{fate}\"");
        grown(&after, &before, "modbus_gateway_requests_total", &[&fate])
    };
    let get = Tally::get;
    println!(
        "soak: {soaked_for:.1?} of soak, {:.0?} in all\n\
         soak: masters sent {} requests on {} connections ({} closed abruptly, {} in order, \
         with {} requests still pending)\n\
         soak: replies: {} data ({} writes acknowledged), {} slave exceptions, {} x 0x0A, \
         {} x 0x0B, {} x 0x06\n\
         soak: the gateway counted {requests} requests: {} ok, {} timeout, {} crc_error, \
         {} frame_error, {} port_down, {} expired, {} queue_full, {} dropped\n\
         soak: the wire carried {} master frames, {} writes; {} collisions, {} gap violations\n\
         soak: adapter unplugged {} times\n\
         soak: heap {warm_live} -> {end_live} B, {warm_heap} -> {end_heap} B without the \
         monitor's frames ({:+} B); RSS {warm_rss} -> {end_rss} KiB; {} -> {} metric series",
        began.elapsed(),
        get(&tally.sent),
        get(&tally.connections),
        get(&tally.abrupt_closes),
        get(&tally.orderly_closes),
        get(&tally.closed_pending),
        get(&tally.data),
        get(&tally.writes_acknowledged),
        get(&tally.slave_exceptions),
        get(&tally.port_down_0a),
        get(&tally.no_response_0b),
        get(&tally.busy_06),
        outcome("ok"),
        outcome("timeout"),
        outcome("crc_error"),
        outcome("frame_error"),
        outcome("port_down"),
        outcome("expired"),
        outcome("queue_full"),
        outcome("dropped"),
        stats.master_frames,
        wire.writes,
        stats.collisions,
        stats.gap_violations,
        unplugs.load(Ordering::Relaxed),
        end_heap as i64 - warm_heap as i64,
        series(&before),
        series(&after),
    );

    // Every request one reply, in order, to its own master, or its connection closed.
    assert_eq!(tally.failures(), Vec::<String>::new());
    assert_eq!(get(&tally.closed_by_gateway), 0);
    assert_eq!(
        get(&tally.sent),
        tally.replies() + get(&tally.closed_pending),
        "every request was answered or its connection closed by its master"
    );
    assert_eq!(PANICS.load(Ordering::Relaxed), 0, "something panicked");
    assert!(
        gateway.stalled_buses().is_empty(),
        "{:?}",
        gateway.stalled_buses()
    );

    // No write twice on the wire, and every frame the line carried was looked at.
    assert_eq!(wire.duplicates, Vec::<String>::new(), "writes sent twice");
    assert_eq!(
        wire.strangers,
        Vec::<String>::new(),
        "writes nobody asked for"
    );
    assert_eq!(
        wire.master_frames, stats.master_frames,
        "the line's log overflowed between two looks: poll more often"
    );

    // The faults and the vanishing port did happen, and were answered as such.
    assert_eq!(unplugs.load(Ordering::Relaxed), 2);
    assert!(get(&tally.port_down_0a) > 0 && outcome("port_down") > 0);
    assert!(get(&tally.no_response_0b) > 0 && outcome("timeout") > 0);
    assert!(get(&tally.data) > 0 && get(&tally.closed_pending) > 0);

    // /metrics tells the same story: each request it counted was answered, or was outstanding
    // when its master left (then the master never saw the answer).
    let pending = get(&tally.closed_pending);
    let within = |seen: u64, counted: u64, what: &str| {
        assert!(
            seen <= counted && counted <= seen + pending,
            "{what}: masters saw {seen}, the gateway counted {counted}, {pending} left pending"
        );
    };
    within(tally.replies(), requests, "requests");
    within(get(&tally.port_down_0a), gateway_exceptions("0x0A"), "0x0A");
    within(
        get(&tally.no_response_0b),
        gateway_exceptions("0x0B"),
        "0x0B",
    );
    within(get(&tally.busy_06), gateway_exceptions("0x06"), "0x06");
    within(
        get(&tally.data) + get(&tally.slave_exceptions),
        outcome("ok") + outcome("exception"),
        "answers from slaves",
    );
    assert!(outcome("dropped") <= pending);
    assert_eq!(
        after.value("modbus_gateway_tcp_connections{protocol=\"tcp\"}"),
        0.0
    );

    // The heap is back at its warm level.
    let new_series = series(&after).saturating_sub(series(&before));
    heap_is_back_at_its_warm_level(warm_heap, end_heap, new_series);
}

/// What the gateway may rightly make during the soak and keep: the metric series of (slave,
/// function, outcome) combinations the warm-up happened not to produce (rare ones such as a CRC
/// error on a healthy slave, when a late reply collides with its answer), bounded by the labels'
/// cardinality; and slack for pools that grow with the peak load ([`HEAP_SLACK`]). A leak of 4
/// bytes per request (tens of thousands) or of 450 per connection (hundreds) is beyond it.
fn heap_is_back_at_its_warm_level(warm: usize, end: usize, new_series: usize) {
    let allowed = HEAP_SLACK + new_series * HEAP_PER_SERIES;
    assert!(
        end <= warm + allowed,
        "heap grew from {warm} to {end} B, more than the {allowed} B allowed \
         ({new_series} new metric series)"
    );
}
