//! The `modbus-gateway` command's subcommands, each a function from the parsed arguments and the
//! loaded configuration to an exit code: [`run`] serves the gateway, [`check_config`] describes the
//! configuration, [`simulate`] serves a bus's simulated slaves on a serial device, [`trace`]
//! prints the frames on the lines of a running gateway, [`audit`] prints the journal of writes.
//! Here too what they share: loading the configuration (file and environment) and starting the
//! runtime. Knows nothing of argument parsing, which is the binary's.

pub mod audit;
pub mod check_config;
pub mod health;
mod http;
pub mod run;
pub mod simulate;
pub mod trace;

use crate::config::{self, Config, ENV_PREFIX};
use crate::logging;
use std::io::{self, Write};
use std::path::Path;
use std::process::ExitCode;
use tracing::error;

/// Exit status for a configuration that cannot be used.
pub(crate) const EXIT_CONFIG: u8 = 2;

/// Write `text` to stdout and flush it.
pub(crate) fn print_out(text: &str) -> io::Result<()> {
    let mut out = io::stdout().lock();
    out.write_all(text.as_bytes()).and_then(|()| out.flush())
}

/// Whether a failed write to stdout means its reader went away (`| head`): every subcommand then
/// stops quietly with status 0, as when the reader had read it all.
pub fn reader_gone(error: &io::Error) -> bool {
    error.kind() == io::ErrorKind::BrokenPipe
}

/// The environment as UTF-8 pairs. A `MBGW__` variable that is not UTF-8 is an error, not skipped.
fn environment() -> Result<Vec<(String, String)>, String> {
    let mut vars = Vec::new();
    for (name, value) in std::env::vars_os() {
        let Some(name) = name.to_str().map(str::to_owned) else {
            continue;
        };
        match value.into_string() {
            Ok(value) => vars.push((name, value)),
            Err(_) if name.starts_with(ENV_PREFIX) => {
                return Err(format!("{name}: is not valid UTF-8"));
            }
            Err(_) => {}
        }
    }
    Ok(vars)
}

/// The file and the environment, validated; or every problem, one line each.
pub(crate) fn read_config(path: &Path) -> Result<Config, Vec<String>> {
    let env = environment().map_err(|e| vec![e])?;
    crate::gateway::load_config(path, env)
        .map_err(|errors| errors.0.iter().map(ToString::to_string).collect())
}

/// The configuration at `path` with the environment's overrides; on errors, each is written to
/// stderr and the exit code is `EXIT_CONFIG`.
pub fn load(path: &Path) -> Result<Config, ExitCode> {
    // Logging is configured by the file, so its errors are written before logging starts: in
    // the journal, at error priority.
    let priority = if logging::stderr_is_journal() {
        "<3>"
    } else {
        ""
    };
    read_config(path).map_err(|errors| {
        for e in &errors {
            eprintln!("{priority}modbus-gateway: {}: {e}", path.display());
        }
        ExitCode::from(EXIT_CONFIG)
    })
}

async fn stop_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => tokio::select! {
                _ = term.recv() => {}
                _ = tokio::signal::ctrl_c() => {}
            },
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// Start logging as configured and the runtime the daemon's work runs on.
fn start_runtime(
    log: &config::Log,
) -> Result<(tokio::runtime::Runtime, logging::LevelSwitch), ExitCode> {
    let level = logging::init(&log.level, log.format);
    // The daemon times a real line (or the simulated one in real time): keep t3.5 to the
    // microsecond, not to tokio's millisecond.
    crate::timer::use_precise_timer();
    // One thread: each transaction is a handful of task wake-ups, and on one thread none of them
    // crosses threads. Measured with modbus-gateway-bench against the multi-thread runtime: CPU
    // per transaction 87 us instead of 141 (pty, 115200), and with 1000 masters at 115200
    // efficiency 0.970 instead of 0.927. The line, not the CPU, is the limit: a thread serves
    // about ten thousand transactions a second.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build();
    let runtime = runtime.map_err(|e| {
        error!(error = %e, "cannot start the runtime");
        ExitCode::FAILURE
    })?;
    Ok((runtime, level))
}
