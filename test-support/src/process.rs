//! The gateway as a process: external tools, free ports, logs, signals, exit.

use crate::wait::within;
use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

/// An external tool on the PATH. Without it the calling test has nothing to check and says so;
/// with `MBGW_REQUIRE_TOOLS=1` (as `.ci/run` sets) its absence fails the test instead.
pub fn tool(name: &str) -> Option<std::path::PathBuf> {
    let found = std::env::var_os("PATH").and_then(|path| {
        std::env::split_paths(&path)
            .map(|dir| dir.join(name))
            .find(|candidate| candidate.is_file())
    });
    if found.is_none() {
        assert!(
            std::env::var_os("MBGW_REQUIRE_TOOLS").is_none(),
            "{name} is required (MBGW_REQUIRE_TOOLS is set) but not on the PATH"
        );
        eprintln!("{name} is not on the PATH: this test checks nothing here");
    }
    found
}

/// A loopback address nobody listens on right now, for a gateway process to bind.
pub fn free_addr() -> SocketAddr {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("a free port");
    listener.local_addr().expect("bound")
}

/// Wait (bounded) until the log file at `path` contains `what`.
pub async fn until_logged(path: &Path, what: &str) {
    within(&format!("the log says {what:?}"), async {
        while !std::fs::read_to_string(path).unwrap().contains(what) {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

/// Send signal `name` (TERM, HUP, KILL...) to a child process.
pub fn signal(child: &std::process::Child, name: &str) {
    let status = std::process::Command::new("kill")
        .args(["-s", name, &child.id().to_string()])
        .status()
        .expect("kill runs");
    assert!(status.success(), "kill -s {name}");
}

/// Wait (bounded) for a child process to exit.
pub async fn exit_status(mut child: std::process::Child) -> std::process::ExitStatus {
    within(
        "the gateway exits",
        tokio::task::spawn_blocking(move || child.wait()),
    )
    .await
    .expect("the waiting task runs")
    .expect("wait for the child")
}
