//! The walkthrough "Modbus/TCP Security (TLS)" (docs/security.md), run as a user would: its shell
//! blocks (openssl) make a CA, the gateway's certificate and the operator's and viewer's in a fresh
//! directory, `config/demo-tls.toml` serves them, and pymodbus's TLS client
//! (`tests/peers/pymodbus_tls_master.py`, and the README's own Python) is the master. The
//! section's blocks are found by its heading; a missing section or block fails the test.
//!
//! openssl comes from the PATH; without it (or Python with pymodbus) a test checks nothing and
//! says so, or fails under `MBGW_REQUIRE_TOOLS=1`.

use super::{frames, python_with_pymodbus, run_command, Pymodbus, RESPONSE_TIMEOUT, UNIT};
use crate::support::{pty_config, start, Scrape};
use std::ffi::OsString;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicUsize, Ordering};

/// The walkthrough's page.
const README: &str = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/security.md"));
const DEMO_TLS: &str = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/config/demo-tls.toml"));
const HEADING: &str = "## Modbus/TCP Security (TLS)";
const TLS_MASTER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/peers/pymodbus_tls_master.py"
);
/// The TLS port the README's walkthrough uses; the tests put the gateway's own in its place.
const README_PORT: &str = "port=8020";
static DIRS: AtomicUsize = AtomicUsize::new(0);

/// The README's section, from its heading to the next `## ` heading.
fn section() -> &'static str {
    let start = README
        .find(&format!("\n{HEADING}\n"))
        .unwrap_or_else(|| panic!("docs/security.md has no section `{HEADING}`"));
    let body = &README[start + HEADING.len() + 2..];
    &body[..body.find("\n## ").unwrap_or(body.len())]
}

/// The contents of the section's fenced blocks whose info string is `lang`, in order. A fence
/// left open fails.
fn blocks(lang: &str) -> Vec<String> {
    let mut found = Vec::new();
    let mut open: Option<(&str, String)> = None;
    for line in section().lines() {
        match (&mut open, line.strip_prefix("```")) {
            (None, Some(info)) => open = Some((info.trim(), String::new())),
            (Some(_), Some("")) => {
                let (info, text) = open.take().expect("a block is open");
                if info == lang {
                    found.push(text);
                }
            }
            (Some((_, text)), _) => {
                text.push_str(line);
                text.push('\n');
            }
            (None, None) => {}
        }
    }
    assert!(
        open.is_none(),
        "`{HEADING}`: a fenced block is never closed"
    );
    assert!(
        !found.is_empty(),
        "`{HEADING}` in docs/security.md has no ```{lang} block"
    );
    found
}

/// A fresh directory where the walkthrough's commands ran; removed when dropped.
struct Walkthrough {
    dir: PathBuf,
}

impl Drop for Walkthrough {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

impl Walkthrough {
    /// Run the section's shell blocks, in order, with bash in a fresh directory; `None` without
    /// openssl.
    async fn run() -> Option<Walkthrough> {
        crate::support::tool("openssl")?;
        let dir = std::env::temp_dir().join(format!(
            "mbgw-walkthrough-{}-{}",
            std::process::id(),
            DIRS.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("a fresh directory");
        let walkthrough = Walkthrough { dir };
        // Their standard error too into the output, shown if they fail.
        let script = format!("exec 2>&1\n{}", blocks("sh").concat());
        let mut bash = Command::new("bash");
        bash.args(["-euo", "pipefail", "-c", &script])
            .current_dir(&walkthrough.dir);
        let output = run_command(bash).await;
        assert!(
            output.status.success(),
            "the README's commands: {}\n{}",
            output.status,
            String::from_utf8_lossy(&output.stdout)
        );
        for name in ["ca", "server", "operator", "viewer"] {
            for ext in ["crt", "key"] {
                let file = walkthrough.file(&format!("{name}.{ext}"));
                assert!(file.is_file(), "the README's commands made no {file:?}");
            }
        }
        Some(walkthrough)
    }

    /// A file the walkthrough made, in its `tls/`.
    fn file(&self, name: &str) -> PathBuf {
        self.dir.join("tls").join(name)
    }

    /// `config/demo-tls.toml`'s `[server.tls]` table, its paths in this directory.
    fn tls_table(&self) -> String {
        let start = DEMO_TLS
            .find("[server.tls]\n")
            .expect("config/demo-tls.toml has a [server.tls] table");
        let table = &DEMO_TLS[start..];
        let table = &table[..table.find("\n\n").unwrap_or(table.len())];
        let relative = "\"tls/";
        assert_eq!(table.matches(relative).count(), 3, "{table}");
        let absolute = format!("\"{}/", self.dir.join("tls").display());
        format!("{}\n", table.replace(relative, &absolute))
    }

    /// `config/demo-tls.toml` with loopback ports of the system's choosing and the certificates
    /// of this directory.
    fn demo_tls_config(&self) -> String {
        let mut config = DEMO_TLS.to_owned();
        for (from, to) in [
            (
                "listen = [\"127.0.0.1:5020\"]",
                "listen = [\"127.0.0.1:0\"]",
            ),
            (
                "listen_tls = [\"127.0.0.1:8020\"]",
                "listen_tls = [\"127.0.0.1:0\"]",
            ),
        ] {
            assert_eq!(config.matches(from).count(), 1, "{from} in demo-tls.toml");
            config = config.replace(from, to);
        }
        let start = config.find("[server.tls]\n").expect("the TLS table");
        let end = start + config[start..].find("\n\n").expect("the table ends");
        config.replace_range(start..=end, &self.tls_table());
        config
    }

    /// Run the TLS master script at `addr` for `unit` with the certificate of `role`; its lines.
    async fn master(
        &self,
        python: &OsString,
        addr: SocketAddr,
        role: &str,
        unit: u8,
        operations: &[&str],
    ) -> Vec<String> {
        let mut command = Command::new(python);
        command
            .arg(TLS_MASTER)
            .args([addr.ip().to_string(), addr.port().to_string()])
            .args([
                self.file("ca.crt"),
                self.file(&format!("{role}.crt")),
                self.file(&format!("{role}.key")),
            ])
            .arg(unit.to_string())
            .args(operations);
        let output = run_command(command).await;
        let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
        assert!(
            output.status.success(),
            "{role}: {}\n{stdout}",
            output.status
        );
        stdout.lines().map(str::to_owned).collect()
    }
}

/// Write `script` into `dir` and run it there with `python`; its standard output.
async fn run_python_in(dir: &Path, python: &OsString, script: &str) -> String {
    let path = dir.join("readme.py");
    std::fs::write(&path, script).expect("write the README's Python");
    let mut command = Command::new(python);
    command.arg(&path).current_dir(dir);
    let output = run_command(command).await;
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "the README's Python: {}\n{stdout}",
        output.status
    );
    stdout
}

#[test]
fn the_walkthrough_has_its_commands_its_python_and_the_output_it_shows() {
    let commands = blocks("sh").concat();
    for role in ["operator", "viewer"] {
        let extension = format!("1.3.6.1.4.1.50316.802.1 = ASN1:UTF8String:{role}");
        assert!(
            commands.lines().any(|line| line == extension),
            "no line `{extension}`"
        );
    }
    assert_eq!(blocks("python").len(), 1);
    assert_eq!(blocks("python")[0].matches(README_PORT).count(), 1);
    assert_eq!(blocks("text").len(), 1);
    // The section's TOML is config/demo-tls.toml's, comments aside.
    let code = |text: &str| -> Vec<String> {
        text.lines()
            .map(|line| line.split('#').next().unwrap_or("").trim_end().to_owned())
            .filter(|line| !line.is_empty())
            .collect()
    };
    let shown = code(&blocks("toml")[0]);
    let shipped = code(DEMO_TLS);
    assert!(
        shipped.windows(2).any(|w| w == &shown[..2]) && shown.iter().all(|l| shipped.contains(l)),
        "the README shows what config/demo-tls.toml has: {shown:?}"
    );
}

/// A pymodbus TLS master with the README's viewer certificate reads the sim line and is refused a
/// write.
#[tokio::test]
async fn the_readmes_viewer_certificate_lets_pymodbus_read_over_tls_but_not_write() {
    let Some(python) = python_with_pymodbus() else {
        return;
    };
    let Some(walkthrough) = Walkthrough::run().await else {
        return;
    };
    let gateway = start(&walkthrough.demo_tls_config()).await;
    let tls = gateway.tls_addrs()[0];

    // Unit 2, the GD300: the operator sets its frequency reference (2001H) and reads it back.
    assert_eq!(
        walkthrough
            .master(
                &python,
                tls,
                "operator",
                2,
                &["write", "0x2001", "2500", "read", "0x2001", "1"]
            )
            .await,
        ["result 6 ok", "result 3 2500"],
        "the operator"
    );
    // The viewer reads the identifying code (2103H: 010AH), is refused its write (0x01), and the
    // reference is still the operator's.
    assert_eq!(
        walkthrough
            .master(
                &python,
                tls,
                "viewer",
                2,
                &["read", "0x2103", "1", "write", "0x2001", "1234", "read", "0x2001", "1"]
            )
            .await,
        ["result 3 266", "exception 6 1", "result 3 2500"],
        "the viewer"
    );

    // The README's own Python, in the walkthrough's directory, on this gateway's port: what the
    // README says it prints.
    let script = blocks("python")[0].replace(README_PORT, &format!("port={}", tls.port()));
    assert_eq!(
        run_python_in(&walkthrough.dir, &python, &script).await,
        blocks("text")[0],
        "the README's Python prints what the README shows"
    );

    let scrape = Scrape::of(&gateway).await;
    let writes = |outcome: &str| {
        scrape.value(&format!(
            "modbus_gateway_requests_total{{bus=\"demo\",function=\"0x06\",outcome=\"{outcome}\",\
             protocol=\"tls\",slave=\"2\"}}"
        ))
    };
    assert_eq!(writes("ok"), 1.0, "the operator's write went to the line");
    assert_eq!(writes("read_only"), 2.0, "the viewer's two writes did not");
}

#[tokio::test]
async fn a_pymodbus_tls_master_reads_a_pymodbus_rtu_slave_on_a_pty_through_the_gateway() {
    let Some(python) = python_with_pymodbus() else {
        return;
    };
    let Some(walkthrough) = Walkthrough::run().await else {
        return;
    };
    let Some(slave) = Pymodbus::start("rtu").await else {
        return;
    };
    let listen = "listen = \"127.0.0.1:0\"\n";
    let config = pty_config(&slave.path, RESPONSE_TIMEOUT).replacen(
        listen,
        &format!(
            "{listen}listen_tls = \"127.0.0.1:0\"\n{}",
            walkthrough.tls_table()
        ),
        1,
    );
    let gateway = start(&config).await;
    let tls = gateway.tls_addrs()[0];

    // The script's registers 0-9 hold 1000-1009. The operator writes register 5 and reads it
    // back with register 6, then reads 0-2; the viewer is refused a write and reads 5.
    assert_eq!(
        walkthrough
            .master(
                &python,
                tls,
                "operator",
                UNIT,
                &["write", "5", "4242", "read", "5", "2", "read", "0", "3"]
            )
            .await,
        [
            "result 6 ok",
            "result 3 4242 1006",
            "result 3 1000 1001 1002"
        ],
        "the operator"
    );
    assert_eq!(
        walkthrough
            .master(
                &python,
                tls,
                "viewer",
                UNIT,
                &["write", "5", "1", "read", "5", "1"]
            )
            .await,
        ["exception 6 1", "result 3 4242"],
        "the viewer"
    );

    // On the wire: the operator's three requests and the viewer's read, nothing else.
    let requests: [&[u8]; 4] = [
        &[0x06, 0x00, 0x05, 0x10, 0x92],
        &[0x03, 0x00, 0x05, 0x00, 0x02],
        &[0x03, 0x00, 0x00, 0x00, 0x03],
        &[0x03, 0x00, 0x05, 0x00, 0x01],
    ];
    let replies: [&[u8]; 4] = [
        &[0x06, 0x00, 0x05, 0x10, 0x92],
        &[0x03, 0x04, 0x10, 0x92, 0x03, 0xEE],
        &[0x03, 0x06, 0x03, 0xE8, 0x03, 0xE9, 0x03, 0xEA],
        &[0x03, 0x02, 0x10, 0x92],
    ];
    let (to_slave, to_gateway) = slave
        .wire(frames(&requests).len(), frames(&replies).len())
        .await;
    assert_eq!(to_slave, frames(&requests), "the requests on the wire");
    assert_eq!(to_gateway, frames(&replies), "the slave's answers");
}
