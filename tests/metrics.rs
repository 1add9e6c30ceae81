//! What `/metrics`, `/healthz` and `/readyz` say about known traffic through a real gateway on
//! the simulated line, read over a real HTTP connection; promtool's verdict on the scrape; the
//! shipped alert rules and dashboard naming only metrics the gateway exports; and scrapes that
//! succeed while stalled trace readers and silent sockets hold the endpoint.

use crate::support::{
    addr, http_get, sim_line, start, within, Bus, GatewayConfig, RawMaster, Scrape,
};
use modbus_gateway::testing::sim::Source;
use modbus_gateway::Gateway;
use std::collections::BTreeSet;
use std::time::Duration;

/// Read two holding registers from 0000H: 8 bytes on the wire, 9 back from a register slave.
const READ_2: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x02];
/// 126 registers is one more than a read may ask for: the slave's exception 03, 5 bytes back.
const READ_126: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x7E];

/// One 9600 8E1 line "sim" with register slaves 1-4, and slave 5 configured but absent (silent),
/// with a short timeout and one retry for reads.
fn line() -> GatewayConfig {
    GatewayConfig::new().bus(
        sim_line()
            .key("retries", 1)
            .key("reopen_delay", "10ms")
            .key("reopen_delay_max", "20ms")
            .slave(5, &[("response_timeout", "50ms".into())])
            .sim_slaves("1-4"),
    )
}

/// `name{labels}` as the gateway writes a series: labels sorted by name.
fn series(name: &str, labels: &[(&str, &str)]) -> String {
    let mut labels = labels.to_vec();
    labels.sort();
    let inner: Vec<String> = labels.iter().map(|(k, v)| format!("{k}=\"{v}\"")).collect();
    format!("{name}{{{}}}", inner.join(","))
}

fn requests(bus: &str, slave: &str, outcome: &str) -> String {
    series(
        "modbus_gateway_requests_total",
        &[
            ("bus", bus),
            ("slave", slave),
            ("function", "0x03"),
            ("outcome", outcome),
            ("protocol", "tcp"),
        ],
    )
}

fn exceptions(bus: &str, slave: &str, source: &str, code: &str) -> String {
    series(
        "modbus_gateway_exceptions_total",
        &[
            ("bus", bus),
            ("slave", slave),
            ("source", source),
            ("code", code),
        ],
    )
}

fn of_bus(name: &str) -> String {
    series(name, &[("bus", "sim")])
}

fn of_slave(name: &str, slave: &str) -> String {
    series(name, &[("bus", "sim"), ("slave", slave)])
}

fn sum(scrape: &Scrape, name: &str) -> f64 {
    scrape.series_of(name).iter().map(|(_, v)| v).sum()
}

#[tokio::test]
async fn known_traffic_moves_each_counter_and_histogram_by_exactly_what_it_caused() {
    let gateway = line().start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // Wait for the port, and a first answer, so the start-up itself is not in the figures.
    assert_eq!(master.call(0, 1, &READ_2).await, [0x03, 0x04, 0, 0, 0, 0]);
    let before = Scrape::of(&gateway).await;

    for tid in 1..=3 {
        assert_eq!(master.call(tid, 1, &READ_2).await, [0x03, 0x04, 0, 0, 0, 0]);
    }
    assert_eq!(master.call(4, 2, &READ_126).await, [0x83, 0x03]);
    assert_eq!(master.call(5, 5, &READ_2).await, [0x83, 0x0B]);
    assert_eq!(master.call(6, 250, &READ_2).await, [0x83, 0x0A]);
    let after = Scrape::of(&gateway).await;

    let increments = [
        (requests("sim", "1", "ok"), 3.0),
        (requests("sim", "2", "exception"), 1.0),
        (exceptions("sim", "2", "slave", "0x03"), 1.0),
        (requests("sim", "5", "timeout"), 1.0),
        (exceptions("sim", "5", "gateway", "0x0B"), 1.0),
        (of_slave("modbus_gateway_retries_total", "5"), 1.0),
        (of_slave("modbus_gateway_retries_total", "1"), 0.0),
        // No route: no bus, and no slave (the unit id is the master's to choose).
        (requests("", "other", "no_route"), 1.0),
        (exceptions("", "other", "gateway", "0x0A"), 1.0),
        // Four requests answered on the line, one timed out twice.
        (of_bus("modbus_gateway_round_trip_seconds_count"), 5.0),
        (
            series(
                "modbus_gateway_queue_wait_seconds_count",
                &[("bus", "sim"), ("class", "normal")],
            ),
            5.0,
        ),
        // 3 reads of 8 + 9 bytes, 8 + 5 for the exception, 2 x 8 unanswered.
        (of_bus("modbus_gateway_line_sent_bytes_total"), 48.0),
        (of_bus("modbus_gateway_line_received_bytes_total"), 32.0),
        (of_bus("modbus_gateway_discarded_frames_total"), 0.0),
        (of_bus("modbus_gateway_stray_bytes_total"), 0.0),
    ];
    for (series, increment) in &increments {
        assert_eq!(after.delta(&before, series), *increment, "{series}");
    }
    // Nothing else was counted: six requests, three exceptions.
    assert_eq!(
        sum(&after, "modbus_gateway_requests_total")
            - sum(&before, "modbus_gateway_requests_total"),
        6.0
    );
    assert_eq!(
        sum(&after, "modbus_gateway_exceptions_total")
            - sum(&before, "modbus_gateway_exceptions_total"),
        3.0
    );

    // The line was busy for exactly its 80 characters of 11 bits at 9600 baud.
    let busy = after.delta(&before, &of_bus("modbus_gateway_line_busy_seconds_total"));
    assert!((busy - 80.0 * 11.0 / 9600.0).abs() < 1e-6, "busy {busy} s");

    // Physics bounds the round trips from below: at 9600 baud no exchange takes under 10 ms,
    // and the timed-out read waited two 50 ms timeouts.
    let bucket = |le: &str| {
        let labels = [("bus", "sim"), ("le", le)];
        after.delta(
            &before,
            &series("modbus_gateway_round_trip_seconds_bucket", &labels),
        )
    };
    assert_eq!(bucket("0.01"), 0.0);
    assert!(bucket("0.1") <= 4.0, "the timed-out read took over 100 ms");
    assert_eq!(bucket("+Inf"), 5.0);
    let round_trips = after.delta(&before, &of_bus("modbus_gateway_round_trip_seconds_sum"));
    assert!(round_trips >= 0.1 + 4.0 * 0.013, "{round_trips}");

    // Slaves that answered are up with the time of that answer; the silent one is down; those
    // never asked stay at zero.
    for (slave, up) in [("1", 1.0), ("2", 1.0), ("3", 0.0), ("4", 0.0), ("5", 0.0)] {
        let at = after.value(&of_slave("modbus_gateway_slave_up", slave));
        assert_eq!(at, up, "slave {slave} up");
        let last = of_slave("modbus_gateway_slave_last_success_timestamp_seconds", slave);
        assert_eq!(
            after.value(&last) > 0.0,
            up == 1.0,
            "slave {slave} last success"
        );
    }
    assert_eq!(
        after.value("modbus_gateway_tcp_connections{protocol=\"tcp\"}"),
        1.0
    );
    assert_eq!(
        after.value("modbus_gateway_tcp_connections_accepted_total{protocol=\"tcp\"}"),
        1.0
    );
}

#[tokio::test]
async fn readyz_turns_503_while_a_port_is_lost_and_200_when_it_is_back() {
    let gateway = line().start().await;
    let metrics = gateway.metrics_addr();
    let ready = || async move { http_get(metrics, "/readyz").await };
    let wait_for = |status: u16| async move {
        within(&format!("/readyz answers {status}"), async {
            loop {
                let (code, body) = ready().await;
                if code == status {
                    return body;
                }
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await
    };
    wait_for(200).await;
    assert_eq!(http_get(metrics, "/healthz").await.0, 200);

    let line = gateway.sim_line("sim").unwrap().clone();
    line.unplug();
    let body = wait_for(503).await;
    assert!(body.contains("bus sim: port down"), "{body}");
    assert_eq!(http_get(metrics, "/healthz").await.0, 200, "still alive");
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ_2).await, [0x83, 0x0A]);
    let down = Scrape::of(&gateway).await;
    assert_eq!(down.value(&of_bus("modbus_gateway_port_up")), 0.0);
    assert_eq!(down.value(&requests("sim", "1", "port_down")), 1.0);
    assert_eq!(down.value(&exceptions("sim", "1", "gateway", "0x0A")), 1.0);

    line.plug();
    assert_eq!(wait_for(200).await, "ready\n");
    let back = Scrape::of(&gateway).await;
    assert_eq!(back.value(&of_bus("modbus_gateway_port_up")), 1.0);
    assert_eq!(
        back.value(&of_bus("modbus_gateway_port_reopens_total")),
        1.0
    );
    assert_eq!(http_get(metrics, "/nothing-here").await.0, 404);
}

#[tokio::test]
async fn requests_of_a_master_that_left_are_counted_dropped_and_never_sent() {
    let gateway = GatewayConfig::new()
        .bus(
            Bus::sim("sim")
                .baud(9600)
                .sim_slave("1", &[("processing_delay", "300ms".into())]),
        )
        .start()
        .await;
    let line = gateway.sim_line("sim").unwrap().clone();
    let mut master = RawMaster::connect(addr(&gateway)).await;
    for tid in 0..5 {
        master.send(tid, 1, &READ_2).await;
    }
    within("the first request is on the wire", async {
        while line.frames().is_empty() {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    })
    .await;
    drop(master);
    let scrape = within("all five requests are counted", async {
        loop {
            let scrape = Scrape::of(&gateway).await;
            if sum(&scrape, "modbus_gateway_requests_total") == 5.0 {
                return scrape;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    assert_eq!(scrape.value(&requests("sim", "1", "ok")), 1.0);
    assert_eq!(scrape.value(&requests("sim", "1", "dropped")), 4.0);
    let sent = line
        .frames()
        .iter()
        .filter(|f| f.from == Source::Master)
        .count();
    assert_eq!(sent, 1, "only the request already on the wire was sent");
    assert_eq!(
        scrape.value(
            "modbus_gateway_tcp_connections_closed_total{protocol=\"tcp\",reason=\"by_master\"}"
        ),
        1.0
    );
    assert_eq!(
        scrape.value("modbus_gateway_tcp_connections{protocol=\"tcp\"}"),
        0.0
    );
}

#[tokio::test]
async fn refused_and_broken_connections_are_counted_by_reason() {
    let gateway = line()
        .max_connections(1)
        .server("when_full", "refuse")
        .start()
        .await;
    let mut first = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(first.call(1, 1, &READ_2).await.len(), 6);
    let mut second = RawMaster::connect(addr(&gateway)).await;
    assert!(second.is_closed().await, "over max_connections");
    // Protocol id 1 is not Modbus: the connection is closed.
    first.send_raw(&[0, 1, 0, 1, 0, 6, 1, 3, 0, 0, 0, 1]).await;
    assert!(first.is_closed().await);
    let scrape = within("the close is counted", async {
        loop {
            let scrape = Scrape::of(&gateway).await;
            if scrape.value("modbus_gateway_tcp_connections{protocol=\"tcp\"}") == 0.0 {
                return scrape;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    let reason = |name: &str, reason: &str| {
        scrape.value(&series(name, &[("protocol", "tcp"), ("reason", reason)]))
    };
    let rejected = "modbus_gateway_tcp_connections_rejected_total";
    let closed = "modbus_gateway_tcp_connections_closed_total";
    assert_eq!(reason(rejected, "max_connections"), 1.0);
    assert_eq!(reason(closed, "protocol_error"), 1.0);
    assert_eq!(reason(closed, "by_master"), 0.0);
    assert_eq!(
        scrape.value("modbus_gateway_tcp_connections_accepted_total{protocol=\"tcp\"}"),
        1.0
    );
}

#[tokio::test]
async fn every_one_of_247_known_slaves_has_its_series_from_the_start() {
    let gateway = GatewayConfig::new()
        .bus(Bus::sim("sim").sim_slaves("1-247"))
        .start()
        .await;
    let scrape = Scrape::of(&gateway).await;
    for name in [
        "modbus_gateway_slave_up",
        "modbus_gateway_slave_last_success_timestamp_seconds",
        "modbus_gateway_retries_total",
    ] {
        let series = scrape.series_of(name);
        assert_eq!(series.len(), 247, "{name}");
        assert!(series.iter().all(|(_, v)| *v == 0.0), "{name}");
    }
}

#[tokio::test]
async fn a_polled_slave_has_a_zero_series_for_every_poll_outcome_before_any_fails() {
    let gateway = GatewayConfig::new()
        .bus(sim_line().sim_slaves("1-4").text(
            "[[bus.slave]]\naddress = 1\npoll_interval = \"1h\"\n\
             [[bus.slave.value]]\nname = \"register_zero\"\nregister = 0\n",
        ))
        .start()
        .await;
    let polls = "modbus_gateway_polls_total{bus=\"sim\",slave=\"1\"}";
    let scrape = within("the first poll", async {
        loop {
            let scrape = Scrape::of(&gateway).await;
            if scrape.get(polls) == Some(1.0) {
                return scrape;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    // The poll was good: every outcome of a failed one is there all the same, at 0.
    let failed = scrape.series_of("modbus_gateway_poll_errors_total");
    let outcomes: BTreeSet<&str> = failed
        .iter()
        .map(|(series, value)| {
            assert_eq!(*value, 0.0, "{series}");
            assert!(series.contains("bus=\"sim\"") && series.contains("slave=\"1\""));
            let outcome = series.split("outcome=\"").nth(1).unwrap();
            &outcome[..outcome.find('"').unwrap()]
        })
        .collect();
    let documented = [
        "timeout",
        "exception",
        "bad_reply",
        "port_down",
        "slave_down",
        "queue_full",
        "expired",
    ];
    assert_eq!(outcomes, BTreeSet::from(documented), "{failed:?}");
    assert_eq!(failed.len(), documented.len());
}

#[tokio::test]
async fn the_bus_info_help_names_every_framing_and_transport_its_labels_take() {
    use modbus_gateway::testing::line::Framing;
    let gateway = line().start().await;
    let scrape = Scrape::of(&gateway).await;
    let help = scrape
        .text
        .lines()
        .find_map(|line| line.strip_prefix("# HELP modbus_gateway_bus_info "))
        .expect("a HELP line");
    // The words in the brackets after `framing` and after `transport`.
    let listed = |after: &str| -> BTreeSet<&str> {
        let start = help.find(&format!("{after} (")).expect(after) + after.len() + 2;
        let end = start + help[start..].find(')').expect("the list ends");
        help[start..end]
            .split(|c: char| !c.is_ascii_alphanumeric())
            .collect()
    };
    // Every framing (the match stops compiling when one is added) and every transport label.
    let framings = [Framing::Rtu, Framing::Ascii, Framing::Tcp].map(|framing| match framing {
        Framing::Rtu | Framing::Ascii | Framing::Tcp => framing.name(),
    });
    let transports = ["serial", "sim", "tcp", "rfc2217", "tls"];
    let monitoring =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/monitoring.md"))
            .unwrap();
    let row = monitoring
        .lines()
        .find(|line| line.starts_with("| `modbus_gateway_bus_info` |"))
        .expect("docs/monitoring.md's row");
    for (label, list) in framings
        .iter()
        .map(|f| (f, "framing"))
        .chain(transports.iter().map(|t| (t, "transport")))
    {
        assert!(
            listed(list).contains(label),
            "the HELP names no {list} {label}: {help}"
        );
        assert!(
            row.contains(&format!("`{label}`")),
            "the docs name no {label}: {row}"
        );
    }
}

/// A gateway that has seen every kind of outcome and event the metrics describe.
async fn gateway_after_mixed_traffic() -> Gateway {
    let gateway = line().start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ_2).await.len(), 6);
    assert_eq!(master.call(2, 2, &READ_126).await, [0x83, 0x03]);
    assert_eq!(master.call(3, 5, &READ_2).await, [0x83, 0x0B]);
    assert_eq!(master.call(4, 250, &READ_2).await, [0x83, 0x0A]);
    assert_eq!(master.call(5, 0, &READ_2).await, [0x83, 0x01]);
    assert_eq!(
        master.call(6, 0, &[0x06, 0, 1, 0, 7]).await,
        [0x06, 0, 1, 0, 7]
    );
    gateway
}

#[tokio::test]
async fn promtool_finds_nothing_to_lint_in_a_scrape() {
    let gateway = gateway_after_mixed_traffic().await;
    let scrape = Scrape::of(&gateway).await;
    assert_promtool_finds_nothing_to_lint(&scrape.text).await;
}

/// `promtool check metrics` on `text` succeeds and says nothing (or, without promtool, the test
/// says it checks nothing).
pub(crate) async fn assert_promtool_finds_nothing_to_lint(text: &str) {
    let Some(promtool) = crate::support::tool("promtool") else {
        return;
    };
    let mut child = std::process::Command::new(promtool)
        .args(["check", "metrics"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("promtool runs");
    {
        use std::io::Write;
        let mut stdin = child.stdin.take().unwrap();
        stdin.write_all(text.as_bytes()).unwrap();
    }
    let out = within(
        "promtool",
        tokio::task::spawn_blocking(move || child.wait_with_output()),
    )
    .await
    .unwrap()
    .unwrap();
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{said}");
    assert_eq!(said.trim(), "", "promtool lint output");
}

/// The `modbus_gateway_*` metric names a text mentions.
fn names_in(text: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut rest = text;
    while let Some(at) = rest.find("modbus_gateway_") {
        let tail = &rest[at..];
        let len = tail
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(tail.len());
        names.insert(tail[..len].to_owned());
        rest = &tail[len..];
    }
    names
}

#[tokio::test]
async fn the_shipped_alerts_and_dashboard_use_only_metrics_the_gateway_exports() {
    // The mixed traffic's line, with a plant value on a slave that never answers: its polls
    // time out, so the poll metrics have series too; a journal of writes; and an MQTT client
    // (its metrics exist with [mqtt], whether a broker answers or not).
    let journal = std::env::temp_dir().join(format!("mbgw-alerts-{}.jsonl", std::process::id()));
    let broker = format!("mqtt://{}", crate::support::free_addr());
    let gateway = GatewayConfig::new()
        .table("audit", &[("path", journal.display().to_string().into())])
        .table("mqtt", &[("url", broker.into())])
        .bus(
            sim_line()
                .slave(5, &[("response_timeout", "50ms".into())])
                .sim_slaves("1-4")
                .text(
                    "[[bus.slave]]\naddress = 6\nresponse_timeout = \"50ms\"\n\
                     poll_interval = \"100ms\"\n[[bus.slave.value]]\nname = \"silent_value\"\n\
                     register = 0\n",
                ),
        )
        .start()
        .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ_2).await.len(), 6);
    assert_eq!(master.call(2, 2, &READ_126).await, [0x83, 0x03]);
    let errors = "modbus_gateway_poll_errors_total{bus=\"sim\",outcome=\"timeout\",slave=\"6\"}";
    let scrape = within("a poll times out", async {
        loop {
            let scrape = Scrape::of(&gateway).await;
            if scrape.get(errors).is_some_and(|n| n >= 1.0) {
                return scrape;
            }
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        }
    })
    .await;
    let exported: BTreeSet<String> = scrape
        .text
        .lines()
        .filter_map(|line| line.strip_prefix("# TYPE "))
        .flat_map(|line| {
            let mut words = line.split(' ');
            let name = words.next().unwrap_or_default().to_owned();
            let kind = words.next().unwrap_or_default();
            let mut names = vec![name.clone()];
            if kind == "histogram" {
                names.extend(["_bucket", "_sum", "_count"].map(|s| format!("{name}{s}")));
            }
            names
        })
        .collect();
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/config/prometheus");
    let mut checked = 0;
    for entry in std::fs::read_dir(dir).expect("config/prometheus exists") {
        let path = entry.unwrap().path();
        let text = std::fs::read_to_string(&path).unwrap();
        let named = names_in(&text);
        let unknown: Vec<_> = named.difference(&exported).collect();
        assert!(unknown.is_empty(), "{}: {unknown:?}", path.display());
        checked += named.len();
    }
    assert!(checked > 10, "the shipped files name the gateway's metrics");
}

/// While eight stalled trace readers and silent sockets hold the endpoint.
#[tokio::test]
async fn every_scrape_succeeds_beside_stalled_trace_readers_and_silent_sockets() {
    use crate::support::{
        fast_sim_config, fill_trace_with_stalled_readers, keep_line_busy, silent_socket,
        stalled_trace_reader, try_http_get,
    };
    let gateway = start(&fast_sim_config()).await;
    let metrics = gateway.metrics_addr();
    let traffic = keep_line_busy(addr(&gateway));
    let mut stalled = fill_trace_with_stalled_readers(metrics).await;
    // A stalled reader is dropped after a while: two more a second take the places that free.
    let more_stalled = tokio::spawn(async move {
        loop {
            tokio::time::sleep(Duration::from_millis(500)).await;
            stalled.push(stalled_trace_reader(metrics).await);
        }
    });
    // Ten silent sockets, more than the places left, each opened again once closed.
    let silent: Vec<_> = (0..10)
        .map(|_| silent_socket(metrics, Duration::from_millis(100)))
        .collect();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut failed = Vec::new();
    for scrape in 0..40 {
        match try_http_get(metrics, "/metrics", Duration::from_secs(5)).await {
            Ok((200, body)) if body.contains("modbus_gateway_build_info") => {}
            other => failed.push((scrape, other)),
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    for task in silent.iter().chain([&more_stalled, &traffic]) {
        task.abort();
    }
    assert!(
        failed.is_empty(),
        "{} of 40 scrapes failed: {failed:?}",
        failed.len()
    );
    gateway.shutdown().await;
}

#[tokio::test]
async fn a_connection_to_the_endpoint_that_sends_nothing_is_closed_within_seconds() {
    use tokio::io::AsyncReadExt;
    let gateway = line().start().await;
    let mut silent = within(
        "connect",
        tokio::net::TcpStream::connect(gateway.metrics_addr()),
    )
    .await
    .unwrap();
    let mut byte = [0u8; 1];
    // Well within the 10 s a request head may take once begun, well past the 2 s limit.
    let closed = tokio::time::timeout(Duration::from_secs(6), silent.read(&mut byte)).await;
    assert!(
        matches!(closed, Ok(Ok(0) | Err(_))),
        "closed without a byte: {closed:?}"
    );
    gateway.shutdown().await;
}

#[tokio::test]
async fn the_endpoints_connections_get_tcp_keepalive_probes() {
    let Some(ss) = crate::support::tool("ss") else {
        return;
    };
    let gateway = line().start().await;
    let metrics = gateway.metrics_addr();
    // A trace stream: a connection that stays.
    let _reader = crate::support::stalled_trace_reader(metrics).await;
    let gateway_side = || {
        let output = std::process::Command::new(&ss)
            .args(["-tnoH", "state", "established"])
            .arg(format!("( sport = :{} )", metrics.port()))
            .output()
            .expect("ss runs");
        String::from_utf8_lossy(&output.stdout).into_owned()
    };
    // Once the stream is answered (its request read, nothing queued either way).
    let mut sockets = gateway_side();
    for _ in 0..100 {
        if sockets.contains("timer:(keepalive,") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
        sockets = gateway_side();
    }
    assert_eq!(sockets.lines().count(), 1, "{sockets}");
    assert!(sockets.contains("timer:(keepalive,"), "{sockets}");
    gateway.shutdown().await;
}
