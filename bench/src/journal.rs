//! The audit journal of the journal scenarios as the bench sees it from outside: a directory of
//! its own for the gateway's `[audit] path` (made for the scenario, removed after it), the file
//! system that directory is on (an fsync on tmpfs costs nothing, on a disk it waits for the
//! disk), and the bytes the journal holds. Knows nothing of the gateway's process or of the
//! masters.

use std::fs;
use std::path::{Path, PathBuf};

/// The journal's file in its directory; rotated files are `writes.jsonl.1`, ... beside it.
const FILE: &str = "writes.jsonl";
/// The directory of one scenario's journal, removed with everything in it when dropped.
pub(crate) struct JournalDir {
    dir: PathBuf,
}

impl Drop for JournalDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.dir);
    }
}

impl JournalDir {
    /// A new directory for `scenario`'s journal in `parent`, named after the bench's process.
    pub(crate) fn make(parent: &Path, scenario: &str) -> Result<JournalDir, String> {
        let dir = parent.join(format!(
            "mbgw-bench-audit-{}-{scenario}",
            std::process::id()
        ));
        fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        Ok(JournalDir { dir })
    }

    /// What the gateway's `audit.path` is.
    pub(crate) fn file(&self) -> PathBuf {
        self.dir.join(FILE)
    }

    /// The bytes in the journal now, its rotated files included.
    pub(crate) fn bytes(&self) -> u64 {
        let Ok(entries) = fs::read_dir(&self.dir) else {
            return 0;
        };
        entries
            .filter_map(|e| {
                let e = e.ok()?;
                e.file_name()
                    .to_string_lossy()
                    .starts_with(FILE)
                    .then(|| e.metadata().ok())?
                    .map(|m| m.len())
            })
            .sum()
    }

    /// The type of the file system the directory is on (`ext4`, `tmpfs`...), if /proc says.
    pub(crate) fn file_system(&self) -> Option<String> {
        let mounts = fs::read_to_string("/proc/self/mounts").ok()?;
        let dir = fs::canonicalize(&self.dir).ok()?;
        file_system_of(&mounts, &dir).map(str::to_owned)
    }
}

/// The file system type of the mount that holds `path` (absolute, without symbolic links), by
/// `mounts` in the format of /proc/self/mounts: the entry with the longest mount point that is
/// `path` or one of its ancestors; the last such entry, as a later mount hides an earlier one.
fn file_system_of<'a>(mounts: &'a str, path: &Path) -> Option<&'a str> {
    mounts
        .lines()
        .filter_map(|line| {
            let mut fields = line.split_whitespace();
            let (_source, point, kind) = (fields.next()?, fields.next()?, fields.next()?);
            // The kernel writes a space, tab, newline or backslash in a mount point as octal.
            let point = point
                .replace("\\040", " ")
                .replace("\\011", "\t")
                .replace("\\012", "\n")
                .replace("\\134", "\\");
            path.starts_with(&point).then_some((point.len(), kind))
        })
        .fold(
            None,
            |best: Option<(usize, &str)>, (len, kind)| match best {
                Some((longest, _)) if longest > len => best,
                _ => Some((len, kind)),
            },
        )
        .map(|(_, kind)| kind)
}

#[cfg(test)]
mod tests {
    use super::{file_system_of, JournalDir};
    use std::path::Path;

    const MOUNTS: &str = "\
/dev/vda / ext4 rw,relatime 0 0
proc /proc proc rw,nosuid,nodev,noexec,relatime 0 0
tmpfs /tmp tmpfs rw,nosuid,nodev 0 0
/dev/vdb /tmp/disk\\040b xfs rw 0 0
tmpfs /run tmpfs rw 0 0
/dev/vdc /run ext4 rw 0 0
";

    #[test]
    fn a_path_is_on_the_file_system_of_its_longest_mounted_ancestor() {
        let fs = |path: &str| file_system_of(MOUNTS, Path::new(path));
        assert_eq!(fs("/work/target/x"), Some("ext4"));
        assert_eq!(fs("/tmp/mbgw-bench-audit-1-x"), Some("tmpfs"));
        assert_eq!(fs("/tmp/disk b/journal"), Some("xfs"));
        // A mount point is a whole component: /tmpfoo is on /, not on /tmp.
        assert_eq!(fs("/tmpfoo"), Some("ext4"));
        // Mounted over: the later mount is the one in force.
        assert_eq!(fs("/run/user"), Some("ext4"));
        assert_eq!(file_system_of("", Path::new("/tmp")), None);
    }

    #[test]
    fn the_journal_s_directory_counts_its_files_bytes_and_is_removed_when_dropped() {
        let dir = JournalDir::make(&std::env::temp_dir(), "journal-test").unwrap();
        std::fs::write(dir.file(), [b'a'; 100]).unwrap();
        let mut rotated = dir.file().into_os_string();
        rotated.push(".1");
        std::fs::write(&rotated, [b'b'; 30]).unwrap();
        // Only the journal's files count.
        std::fs::write(dir.dir.join("other"), [b'c'; 7]).unwrap();
        assert_eq!(dir.bytes(), 130);
        assert!(dir.file_system().is_some());
        let path = dir.dir.clone();
        drop(dir);
        assert!(!path.exists(), "{} is left behind", path.display());
    }
}
