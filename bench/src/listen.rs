//! The `listen-` scenarios: a listen-only line (`mode = "listen"`), the simulated 115200 8N1
//! line with [`SLAVES`] register slaves and its other master (`[bus.sim_master]`) reading
//! [`READS`] back to back (pause 0), the line as full as the physics allow; slave
//! [`VALUES_SLAVE`] lists the plant values, which follow the shadow. Once the shadow answers,
//! two windows of `--seconds`: the gateway only hearing, then with one Modbus TCP master reading
//! the shadow every [`SHADOW_PERIOD`] ([`SHADOW_READS`] in turn), as a busy SCADA would. Each
//! takes the gateway's `modbus_gateway_observed_*` counters at its ends (the other master's
//! transactions it heard and paired), its CPU and the shadow reads' latency; what the other
//! master made is the physics' count, which the simulated master keeps exactly. The figures
//! are `report`'s.

use crate::gateway::{cpu_time, rss_mb, Gateway};
use crate::masters::{Answer, Conn};
use crate::plant;
use crate::scenarios::Scenario;
use crate::watch::{sample, scrape};
use crate::Cli;
use modbus_gateway::testing::line::{Framing, LineTiming};
use std::fmt::Write as _;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use test_support::Bus;
use tokio::net::TcpStream;

/// Register slaves on the line, 1 up.
pub(crate) const SLAVES: u8 = 4;
/// The slave whose `[[bus.slave.value]]`s (the `values-` scenario's, in its input registers)
/// the gateway takes from the shadow.
pub(crate) const VALUES_SLAVE: u8 = 2;
/// How long the other master waits for a reply; none is late here.
const RESPONSE_TIMEOUT: &str = "100ms";
/// How often the shadow's master reads: 500 reads a second. Back to back, on a machine of two
/// CPUs, it and the gateway's session would take both, and the figures would be of that
/// contention rather than of the listen line.
pub(crate) const SHADOW_PERIOD: Duration = Duration::from_millis(2);
/// How long the shadow and the plant values may take to be filled after the start.
const FILL_LIMIT: Duration = Duration::from_secs(10);

/// One read of the other master: slave, table, first register, count.
pub(crate) struct Read {
    pub(crate) slave: u8,
    pub(crate) table: &'static str,
    pub(crate) register: u16,
    pub(crate) count: u16,
}

const fn read(slave: u8, table: &'static str, register: u16, count: u16) -> Read {
    Read {
        slave,
        table,
        register,
        count,
    }
}

/// What the other master reads, in turn: a mix of tables and sizes (7 to 125 bytes back), each
/// (slave, function) once, so that the gateway's counts by slave and function tell them apart.
/// Slave 2's block of 24 input registers from 200 holds its plant values.
pub(crate) const READS: [Read; 8] = [
    read(1, "holding", 0, 10),
    read(2, "input", 200, 24),
    read(3, "coil", 0, 16),
    read(4, "discrete", 0, 32),
    read(1, "input", 100, 2),
    read(2, "holding", 0, 60),
    read(3, "input", 300, 8),
    read(4, "holding", 10, 1),
];

/// The TCP master's reads, in turn, each of something the other master reads: slave 2's whole
/// block of plant values, and a subset of slave 1's holding registers 0-9.
pub(crate) const SHADOW_READS: [(u8, [u8; 5]); 2] = [
    (2, [0x04, 0x00, 0xC8, 0x00, 0x18]),
    (1, [0x03, 0x00, 0x02, 0x00, 0x05]),
];

impl Read {
    /// The function code that reads its table.
    pub(crate) fn function(&self) -> u8 {
        match self.table {
            "coil" => 0x01,
            "discrete" => 0x02,
            "input" => 0x04,
            _ => 0x03,
        }
    }

    /// Its reply's PDU: function, byte count, the data.
    fn reply_pdu(&self) -> usize {
        let data = match self.function() {
            0x01 | 0x02 => self.count.div_ceil(8),
            _ => 2 * self.count,
        };
        2 + usize::from(data)
    }

    /// The physical minimum of its transaction: request and reply on the wire, the slave's
    /// t3.5 (it answers at once) and the master's before the next.
    pub(crate) fn minimum(&self, timing: &LineTiming) -> Duration {
        Framing::Rtu.transaction_minimum(timing, 5, self.reply_pdu())
    }
}

/// One round of [`READS`] on a line of `timing`, back to back: what the other master takes.
pub(crate) fn round(timing: &LineTiming) -> Duration {
    READS.iter().map(|r| r.minimum(timing)).sum()
}

/// `bus` as the scenario's listen line: the mode, the other master, the register slaves and the
/// plant values of [`VALUES_SLAVE`].
pub(crate) fn line(bus: Bus) -> Bus {
    let mut toml =
        format!("[bus.sim_master]\npause = \"0s\"\nresponse_timeout = \"{RESPONSE_TIMEOUT}\"\n");
    for r in &READS {
        let _ = writeln!(
            toml,
            "[[bus.sim_master.read]]\nslave = {}\ntable = \"{}\"\nregister = {}\ncount = {}",
            r.slave, r.table, r.register, r.count
        );
    }
    toml.push_str(&plant::slave(VALUES_SLAVE));
    bus.key("mode", "listen")
        .text(&toml)
        .sim_slaves(&format!("1-{SLAVES}"))
}

/// The gateway's counts of what it heard, at one moment.
#[derive(Clone, Default)]
pub(crate) struct Observed {
    pub(crate) requests: f64,
    /// Replies that answered a request, exceptions among them.
    pub(crate) replies: f64,
    pub(crate) exceptions: f64,
    pub(crate) timeouts: f64,
    pub(crate) crc_errors: f64,
    pub(crate) discarded: f64,
    /// Replies by read of [`READS`].
    pub(crate) by_read: Vec<f64>,
}

impl Observed {
    fn of(page: &str) -> Observed {
        let total = |name: &str| sample(page, name, &[]);
        Observed {
            requests: total("modbus_gateway_observed_requests_total"),
            replies: total("modbus_gateway_observed_replies_total"),
            exceptions: sample(
                page,
                "modbus_gateway_observed_replies_total",
                &["outcome=\"exception\""],
            ),
            timeouts: total("modbus_gateway_observed_timeouts_total"),
            crc_errors: total("modbus_gateway_observed_crc_errors_total"),
            discarded: total("modbus_gateway_observed_discarded_total"),
            by_read: READS
                .iter()
                .map(|r| {
                    let slave = format!("slave=\"{}\"", r.slave);
                    let function = format!("function=\"0x{:02X}\"", r.function());
                    sample(
                        page,
                        "modbus_gateway_observed_replies_total",
                        &[&slave, &function],
                    )
                })
                .collect(),
        }
    }

    /// What was counted from `before` to this.
    fn since(&self, before: &Observed) -> Observed {
        Observed {
            requests: self.requests - before.requests,
            replies: self.replies - before.replies,
            exceptions: self.exceptions - before.exceptions,
            timeouts: self.timeouts - before.timeouts,
            crc_errors: self.crc_errors - before.crc_errors,
            discarded: self.discarded - before.discarded,
            by_read: self
                .by_read
                .iter()
                .zip(&before.by_read)
                .map(|(a, b)| a - b)
                .collect(),
        }
    }
}

/// One window: its length, the gateway's CPU time across it, what it heard, and the shadow
/// reads' latencies and exceptions (none in the window without the master).
pub(crate) struct Phase {
    pub(crate) wall: Duration,
    pub(crate) cpu: Duration,
    pub(crate) heard: Observed,
    pub(crate) shadow: Vec<Duration>,
    pub(crate) shadow_exceptions: u64,
}

/// What the scenario saw.
pub(crate) struct ListenWindow {
    pub(crate) timing: LineTiming,
    /// From the gateway listening until the shadow answered a read, and until every plant value
    /// had been read once (from the shadow), and how many values there are.
    pub(crate) shadowed: Duration,
    pub(crate) values_read: Duration,
    pub(crate) values: usize,
    pub(crate) hearing: Phase,
    pub(crate) reading: Phase,
    pub(crate) rss_mb: f64,
}

/// Run the scenario `s` on the gateway binary at `binary`.
pub(crate) async fn measure(
    cli: &Cli,
    binary: &std::path::Path,
    s: &Scenario,
) -> Result<ListenWindow, String> {
    let gateway = Gateway::start(binary, s, "sim", None).await?;
    let listening = Instant::now();
    let mut conn = connect(&gateway).await?;
    until_shadowed(&mut conn).await?;
    let shadowed = listening.elapsed();
    let values = plant::first_pass(gateway.metrics).await?;
    let values_read = listening.elapsed();
    let length = Duration::from_secs_f64(cli.seconds);
    let hearing = phase(&gateway, None, length).await?;
    let reading = phase(&gateway, Some(conn), length).await?;
    Ok(ListenWindow {
        timing: LineTiming::new(&s.format),
        shadowed,
        values_read,
        values,
        hearing,
        reading,
        rss_mb: rss_mb(gateway.pid()),
    })
}

async fn connect(gateway: &Gateway) -> Result<Conn, String> {
    let stream = TcpStream::connect(gateway.listen)
        .await
        .map_err(|e| format!("the shadow's master: connect: {e}"))?;
    stream.set_nodelay(true).map_err(|e| e.to_string())?;
    Ok(Conn::Tcp(stream))
}

/// Wait (at most [`FILL_LIMIT`]) until every one of [`SHADOW_READS`] is answered normally.
async fn until_shadowed(conn: &mut Conn) -> Result<(), String> {
    let started = Instant::now();
    let mut reply = vec![0u8; 512];
    for (tid, (slave, pdu)) in (1u16..).zip(SHADOW_READS.iter().cycle()) {
        let answer = conn
            .exchange(tid, *slave, pdu, &mut reply)
            .await
            .map_err(|e| format!("the shadow: {e}"))?;
        if answer == Answer::Normal && usize::from(tid) >= SHADOW_READS.len() {
            return Ok(());
        }
        if started.elapsed() > FILL_LIMIT {
            return Err(format!(
                "the shadow still answers {answer:?} after {FILL_LIMIT:?}"
            ));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    Ok(())
}

/// A window of `length`: the gateway's counters and CPU at its ends, with `conn` (if any)
/// reading the shadow meanwhile.
async fn phase(gateway: &Gateway, conn: Option<Conn>, length: Duration) -> Result<Phase, String> {
    let pid = gateway.pid();
    let stop = Arc::new(AtomicBool::new(false));
    let reader = conn.map(|conn| tokio::spawn(read_shadow(conn, stop.clone())));
    // The reader's first exchange under way before the window opens.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let before = Observed::of(&scrape(gateway.metrics).await?);
    let (start, cpu_start) = (Instant::now(), cpu_time(pid));
    tokio::time::sleep(length).await;
    let (end, cpu_end) = (Instant::now(), cpu_time(pid));
    let after = Observed::of(&scrape(gateway.metrics).await?);
    stop.store(true, Ordering::Relaxed);
    let (mut shadow, mut shadow_exceptions) = (Vec::new(), 0);
    if let Some(reader) = reader {
        let done = reader.await.map_err(|e| e.to_string())??;
        let within = |at: &Instant| (start..=end).contains(at);
        shadow = done
            .0
            .iter()
            .filter(|(at, _)| within(at))
            .map(|(_, d)| *d)
            .collect();
        shadow_exceptions = done.1.iter().filter(|at| within(at)).count() as u64;
    }
    Ok(Phase {
        wall: end - start,
        cpu: cpu_end - cpu_start,
        heard: after.since(&before),
        shadow,
        shadow_exceptions,
    })
}

/// Completed shadow reads (when, how long) and when an exception came, until `stop`.
type ShadowReads = (Vec<(Instant, Duration)>, Vec<Instant>);

/// Read [`SHADOW_READS`] in turn, one every [`SHADOW_PERIOD`], until `stop`.
async fn read_shadow(mut conn: Conn, stop: Arc<AtomicBool>) -> Result<ShadowReads, String> {
    let (mut done, mut exceptions) = (Vec::new(), Vec::new());
    let mut reply = vec![0u8; 512];
    let mut next = tokio::time::Instant::now();
    for (tid, (slave, pdu)) in (1u16..).zip(SHADOW_READS.iter().cycle()) {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        tokio::time::sleep_until(next).await;
        next += SHADOW_PERIOD;
        let sent = Instant::now();
        let answer = conn
            .exchange(tid, *slave, pdu, &mut reply)
            .await
            .map_err(|e| format!("the shadow's master: {e}"))?;
        let now = Instant::now();
        match answer {
            Answer::Normal => done.push((now, now - sent)),
            Answer::Exception => exceptions.push(now),
            Answer::Unexpected => {
                return Err(format!(
                    "the shadow's master: unexpected reply {:02X?}",
                    &reply[..16]
                ))
            }
        }
    }
    Ok((done, exceptions))
}

#[cfg(test)]
mod tests {
    use super::*;
    use modbus_gateway::config::BusMode;
    use modbus_gateway::testing::line::{Parity, SerialFormat};
    use test_support::GatewayConfig;

    #[test]
    fn the_listen_line_is_a_simulated_line_with_its_other_master_reading_every_block() {
        let config = GatewayConfig::new()
            .bus(line(Bus::sim("bench").baud(115_200).parity("none")))
            .load();
        let bus = &config.bus[0];
        assert_eq!(bus.mode, BusMode::Listen);
        let master = bus.sim_master.as_ref().expect("[bus.sim_master]");
        assert!(master.pause.is_zero());
        assert_eq!(master.read.len(), READS.len());
        for (heard, r) in master.read.iter().zip(&READS) {
            assert_eq!(
                (heard.slave, heard.register, heard.count),
                (r.slave, r.register, r.count)
            );
            assert_eq!(heard.table.function(), r.function());
        }
        let mut pairs: Vec<_> = READS.iter().map(|r| (r.slave, r.function())).collect();
        pairs.sort_unstable();
        pairs.dedup();
        assert_eq!(pairs.len(), READS.len(), "each (slave, function) once");
        assert_eq!(bus.slave.len(), 1);
        assert_eq!(
            bus.slave[0].value.len(),
            crate::scenarios::PLANT_VALUES.len()
        );
        // Every shadow read is within a block the other master reads.
        for (slave, pdu) in &SHADOW_READS {
            let first = u16::from_be_bytes([pdu[1], pdu[2]]);
            let count = u16::from_be_bytes([pdu[3], pdu[4]]);
            assert!(READS.iter().any(|r| r.slave == *slave
                && r.function() == pdu[0]
                && r.register <= first
                && first + count <= r.register + r.count));
        }
    }

    #[test]
    fn a_round_at_115200_is_its_bytes_at_the_character_time_and_two_t35_a_read() {
        let timing = LineTiming::new(&SerialFormat {
            baud: 115_200,
            data_bits: 8,
            parity: Parity::None,
            stop_bits: 1,
        });
        // 8 requests of 8 bytes; replies of 25, 53, 7, 9, 9, 125, 21 and 7 bytes.
        let bytes = 8 * 8 + 25 + 53 + 7 + 9 + 9 + 125 + 21 + 7;
        let expected = timing.frame_time(bytes) + 16 * timing.t35;
        assert_eq!(round(&timing), expected);
    }
}
