//! The `[log]` section: the log filter and line format, as values. Knows nothing of the logger.

use super::defaults;
use super::serde_adapters::{words, Choice};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Log {
    /// A tracing filter: `info`, `debug`, `modbus_gateway=trace`; `RUST_LOG` overrides it.
    pub level: String,
    pub format: LogFormat,
}

/// How log lines are written to stderr.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LogFormat {
    /// Human text; under systemd, without timestamps and with the journal's priority prefix.
    #[default]
    Text,
    /// One JSON object per line.
    Json,
}

impl Choice for LogFormat {
    const ALL: &'static [Self] = &[LogFormat::Text, LogFormat::Json];
    fn word(self) -> &'static str {
        match self {
            LogFormat::Text => "text",
            LogFormat::Json => "json",
        }
    }
}

words!(LogFormat);

impl Default for Log {
    fn default() -> Self {
        Log {
            level: defaults::LOG_LEVEL.to_owned(),
            format: LogFormat::default(),
        }
    }
}
