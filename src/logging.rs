//! The daemon's log lines on stderr. With `log.format = "text"`: human text, coloured on a
//! terminal; when stderr is the systemd journal, no timestamp (journald adds its own) and each
//! line starts with its syslog priority (`<4>` for a warning) so `journalctl -p` filters by level.
//! With `log.format = "json"`: one JSON object per line. The level is `log.level`, or `RUST_LOG`
//! when that is set. Knows nothing of what is logged.

use crate::config::LogFormat;
use std::fmt;
use std::io::IsTerminal;
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::fmt::format::Writer;
use tracing_subscriber::fmt::{FmtContext, FormatEvent, FormatFields};
use tracing_subscriber::registry::LookupSpan;
use tracing_subscriber::EnvFilter;

/// Changes the level filter of the running logger (a reload of `log.level`).
pub(crate) struct LevelSwitch(Option<Box<SetFilter>>);

type SetFilter = dyn Fn(EnvFilter) -> Result<(), String> + Send + Sync;

impl LevelSwitch {
    /// Log at `level` from now on. With `RUST_LOG` set, that wins and nothing changes.
    pub(crate) fn set(&self, level: &str) -> Result<(), String> {
        let Some(set) = &self.0 else {
            return Ok(());
        };
        set(EnvFilter::try_new(level).map_err(|e| e.to_string())?)
    }
}

/// Start logging. Call once, before anything logs.
pub(crate) fn init(level: &str, format: LogFormat) -> LevelSwitch {
    let from_env = EnvFilter::try_from_default_env().ok();
    let fixed = from_env.is_some();
    let filter = from_env.unwrap_or_else(|| EnvFilter::new(level));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    macro_rules! start {
        ($builder:expr) => {{
            let builder = $builder.with_filter_reloading();
            let handle = builder.reload_handle();
            builder.init();
            let set = move |filter| handle.reload(filter).map_err(|e| e.to_string());
            LevelSwitch((!fixed).then(|| Box::new(set) as _))
        }};
    }
    match format {
        LogFormat::Json => start!(builder
            .json()
            .flatten_event(true)
            .with_current_span(false)
            .with_span_list(false)),
        LogFormat::Text if stderr_is_journal() => {
            start!(builder.with_ansi(false).event_format(Prioritised(
                tracing_subscriber::fmt::format()
                    .without_time()
                    .with_level(false)
                    .with_ansi(false),
            )))
        }
        LogFormat::Text => start!(builder.with_ansi(std::io::stderr().is_terminal())),
    }
}

/// systemd sets `JOURNAL_STREAM` to the device and inode of the journal socket it connects to
/// stdout and stderr. A child whose stderr was redirected inherits the variable, so it counts
/// only if stderr is still that socket.
pub(crate) fn stderr_is_journal() -> bool {
    use std::os::unix::fs::MetadataExt;
    let stderr = std::fs::metadata("/proc/self/fd/2")
        .ok()
        .map(|m| (m.dev(), m.ino()));
    let stream = std::env::var("JOURNAL_STREAM").ok();
    is_journal(stream.as_deref(), stderr)
}

/// Whether `JOURNAL_STREAM` (`DEV:INODE`) names the file `stderr` (device, inode) is.
fn is_journal(journal_stream: Option<&str>, stderr: Option<(u64, u64)>) -> bool {
    let parse = |stream: &str| {
        let (dev, ino) = stream.split_once(':')?;
        Some((dev.parse().ok()?, ino.parse().ok()?))
    };
    matches!((journal_stream.and_then(parse), stderr), (Some(a), Some(b)) if a == b)
}

/// The syslog priority journald reads from a `<N>` line prefix.
fn priority(level: &Level) -> u8 {
    match *level {
        Level::ERROR => 3,
        Level::WARN => 4,
        Level::INFO => 6,
        _ => 7,
    }
}

/// Prefixes each line of the inner format with its priority.
struct Prioritised<F>(F);

impl<S, N, F> FormatEvent<S, N> for Prioritised<F>
where
    S: Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
    F: FormatEvent<S, N>,
{
    fn format_event(
        &self,
        ctx: &FmtContext<'_, S, N>,
        mut writer: Writer<'_>,
        event: &Event<'_>,
    ) -> fmt::Result {
        write!(writer, "<{}>", priority(event.metadata().level()))?;
        self.0.format_event(ctx, writer, event)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stderr_is_the_journal_only_if_it_is_the_socket_systemd_named() {
        assert!(is_journal(Some("8:12345"), Some((8, 12345))));
        // Redirected to a file: the variable is inherited, the inode differs.
        assert!(!is_journal(Some("8:12345"), Some((8, 999))));
        assert!(!is_journal(None, Some((8, 12345))));
        assert!(!is_journal(Some("garbage"), Some((8, 12345))));
        assert!(!is_journal(Some("8:12345"), None));
    }

    #[test]
    fn warnings_and_errors_keep_their_syslog_priority() {
        assert_eq!(priority(&Level::ERROR), 3);
        assert_eq!(priority(&Level::WARN), 4);
        assert_eq!(priority(&Level::INFO), 6);
        assert_eq!(priority(&Level::DEBUG), 7);
        assert_eq!(priority(&Level::TRACE), 7);
    }
}
