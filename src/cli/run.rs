//! `run`, the default: serve the configured gateway until SIGINT or SIGTERM, reload the file on
//! SIGHUP, and keep systemd's STATUS= line and watchdog current. Knows nothing of the gateway's
//! parts beyond [`Gateway`]'s own methods.

use super::{read_config, start_runtime, stop_signal};
use crate::{logging, Config, Gateway};
use sd_notify::NotifyState;
use std::convert::Infallible;
use std::path::Path;
use std::process::ExitCode;
use std::time::Duration;
use tracing::{error, info, warn};

/// How often the service manager's STATUS= line is refreshed when no watchdog asks for more.
const STATUS_PERIOD: Duration = Duration::from_secs(5);

/// The running logger's level, which a reload may change.
struct Logging {
    switch: logging::LevelSwitch,
    level: String,
}

/// SIGHUP: read the file again and apply it; on any error keep the configuration in force.
fn reload(path: &Path, gateway: &Gateway, logging: &mut Logging) {
    let mut reloading = vec![NotifyState::Reloading];
    reloading.extend(NotifyState::monotonic_usec_now().ok());
    let _ = sd_notify::notify(&reloading);
    let file = path.display().to_string();
    match read_config(path) {
        Err(errors) => {
            for e in &errors {
                error!(file, error = %e, "configuration not reloaded; keeping the one in force");
            }
        }
        Ok(config) => match gateway.reload(&config) {
            Ok(mut done) => {
                if config.log.level != logging.level {
                    match logging.switch.set(&config.log.level) {
                        Ok(()) => done.applied.push("log.level".to_owned()),
                        Err(e) => error!(error = %e, "cannot change the log level"),
                    }
                    logging.level = config.log.level.clone();
                }
                info!(file, applied = ?done.applied, "configuration reloaded");
                if !done.need_restart.is_empty() {
                    warn!(changed = ?done.need_restart, "these changes take a restart");
                }
                for kept in &done.kept {
                    error!(file, error = %kept, "part of the configuration not reloaded");
                }
            }
            Err(e) => {
                error!(file, error = %e, "configuration not reloaded; keeping the one in force")
            }
        },
    }
    let _ = sd_notify::notify(&[NotifyState::Ready, NotifyState::Status(&gateway.status())]);
}

/// A stream of SIGHUPs (never, where there are none).
struct Hangups(Option<tokio::signal::unix::Signal>);

impl Hangups {
    fn new() -> Self {
        use tokio::signal::unix::{signal, SignalKind};
        Hangups(signal(SignalKind::hangup()).ok())
    }

    async fn next(&mut self) {
        match &mut self.0 {
            Some(signal) => {
                signal.recv().await;
            }
            None => std::future::pending().await,
        }
    }
}

/// Keep the service manager's STATUS= line current and, when systemd runs a watchdog
/// (`WatchdogSec=`), ping it at half its period, only while every bus task makes progress: a
/// stuck bus task stops the pings and systemd restarts the gateway. Without systemd, only the
/// stall is logged.
async fn supervise(gateway: &Gateway) -> Infallible {
    let watchdog = sd_notify::watchdog_enabled();
    let period = watchdog.map_or(STATUS_PERIOD, |w| (w / 2).min(STATUS_PERIOD));
    let mut withholding = false;
    loop {
        tokio::time::sleep(period).await;
        let stalled = gateway.stalled_buses();
        let status = gateway.status();
        let mut states = vec![NotifyState::Status(&status)];
        match stalled.first() {
            None => {
                if withholding {
                    info!("every bus task is progressing again");
                    withholding = false;
                }
                if watchdog.is_some() {
                    states.push(NotifyState::Watchdog);
                }
            }
            Some((bus, silent)) if !withholding => {
                error!(
                    bus,
                    stalled_s = silent.as_secs_f64(),
                    "bus task stalled; withholding watchdog pings so that systemd restarts the gateway"
                );
                withholding = true;
            }
            Some(_) => {}
        }
        let _ = sd_notify::notify(&states);
    }
}

/// Serve `config`, read from `path`, until stopped.
pub fn run(path: &Path, config: Config) -> ExitCode {
    let (runtime, level) = match start_runtime(&config.log) {
        Ok(started) => started,
        Err(code) => return code,
    };
    let mut logging = Logging {
        switch: level,
        level: config.log.level.clone(),
    };
    runtime.block_on(async {
        let gateway = match Gateway::start(&config).await {
            Ok(gateway) => gateway,
            Err(e) => {
                error!(error = %e, "cannot start");
                return ExitCode::FAILURE;
            }
        };
        info!(
            version = env!("CARGO_PKG_VERSION"),
            "modbus-gateway running"
        );
        let _ = sd_notify::notify(&[NotifyState::Ready, NotifyState::Status(&gateway.status())]);
        {
            let mut hangups = Hangups::new();
            let stop = stop_signal();
            let supervisor = supervise(&gateway);
            tokio::pin!(stop, supervisor);
            loop {
                tokio::select! {
                    () = &mut stop => break,
                    never = &mut supervisor => match never {},
                    () = hangups.next() => reload(path, &gateway, &mut logging),
                }
            }
        }
        let _ = sd_notify::notify(&[NotifyState::Stopping, NotifyState::Status("stopping")]);
        info!("stopping: no new masters; serving what is queued");
        gateway.shutdown().await;
        info!("stopped");
        ExitCode::SUCCESS
    })
}
