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

/// A folder of the test's own under the system's temporary folder, `mbgw-WHAT-PID`, made fresh
/// and removed with what is in it when dropped.
pub struct TempDir(std::path::PathBuf);

impl TempDir {
    pub fn new(what: &str) -> TempDir {
        let dir = std::env::temp_dir().join(format!("mbgw-{what}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("a temporary folder");
        TempDir(dir)
    }

    pub fn path(&self) -> &Path {
        &self.0
    }

    /// `name` in the folder.
    pub fn join(&self, name: &str) -> std::path::PathBuf {
        self.0.join(name)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Wait (bounded) until `path` exists: a pty link a serial master port makes, a file a process
/// writes.
pub async fn until_exists(path: &Path) {
    within(&format!("{} exists", path.display()), async {
        while !path.exists() {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
}

/// A Python that can load Debian's libmodbus5 through ctypes (`MBGW_PYTHON`, else `python3`),
/// for the scripts that drive libmodbus. Without one the calling test has nothing to check and
/// says so; with `MBGW_REQUIRE_TOOLS=1` its absence fails the test instead.
pub fn python_with_libmodbus() -> Option<std::ffi::OsString> {
    let python =
        std::env::var_os("MBGW_PYTHON").unwrap_or_else(|| std::ffi::OsString::from("python3"));
    let usable = std::process::Command::new(&python)
        .args(["-c", "import ctypes; ctypes.CDLL('libmodbus.so.5')"])
        .status()
        .is_ok_and(|status| status.success());
    if !usable {
        assert!(
            std::env::var_os("MBGW_REQUIRE_TOOLS").is_none(),
            "libmodbus (libmodbus5) is required (MBGW_REQUIRE_TOOLS is set) but cannot be loaded"
        );
        eprintln!("libmodbus cannot be loaded: this test checks nothing here");
        return None;
    }
    Some(python)
}
