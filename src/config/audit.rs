//! The `[audit]` table: where the journal of writes goes, how big it may grow and how many
//! rotated files are kept, what writes do when it cannot be written, and whether each entry is
//! synced to the disk. Values only: writing the journal is `crate::audit`'s business.

use super::defaults;
use super::serde_adapters::{words, Choice};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::PathBuf;

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Audit {
    /// The journal: one JSON object a line. Its folder must exist and be writable.
    pub path: PathBuf,
    /// Past this size the file is renamed `PATH.1` (the older ones moving up) and a new one
    /// started: a byte count, or a size like `"10MiB"`; at least 4 KiB.
    #[serde(default = "defaults::audit_max_size")]
    pub max_size: ByteSize,
    /// Rotated files kept (`PATH.1` ... `PATH.keep`); the oldest beyond them is deleted.
    #[serde(default = "defaults::audit_keep")]
    pub keep: u32,
    /// What a write does when its entry cannot be written.
    #[serde(default)]
    pub on_error: OnError,
    /// Sync each entry to the disk before its write is sent (for power loss), not only hand it
    /// to the kernel.
    #[serde(default)]
    pub fsync: bool,
}

/// What writes do while the journal cannot be written.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum OnError {
    /// Refused with exception 0x0A until an entry can be written again: no write goes
    /// unrecorded.
    #[default]
    DenyWrites,
    /// Sent all the same, the error logged and counted: no write is refused for the journal.
    Allow,
}

impl Choice for OnError {
    const ALL: &'static [Self] = &[OnError::DenyWrites, OnError::Allow];
    fn word(self) -> &'static str {
        self.label()
    }
}

words!(OnError);

impl OnError {
    pub fn label(self) -> &'static str {
        match self {
            OnError::DenyWrites => "deny_writes",
            OnError::Allow => "allow",
        }
    }
}

/// A size in bytes: written as a number of bytes, or with a unit (`"4KiB"`, `"10MiB"`,
/// `"1GiB"`, `"500kB"`, `"10MB"`, `"1GB"`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct ByteSize(pub u64);

/// Smallest journal before rotation: a few dozen entries.
pub(crate) const MIN_AUDIT_SIZE: u64 = 4096;
/// Most rotated journal files kept.
pub(crate) const MAX_AUDIT_KEEP: u32 = 1000;

impl ByteSize {
    fn parse(text: &str) -> Result<ByteSize, String> {
        let text = text.trim();
        let split = text
            .find(|c: char| !c.is_ascii_digit())
            .unwrap_or(text.len());
        let (number, unit) = text.split_at(split);
        let multiplier: u64 = match unit.trim() {
            "" | "B" => 1,
            "KiB" => 1 << 10,
            "MiB" => 1 << 20,
            "GiB" => 1 << 30,
            "kB" | "KB" => 1_000,
            "MB" => 1_000_000,
            "GB" => 1_000_000_000,
            other => {
                return Err(format!(
                    "`{other}` is no size unit (B, KiB, MiB, GiB, kB, MB, GB)"
                ))
            }
        };
        number
            .parse::<u64>()
            .ok()
            .and_then(|n| n.checked_mul(multiplier))
            .map(ByteSize)
            .ok_or_else(|| format!("`{text}` is no size like \"10MiB\" or 4096"))
    }
}

impl fmt::Display for ByteSize {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let units = [(1 << 30, "GiB"), (1 << 20, "MiB"), (1 << 10, "KiB")];
        match units
            .iter()
            .find(|(size, _)| self.0 >= *size && self.0.is_multiple_of(*size))
        {
            Some((size, unit)) => write!(f, "{}{unit}", self.0 / size),
            None => write!(f, "{} bytes", self.0),
        }
    }
}

impl Serialize for ByteSize {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_u64(self.0)
    }
}

impl<'de> Deserialize<'de> for ByteSize {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = ByteSize;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a byte count, or a size like \"10MiB\"")
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<ByteSize, E> {
                u64::try_from(v)
                    .map(ByteSize)
                    .map_err(|_| E::custom(format!("{v} bytes: a size cannot be negative")))
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<ByteSize, E> {
                Ok(ByteSize(v))
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<ByteSize, E> {
                ByteSize::parse(v).map_err(E::custom)
            }
        }
        d.deserialize_any(Visitor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::testing::{errors, MINIMAL};
    use crate::config::Config;

    #[test]
    fn sizes_take_bytes_binary_and_decimal_units() {
        assert_eq!(ByteSize::parse("4096"), Ok(ByteSize(4096)));
        assert_eq!(ByteSize::parse("10MiB"), Ok(ByteSize(10 << 20)));
        assert_eq!(ByteSize::parse("4 KiB"), Ok(ByteSize(4096)));
        assert_eq!(ByteSize::parse("2MB"), Ok(ByteSize(2_000_000)));
        assert!(ByteSize::parse("10 mb").is_err());
        assert!(ByteSize::parse("MiB").is_err());
        assert_eq!(ByteSize(10 << 20).to_string(), "10MiB");
        assert_eq!(ByteSize(5000).to_string(), "5000 bytes");
    }

    #[test]
    fn the_audit_table_has_defaults_but_its_path_and_prints_back_the_same() {
        let c = Config::from_toml_str(&format!(
            "{MINIMAL}\n[audit]\npath = \"/var/lib/modbus-gateway/writes.jsonl\"\n"
        ))
        .unwrap();
        let audit = c.audit.as_ref().unwrap();
        assert_eq!(audit.max_size, ByteSize(10 << 20));
        assert_eq!(audit.keep, 5);
        assert_eq!(audit.on_error, OnError::DenyWrites);
        assert!(!audit.fsync);
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
        let found = errors(&format!(
            "{MINIMAL}\n[audit]\npath = \"w.jsonl\"\nmax_size = \"1KiB\"\nkeep = 0\n\
             on_error = \"ignore\"\n"
        ))
        .join("\n");
        assert!(found.contains("audit.on_error"), "{found}");
        let found = errors(&format!(
            "{MINIMAL}\n[audit]\npath = \"w.jsonl\"\nmax_size = \"1KiB\"\nkeep = 0\n"
        ))
        .join("\n");
        assert!(found.contains("audit.max_size: 1KiB"), "{found}");
        assert!(found.contains("audit.keep"), "{found}");
        assert!(errors(&format!("{MINIMAL}\n[audit]\nkeep = 2\n"))
            .join("\n")
            .contains("audit.path"));
    }
}
