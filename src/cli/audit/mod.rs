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
use join::{Joiner, Listed};
use read::{Chunk, Lines, MAX_LINE};
use std::fs::File;
use std::io::{self, BufReader};
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
    let mut listing = Listing {
        filter,
        json: options.json,
        out: io::BufWriter::new(io::stdout().lock()),
        joiner: Joiner::default(),
        unreadable: 0,
    };
    for (name, file) in files {
        if let Err(code) = listing.read(&name, file) {
            return code;
        }
    }
    listing.finish()
}

/// The listing under way: what it prints, and what it has read.
struct Listing<W> {
    filter: Filter,
    json: bool,
    out: W,
    joiner: Joiner,
    /// Lines that are none of the journal's.
    unreadable: u64,
}

impl<W: io::Write> Listing<W> {
    /// Read the file `name`, printing what is whole as it goes; an error is the exit code.
    fn read(&mut self, name: &str, file: File) -> Result<(), ExitCode> {
        let mut lines = Lines::new(BufReader::with_capacity(64 << 10, file));
        let mut number = 0u64;
        loop {
            let line = match lines.next_line() {
                Ok(Some(line)) => line,
                Ok(None) => return Ok(()),
                Err(e) => {
                    eprintln!("modbus-gateway: audit: cannot read {name}: {e}");
                    return Err(ExitCode::FAILURE);
                }
            };
            number += 1;
            let why = match line {
                Chunk::Whole(bytes) => self.joiner.feed(bytes).err().map(|_| String::new()),
                Chunk::TooLong => Some(format!(": longer than {} MiB, read past", MAX_LINE >> 20)),
            };
            if let Some(why) = why {
                self.unreadable += 1;
                eprintln!("{name}:{number}: unreadable line{why}");
            }
            for item in self.joiner.ready() {
                self.print(&item).map_err(|e| write_failed(&e))?;
            }
        }
    }

    fn print(&mut self, item: &Listed) -> io::Result<()> {
        if !self.filter.shows(item) {
            return Ok(());
        }
        let text = if self.json {
            print::as_json(item)
        } else {
            print::describe(item)
        };
        writeln!(self.out, "{text}")
    }

    /// Print what is left at the end of the journal, then what was skipped, on stderr.
    fn finish(mut self) -> ExitCode {
        let (rest, tally) = std::mem::take(&mut self.joiner).finish();
        for item in rest {
            if let Err(e) = self.print(&item) {
                return write_failed(&e);
            }
        }
        if let Err(e) = self.out.flush() {
            return write_failed(&e);
        }
        if self.unreadable > 0 {
            eprintln!(
                "modbus-gateway: audit: {} unreadable line(s) skipped",
                self.unreadable
            );
        }
        if tally.orphans > 0 {
            eprintln!(
                "modbus-gateway: audit: {} outcome line(s) name no write before them in their \
                 run (the write is in a file no longer kept, or unreadable)",
                tally.orphans
            );
        }
        if tally.late > 0 {
            eprintln!(
                "modbus-gateway: audit: {} outcome line(s) came after their write was printed \
                 as pending ({} writes after it, or after a gap that lost outcome lines), and \
                 were not joined to it",
                tally.late,
                join::MAX_HELD
            );
        }
        ExitCode::SUCCESS
    }
}

/// A reader that went away (`| head`) ends the listing quietly.
fn write_failed(error: &io::Error) -> ExitCode {
    if super::reader_gone(error) {
        return ExitCode::SUCCESS;
    }
    eprintln!("modbus-gateway: audit: cannot write to stdout: {error}");
    ExitCode::FAILURE
}
