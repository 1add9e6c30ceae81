//! `modbus-gateway audit`: a journal and its rotated files read back as an auditor runs it, and
//! journals that would make a reader lie, block or grow without end.

// Unsafe blocks, each with its SAFETY comment: the child's limits before exec, wait4.
#![allow(unsafe_code)]

use crate::support::{Bus, GatewayConfig};
use serde_json::Value;
use std::io::{BufRead, BufReader, Seek, SeekFrom, Write as _};
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Output, Stdio};

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// A folder of its own for the test `name`.
fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mbgw-audit-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The `open` line of a run of the process `pid`.
fn open(time: &str, pid: u32) -> String {
    format!(r#"{{"kind":"open","time":"{time}","pid":{pid},"version":"0.1.0"}}"#)
}

/// A `write` line of Write Multiple Registers 0x2000-0x2001 = 1388 0032 from `master` to
/// `unit`, routed to `bus` slave `unit`, allowed by the rule `wallbox`.
fn write(id: u64, time: &str, master: &str, unit: u8, bus: &str) -> String {
    format!(
        r#"{{"kind":"write","time":"{time}","id":{id},"master":"{master}","protocol":"tcp","unit":{unit},"bus":"{bus}","slave":{unit},"function":16,"table":"holding","start":8192,"count":2,"values":"13880032","rule":"wallbox","action":"allow"}}"#
    )
}

fn answered(id: u64, time: &str) -> String {
    format!(
        r#"{{"kind":"outcome","time":"{time}","id":{id},"outcome":"answered","carried_out":"yes"}}"#
    )
}

/// The journal of two runs over three files, oldest first, and a stray older file past a gap
/// in the numbers (`.4` without `.3`), which is not read.
fn journal(dir: &Path) -> PathBuf {
    let path = dir.join("writes.jsonl");
    let file = |suffix: &str, lines: &[String]| {
        let name = format!("writes.jsonl{suffix}");
        std::fs::write(dir.join(name), lines.join("\n") + "\n").unwrap();
    };
    file(
        ".4",
        &[write(
            9,
            "2026-11-27T09:00:00.000000Z",
            "10.9.9.9:1",
            9,
            "line9",
        )],
    );
    file(
        ".2",
        &[
            open("2026-11-28T10:00:00.000000Z", 812),
            write(
                1,
                "2026-11-28T10:15:02.123456Z",
                "192.168.20.5:50312",
                3,
                "line1",
            ),
            answered(1, "2026-11-28T10:15:02.140000Z"),
            write(
                2,
                "2026-11-28T10:16:00.000000Z",
                "192.168.20.6:40000",
                5,
                "line1",
            ),
            write(
                3,
                "2026-11-28T10:17:00.000000Z",
                "192.168.30.7:40001",
                3,
                "line1",
            ),
        ],
    );
    file(
        ".1",
        &[
            // Write 2's outcome, after the rotation.
            r#"{"kind":"outcome","time":"2026-11-28T10:16:01.000000Z","id":2,"outcome":"timeout","carried_out":"maybe","exception":11,"detail":"no valid reply after 1 attempt(s): no reply; may have been carried out"}"#.to_owned(),
            // The gateway restarted before write 3's outcome.
            open("2026-11-28T11:00:00.000000Z", 2307),
            "{\"kind\":\"write\",\"time\":".to_owned(),
            r#"{"kind":"write","time":"2026-11-28T11:05:00.000000Z","id":1,"master":"192.168.20.5:50999","protocol":"tls","subject":"CN=hmi-1","role":"operator","unit":3,"bus":"line2","slave":1,"function":6,"table":"holding","start":256,"count":1,"values":"00FF","rule":"operators","action":"deny"}"#.to_owned(),
            r#"{"kind":"outcome","time":"2026-11-28T11:05:00.000100Z","id":1,"outcome":"denied","carried_out":"no","exception":1,"detail":"rule operators denies it"}"#.to_owned(),
            r#"{"kind":"gap","time":"2026-11-28T11:10:00.000000Z","since":"2026-11-28T11:06:00.000000Z","unrecorded":0,"refused":2,"lost_outcomes":0,"error":"No space left on device (os error 28)"}"#.to_owned(),
        ],
    );
    file(
        "",
        &[
            r#"{"kind":"write","time":"2026-11-28T11:20:00.000000Z","id":2,"master":"192.168.20.5:50999","protocol":"tcp","unit":7,"bus":"line2","slave":7,"function":65,"values":"0102","rule":null,"action":"allow"}"#.to_owned(),
        ],
    );
    path
}

fn audit(args: &[&str]) -> Output {
    Command::new(BINARY)
        .arg("audit")
        .args(args)
        .env_remove("RUST_LOG")
        .output()
        .expect("binary runs")
}

fn lines(out: &Output) -> Vec<String> {
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout.clone())
        .unwrap()
        .lines()
        .map(str::to_owned)
        .collect()
}

/// The time of each line: which writes (and gaps) were printed.
fn times(out: &Output) -> Vec<String> {
    lines(out)
        .iter()
        .map(|line| line.split("  ").next().unwrap().to_owned())
        .collect()
}

#[test]
fn every_write_of_the_rotated_files_is_printed_oldest_first_with_its_outcome() {
    let dir = temp_dir("all");
    let path = journal(&dir);
    let out = audit(&["--journal", path.to_str().unwrap()]);
    let path = path.display();
    assert_eq!(
        lines(&out),
        [
            "2026-11-28T10:15:02.123456Z  192.168.20.5:50312 tcp  unit 3 -> line1 slave 3  \
             Write Multiple Registers (0x10) holding 0x2000-0x2001 = 1388 0032  rule wallbox: \
             allow  answered",
            "2026-11-28T10:16:00.000000Z  192.168.20.6:40000 tcp  unit 5 -> line1 slave 5  \
             Write Multiple Registers (0x10) holding 0x2000-0x2001 = 1388 0032  rule wallbox: \
             allow  timeout (0x0B): no valid reply after 1 attempt(s): no reply; may have been \
             carried out",
            "2026-11-28T10:17:00.000000Z  192.168.30.7:40001 tcp  unit 3 -> line1 slave 3  \
             Write Multiple Registers (0x10) holding 0x2000-0x2001 = 1388 0032  rule wallbox: \
             allow  no outcome recorded: may have been carried out (the gateway stopped before \
             its outcome)",
            "2026-11-28T11:05:00.000000Z  192.168.20.5:50999 tls subject \"CN=hmi-1\" role \
             operator  unit 3 -> line2 slave 1  Write Single Register (0x06) holding 0x0100 = \
             00FF  rule operators: deny  denied (0x01): rule operators denies it",
            "2026-11-28T11:10:00.000000Z  gap: the journal could not be written from \
             2026-11-28T11:06:00.000000Z: No space left on device (os error 28); 2 writes \
             refused (0x0A)",
            "2026-11-28T11:20:00.000000Z  192.168.20.5:50999 tcp  unit 7 -> line2 slave 7  \
             function 0x41 = 01 02  no rule: allow  no outcome recorded: may have been carried \
             out (no outcome yet)",
        ]
    );
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.lines()
            .any(|line| line == format!("{path}.1:3: unreadable line")),
        "{err}"
    );
    assert!(err.contains("1 unreadable line(s) skipped"), "{err}");
}

#[test]
fn the_filters_select_the_writes_matching_all_of_them() {
    let dir = temp_dir("filters");
    let path = journal(&dir);
    let journal = path.to_str().unwrap();
    let select = |args: &[&str]| {
        let mut all = vec!["--journal", journal];
        all.extend_from_slice(args);
        times(&audit(&all))
    };
    let (first, second, third) = (
        "2026-11-28T10:15:02.123456Z",
        "2026-11-28T10:16:00.000000Z",
        "2026-11-28T10:17:00.000000Z",
    );
    let (denied, gap, last) = (
        "2026-11-28T11:05:00.000000Z",
        "2026-11-28T11:10:00.000000Z",
        "2026-11-28T11:20:00.000000Z",
    );
    // Gaps are shown whatever the filters but time: their writes could have matched.
    assert_eq!(
        select(&["--unit", "3", "--outcome", "answered,denied"]),
        [first, denied, gap]
    );
    assert_eq!(
        select(&["--master", "192.168.20.0/24", "--register", "0x2001-0x2005"]),
        [first, second, gap]
    );
    assert_eq!(
        select(&["--master", "192.168.20.5:50999"]),
        [denied, gap, last]
    );
    assert_eq!(
        select(&["--outcome", "pending", "--outcome", "timeout"]),
        [second, third, gap, last]
    );
    assert_eq!(
        select(&[
            "--since",
            "2026-11-28 10:16:00",
            "--until",
            "2026-11-28T11:00:00Z"
        ]),
        [second, third]
    );
    assert_eq!(
        select(&["--bus", "line2", "--since", "2026-11-28T11:15:00Z"]),
        [last]
    );
    assert!(
        select(&["--bus", "line9"]).iter().all(|t| t == gap),
        "nothing matches: exit 0"
    );
    // 100000 days ago is in the 18th century, whatever the clock of the machine says.
    assert!(
        select(&["--until", "100000days"]).is_empty(),
        "all of it is newer"
    );
    assert_eq!(select(&["--since", "100000days"]).len(), 6);
}

#[test]
fn json_prints_each_write_with_its_outcome_object_or_null() {
    let dir = temp_dir("json");
    let path = journal(&dir);
    let out = audit(&["--journal", path.to_str().unwrap(), "--json"]);
    let objects: Vec<Value> = lines(&out)
        .iter()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect();
    assert_eq!(objects.len(), 6);
    assert_eq!(objects[1]["kind"], "write");
    assert_eq!(objects[1]["master"], "192.168.20.6:40000");
    assert_eq!(objects[1]["start"], 8192);
    assert_eq!(objects[1]["outcome"]["outcome"], "timeout");
    assert_eq!(objects[1]["outcome"]["exception"], 11);
    assert_eq!(objects[2]["outcome"], Value::Null);
    assert_eq!(objects[2]["pending"], "gateway_stopped");
    assert_eq!(objects[3]["subject"], "CN=hmi-1");
    assert_eq!(objects[4]["kind"], "gap");
    assert_eq!(objects[4]["refused"], 2);
    assert_eq!(objects[5]["pending"], "no_outcome_yet");
}

#[test]
fn the_configured_journal_is_read_without_journal_and_a_config_without_one_exits_2() {
    let dir = temp_dir("config");
    let path = journal(&dir);
    let config = dir.join("gateway.toml");
    let line1 = GatewayConfig::new().default_listen().bus(Bus::sim("line1"));
    std::fs::write(
        &config,
        line1
            .clone()
            .table("audit", &[("path", path.display().to_string().into())])
            .to_toml(),
    )
    .unwrap();
    let out = audit(&["--config", config.to_str().unwrap(), "--unit", "5"]);
    assert_eq!(
        times(&out),
        ["2026-11-28T10:16:00.000000Z", "2026-11-28T11:10:00.000000Z"]
    );
    let out = Command::new(BINARY)
        .args(["--config", config.to_str().unwrap(), "audit", "--unit", "5"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "--config before the subcommand");

    let bare = dir.join("no-audit.toml");
    std::fs::write(&bare, line1.to_toml()).unwrap();
    let out = audit(&["--config", bare.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("has no [audit] table") && err.contains("--journal"),
        "{err}"
    );
}

#[test]
fn a_missing_journal_exits_1_and_bad_filters_exit_2_naming_them() {
    let dir = temp_dir("errors");
    let missing = dir.join("none.jsonl");
    let out = audit(&["--journal", missing.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains(&format!("no journal at {}", missing.display())),
        "{err}"
    );

    let path = journal(&dir);
    let out = audit(&[
        "--journal",
        path.to_str().unwrap(),
        "--outcome",
        "answered,fine",
        "--unit",
        "1-300",
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(out.stdout.is_empty());
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains(
            "--outcome: `fine` is not an outcome; the outcomes are answered, slave_exception,"
        ),
        "{err}"
    );
    assert!(err.contains("pending"), "{err}");
    assert!(err.contains("--unit: `300` is not a number"), "{err}");

    // Only rotated files, the live one not made yet: read all the same.
    std::fs::remove_file(&path).unwrap();
    let out = audit(&["--journal", path.to_str().unwrap()]);
    assert_eq!(lines(&out).len(), 5);
}

#[test]
fn a_reader_that_goes_away_ends_the_listing_quietly_with_status_0() {
    let dir = temp_dir("pipe");
    let path = dir.join("big.jsonl");
    // Far more than a pipe holds, so the listing is still writing when its reader leaves.
    let lines: Vec<String> = (1..=5000)
        .flat_map(|id| {
            [
                write(
                    id,
                    "2026-11-28T10:15:02.123456Z",
                    "192.168.20.5:50312",
                    3,
                    "line1",
                ),
                answered(id, "2026-11-28T10:15:02.140000Z"),
            ]
        })
        .collect();
    std::fs::write(&path, lines.join("\n") + "\n").unwrap();
    let mut child = Command::new(BINARY)
        .args(["audit", "--journal", path.to_str().unwrap()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    assert!(first.ends_with("answered\n"), "{first}");
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(0));
    assert!(
        out.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_hostile_certificate_subject_prints_escaped_in_the_text_and_the_json() {
    let dir = temp_dir("hostile");
    let path = dir.join("writes.jsonl");
    // A certificate without a role whose subject reads as if it had one, with a right-to-left
    // override and a zero-width space; its JSON line as the gateway writes it.
    let write = serde_json::json!({
        "kind": "write", "time": "2026-11-28T10:15:02.123456Z", "id": 1,
        "master": "192.168.20.5:50312", "protocol": "tls",
        "subject": "CN=maint\" role operator\u{202E}\u{200B}", "unit": 3, "bus": "line1",
        "slave": 3, "function": 6, "table": "holding", "start": 256, "count": 1,
        "values": "00FF", "rule": "maint", "action": "allow"
    });
    std::fs::write(
        &path,
        format!("{write}\n{}\n", answered(1, "2026-11-28T10:15:03Z")),
    )
    .unwrap();
    let out = audit(&["--journal", path.to_str().unwrap()]);
    let text = lines(&out).join("\n");
    assert!(
        text.contains(r#" tls subject "CN=maint\" role operator\u{202e}\u{200b}"  unit 3 -> "#),
        "{text}"
    );
    let out = audit(&["--journal", path.to_str().unwrap(), "--json"]);
    let json = lines(&out).join("\n");
    assert!(
        json.contains(r#""subject":"CN=maint\" role operator\u202e\u200b""#),
        "{json}"
    );
    let object: Value = serde_json::from_str(&json).unwrap();
    assert_eq!(object["subject"], write["subject"]);
}

/// `audit ARGS` run to its end as [`audit`] does, and the most memory it held (its peak
/// resident set, in KiB, from `wait4`). Bounds, not claims: past 1 GiB of address space or 120
/// s it is killed, as a reader that grows without end or blocks forever would be.
fn audit_measured(dir: &Path, args: &[&str]) -> (Output, u64) {
    let (stdout, stderr) = (dir.join("stdout"), dir.join("stderr"));
    let mut command = Command::new(BINARY);
    command
        .arg("audit")
        .args(args)
        .env_remove("RUST_LOG")
        .stdout(std::fs::File::create(&stdout).unwrap())
        .stderr(std::fs::File::create(&stderr).unwrap());
    // SAFETY: setrlimit and alarm are async-signal-safe, as a child between fork and exec
    // needs.
    unsafe {
        command.pre_exec(|| {
            let most = libc::rlimit {
                rlim_cur: 1 << 30,
                rlim_max: 1 << 30,
            };
            libc::setrlimit(libc::RLIMIT_AS, &most);
            libc::alarm(120);
            Ok(())
        });
    }
    // Waited for by wait4 below, which gives its resource usage too.
    #[allow(clippy::zombie_processes)]
    let child = command.spawn().expect("binary runs");
    let pid = child.id() as libc::pid_t;
    let mut status = 0;
    // SAFETY: a zeroed rusage is a valid one; wait4 fills it in.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: the child is ours and waited for once, here.
    let waited = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
    assert_eq!(waited, pid);
    let out = Output {
        status: ExitStatus::from_raw(status),
        stdout: std::fs::read(stdout).unwrap(),
        stderr: std::fs::read(stderr).unwrap(),
    };
    (out, u64::try_from(usage.ru_maxrss).unwrap())
}

/// The issue's ceiling for `audit` on any journal.
const MOST_RSS_KIB: u64 = 50 << 10;

#[test]
fn a_journal_that_is_not_a_regular_file_exits_1_naming_it() {
    let dir = temp_dir("not-a-file");
    let folder = dir.join("folder.jsonl");
    std::fs::create_dir(&folder).unwrap();
    let fifo = dir.join("fifo.jsonl");
    let made = Command::new("mkfifo").arg(&fifo).status().unwrap();
    assert!(made.success());
    // The live file is fine, its rotated one is not.
    let rotated = dir.join("rotated.jsonl");
    std::fs::write(&rotated, "").unwrap();
    std::fs::create_dir(dir.join("rotated.jsonl.1")).unwrap();
    let cases = [
        (
            Path::new("/dev/zero").to_owned(),
            "/dev/zero",
            "a character device",
        ),
        (folder.clone(), folder.to_str().unwrap(), "a directory"),
        (fifo.clone(), fifo.to_str().unwrap(), "a FIFO"),
        (
            rotated.clone(),
            &format!("{}.1", rotated.display()),
            "a directory",
        ),
    ];
    for (path, named, kind) in &cases {
        let (out, _) = audit_measured(&dir, &["--journal", path.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{named}: {err}");
        assert!(out.stdout.is_empty());
        assert_eq!(
            err,
            format!("modbus-gateway: audit: {named}: is {kind}, not a journal (a journal is a regular file)\n")
        );
    }
}

#[test]
fn a_line_of_a_gigabyte_is_skipped_unheld_and_the_lines_after_it_are_read() {
    let dir = temp_dir("long-line");
    let path = dir.join("writes.jsonl");
    let mut file = std::fs::File::create(&path).unwrap();
    let line = |id| {
        let at = "2026-11-28T10:15:02.123456Z";
        write(id, at, "192.168.20.5:50312", 3, "line1") + "\n" + &answered(id, at) + "\n"
    };
    file.write_all(line(1).as_bytes()).unwrap();
    // A line of 1 GiB of zero bytes, a hole in the file: it takes no disk.
    file.seek(SeekFrom::Current(1 << 30)).unwrap();
    file.write_all(format!("\n{}", line(2)).as_bytes()).unwrap();
    drop(file);
    let (out, rss) = audit_measured(&dir, &["--journal", path.to_str().unwrap()]);
    assert_eq!(times(&out).len(), 2, "both writes, the one after it too");
    assert!(lines(&out).iter().all(|l| l.ends_with("allow  answered")));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.starts_with(&format!(
            "{}:3: unreadable line: longer than 1 MiB, read past\n",
            path.display()
        )),
        "{err}"
    );
    assert!(rss < MOST_RSS_KIB, "{rss} KiB");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn writes_without_their_outcome_do_not_hold_the_writes_after_them_in_memory() {
    let dir = temp_dir("lost-outcome");
    let path = dir.join("writes.jsonl");
    let at = "2026-11-28T10:15:02.123456Z";
    let pair =
        |id| write(id, at, "192.168.20.5:50312", 3, "line1") + "\n" + &answered(id, at) + "\n";
    let mut text = open("2026-11-28T10:00:00.000000Z", 812) + "\n";
    // Write 1's outcome line is missing, as a journal cut short leaves it; write 100002's was
    // lost to a full disk, as its gap says.
    text += &(write(1, at, "192.168.20.5:50312", 3, "line1") + "\n");
    (2..=100_001).for_each(|id| text += &pair(id));
    text += &(write(100_002, at, "192.168.20.5:50312", 3, "line1") + "\n");
    text += r#"{"kind":"gap","time":"2026-11-28T10:20:00.000000Z","since":"2026-11-28T10:16:00.000000Z","unrecorded":0,"refused":0,"lost_outcomes":1,"error":"No space left on device (os error 28)"}"#;
    text += "\n";
    (100_003..=100_010).for_each(|id| text += &pair(id));
    std::fs::write(&path, text).unwrap();
    let (out, rss) = audit_measured(&dir, &["--journal", path.to_str().unwrap()]);
    let printed = lines(&out);
    assert_eq!(printed.len(), 100_011, "every write and the gap");
    let pending = "no outcome recorded: may have been carried out";
    assert!(
        printed[0].ends_with(&format!("{pending} (no outcome yet)")),
        "{}",
        printed[0]
    );
    assert!(printed[1..100_001]
        .iter()
        .all(|l| l.ends_with("allow  answered")));
    assert!(
        printed[100_001].ends_with(&format!(
            "{pending} (its outcome line was lost: see the gap after it)"
        )),
        "{}",
        printed[100_001]
    );
    assert!(printed[100_002].contains("  gap: "));
    assert!(printed[100_003..]
        .iter()
        .all(|l| l.ends_with("allow  answered")));
    assert!(
        out.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(rss < MOST_RSS_KIB, "{rss} KiB");
    std::fs::remove_dir_all(dir).unwrap();
}
