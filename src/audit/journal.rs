//! The journal's file: lines appended whole or not at all, rotated past `max_size`, reopened
//! after an error, and what went unrecorded meanwhile. One writer (a mutex around the file), so
//! a line is one `write` at the end of the file; a line that fails part-way is cut off again,
//! so the file holds whole lines only. With `fsync`, a thread of its own syncs the file to the
//! disk, every entry written since its last sync at once, and a write waits for its entry's
//! sync just before it goes on the wire: the runtime's one thread never waits for the disk.

use super::entry::{self, Gap, Line, Opened};
use crate::config::{self, OnError};
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write as _};
use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, PoisonError};

/// Who may read the journal: its owner (the service account) and its group.
const MODE: u32 = 0o640;

pub(crate) struct Journal {
    path: PathBuf,
    state: Mutex<State>,
    metrics: Arc<crate::metrics::Metrics>,
    syncer: Arc<Syncer>,
}

/// The thread that syncs the journal to the disk, and how far it has.
pub(crate) struct Syncer {
    asked: Mutex<SyncOrders>,
    wake: Condvar,
    synced: tokio::sync::watch::Sender<Synced>,
}

/// What the syncing thread is asked to do.
struct SyncOrders {
    /// The live file (a second handle on it).
    file: Option<File>,
    /// Entries written that must reach the disk, counted since the journal opened.
    upto: u64,
    stop: bool,
}

/// How far the entries have reached the disk: every entry up to `upto` has been synced or has
/// failed to; those up to `failed` may not be on the disk.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Synced {
    upto: u64,
    failed: u64,
}

/// An entry's place in the line of entries to sync.
#[derive(Clone, Debug)]
pub(crate) struct Ticket {
    syncer: Arc<Syncer>,
    number: u64,
}

impl Ticket {
    /// Wait until the entry is on the disk; `false` if syncing it failed.
    pub(crate) async fn synced(&self) -> bool {
        let mut synced = self.syncer.synced.subscribe();
        loop {
            let now = *synced.borrow_and_update();
            if now.upto >= self.number {
                return now.failed < self.number;
            }
            if synced.changed().await.is_err() {
                return false;
            }
        }
    }
}

impl Syncer {
    fn start(path: &Path) -> Arc<Syncer> {
        let syncer = Arc::new(Syncer {
            asked: Mutex::new(SyncOrders {
                file: None,
                upto: 0,
                stop: false,
            }),
            wake: Condvar::new(),
            synced: tokio::sync::watch::Sender::new(Synced::default()),
        });
        let thread = syncer.clone();
        let name = format!("audit-sync {}", path.display());
        let spawned = std::thread::Builder::new()
            .name("audit-sync".to_owned())
            .spawn(move || thread.run());
        if let Err(error) = spawned {
            // Without the thread no entry is ever synced: writes then wait, and fail, at once.
            tracing::error!(target: "modbus_gateway::audit", %error, name, "cannot start the journal's sync thread");
            syncer.synced.send_replace(Synced {
                upto: u64::MAX,
                failed: u64::MAX,
            });
        }
        syncer
    }

    fn asked(&self) -> std::sync::MutexGuard<'_, SyncOrders> {
        self.asked.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Sync whatever was asked since the last sync, in one `fdatasync`, until stopped.
    fn run(&self) {
        let mut done = 0;
        loop {
            let (file, upto) = {
                let mut asked = self.asked();
                while asked.upto <= done && !asked.stop {
                    asked = self
                        .wake
                        .wait(asked)
                        .unwrap_or_else(PoisonError::into_inner);
                }
                if asked.stop {
                    return;
                }
                let file = asked.file.as_ref().map(File::try_clone);
                (file, asked.upto)
            };
            let synced = match file {
                Some(Ok(file)) => file.sync_data().is_ok(),
                _ => false,
            };
            self.synced.send_modify(|now| {
                now.upto = upto;
                if !synced {
                    now.failed = upto;
                }
            });
            done = upto;
        }
    }

    /// The live file is now `file` (`None`: none open).
    fn follow(&self, file: Option<&File>) {
        self.asked().file = file.and_then(|f| f.try_clone().ok());
    }

    /// One more entry written; its ticket.
    fn ask(self: &Arc<Self>) -> Ticket {
        let number = {
            let mut asked = self.asked();
            asked.upto += 1;
            asked.upto
        };
        self.wake.notify_one();
        Ticket {
            syncer: self.clone(),
            number,
        }
    }
}

impl std::fmt::Debug for Syncer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Syncer")
    }
}

impl Drop for Journal {
    fn drop(&mut self) {
        self.syncer.asked().stop = true;
        self.syncer.wake.notify_one();
    }
}

struct State {
    settings: config::Audit,
    /// `None` after an error, until the next entry opens it again.
    file: Option<File>,
    /// Bytes in the live file: where a line that fails part-way is cut back to.
    len: u64,
    failing: Option<Failing>,
    /// This run's `open` line while the file has not taken it: it goes first, before the next
    /// entry and the `gap` before that one, so the ids that follow read as this run's.
    opening: Option<Vec<u8>>,
}

/// Since the journal could not be written.
struct Failing {
    since: String,
    error: String,
    unrecorded: u64,
    refused: u64,
    /// Outcome lines that could not be written.
    outcomes: u64,
}

/// Why an entry was not written, and what its write does about it.
#[derive(Debug)]
pub(crate) struct Unwritten {
    /// Refused (0x0A) under `on_error = "deny_writes"`; sent unrecorded under `"allow"`.
    pub(crate) refuse: bool,
}

impl Journal {
    /// Open (or create) the journal of `settings` and begin this run on it with an `open` line.
    /// A file that cannot be opened is an error, a start error naming `audit.path`. A file that
    /// opens but takes no line (its file system full, say) is not: the journal begins failing,
    /// so writes do what `on_error` says, as they would had it filled up a moment later,
    /// rather than the whole gateway, reads included, staying down until there is room.
    pub(crate) fn open(
        settings: &config::Audit,
        metrics: Arc<crate::metrics::Metrics>,
    ) -> io::Result<Journal> {
        let path = settings.path.clone();
        let (file, len) = open_file(&path)?;
        let syncer = Syncer::start(&path);
        syncer.follow(Some(&file));
        let journal = Journal {
            path,
            state: Mutex::new(State {
                settings: settings.clone(),
                file: Some(file),
                len,
                failing: None,
                opening: None,
            }),
            metrics,
            syncer,
        };
        let opened = line_of(&Line::Open(Opened {
            time: entry::now(),
            pid: std::process::id(),
            version: env!("CARGO_PKG_VERSION").to_owned(),
        }));
        let mut state = journal.state();
        match journal.append(&mut state, &opened) {
            Ok(()) => {
                if settings.fsync {
                    if let Some(file) = &state.file {
                        file.sync_data()?;
                    }
                }
                journal.metrics.audit.journal(Some(state.len));
            }
            Err(error) => {
                state.opening = Some(opened);
                failing(&mut state, &error);
                journal.metrics.audit.journal_bytes(state.len);
            }
        }
        drop(state);
        Ok(journal)
    }

    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    /// Take `settings` (of this same path) from the next entry on.
    pub(crate) fn set(&self, settings: &config::Audit) {
        self.state().settings = settings.clone();
    }

    pub(crate) fn settings(&self) -> config::Audit {
        self.state().settings.clone()
    }

    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Write `line`, an entry that must be in the file before its write is sent; with `fsync`,
    /// the ticket its write waits on before it goes on the wire.
    pub(crate) fn record(&self, line: &Line) -> Result<Option<Ticket>, Unwritten> {
        let mut state = self.state();
        let written = self.append(&mut state, &line_of(line));
        match written {
            Ok(()) => Ok(state.settings.fsync.then(|| self.syncer.ask())),
            Err(error) => Err(Unwritten {
                refuse: self.without_entry(&mut state, &error),
            }),
        }
    }

    /// Write `line`, an outcome: handed to the kernel, not synced (an outcome missing after a
    /// power loss reads as "may have been carried out", which is what the gateway then knows).
    pub(crate) fn note(&self, line: &Line) {
        let mut state = self.state();
        if let Err(error) = self.append(&mut state, &line_of(line)) {
            failing(&mut state, &error).outcomes += 1;
        }
    }

    /// The entries' sync to the disk failed (`fsync`): counted and logged as the journal's
    /// other errors are; whether the write goes on is `on_error`'s.
    pub(crate) fn sync_failed(&self) -> bool {
        let mut state = self.state();
        let first = state.failing.is_none();
        let error = io::Error::other("cannot sync the journal to the disk");
        let refuse = self.without_entry(&mut state, &error);
        let writes = writes_word(state.settings.on_error);
        let metrics = &self.metrics.audit;
        metrics.journal_failed(&self.path, "sync", &error, first, writes);
        refuse
    }

    /// A write whose entry is not on record (or not on the disk), in the failure streak of
    /// `error` and counted; whether `on_error` refuses it.
    fn without_entry(&self, state: &mut State, error: &io::Error) -> bool {
        let refuse = state.settings.on_error == OnError::DenyWrites;
        let failing = failing(state, error);
        if refuse {
            failing.refused += 1;
        } else {
            failing.unrecorded += 1;
        }
        self.metrics.audit.unrecorded(refuse);
        refuse
    }

    /// Append `bytes` (whole lines), rotating first if they would take the file past
    /// `max_size`, with a `gap` line first if entries went unwritten before.
    fn append(&self, state: &mut State, bytes: &[u8]) -> io::Result<()> {
        let first_failure = state.failing.is_none();
        let done = self.try_append(state, bytes);
        if let Err((operation, error)) = &done {
            let writes = writes_word(state.settings.on_error);
            let metrics = &self.metrics.audit;
            metrics.journal_failed(&self.path, operation, error, first_failure, writes);
        }
        done.map_err(|(_, error)| error)
    }

    fn try_append(&self, state: &mut State, bytes: &[u8]) -> Result<(), (&'static str, io::Error)> {
        let reopen = match &state.file {
            None => true,
            // Deleted under the gateway: what it writes would go nowhere anyone can read.
            Some(file) => file.metadata().is_ok_and(|m| m.nlink() == 0),
        };
        if reopen {
            let (file, len) = open_file(&self.path).map_err(|e| ("open", e))?;
            self.syncer.follow(Some(&file));
            state.file = Some(file);
            state.len = len;
        }
        let mut all = state.opening.clone().unwrap_or_default();
        if let Some(failing) = &state.failing {
            all.extend(line_of(&Line::Gap(Gap {
                time: entry::now(),
                since: failing.since.clone(),
                unrecorded: failing.unrecorded,
                refused: failing.refused,
                lost_outcomes: failing.outcomes,
                error: failing.error.clone(),
            })));
        }
        all.extend_from_slice(bytes);
        if state.len > 0 && state.len + all.len() as u64 > state.settings.max_size.0 {
            self.rotate(state).map_err(|e| ("rotate", e))?;
        }
        write_whole(state, &all).map_err(|e| ("write", e))?;
        state.opening = None;
        if let Some(failing) = state.failing.take() {
            let metrics = &self.metrics.audit;
            metrics.journal_recovered(&self.path, failing.unrecorded, failing.refused);
        }
        self.metrics.audit.journal_bytes(state.len);
        Ok(())
    }

    /// `PATH.(keep-1)` to `PATH.keep` ... `PATH` to `PATH.1`, and a new `PATH`.
    fn rotate(&self, state: &mut State) -> io::Result<()> {
        if let Some(file) = state.file.take() {
            if state.settings.fsync {
                // Entries not yet synced by the thread are in this file: sync it before it goes.
                file.sync_data()?;
            }
        }
        let keep = state.settings.keep.max(1);
        for n in (1..keep).rev() {
            match fs::rename(rotated(&self.path, n), rotated(&self.path, n + 1)) {
                Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
                _ => {}
            }
        }
        fs::rename(&self.path, rotated(&self.path, 1))?;
        let (file, len) = open_file(&self.path)?;
        if state.settings.fsync {
            // The renames and the new file are in the folder's entries: sync them too.
            if let Some(dir) = self.path.parent().filter(|d| !d.as_os_str().is_empty()) {
                File::open(dir)?.sync_all()?;
            }
        }
        self.syncer.follow(Some(&file));
        state.file = Some(file);
        state.len = len;
        Ok(())
    }
}

/// The failure streak `error` starts, or the one it continues.
fn failing<'a>(state: &'a mut State, error: &io::Error) -> &'a mut Failing {
    state.failing.get_or_insert_with(|| Failing {
        since: entry::now(),
        error: error.to_string(),
        unrecorded: 0,
        refused: 0,
        outcomes: 0,
    })
}

/// What writes do while the journal fails, for its log line.
fn writes_word(on_error: OnError) -> &'static str {
    match on_error {
        OnError::DenyWrites => "writes are refused (0x0A) until it can",
        OnError::Allow => "writes go on unrecorded (audit.on_error = \"allow\")",
    }
}

/// `bytes` at the end of the file, or none of them: a write that fails part-way is cut back
/// (if even that fails, the file is reopened before the next entry, at its real end).
fn write_whole(state: &mut State, bytes: &[u8]) -> io::Result<()> {
    let Some(file) = state.file.as_mut() else {
        return Err(io::Error::other("the journal is not open"));
    };
    let written = file.write_all(bytes);
    match written {
        Ok(()) => {
            state.len += bytes.len() as u64;
            Ok(())
        }
        Err(error) => {
            let _ = file.set_len(state.len);
            state.file = None;
            Err(error)
        }
    }
}

/// The rotated file `n` of the journal at `path`: `PATH.n`.
pub(crate) fn rotated(path: &Path, n: u32) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(format!(".{n}"));
    PathBuf::from(name)
}

fn open_file(path: &Path) -> io::Result<(File, u64)> {
    let file = OpenOptions::new()
        .create(true)
        .append(true)
        .mode(MODE)
        .open(path)?;
    let len = file.metadata()?.len();
    Ok((file, len))
}

/// `line` as the journal writes it: one JSON object and a newline.
fn line_of(line: &Line) -> Vec<u8> {
    let mut bytes = serde_json::to_vec(line)
        .unwrap_or_else(|e| format!("{{\"kind\":\"error\",\"error\":\"{e}\"}}").into_bytes());
    bytes.push(b'\n');
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(path: &Path, fsync: bool) -> config::Audit {
        config::Audit {
            path: path.to_owned(),
            max_size: config::ByteSize(4096),
            keep: 2,
            on_error: OnError::DenyWrites,
            fsync,
        }
    }

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("mbgw-journal-{}-{name}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).unwrap();
        dir.join("w.jsonl")
    }

    fn gap() -> Line {
        Line::Gap(Gap {
            time: entry::now(),
            since: entry::now(),
            unrecorded: 0,
            refused: 0,
            lost_outcomes: 0,
            error: "x".repeat(100),
        })
    }

    #[tokio::test]
    async fn with_fsync_each_entry_gets_a_ticket_that_resolves_once_the_thread_has_synced_it() {
        let path = temp("fsync");
        let metrics = Arc::new(crate::metrics::Metrics::new());
        let journal = Journal::open(&settings(&path, true), metrics.clone()).unwrap();
        let tickets: Vec<Ticket> = (0..5)
            .map(|_| journal.record(&gap()).unwrap().expect("a ticket"))
            .collect();
        for ticket in &tickets {
            assert!(ticket.synced().await);
        }
        // Without fsync there is nothing to wait for.
        let plain = Journal::open(&settings(&temp("plain"), false), metrics).unwrap();
        assert!(plain.record(&gap()).unwrap().is_none());
        // A file the thread cannot sync: the entry is not on the disk, and says so.
        journal.syncer.follow(None);
        let ticket = journal.record(&gap()).unwrap().expect("a ticket");
        assert!(!ticket.synced().await);
    }

    #[test]
    fn entries_past_max_size_rotate_into_keep_files_of_whole_lines() {
        let path = temp("rotate");
        let metrics = Arc::new(crate::metrics::Metrics::new());
        let journal = Journal::open(&settings(&path, false), metrics).unwrap();
        for _ in 0..100 {
            journal.record(&gap()).unwrap();
        }
        for file in [path.clone(), rotated(&path, 1), rotated(&path, 2)] {
            let text = fs::read_to_string(&file).unwrap();
            assert!(text.len() <= 4096, "{}: {}", file.display(), text.len());
            assert!(text.ends_with('\n'));
            for line in text.lines() {
                serde_json::from_str::<Line>(line).unwrap();
            }
        }
        assert!(!rotated(&path, 3).exists());
    }

    fn write(id: u64) -> Line {
        Line::Write(entry::Write {
            time: entry::now(),
            id,
            master: "127.0.0.1:50312".into(),
            protocol: "tcp".into(),
            subject: None,
            role: None,
            unit: 1,
            bus: Some("line1".into()),
            slave: Some(1),
            virtual_unit: None,
            function: 0x06,
            table: Some("holding".into()),
            start: Some(5),
            count: Some(1),
            values: "0001".into(),
            rule: None,
            action: "allow".into(),
        })
    }

    /// An outcome the file refuses is counted in the gap, and the journal reads writable again.
    #[test]
    fn a_refused_outcome_is_counted_in_the_gap_and_the_journal_recovers() {
        let path = temp("outcome");
        let metrics = Arc::new(crate::metrics::Metrics::new());
        let writable = || {
            let text = metrics.render().unwrap();
            crate::metrics::sample(&text, "modbus_gateway_audit_journal_writable")
        };
        let journal = Journal::open(&settings(&path, false), metrics.clone()).unwrap();
        journal.record(&write(1)).unwrap();
        assert_eq!(writable(), Some(1.0));
        // The file refuses the outcome (its disk full for a moment): lost, and not writable.
        journal.state().file = Some(OpenOptions::new().append(true).open("/dev/full").unwrap());
        journal.note(&Line::Outcome(entry::Ended {
            time: entry::now(),
            id: 1,
            outcome: entry::WriteOutcome::Answered,
            carried_out: entry::Carried::Yes,
            exception: None,
            detail: None,
        }));
        assert_eq!(writable(), Some(0.0));
        // The next entry reopens the file, which takes it after the gap that says so.
        journal.record(&write(2)).unwrap();
        assert_eq!(writable(), Some(1.0));
        let text = fs::read_to_string(&path).unwrap();
        let lines: Vec<Line> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        match lines.as_slice() {
            [Line::Open(_), Line::Write(first), Line::Gap(gap), Line::Write(second)] => {
                assert_eq!((first.id, second.id), (1, 2));
                assert_eq!((gap.lost_outcomes, gap.unrecorded, gap.refused), (1, 0, 0));
            }
            other => panic!("{other:#?}"),
        }
    }
}
