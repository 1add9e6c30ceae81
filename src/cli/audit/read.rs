//! Reading the journal's files: which there are, oldest first, and their lines, in bounded
//! memory whatever a file holds.

use std::fs::{File, FileType, OpenOptions};
use std::io::{self, BufRead, Read as _};
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::path::{Path, PathBuf};

/// The longest line held. The gateway's lines are a few hundred bytes: a write's values are at
/// most 504 hex digits, and a certificate's subject is rarely over a few KiB. A longer line is
/// none of the gateway's, and is read past without being held.
pub(super) const MAX_LINE: usize = 1 << 20;

/// The journal's files, oldest first: `PATH.k` ... `PATH.1` (up to the first number missing),
/// then `PATH`; each opened now, so that a rotation meanwhile moves none under the reader.
/// One that is not a regular file (a directory, a FIFO, `/dev/zero`) is an error naming it: a
/// journal is a file the gateway appends to, and those would block or never end.
pub(super) fn open(path: &Path) -> Result<Vec<(String, File)>, String> {
    let opened = |path: PathBuf| -> Result<_, String> {
        Ok(open_file(&path)?.map(|file| (path.display().to_string(), file)))
    };
    let mut files = Vec::new();
    for n in 1.. {
        match opened(crate::audit::rotated(path, n))? {
            Some(file) => files.push(file),
            None => break,
        }
    }
    files.reverse();
    match opened(path.to_owned())? {
        Some(file) => files.push(file),
        None if files.is_empty() => {
            return Err(format!(
                "no journal at {} (nor a rotated {})",
                path.display(),
                crate::audit::rotated(path, 1).display()
            ));
        }
        // Between a rotation's rename and the new file, or after the gateway's last run.
        None => {}
    }
    Ok(files)
}

/// The regular file at `path`, or `None` if there is none.
fn open_file(path: &Path) -> Result<Option<File>, String> {
    // Without blocking: opening a FIFO would wait for a writer before it could be refused. On
    // a regular file the flag does nothing.
    let file = match OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
    {
        Ok(file) => file,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(format!("cannot read {}: {e}", path.display())),
    };
    let kind = file
        .metadata()
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?
        .file_type();
    if !kind.is_file() {
        return Err(format!(
            "{}: is {}, not a journal (a journal is a regular file)",
            path.display(),
            kind_of(kind)
        ));
    }
    Ok(Some(file))
}

fn kind_of(kind: FileType) -> &'static str {
    if kind.is_dir() {
        "a directory"
    } else if kind.is_fifo() {
        "a FIFO"
    } else if kind.is_char_device() {
        "a character device"
    } else if kind.is_block_device() {
        "a block device"
    } else if kind.is_socket() {
        "a socket"
    } else {
        "something else"
    }
}

/// One line of a file.
#[derive(Debug, PartialEq)]
pub(super) enum Chunk<'a> {
    /// Its bytes, without the newline.
    Whole(&'a [u8]),
    /// Longer than [`MAX_LINE`]: read past, not held.
    TooLong,
}

/// The lines of a file, none held longer than [`MAX_LINE`].
pub(super) struct Lines<R> {
    reader: R,
    line: Vec<u8>,
}

impl<R: BufRead> Lines<R> {
    pub(super) fn new(reader: R) -> Self {
        Lines {
            reader,
            line: Vec::new(),
        }
    }

    /// The next line (the last may lack its newline), or `None` at the end of the file.
    pub(super) fn next_line(&mut self) -> io::Result<Option<Chunk<'_>>> {
        self.line.clear();
        // The line and its newline.
        let most = MAX_LINE as u64 + 1;
        let read = (&mut self.reader)
            .take(most)
            .read_until(b'\n', &mut self.line)?;
        if read == 0 {
            return Ok(None);
        }
        if self.line.last() == Some(&b'\n') {
            self.line.pop();
        } else if read as u64 == most {
            // The rest up to the newline, a buffer at a time.
            self.reader.skip_until(b'\n')?;
            self.line.clear();
            return Ok(Some(Chunk::TooLong));
        }
        Ok(Some(Chunk::Whole(&self.line)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What `next_line` says of each line of `text`, read through a buffer of `capacity`.
    fn lines_of(text: &[u8], capacity: usize) -> Vec<Result<Vec<u8>, ()>> {
        let mut lines = Lines::new(io::BufReader::with_capacity(capacity, text));
        let mut all = Vec::new();
        while let Some(line) = lines.next_line().unwrap() {
            all.push(match line {
                Chunk::Whole(bytes) => Ok(bytes.to_vec()),
                Chunk::TooLong => Err(()),
            });
        }
        all
    }

    #[test]
    fn a_line_over_the_limit_is_skipped_and_the_lines_after_it_are_read() {
        let mut text = b"first\n".to_vec();
        text.extend(std::iter::repeat_n(b'x', MAX_LINE + 1));
        text.extend_from_slice(b"\n");
        text.extend(std::iter::repeat_n(b'y', MAX_LINE));
        text.extend_from_slice(b"\nlast");
        for capacity in [1, 4096, 3 * MAX_LINE] {
            assert_eq!(
                lines_of(&text, capacity),
                [
                    Ok(b"first".to_vec()),
                    Err(()),
                    Ok(vec![b'y'; MAX_LINE]),
                    Ok(b"last".to_vec())
                ],
                "through a buffer of {capacity}"
            );
        }
        let unended = vec![b'x'; MAX_LINE + 1];
        assert_eq!(lines_of(&unended, 8192), [Err(())], "the file ends in it");
        assert_eq!(lines_of(b"\n\n", 8192), [Ok(Vec::new()), Ok(Vec::new())]);
    }

    #[test]
    fn a_line_over_the_limit_is_never_held_whole() {
        let mut text = vec![b'x'; 4 * MAX_LINE];
        text.extend_from_slice(b"\nnext\n");
        let mut lines = Lines::new(io::BufReader::new(text.as_slice()));
        assert_eq!(lines.next_line().unwrap(), Some(Chunk::TooLong));
        assert!(
            lines.line.capacity() <= 2 * MAX_LINE,
            "{}",
            lines.line.capacity()
        );
        assert_eq!(lines.next_line().unwrap(), Some(Chunk::Whole(b"next")));
    }
}
