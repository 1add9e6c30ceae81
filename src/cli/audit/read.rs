//! Reading the journal's files: which there are, oldest first, and their lines.

use std::fs::File;
use std::io;
use std::path::{Path, PathBuf};

/// The journal's files, oldest first: `PATH.k` ... `PATH.1` (up to the first number missing),
/// then `PATH`; each opened now, so that a rotation meanwhile moves none under the reader.
pub(super) fn open(path: &Path) -> Result<Vec<(String, File)>, String> {
    let opened = |path: PathBuf| match File::open(&path) {
        Ok(file) => Ok(Some((path.display().to_string(), file))),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(format!("cannot read {}: {e}", path.display())),
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
