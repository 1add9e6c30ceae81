//! The `audit` subcommand: read the journal of writes (`[audit]`) back, its rotated files oldest
//! first, join each write to its outcome, filter, and print one line (or JSON object) per write.
//! The lines' format is [`crate::audit::entry`]'s; knows nothing of how the gateway writes them.
//! In the order a line flows: [`read`] opens the files and reads their lines, [`join`] joins
//! each write to its outcome, [`filter`] picks what to print, [`print`] says it.

mod filter;
#[cfg(test)]
mod fixtures;
mod join;
mod print;
mod read;

use super::EXIT_CONFIG;
use crate::config::Config;
use filter::Filter;
use join::{Item, Joiner};
use std::io::{self, BufRead, BufReader, Write as _};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::SystemTime;

/// What to print, as given on the command line: checked by [`Filter::parse`].
#[derive(Clone, Debug, Default)]
pub struct Options {
    pub since: Option<String>,
    pub until: Option<String>,
    pub master: Option<String>,
    pub unit: Option<String>,
    pub register: Option<String>,
    /// Outcome words, each maybe a comma list.
    pub outcome: Vec<String>,
    pub bus: Option<String>,
    pub json: bool,
}

/// The journal `audit.path` of the configuration read from `file`; without `[audit]`, says so
/// and gives the exit code.
pub fn journal_of(file: &Path, config: &Config) -> Result<PathBuf, ExitCode> {
    match &config.audit {
        Some(audit) => Ok(audit.path.clone()),
        None => {
            eprintln!(
                "modbus-gateway: audit: {}: has no [audit] table, so no journal to read; \
                 name one with --journal PATH",
                file.display()
            );
            Err(ExitCode::from(EXIT_CONFIG))
        }
    }
}

/// Print the writes of the journal at `path` (and its rotated files) that `options` select.
/// Exit 0 when it was read, matched or not; 1 when it cannot be read; 2 for bad options.
pub fn audit(path: &Path, options: &Options) -> ExitCode {
    let filter = match Filter::parse(options, SystemTime::now()) {
        Ok(filter) => filter,
        Err(errors) => {
            for e in errors {
                eprintln!("modbus-gateway: audit: {e}");
            }
            return ExitCode::from(EXIT_CONFIG);
        }
    };
    let files = match read::open(path) {
        Ok(files) => files,
        Err(e) => {
            eprintln!("modbus-gateway: audit: {e}");
            return ExitCode::FAILURE;
        }
    };
    let mut out = io::BufWriter::new(io::stdout().lock());
    let mut print = |item: &Item| -> io::Result<()> {
        if filter.shows(item) {
            let text = if options.json {
                print::as_json(item)
            } else {
                print::describe(item)
            };
            writeln!(out, "{text}")?;
        }
        Ok(())
    };
    let mut joiner = Joiner::default();
    let mut unreadable = 0u64;
    for (name, file) in files {
        let mut reader = BufReader::new(file);
        let mut bytes = Vec::new();
        let mut number = 0u64;
        loop {
            bytes.clear();
            match reader.read_until(b'\n', &mut bytes) {
                Ok(0) => break,
                Ok(_) => {}
                Err(e) => {
                    eprintln!("modbus-gateway: audit: cannot read {name}: {e}");
                    return ExitCode::FAILURE;
                }
            }
            number += 1;
            if joiner.feed(&bytes).is_err() {
                unreadable += 1;
                eprintln!("{name}:{number}: unreadable line");
            }
            for item in joiner.ready() {
                if let Err(e) = print(&item) {
                    return write_failed(&e);
                }
            }
        }
    }
    let (rest, orphans) = joiner.finish();
    for item in rest {
        if let Err(e) = print(&item) {
            return write_failed(&e);
        }
    }
    if let Err(e) = out.flush() {
        return write_failed(&e);
    }
    if unreadable > 0 {
        eprintln!("modbus-gateway: audit: {unreadable} unreadable line(s) skipped");
    }
    if orphans > 0 {
        eprintln!(
            "modbus-gateway: audit: {orphans} outcome line(s) name no write before them in \
             their run (the write is in a file no longer kept, or unreadable)"
        );
    }
    ExitCode::SUCCESS
}

/// A reader that went away (`| head`) ends the listing quietly.
fn write_failed(error: &io::Error) -> ExitCode {
    if super::reader_gone(error) {
        return ExitCode::SUCCESS;
    }
    eprintln!("modbus-gateway: audit: cannot write to stdout: {error}");
    ExitCode::FAILURE
}
