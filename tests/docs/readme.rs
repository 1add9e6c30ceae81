//! The README's walkthroughs, run as a user would: the metric greps of the ASCII and device server
//! demos. The commands are the README's, with this gateway's ports put in place of the demo's;
//! what they print must be what the README shows.
//!
//! curl comes from the PATH; without it, a test checks nothing and says so, or fails under
//! `MBGW_REQUIRE_TOOLS=1`.

use crate::simulate::Simulator;
use crate::support::{start, tool, within, Scrape};
use std::process::{Command, Output};

const README: &str = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md"));

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
