//! The audit journal of writes (`[audit]`) as an operator relies on it: the gateway killed with
//! `kill -9` in a burst of writes leaves an entry for every write its slave carried out; a full
//! file system (a tmpfs filled up, or `/dev/full`) refuses writes (0x0A) or lets them go on
//! unrecorded, as `on_error` says, while reads go on, and the journal says what it missed once
//! it can be written again; a file system full at start does not keep the gateway down, but a
//! journal that cannot be opened stops the start; rotation keeps `keep` files of at most
//! `max_size` bytes of whole lines.
//!
//! The journal is read here as JSON lines, not through the product's types: a line that does not
//! parse as a JSON object is a broken journal, whatever the product thinks of it.
//!
//! The full file system is a small tmpfs mounted for the test (root only): without the right to
//! mount, those tests check nothing and say so, or fail under `MBGW_REQUIRE_TOOLS=1`.

use crate::simulate::Simulator;
use crate::support::{
    addr, connect_when_listening, free_addr, rtu, within, Bus, GatewayConfig, Scrape, TempDir,
    Value,
};
use modbus_gateway::Gateway;
use serde_json::Value as Json;
use std::collections::{BTreeMap, BTreeSet};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_modbus::client::{tcp, Context, Reader, Writer};
use tokio_modbus::{ExceptionCode, Slave};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// The register-bank slave every test writes to.
const SLAVE: u8 = 1;
/// How often a condition is looked at again while a test waits for it.
const POLL: Duration = Duration::from_millis(5);

const REFUSED: &str = "modbus_gateway_audit_refused_writes_total";
const UNRECORDED: &str = "modbus_gateway_audit_unrecorded_writes_total";
const WRITE_ERRORS: &str = "modbus_gateway_audit_errors_total{operation=\"write\"}";
const WRITABLE: &str = "modbus_gateway_audit_journal_writable";
const BYTES: &str = "modbus_gateway_audit_journal_bytes";
const REFUSED_BY_THE_GATEWAY: &str =
    "modbus_gateway_writes_total{action=\"allow\",outcome=\"gateway_exception\",protocol=\"tcp\"}";

/// A child process, killed (if it still runs) on drop: a failed test leaves no gateway behind.
struct Process(std::process::Child);

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A tmpfs of `size` mounted on a folder of its own, unmounted (lazily, if the gateway of a
/// failed test still holds a file there) and removed on drop.
struct Tmpfs(PathBuf);

impl Tmpfs {
    /// `None` (having said why) where this process may not mount, unless `MBGW_REQUIRE_TOOLS`
    /// is set, where that fails the test.
    fn mount(name: &str, size: &str) -> Option<Tmpfs> {
        let dir = std::env::temp_dir().join(format!("mbgw-tmpfs-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("a mount point");
        let mounted = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(&dir)
            .stderr(Stdio::piped())
            .output();
        let refused = match mounted {
            Ok(out) if out.status.success() => return Some(Tmpfs(dir)),
            Ok(out) => String::from_utf8_lossy(&out.stderr).trim().to_owned(),
            Err(e) => format!("mount does not run: {e}"),
        };
        let _ = std::fs::remove_dir(&dir);
        assert!(
            std::env::var_os("MBGW_REQUIRE_TOOLS").is_none(),
            "a tmpfs is required (MBGW_REQUIRE_TOOLS is set) but cannot be mounted: {refused}"
        );
        eprintln!("cannot mount a tmpfs ({refused}): this test checks nothing here");
        None
    }

    fn join(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }

    /// Fill what is left of it with `path`, until the file system refuses more.
    fn fill(&self, path: &Path) {
        let mut filler = std::fs::File::create(path).expect("the filler file");
        let block = [0x55u8; 4096];
        loop {
            match filler.write(&block) {
                Ok(0) | Err(_) => break,
                Ok(_) => {}
            }
        }
        assert!(
            filler.write(&[0x55]).is_err(),
            "the file system is full: the filler takes no byte more"
        );
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let unmounted = Command::new("umount")
            .arg(&self.0)
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if !unmounted {
            let _ = Command::new("umount").arg("-l").arg(&self.0).status();
        }
        let _ = std::fs::remove_dir(&self.0);
    }
}

/// Every line of the journal at `path`, each of which must be a whole JSON object: the file
/// ends with a newline and no line is cut short.
fn journal_lines(path: &Path) -> Vec<Json> {
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("read the journal {}: {e}", path.display()));
    assert!(
        text.is_empty() || text.ends_with('\n'),
        "{} ends in the middle of a line: {text}",
        path.display()
    );
    text.lines()
        .map(|line| {
            let entry: Json = serde_json::from_str(line).unwrap_or_else(|e| {
                panic!("{}: not a whole JSON line ({e}): {line:?}", path.display())
            });
            assert!(entry["kind"].is_string(), "no kind: {line}");
            entry
        })
        .collect()
}

fn kind(entry: &Json) -> &str {
    entry["kind"].as_str().unwrap_or_default()
}

fn of_kind<'a>(entries: &'a [Json], wanted: &str) -> Vec<&'a Json> {
    entries.iter().filter(|e| kind(e) == wanted).collect()
}

/// The `write` line of a write of `value` to register `register` of [`SLAVE`] with function 06.
fn write_line(entries: &[Json], register: u16, value: u16) -> Option<&Json> {
    let values = format!("{value:04X}");
    of_kind(entries, "write").into_iter().find(|w| {
        w["function"] == 6
            && w["slave"] == SLAVE
            && w["table"] == "holding"
            && w["start"] == register
            && w["values"] == values.as_str()
    })
}

/// The `[audit]` table: the journal at `path`, writes doing `on_error` when it cannot be written,
/// and `more` keys.
fn audit_table(path: &Path, on_error: &str, more: Vec<(&'static str, Value)>) -> GatewayConfig {
    let path = path.to_str().expect("a UTF-8 path");
    let mut keys = vec![("path", Value::from(path)), ("on_error", on_error.into())];
    keys.extend(more);
    GatewayConfig::new().table("audit", &keys)
}

/// A gateway on the simulated line (115200 8N2, register slave [`SLAVE`]) journaling to `path`.
async fn journaled_sim(path: &Path, on_error: &str, more: Vec<(&'static str, Value)>) -> Gateway {
    audit_table(path, on_error, more)
        .bus(
            Bus::sim("sim")
                .baud(115_200)
                .parity("none")
                .sim_slaves(&SLAVE.to_string()),
        )
        .start()
        .await
}

async fn master(gateway: &Gateway) -> Context {
    within("connect", tcp::connect_slave(addr(gateway), Slave(SLAVE)))
        .await
        .expect("the gateway accepts")
}

/// Write `value` to `register`: the slave's answer, or the exception the master got.
async fn write(ctx: &mut Context, register: u16, value: u16) -> Result<(), ExceptionCode> {
    within(
        "a write's answer",
        ctx.write_single_register(register, value),
    )
    .await
    .expect("an answer on the connection")
}

async fn read(ctx: &mut Context, register: u16) -> u16 {
    let words = within("a read's answer", ctx.read_holding_registers(register, 1))
        .await
        .expect("an answer on the connection")
        .unwrap_or_else(|e| panic!("a read of register {register} is served: {e:?}"));
    words[0]
}

/// The value of every holding register from `start`, `count` of them, read from slave [`SLAVE`]
/// of a `simulate --listen` line at `addr` with raw RTU frames. The line takes one client at a
/// time and may still be serving one that has just died: a connection closed or silent is tried
/// again until the line answers.
async fn read_over_rtu(addr: &str, start: u16, count: u16) -> Vec<u16> {
    let mut request = vec![0x03];
    request.extend_from_slice(&start.to_be_bytes());
    request.extend_from_slice(&count.to_be_bytes());
    let frame = rtu(SLAVE, &request);
    // Address, function, byte count, the words, CRC.
    let mut reply = vec![0u8; 5 + 2 * usize::from(count)];
    within("the simulated line answers a read", async {
        loop {
            let answered = async {
                let mut stream = TcpStream::connect(addr).await?;
                stream.write_all(&frame).await?;
                stream.read_exact(&mut reply).await?;
                std::io::Result::Ok(())
            };
            // A bound on one try, not a claim about timing: the next try starts over.
            if let Ok(Ok(())) = tokio::time::timeout(Duration::from_secs(2), answered).await {
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    assert!(
        modbus_gateway::testing::line::rtu::crc_ok(&reply),
        "{reply:02X?}"
    );
    assert_eq!(reply[..3], [SLAVE, 0x03, (2 * count) as u8], "{reply:02X?}");
    reply[3..reply.len() - 2]
        .chunks(2)
        .map(|w| u16::from_be_bytes([w[0], w[1]]))
        .collect()
}

/// Masters writing at once in the kill test; each has one write outstanding at a time.
const MASTERS: u16 = 4;
/// Writes each master may make; registers `0x100 * m ..` are master `m`'s.
const PER_MASTER: u16 = 0x100;
/// Writes answered before the gateway is killed.
const ANSWERED_BEFORE_KILL: usize = 40;

/// Master `m`'s `k`th write: its register and its value, both found nowhere else.
fn burst_write(m: u16, k: u16) -> (u16, u16) {
    (PER_MASTER * m + k, 0x1000 * (m + 1) + k + 1)
}

/// Every write the slave carried out before a kill -9 has its write line.
#[tokio::test]
async fn every_write_carried_out_before_a_kill_9_has_its_line_in_the_journal() {
    let dir = TempDir::new("audit-kill");
    // The line outlives the gateway: `simulate --listen` serves it in a process of its own. The
    // slave carries a write out as it hears it and answers 20 ms later, so a kill most likely
    // finds one carried out and not yet answered.
    let line = Bus::sim("line")
        .baud(115_200)
        .parity("none")
        .sim_slave(&SLAVE.to_string(), &[("processing_delay", "20ms".into())]);
    let sim_config = dir.join("sim.toml");
    std::fs::write(&sim_config, GatewayConfig::new().bus(line).to_toml()).unwrap();
    let simulator =
        Simulator::listen_with(sim_config.to_str().unwrap(), "127.0.0.1:0", "115200 baud").await;
    let sim_addr = simulator
        .path
        .strip_prefix("tcp://")
        .expect("simulate announces tcp://ADDR")
        .to_owned();

    let journal = dir.join("writes.jsonl");
    let listen = free_addr();
    let config = audit_table(&journal, "deny_writes", vec![])
        .listen(listen)
        .metrics_listen(free_addr())
        .bus(
            Bus::on("line", &simulator.path)
                .baud(115_200)
                .parity("none")
                .response_timeout("1s"),
        )
        .to_toml();
    let gateway_config = dir.join("gateway.toml");
    std::fs::write(&gateway_config, config).unwrap();
    let mut gateway = Process(
        Command::new(BINARY)
            .args(["--config", gateway_config.to_str().unwrap(), "run"])
            .env_remove("RUST_LOG")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("gateway.log")).unwrap())
            .spawn()
            .expect("the gateway runs"),
    );
    drop(connect_when_listening(listen).await);

    let answered = Arc::new(AtomicUsize::new(0));
    let masters: Vec<_> = (0..MASTERS)
        .map(|m| {
            let answered = answered.clone();
            let log = dir.join("gateway.log");
            tokio::spawn(async move {
                let mut ctx = tcp::connect_slave(listen, Slave(SLAVE))
                    .await
                    .expect("the gateway accepts");
                // The writes this master saw answered; the loop ends when the gateway dies.
                let mut done = Vec::new();
                for k in 0..PER_MASTER {
                    let (register, value) = burst_write(m, k);
                    match ctx.write_single_register(register, value).await {
                        Ok(Ok(())) => {
                            done.push((register, value));
                            answered.fetch_add(1, Ordering::SeqCst);
                        }
                        Ok(Err(e)) => panic!(
                            "write {register}={value} refused: {e:?}; the gateway's log:\n{}",
                            std::fs::read_to_string(&log).unwrap_or_default()
                        ),
                        Err(_) => break,
                    }
                }
                done
            })
        })
        .collect();
    within("writes are answered", async {
        while answered.load(Ordering::SeqCst) < ANSWERED_BEFORE_KILL {
            tokio::time::sleep(POLL).await;
        }
    })
    .await;
    // SIGKILL, with every master's next write on its way.
    gateway.0.kill().expect("kill -9 the gateway");
    let _ = gateway.0.wait();
    let mut confirmed = Vec::new();
    for master in masters {
        confirmed.extend(within("a master stops", master).await.expect("a master"));
    }
    assert!(confirmed.len() >= ANSWERED_BEFORE_KILL);

    let entries = journal_lines(&journal);
    assert_eq!(kind(&entries[0]), "open", "a run begins with its open line");
    let outcomes: BTreeMap<u64, &Json> = of_kind(&entries, "outcome")
        .into_iter()
        .map(|o| (o["id"].as_u64().expect("an id"), o))
        .collect();

    // What the slave holds now, straight from the line.
    let mut held = BTreeMap::new();
    for m in 0..MASTERS {
        let first = PER_MASTER * m;
        let mut words = Vec::new();
        for (start, count) in [(first, 125), (first + 125, 125), (first + 250, 6)] {
            words.extend(read_over_rtu(&sim_addr, start, count).await);
        }
        for (k, word) in (0..PER_MASTER).zip(words) {
            if word != 0 {
                assert_eq!(
                    (first + k, word),
                    burst_write(m, k),
                    "a register holds only the value its master wrote"
                );
                held.insert(first + k, word);
            }
        }
    }
    for (register, value) in &confirmed {
        assert_eq!(
            held.get(register),
            Some(value),
            "an answered write is carried out"
        );
        let line = write_line(&entries, *register, *value)
            .unwrap_or_else(|| panic!("no write line for answered {register}={value:04X}"));
        let id = line["id"].as_u64().unwrap();
        assert_eq!(
            outcomes.get(&id).map(|o| &o["outcome"]),
            Some(&Json::from("answered")),
            "an answered write's outcome is written before its answer goes back"
        );
    }
    for (register, value) in &held {
        assert!(
            write_line(&entries, *register, *value).is_some(),
            "register {register} holds {value:04X}, carried out by the slave, but the journal \
             has no write line for it"
        );
    }
    let writes = of_kind(&entries, "write");
    let unended: Vec<u64> = writes
        .iter()
        .map(|w| w["id"].as_u64().unwrap())
        .filter(|id| !outcomes.contains_key(id))
        .collect();
    // Those are the "may have been carried out" ones: queued or on the line when it died.
    eprintln!(
        "{} writes journaled, {} answered to their masters, {} carried out ({} of them \
         unanswered); {} without an outcome line (ids {unended:?})",
        writes.len(),
        confirmed.len(),
        held.len(),
        held.len() - confirmed.len(),
        unended.len()
    );
    assert!(
        unended.len() <= usize::from(MASTERS),
        "only writes in flight (one a master) lack an outcome: {unended:?}"
    );
    simulator.stop().await;
}

/// A full file system; the gap is journaled after there is room again.
#[tokio::test]
async fn a_full_disk_refuses_writes_with_0x0a_serves_reads_and_journals_the_gap() {
    let Some(tmpfs) = Tmpfs::mount("deny", "64k") else {
        return;
    };
    let journal = tmpfs.join("writes.jsonl");
    let gateway = journaled_sim(&journal, "deny_writes", vec![]).await;
    let mut ctx = master(&gateway).await;
    write(&mut ctx, 1, 0x0101).await.expect("a write before");
    tmpfs.fill(&tmpfs.join("filler"));

    // The journal's last page may still take a few lines: the writes that fit are answered.
    let mut answered = Vec::new();
    let mut refused = Vec::new();
    for k in 0..64 {
        let (register, value) = (100 + k, 0x2000 + k);
        match write(&mut ctx, register, value).await {
            Ok(()) => answered.push((register, value)),
            Err(ExceptionCode::GatewayPathUnavailable) => {
                refused.push((register, value));
                break;
            }
            Err(e) => panic!("write {register}: {e:?}"),
        }
    }
    assert_eq!(
        refused.len(),
        1,
        "a write is refused once the journal is full"
    );
    for k in 1..=5 {
        let (register, value) = (200 + k, 0x3000 + k);
        assert_eq!(
            write(&mut ctx, register, value).await,
            Err(ExceptionCode::GatewayPathUnavailable),
            "every write is refused while the journal cannot be written"
        );
        refused.push((register, value));
    }
    // Reads go on, and what was refused never reached the slave.
    assert_eq!(read(&mut ctx, 1).await, 0x0101);
    for (register, value) in &answered {
        assert_eq!(read(&mut ctx, *register).await, *value);
    }
    for (register, _) in &refused {
        assert_eq!(read(&mut ctx, *register).await, 0, "refused, not sent");
    }
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(REFUSED), refused.len() as f64);
    assert_eq!(scrape.value(REFUSED_BY_THE_GATEWAY), refused.len() as f64);
    assert_eq!(scrape.value(UNRECORDED), 0.0);
    assert_eq!(scrape.value(WRITABLE), 0.0);
    assert!(scrape.value(WRITE_ERRORS) >= refused.len() as f64);
    let full = journal_lines(&journal);
    for (register, value) in &refused {
        assert!(write_line(&full, *register, *value).is_none());
    }

    std::fs::remove_file(tmpfs.join("filler")).unwrap();
    write(&mut ctx, 300, 0x4000)
        .await
        .expect("writes go on once the journal can be written");
    assert_eq!(read(&mut ctx, 300).await, 0x4000);
    let entries = journal_lines(&journal);
    let at = entries
        .iter()
        .position(|e| kind(e) == "gap")
        .unwrap_or_else(|| panic!("a gap line: {entries:#?}"));
    let gap = &entries[at];
    assert_eq!(gap["refused"], refused.len(), "{gap}");
    assert_eq!(gap["unrecorded"], 0, "{gap}");
    assert!(
        gap["error"].as_str().is_some_and(|e| !e.is_empty()),
        "{gap}"
    );
    assert_eq!(
        Some(&entries[at + 1]),
        write_line(&entries, 300, 0x4000),
        "the gap comes right before the first entry written again"
    );
    assert_eq!(of_kind(&entries, "gap").len(), 1);
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(WRITABLE), 1.0);
    assert_eq!(scrape.value(REFUSED), refused.len() as f64);
    drop(ctx);
    gateway.shutdown().await;
}

#[tokio::test]
async fn a_full_file_system_under_allow_lets_writes_go_on_unrecorded_and_counts_them() {
    let Some(tmpfs) = Tmpfs::mount("allow", "64k") else {
        return;
    };
    let journal = tmpfs.join("writes.jsonl");
    let gateway = journaled_sim(&journal, "allow", vec![]).await;
    let mut ctx = master(&gateway).await;
    tmpfs.fill(&tmpfs.join("filler"));

    // More writes than the journal's last page can take lines for.
    let writes: Vec<(u16, u16)> = (0..40).map(|k| (100 + k, 0x2000 + k)).collect();
    for (register, value) in &writes {
        write(&mut ctx, *register, *value)
            .await
            .expect("a write goes on while the journal is full");
    }
    for (register, value) in &writes {
        assert_eq!(read(&mut ctx, *register).await, *value, "carried out");
    }
    let full = journal_lines(&journal);
    let recorded = writes
        .iter()
        .filter(|(register, value)| write_line(&full, *register, *value).is_some())
        .count();
    let unrecorded = writes.len() - recorded;
    assert!(unrecorded > 0, "the journal took them all: {full:#?}");
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(UNRECORDED), unrecorded as f64);
    assert_eq!(scrape.value(REFUSED), 0.0);
    assert!(scrape.value(WRITE_ERRORS) >= unrecorded as f64);
    assert_eq!(scrape.value(WRITABLE), 0.0);

    std::fs::remove_file(tmpfs.join("filler")).unwrap();
    write(&mut ctx, 300, 0x4000).await.expect("a write after");
    let entries = journal_lines(&journal);
    let gaps = of_kind(&entries, "gap");
    assert_eq!(gaps.len(), 1, "{entries:#?}");
    assert_eq!(gaps[0]["unrecorded"], unrecorded, "{}", gaps[0]);
    assert_eq!(gaps[0]["refused"], 0, "{}", gaps[0]);
    assert!(write_line(&entries, 300, 0x4000).is_some());
    assert_eq!(Scrape::of(&gateway).await.value(WRITABLE), 1.0);
    drop(ctx);
    gateway.shutdown().await;
}

/// A file system full at start; the journal's open line leads once there is room.
#[tokio::test]
async fn a_disk_full_at_start_lets_the_gateway_run_and_its_open_line_leads_later() {
    let Some(tmpfs) = Tmpfs::mount("start", "64k") else {
        return;
    };
    tmpfs.fill(&tmpfs.join("filler"));
    let journal = tmpfs.join("writes.jsonl");
    // The file opens (a name takes no block), but takes no line: no reason to keep reads down.
    let gateway = journaled_sim(&journal, "deny_writes", vec![]).await;
    let mut ctx = master(&gateway).await;
    assert_eq!(
        write(&mut ctx, 7, 0x0707).await,
        Err(ExceptionCode::GatewayPathUnavailable)
    );
    assert_eq!(read(&mut ctx, 7).await, 0, "refused, not sent");
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(REFUSED), 1.0);
    assert_eq!(scrape.value(WRITABLE), 0.0);
    assert!(journal_lines(&journal).is_empty());

    std::fs::remove_file(tmpfs.join("filler")).unwrap();
    write(&mut ctx, 7, 0x0707).await.expect("room again");
    let entries = journal_lines(&journal);
    let kinds: Vec<&str> = entries.iter().map(kind).collect();
    // The run's open line first, so the ids after it read as this run's; then what it missed.
    assert_eq!(kinds, ["open", "gap", "write", "outcome"], "{entries:#?}");
    assert_eq!(entries[0]["pid"], std::process::id());
    assert_eq!(entries[1]["refused"], 1);
    assert_eq!(Some(&entries[2]), write_line(&entries, 7, 0x0707));
    assert_eq!(entries[3]["outcome"], "answered");
    assert_eq!(Scrape::of(&gateway).await.value(WRITABLE), 1.0);
    drop(ctx);
    gateway.shutdown().await;
}

#[tokio::test]
async fn a_journal_on_dev_full_lets_writes_go_on_under_allow_and_counts_every_error() {
    let gateway = journaled_sim(Path::new("/dev/full"), "allow", vec![]).await;
    let mut ctx = master(&gateway).await;
    for k in 0..3 {
        write(&mut ctx, 10 + k, 0x0A00 + k)
            .await
            .expect("a write goes on unrecorded");
        assert_eq!(read(&mut ctx, 10 + k).await, 0x0A00 + k);
    }
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(UNRECORDED), 3.0);
    assert_eq!(scrape.value(REFUSED), 0.0);
    assert!(scrape.value(WRITE_ERRORS) >= 3.0, "{}", scrape.text);
    assert_eq!(scrape.value(WRITABLE), 0.0);
    let answered =
        "modbus_gateway_writes_total{action=\"allow\",outcome=\"answered\",protocol=\"tcp\"}";
    assert_eq!(scrape.value(answered), 3.0);
    drop(ctx);
    gateway.shutdown().await;
}

/// Under `deny_writes`.
#[tokio::test]
async fn a_journal_on_dev_full_refuses_writes_with_0x0a_and_serves_reads() {
    let gateway = journaled_sim(Path::new("/dev/full"), "deny_writes", vec![]).await;
    let mut ctx = master(&gateway).await;
    for k in 0..3 {
        assert_eq!(
            write(&mut ctx, 10 + k, 0x0A00 + k).await,
            Err(ExceptionCode::GatewayPathUnavailable)
        );
        assert_eq!(read(&mut ctx, 10 + k).await, 0, "refused, not sent");
    }
    let scrape = Scrape::of(&gateway).await;
    assert_eq!(scrape.value(REFUSED), 3.0);
    assert_eq!(scrape.value(REFUSED_BY_THE_GATEWAY), 3.0);
    assert_eq!(scrape.value(UNRECORDED), 0.0);
    assert!(scrape.value(WRITE_ERRORS) >= 3.0, "{}", scrape.text);
    assert_eq!(scrape.value(WRITABLE), 0.0);
    drop(ctx);
    gateway.shutdown().await;
}

#[tokio::test]
async fn a_journal_in_a_missing_folder_stops_the_start_with_an_error_naming_audit_path() {
    let dir = TempDir::new("missing");
    let journal = dir.join("no-such-folder").join("writes.jsonl");
    let config = audit_table(&journal, "allow", vec![])
        .listen(free_addr())
        .metrics_listen(free_addr())
        .bus(Bus::sim("sim").sim_slaves(&SLAVE.to_string()))
        .to_toml();
    let path = dir.join("gateway.toml");
    std::fs::write(&path, config).unwrap();
    let mut command = Command::new(BINARY);
    command
        .args(["--config", path.to_str().unwrap(), "run"])
        .env_remove("RUST_LOG");
    let out = within(
        "the gateway exits",
        tokio::task::spawn_blocking(move || command.output()),
    )
    .await
    .expect("the task runs")
    .expect("the binary runs");
    assert!(!out.status.success(), "{:?}", out.status);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("audit.path"), "{err}");
    assert!(err.contains(journal.to_str().unwrap()), "{err}");
    assert!(!journal.exists());
}

/// The files hold whole lines; the oldest writes are dropped.
#[tokio::test]
async fn rotation_keeps_keep_files_of_at_most_max_size_dropping_the_oldest() {
    const MAX_SIZE: u64 = 4096;
    const WRITES: u16 = 80;
    let dir = TempDir::new("rotate");
    let journal = dir.join("writes.jsonl");
    let gateway = journaled_sim(
        &journal,
        "deny_writes",
        vec![("max_size", MAX_SIZE.into()), ("keep", 2u32.into())],
    )
    .await;
    let mut ctx = master(&gateway).await;
    for k in 0..WRITES {
        if let Err(e) = write(&mut ctx, k, 0x5000 + k).await {
            let scrape = Scrape::of(&gateway).await;
            let audit = scrape.series_of("modbus_gateway_audit_errors_total");
            panic!("write {k} refused ({e:?}); the journal's errors: {audit:?}");
        }
    }
    let rotated = |n: u32| PathBuf::from(format!("{}.{n}", journal.display()));
    let files = [rotated(2), rotated(1), journal.clone()];
    assert!(!rotated(3).exists(), "keep = 2: no third rotated file");
    let mut all = Vec::new();
    for (i, file) in files.iter().enumerate() {
        let size = std::fs::metadata(file)
            .unwrap_or_else(|e| panic!("{}: {e}", file.display()))
            .len();
        assert!(size <= MAX_SIZE, "{} is {size} bytes", file.display());
        let entries = journal_lines(file);
        assert!(!entries.is_empty(), "{}", file.display());
        if let Some(next) = files.get(i + 1) {
            // Rotated only when the next line would not have fitted.
            let text = std::fs::read_to_string(next).unwrap();
            let first = text.split_inclusive('\n').next().unwrap();
            assert!(
                size + first.len() as u64 > MAX_SIZE,
                "{} rotated at {size} bytes, before a line of {} that fitted",
                file.display(),
                first.len()
            );
        }
        all.extend(entries);
    }
    assert_eq!(
        Scrape::of(&gateway).await.value(BYTES),
        std::fs::metadata(&journal).unwrap().len() as f64
    );
    let ids: Vec<u64> = of_kind(&all, "write")
        .iter()
        .map(|w| w["id"].as_u64().expect("an id"))
        .collect();
    let first = ids[0];
    assert!(first > 1, "the oldest writes are gone with the oldest file");
    assert_eq!(
        ids,
        (first..=u64::from(WRITES)).collect::<Vec<_>>(),
        "the kept writes, oldest file first, in order and none missing"
    );
    assert!(of_kind(&all, "open").is_empty(), "the open line was oldest");
    // Every kept write's outcome is kept too, after it.
    let outcomes: BTreeSet<u64> = of_kind(&all, "outcome")
        .iter()
        .map(|o| o["id"].as_u64().unwrap())
        .collect();
    assert!(ids.iter().all(|id| outcomes.contains(id)));
    drop(ctx);
    gateway.shutdown().await;

    // `modbus-gateway audit` reads across the three files: every kept write, with its outcome;
    // and its register filter picks one.
    let audit = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_modbus-gateway"))
            .args(["audit", "--journal"])
            .arg(&journal)
            .args(args)
            .output()
            .expect("the audit subcommand runs");
        assert!(out.status.success(), "{out:?}");
        String::from_utf8(out.stdout).expect("UTF-8")
    };
    let listed: Vec<serde_json::Value> = audit(&["--json"])
        .lines()
        .map(|line| serde_json::from_str(line).expect("JSON"))
        .collect();
    let listed_ids: Vec<u64> = listed.iter().map(|w| w["id"].as_u64().unwrap()).collect();
    assert_eq!(listed_ids, ids);
    assert!(listed.iter().all(|w| w["outcome"]["outcome"] == "answered"));
    // Register k was written k + 0x5000: the last write, by its register.
    let last = (WRITES - 1).to_string();
    let one = audit(&["--register", &last]);
    assert_eq!(one.lines().count(), 1, "{one}");
    assert!(
        one.contains(&format!("{:04X}", 0x5000 + WRITES - 1)),
        "{one}"
    );
    assert!(one.contains("answered"), "{one}");
}
