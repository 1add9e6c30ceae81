//! The journal's file: lines appended whole or not at all, rotated past `max_size`, reopened
//! after an error, and what went unrecorded meanwhile. One writer (a mutex around the file), so
//! a line is one `write` at the end of the file; a line that fails part-way is cut off again,
//! so the file holds whole lines only.

use super::entry::{self, Gap, Line, Opened};
use crate::config::{self, OnError};
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write as _};
use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};

/// Who may read the journal: its owner (the service account) and its group.
const MODE: u32 = 0o640;

pub(crate) struct Journal {
    path: PathBuf,
    state: Mutex<State>,
    metrics: Arc<crate::metrics::Metrics>,
}

struct State {
    settings: config::Audit,
    /// `None` after an error, until the next entry opens it again.
    file: Option<File>,
    /// Bytes in the live file: where a line that fails part-way is cut back to.
    len: u64,
    failing: Option<Failing>,
}

/// Since the journal could not be written.
struct Failing {
    since: String,
    error: String,
    unrecorded: u64,
    refused: u64,
}

/// Why an entry was not written, and what its write does about it.
#[derive(Debug)]
pub(crate) struct Unwritten {
    /// Refused (0x0A) under `on_error = "deny_writes"`; sent unrecorded under `"allow"`.
    pub(crate) refuse: bool,
}

impl Journal {
    /// Open (or create) the journal of `settings` and begin this run on it with an `open` line.
    /// An error here is a start error naming `audit.path`.
    pub(crate) fn open(
        settings: &config::Audit,
        metrics: Arc<crate::metrics::Metrics>,
    ) -> io::Result<Journal> {
        let path = settings.path.clone();
        let (file, len) = open_file(&path)?;
        let journal = Journal {
            path,
            state: Mutex::new(State {
                settings: settings.clone(),
                file: Some(file),
                len,
                failing: None,
            }),
            metrics,
        };
        let opened = Line::Open(Opened {
            time: entry::now(),
            pid: std::process::id(),
            version: env!("CARGO_PKG_VERSION").to_owned(),
        });
        let mut state = journal.state();
        journal.append(&mut state, &line_of(&opened), settings.fsync)?;
        journal.metrics.audit.journal(Some(state.len));
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

    /// Write `line`, an entry that must be in the file before its write is sent (synced to the
    /// disk first with `fsync`).
    pub(crate) fn record(&self, line: &Line) -> Result<(), Unwritten> {
        let mut state = self.state();
        let sync = state.settings.fsync;
        let written = self.append(&mut state, &line_of(line), sync);
        match written {
            Ok(()) => Ok(()),
            Err(error) => {
                let refuse = state.settings.on_error == OnError::DenyWrites;
                let failing = state.failing.get_or_insert_with(|| Failing {
                    since: entry::now(),
                    error: error.to_string(),
                    unrecorded: 0,
                    refused: 0,
                });
                if refuse {
                    failing.refused += 1;
                } else {
                    failing.unrecorded += 1;
                }
                self.metrics.audit.unrecorded(refuse);
                Err(Unwritten { refuse })
            }
        }
    }

    /// Write `line`, an outcome: handed to the kernel, not synced (an outcome missing after a
    /// power loss reads as "may have been carried out", which is what the gateway then knows).
    pub(crate) fn note(&self, line: &Line) {
        let mut state = self.state();
        let _ = self.append(&mut state, &line_of(line), false);
    }

    /// Append `bytes` (whole lines), rotating first if they would take the file past
    /// `max_size`, with a `gap` line first if entries went unwritten before.
    fn append(&self, state: &mut State, bytes: &[u8], sync: bool) -> io::Result<()> {
        let first_failure = state.failing.is_none();
        let done = self.try_append(state, bytes, sync);
        if let Err((operation, error)) = &done {
            let writes = match state.settings.on_error {
                OnError::DenyWrites => "writes are refused (0x0A) until it can",
                OnError::Allow => "writes go on unrecorded (audit.on_error = \"allow\")",
            };
            let metrics = &self.metrics.audit;
            metrics.journal_failed(&self.path, operation, error, first_failure, writes);
        }
        done.map_err(|(_, error)| error)
    }

    fn try_append(
        &self,
        state: &mut State,
        bytes: &[u8],
        sync: bool,
    ) -> Result<(), (&'static str, io::Error)> {
        let reopen = match &state.file {
            None => true,
            // Deleted under the gateway: what it writes would go nowhere anyone can read.
            Some(file) => file.metadata().is_ok_and(|m| m.nlink() == 0),
        };
        if reopen {
            let (file, len) = open_file(&self.path).map_err(|e| ("open", e))?;
            state.file = Some(file);
            state.len = len;
        }
        let gap = state.failing.as_ref().map(|failing| {
            line_of(&Line::Gap(Gap {
                time: entry::now(),
                since: failing.since.clone(),
                unrecorded: failing.unrecorded,
                refused: failing.refused,
                error: failing.error.clone(),
            }))
        });
        let needed = bytes.len() + gap.as_ref().map_or(0, Vec::len);
        if state.len > 0 && state.len + needed as u64 > state.settings.max_size.0 {
            self.rotate(state).map_err(|e| ("rotate", e))?;
        }
        let mut all = gap.unwrap_or_default();
        all.extend_from_slice(bytes);
        write_whole(state, &all, sync).map_err(|e| ("write", e))?;
        if let Some(failing) = state.failing.take() {
            let metrics = &self.metrics.audit;
            metrics.journal_recovered(&self.path, failing.unrecorded, failing.refused);
        }
        self.metrics.audit.journal_bytes(state.len);
        Ok(())
    }

    /// `PATH.(keep-1)` to `PATH.keep` ... `PATH` to `PATH.1`, and a new `PATH`.
    fn rotate(&self, state: &mut State) -> io::Result<()> {
        state.file = None;
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
        state.file = Some(file);
        state.len = len;
        Ok(())
    }
}

/// `bytes` at the end of the file, or none of them: a write that fails part-way is cut back
/// (if even that fails, the file is reopened before the next entry, at its real end).
fn write_whole(state: &mut State, bytes: &[u8], sync: bool) -> io::Result<()> {
    let Some(file) = state.file.as_mut() else {
        return Err(io::Error::other("the journal is not open"));
    };
    let written = file
        .write_all(bytes)
        .and_then(|()| if sync { file.sync_data() } else { Ok(()) });
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
