//! The far end of the device-server line: the gateway binary's `simulate --listen` as a process,
//! serving the scenario's simulated line (the bus and slaves the `Sim` line would have had) on a
//! loopback port, stopped when dropped. Knows nothing of the gateway in front of it.

use crate::gateway::{bus, TempPath, START_LIMIT};
use crate::scenarios::Scenario;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, ChildStdout, Command, Stdio};
use test_support::GatewayConfig;

/// The `simulate --listen` process, stopped when dropped.
pub(crate) struct DeviceServer {
    child: Child,
    /// What to give the gateway's bus as its `device`: `tcp://ADDR`.
    pub(crate) device: String,
    /// Kept open: `simulate` takes a closed stdout for its reader gone, and stops.
    _stdout: BufReader<ChildStdout>,
    _config: TempPath,
}

impl Drop for DeviceServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The address in `simulate`'s announcement, `serving bus NAME on tcp://ADDR at ...`.
fn announced(line: &str) -> Option<&str> {
    let (_, rest) = line.split_once(" on tcp://")?;
    rest.split_whitespace().next()
}

impl DeviceServer {
    /// `binary simulate --listen 127.0.0.1:0` on scenario `s`'s simulated line, once it
    /// listens: its announcement names the port.
    pub(crate) async fn start(binary: &Path, s: &Scenario) -> Result<DeviceServer, String> {
        let config = GatewayConfig::new()
            .table("log", &[("level", "warn".into())])
            .bus(bus(s, "sim"));
        let path = std::env::temp_dir().join(format!(
            "mbgw-bench-{}-{}-simulate.toml",
            std::process::id(),
            s.name
        ));
        std::fs::write(&path, config.to_toml()).map_err(|e| e.to_string())?;
        let config = TempPath(path);
        let mut child = Command::new(binary)
            .arg("--config")
            .arg(&config.0)
            .args(["simulate", "--listen", "127.0.0.1:0"])
            .env_remove("RUST_LOG")
            .stdout(Stdio::piped())
            .spawn()
            .map_err(|e| format!("{} simulate: {e}", binary.display()))?;
        let Some(stdout) = child.stdout.take() else {
            let _ = child.kill();
            return Err("simulate's stdout is not piped".into());
        };
        // A blocking read of one line; killing the child on a timeout ends it with EOF.
        let reading = tokio::task::spawn_blocking(move || {
            let mut stdout = BufReader::new(stdout);
            let mut line = String::new();
            stdout.read_line(&mut line).map(|_| (line, stdout))
        });
        let outcome = match tokio::time::timeout(START_LIMIT, reading).await {
            Ok(Ok(Ok((line, stdout)))) => announced(&line)
                .map(|addr| (format!("tcp://{addr}"), stdout))
                .ok_or_else(|| format!("simulate did not announce its address: {line:?}")),
            Ok(Ok(Err(e))) => Err(format!("reading simulate's announcement: {e}")),
            Ok(Err(e)) => Err(e.to_string()),
            Err(_) => Err("simulate did not start listening within 10 s".into()),
        };
        match outcome {
            Ok((device, stdout)) => Ok(DeviceServer {
                child,
                device,
                _stdout: stdout,
                _config: config,
            }),
            Err(e) => {
                let _ = child.kill();
                let _ = child.wait();
                Err(e)
            }
        }
    }

    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }
}

#[cfg(test)]
mod tests {
    use super::announced;

    #[test]
    fn the_address_is_read_from_simulate_s_announcement() {
        let line = "serving bus bench on tcp://127.0.0.1:40123 at 9600 baud 8E1\n";
        assert_eq!(announced(line), Some("127.0.0.1:40123"));
        assert_eq!(
            announced("serving bus bench on /dev/pts/5 at 9600 baud 8E1"),
            None
        );
    }
}
