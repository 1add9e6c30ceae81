//! The README's walkthroughs, run as a user would: "Writes under control" (config/demo-writes.toml,
//! mbpoll's writes and `modbus-gateway audit` on the journal), "A master on a serial line"
//! (config/demo-serial.toml, mbpoll's RTU mode on the port's pty), "A unit the gateway answers
//! itself" (config/demo.toml's virtual unit, read with mbpoll as drive 2 ramps) and the metric greps of the
//! ASCII and device server demos. The commands are the README's, with this gateway's ports, journal and
//! binary put in place of the demo's; what they print must be what the README shows, but for the
//! times and the masters' ports, which are the user's own. A missing section or block fails.
//!
//! mbpoll and curl come from the PATH; without one, a test checks nothing and says so, or fails
//! under `MBGW_REQUIRE_TOOLS=1`.

use crate::simulate::Simulator;
use crate::support::{start, tool, until_exists, within, Scrape, TempDir, PATIENCE};
use std::path::Path;
use std::process::{Command, Output};

const README: &str = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md"));
const DEMO_WRITES: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/config/demo-writes.toml"
));
const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

/// The README's section under `heading`, to the next `## ` heading.
fn section(heading: &str) -> &'static str {
    let marker = format!("\n## {heading}\n");
    let start = README
        .find(&marker)
        .unwrap_or_else(|| panic!("README.md has no section `{heading}`"))
        + marker.len();
    let body = &README[start..];
    &body[..body.find("\n## ").unwrap_or(body.len())]
}

/// The contents of `text`'s fenced blocks whose info string is `lang`, in order.
fn blocks(text: &str, lang: &str) -> Vec<String> {
    let mut found = Vec::new();
    let mut open: Option<(String, String)> = None;
    for line in text.lines() {
        match (open.as_mut(), line.strip_prefix("```")) {
            (None, Some(info)) => open = Some((info.trim().to_owned(), String::new())),
            (Some(_), Some("")) => {
                let (info, body) = open.take().expect("a block is open");
                if info == lang {
                    found.push(body);
                }
            }
            (Some((_, body)), _) => {
                body.push_str(line);
                body.push('\n');
            }
            (None, None) => {}
        }
    }
    assert!(open.is_none(), "a fenced block is never closed");
    found
}

/// A `console` block's commands (`$ ...`), each with the lines shown after it.
fn session(block: &str) -> Vec<(String, Vec<String>)> {
    let mut steps: Vec<(String, Vec<String>)> = Vec::new();
    for line in block.lines() {
        match (line.strip_prefix("$ "), steps.last_mut()) {
            (Some(command), _) => steps.push((command.to_owned(), Vec::new())),
            (None, Some((_, shown))) => shown.push(line.to_owned()),
            (None, None) => panic!("output before any command: {line}"),
        }
    }
    steps
}

/// `line` with what is the user's own put aside: a leading RFC 3339 time in UTC with
/// microseconds, and a loopback master's port.
fn normalised(line: &str) -> String {
    let bytes = line.as_bytes();
    let timed = bytes.len() > 27
        && bytes[4] == b'-'
        && bytes[10] == b'T'
        && bytes[26] == b'Z'
        && bytes[27] == b' ';
    let mut rest = if timed {
        format!("TIME{}", &line[27..])
    } else {
        line.to_owned()
    };
    let master = "127.0.0.1:";
    let mut out = String::new();
    while let Some(at) = rest.find(master) {
        out.push_str(&rest[..at + master.len()]);
        let tail = &rest[at + master.len()..];
        let digits = tail.len() - tail.trim_start_matches(|c: char| c.is_ascii_digit()).len();
        out.push_str(if digits > 0 { "PORT" } else { "" });
        rest = tail[digits..].to_owned();
    }
    out.push_str(&rest);
    out
}

/// Run `command` with bash; its output as a terminal shows it (standard output, then standard
/// error), blank lines left out.
async fn run(command: &str) -> (Output, Vec<String>) {
    let command = command.to_owned();
    let output = within(
        "a command of the README",
        tokio::task::spawn_blocking(move || {
            Command::new("bash")
                .args(["-c", &command])
                .env_remove("RUST_LOG")
                .output()
        }),
    )
    .await
    .unwrap()
    .expect("bash runs");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    let lines = text
        .lines()
        .filter(|line| !line.trim().is_empty())
        .map(str::to_owned)
        .collect();
    (output, lines)
}

/// `text` with `from` replaced by `to`, which it must contain.
fn put(text: &str, from: &str, to: &str) -> String {
    assert!(text.contains(from), "no {from:?} in {text}");
    text.replace(from, to)
}

/// config/demo-writes.toml on loopback ports of the system's choosing, its journal at `journal`.
fn demo_writes_config(journal: &Path) -> String {
    let config = put(DEMO_WRITES, "\"127.0.0.1:5023\"", "\"127.0.0.1:0\"");
    let config = put(&config, "\"127.0.0.1:9023\"", "\"127.0.0.1:0\"");
    put(
        &config,
        "path = \"/tmp/modbus-gateway-demo-writes.jsonl\"",
        &format!("path = \"{}\"", journal.display()),
    )
}

#[tokio::test]
async fn the_writes_walkthrough_prints_what_the_readme_shows() {
    let text = section("Writes under control");
    assert_eq!(
        blocks(text, "sh"),
        ["cargo run --release -- --config config/demo-writes.toml\n"]
    );
    assert!(text.contains("`/tmp/modbus-gateway-demo-writes.jsonl`"));
    let steps: Vec<(String, Vec<String>)> = blocks(text, "console")
        .iter()
        .flat_map(|block| session(block))
        .collect();
    let commands = |program: &str| steps.iter().filter(|(c, _)| c.starts_with(program)).count();
    assert_eq!(commands("mbpoll "), 5, "{steps:?}");
    assert_eq!(commands("cargo run --release -- "), 2, "{steps:?}");
    if tool("mbpoll").is_none() {
        return;
    }
    let dir = TempDir::new("readme-writes");
    let config = demo_writes_config(&dir.join("writes.jsonl"));
    let config_path = dir.join("demo-writes.toml");
    std::fs::write(&config_path, &config).unwrap();
    let gateway = start(&config).await;
    let port = gateway.tcp_addrs()[0].port();
    for (command, shown) in &steps {
        let command = if command.starts_with("mbpoll ") {
            put(command, "-p 5023 ", &format!("-p {port} "))
        } else {
            let command = put(command, "cargo run --release --", BINARY);
            put(
                &command,
                "config/demo-writes.toml",
                &config_path.display().to_string(),
            )
        };
        let (output, printed) = run(&command).await;
        let failed = shown.iter().any(|line| line.contains(" failed: "));
        assert_eq!(output.status.success(), !failed, "{command}: {printed:?}");
        // mbpoll's banner comes first; the README shows the last lines.
        let last = &printed[printed.len().saturating_sub(shown.len())..];
        assert_eq!(
            last.iter().map(|l| normalised(l)).collect::<Vec<_>>(),
            shown.iter().map(|l| normalised(l)).collect::<Vec<_>>(),
            "{command}"
        );
    }
    gateway.shutdown().await;
}

/// The README's command that greps `port`'s metrics, and the lines it shows after it (each
/// `# SERIES VALUE`, maybe followed by a remark).
fn metrics_grep(port: u16) -> (String, Vec<String>) {
    let url = format!("curl -s 127.0.0.1:{port}/metrics | grep ");
    let mut lines = README.lines().skip_while(|line| !line.starts_with(&url));
    let command = lines.next().unwrap_or_else(|| panic!("no `{url}`"));
    let shown = lines
        .map_while(|line| line.strip_prefix("# modbus_gateway_"))
        .map(|line| format!("modbus_gateway_{line}"))
        .collect();
    (command.to_owned(), shown)
}

/// A line of a scrape: its series (name and labels) and its value.
fn series_and_value(line: &str) -> (&str, &str) {
    let end = line.rfind('}').expect("a series with labels") + 1;
    let value = line[end..].split_whitespace().next().expect("a value");
    (&line[..end], value)
}

#[test]
fn every_grep_of_the_metrics_in_the_readme_prints_series_lines_only() {
    let mut greps = 0;
    for line in README
        .lines()
        .filter(|line| line.contains("/metrics | grep "))
    {
        let pattern = line.split("| grep ").nth(1).unwrap();
        let pattern = pattern.strip_prefix("-E ").unwrap_or(pattern);
        assert!(
            pattern.starts_with("'^"),
            "prints the # HELP and # TYPE lines too: {line}"
        );
        greps += 1;
    }
    assert!(greps >= 4, "only {greps} greps");
}

/// Run `command`, the README's grep of a demo's metrics, on `metrics`' instead; the lines it
/// printed.
async fn grep_of(command: &str, port: u16, metrics: std::net::SocketAddr) -> Vec<String> {
    let command = put(
        command,
        &format!("127.0.0.1:{port}/metrics"),
        &format!("{metrics}/metrics"),
    );
    let (output, printed) = run(&command).await;
    assert!(output.status.success(), "{command}: {printed:?}");
    printed
}

#[tokio::test]
async fn the_ascii_demos_grep_prints_the_line_the_readme_shows() {
    let (command, shown) = metrics_grep(9021);
    assert_eq!(shown.len(), 1, "{shown:?}");
    if tool("curl").is_none() {
        return;
    }
    let demo = include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/demo-ascii.toml"
    ));
    let gateway = start(&put(demo, "\"127.0.0.1:5021\"", "\"127.0.0.1:0\"")).await;
    assert_eq!(grep_of(&command, 9021, gateway.metrics_addr()).await, shown);
    gateway.shutdown().await;
}

#[tokio::test]
async fn the_device_server_demos_grep_prints_the_series_the_readme_shows() {
    let (command, shown) = metrics_grep(9022);
    assert_eq!(shown.len(), 3, "{shown:?}");
    if tool("curl").is_none() {
        return;
    }
    let simulator = Simulator::listen("127.0.0.1:0").await;
    let demo = include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/demo-device-server.toml"
    ));
    let config = put(demo, "\"127.0.0.1:5022\"", "\"127.0.0.1:0\"");
    let config = put(
        &config,
        "\"tcp://127.0.0.1:4001\"",
        &format!("\"{}\"", simulator.path),
    );
    let gateway = start(&config).await;
    // The link's series are there once the gateway has connected.
    within("the gateway connects to simulate", async {
        while Scrape::of(&gateway)
            .await
            .series_of("modbus_gateway_link_round_trip_seconds")
            .is_empty()
        {
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    })
    .await;
    let printed = grep_of(&command, 9022, gateway.metrics_addr()).await;
    let series = |lines: &[String]| -> Vec<String> {
        lines
            .iter()
            .map(|line| series_and_value(line).0.to_owned())
            .collect()
    };
    assert_eq!(series(&printed), series(&shown), "{printed:?}");
    // The bus's line is as the README says; the link's figures are this machine's.
    assert_eq!(printed[0], shown[0]);
    gateway.shutdown().await;
    simulator.stop().await;
}

#[tokio::test]
async fn the_serial_port_walkthrough_prints_what_the_readme_shows() {
    let text = section("A master on a serial line");
    assert_eq!(
        blocks(text, "sh")[0],
        "cargo run --release -- --config config/demo-serial.toml\n"
    );
    let steps: Vec<(String, Vec<String>)> = blocks(text, "console")
        .iter()
        .flat_map(|block| session(block))
        .collect();
    let rtu = steps.iter().filter(|(c, _)| c.contains(" -m rtu ")).count();
    assert_eq!((steps.len(), rtu), (3, 2), "{steps:?}");
    let (grep, counted) = metrics_grep(9024);
    assert_eq!(counted.len(), 2, "{counted:?}");
    if tool("mbpoll").is_none() || tool("curl").is_none() {
        return;
    }
    let dir = TempDir::new("readme-serial");
    let link = dir.join("scada").display().to_string();
    let demo = include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/demo-serial.toml"
    ));
    let config = put(demo, "\"127.0.0.1:5024\"", "\"127.0.0.1:0\"");
    let config = put(&config, "\"127.0.0.1:9024\"", "\"127.0.0.1:0\"");
    let config = put(
        &config,
        "\"pty:/tmp/modbus-gateway-scada\"",
        &format!("\"pty:{link}\""),
    );
    let gateway = start(&config).await;
    until_exists(Path::new(&link)).await;
    let port = gateway.tcp_addrs()[0].port();
    for (command, shown) in &steps {
        let command = if command.contains(" -m rtu ") {
            put(command, "/tmp/modbus-gateway-scada", &link)
        } else {
            put(command, "-p 5024 ", &format!("-p {port} "))
        };
        let (output, printed) = run(&command).await;
        assert!(output.status.success(), "{command}: {printed:?}");
        let last = &printed[printed.len().saturating_sub(shown.len())..];
        assert_eq!(last, &shown[..], "{command}");
    }
    assert_eq!(grep_of(&grep, 9024, gateway.metrics_addr()).await, counted);
    gateway.shutdown().await;
}

/// How long drive 2 of the demo takes to ramp to 50.00 Hz (P00.11 = 15.0 s), and to be polled
/// there (every 2 s): the virtual unit's read waits this on top of the usual patience.
const RAMP_AND_POLL: std::time::Duration = std::time::Duration::from_secs(17);

#[tokio::test]
async fn the_virtual_unit_walkthrough_prints_what_the_readme_shows() {
    let text = section("A unit the gateway answers itself");
    assert_eq!(
        blocks(text, "sh")[0],
        "cargo run --release -- --config config/demo.toml\n"
    );
    let steps: Vec<(String, Vec<String>)> = blocks(text, "console")
        .iter()
        .flat_map(|block| session(block))
        .collect();
    let virtual_reads = steps.iter().filter(|(c, _)| c.contains(" -a 100 ")).count();
    assert_eq!((steps.len(), virtual_reads), (5, 3), "{steps:?}");
    // The README's grep of the counter, and the series it shows.
    let grep_line = text
        .lines()
        .find(|line| line.starts_with("curl -s 127.0.0.1:9020/metrics | grep "))
        .expect("a grep of the virtual unit's counter");
    let counted: Vec<String> = text
        .lines()
        .skip_while(|line| *line != grep_line)
        .skip(1)
        .map_while(|line| line.strip_prefix("# modbus_gateway_"))
        .map(|line| format!("modbus_gateway_{line}"))
        .collect();
    assert_eq!(counted.len(), 2, "{counted:?}");
    if tool("mbpoll").is_none() || tool("curl").is_none() {
        return;
    }
    let demo = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/config/demo.toml"));
    let config = put(demo, "\"127.0.0.1:5020\"", "\"127.0.0.1:0\"");
    let config = put(&config, "\"127.0.0.1:9020\"", "\"127.0.0.1:0\"");
    let gateway = start(&config).await;
    let port = gateway.tcp_addrs()[0].port();
    // The README's first read is answered once the drives have been polled: until then, 0x0B.
    let (first, _) = &steps[0];
    let first = put(first, "-p 5020 ", &format!("-p {port} "));
    within("the drives' first polls", async {
        while !run(&first).await.0.status.success() {
            tokio::time::sleep(std::time::Duration::from_millis(200)).await;
        }
    })
    .await;
    for (at, (command, shown)) in steps.iter().enumerate() {
        let command = put(command, "-p 5020 ", &format!("-p {port} "));
        let failed = shown.iter().any(|line| line.contains(" failed: "));
        // The read after drive 2 started shows it at 50.00 Hz: "a few seconds later", repeated
        // until it does.
        let repeated = at > 0 && command.contains(" -a 100 ") && !failed;
        let deadline = tokio::time::Instant::now() + RAMP_AND_POLL + PATIENCE;
        loop {
            let (output, printed) = run(&command).await;
            let last = &printed[printed.len().saturating_sub(shown.len())..];
            if repeated && last != &shown[..] && tokio::time::Instant::now() < deadline {
                tokio::time::sleep(std::time::Duration::from_millis(500)).await;
                continue;
            }
            assert_eq!(output.status.success(), !failed, "{command}: {printed:?}");
            assert_eq!(last, &shown[..], "{command}");
            break;
        }
    }
    // The counter's series as the README shows them: not_mapped once (the read of register 11),
    // answered at least as often as the README's reads (this test repeats them).
    let printed = grep_of(grep_line, 9020, gateway.metrics_addr()).await;
    let series = |lines: &[String]| -> Vec<(String, String)> {
        lines
            .iter()
            .map(|line| {
                let (series, value) = series_and_value(line);
                (series.to_owned(), value.to_owned())
            })
            .collect()
    };
    let (printed, counted) = (series(&printed), series(&counted));
    assert_eq!(
        printed.iter().map(|(s, _)| s).collect::<Vec<_>>(),
        counted.iter().map(|(s, _)| s).collect::<Vec<_>>(),
        "{printed:?}"
    );
    assert_eq!(printed[1], counted[1]);
    let answered = |value: &str| value.parse::<u64>().expect("a count");
    assert!(
        answered(&printed[0].1) >= answered(&counted[0].1),
        "{printed:?}"
    );
    gateway.shutdown().await;
}
