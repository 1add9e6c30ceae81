//! The status page as an operator reads it after known traffic: each bus, each slave's answers
//! and errors, the connected masters and their rights, the last writes and how each ended; `/`
//! is one page loading nothing from elsewhere. Over real HTTP from a gateway on the simulated
//! line; `.ci/status-page-check` loads the page in a real browser.

use crate::support::{addr, http_get, sim_line, start, within, GatewayConfig, RawMaster};
use serde_json::Value;
use std::net::SocketAddr;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Read two holding registers from 0000H: a register slave answers.
const READ_2: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x02];
/// 126 registers is one more than a read may ask for: the slave's exception 03.
const READ_126: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x7E];
/// Write 0x1388 to holding register 0x2001.
const WRITE_2001: [u8; 5] = [0x06, 0x20, 0x01, 0x13, 0x88];
/// Write 2 registers from 0x0010: 0x0001, 0x0002.
const WRITE_0010_2: [u8; 10] = [0x10, 0x00, 0x10, 0x00, 0x02, 0x04, 0x00, 0x01, 0x00, 0x02];

/// One 9600 8E1 line "sim" with register slaves 1-4, and slave 5 configured but absent (silent)
/// with a short timeout.
fn line() -> GatewayConfig {
    GatewayConfig::new().bus(
        sim_line()
            .slave(5, &[("response_timeout", "50ms".into())])
            .sim_slave("1-4", &[("model", "registers".into())]),
    )
}

async fn get_status(metrics: SocketAddr) -> Value {
    let (code, body) = http_get(metrics, "/status").await;
    assert_eq!(code, 200, "{body}");
    serde_json::from_str(&body).unwrap_or_else(|e| panic!("/status is not JSON ({e}): {body}"))
}

/// The slave at `address` on the first bus.
fn slave(status: &Value, address: u64) -> &Value {
    let slaves = status["buses"][0]["slaves"].as_array().expect("slaves");
    slaves
        .iter()
        .find(|s| s["address"] == address)
        .unwrap_or_else(|| panic!("slave {address} not listed: {status:#}"))
}

/// One HTTP/1.1 request: the response's head (status line and headers, lower-cased) and its body.
async fn request(addr: SocketAddr, method: &str, path: &str) -> (String, String) {
    let mut stream = within("connect", TcpStream::connect(addr)).await.unwrap();
    let request = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut response = String::new();
    within("response", stream.read_to_string(&mut response))
        .await
        .unwrap();
    let (head, body) = response.split_once("\r\n\r\n").expect("an HTTP response");
    (head.to_lowercase(), body.to_owned())
}

#[tokio::test]
async fn status_shows_the_bus_each_slave_s_answers_and_errors_and_the_connected_master() {
    let gateway = line().start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ_2).await[0], 0x03);
    assert_eq!(master.call(2, 2, &READ_126).await, [0x83, 0x03]);
    assert_eq!(master.call(3, 5, &READ_2).await, [0x83, 0x0B]);
    let status = get_status(gateway.metrics_addr()).await;

    assert_eq!(status["version"], env!("CARGO_PKG_VERSION"));
    assert!(status["uptime_seconds"].as_f64().unwrap() > 0.0);
    let bus = &status["buses"][0];
    assert_eq!(bus["name"], "sim");
    assert_eq!(bus["device"], "simulated");
    assert_eq!(bus["framing"], "rtu");
    assert_eq!(bus["port_up"], true);
    assert_eq!(bus["queue_depth"], 0);
    assert_eq!(bus["queue_capacity"], 256);
    assert_eq!(bus["transactions"], 3);
    let utilisation = bus["utilisation"].as_f64().unwrap();
    assert!(utilisation > 0.0 && utilisation <= 1.0, "{utilisation}");

    let answered = slave(&status, 1);
    assert_eq!(answered["up"], true);
    assert_eq!(answered["model"], "registers");
    assert!(answered["last_answer"].as_str().unwrap().ends_with('Z'));
    assert!(answered["last_answer_seconds_ago"].as_f64().unwrap() < 60.0);
    // 8 bytes out and 9 back at 9600 8E1 are 19.5 ms of characters alone.
    let p50 = answered["round_trip_p50_seconds"].as_f64().unwrap();
    assert!(p50 > 0.0195 && p50 < 1.0, "{p50}");
    assert_eq!(answered["requests"], serde_json::json!({ "ok": 1 }));
    assert_eq!(answered["errors"], 0);

    let refused = slave(&status, 2);
    assert_eq!(refused["up"], true, "an exception is an answer");
    assert_eq!(refused["requests"]["exception"], 1);
    assert_eq!(refused["errors"], 1);

    let silent = slave(&status, 5);
    assert_eq!(silent["up"], false);
    assert_eq!(silent["model"], Value::Null);
    assert_eq!(silent["last_answer"], Value::Null);
    assert_eq!(silent["requests"]["timeout"], 1);
    assert_eq!(silent["errors"], 1);
    let never_asked = slave(&status, 3);
    assert_eq!(never_asked["requests"], serde_json::json!({}));
    assert_eq!(never_asked["round_trip_p50_seconds"], Value::Null);

    let masters = status["masters"].as_array().unwrap();
    assert_eq!(masters.len(), 1, "{status:#}");
    let master_status = &masters[0];
    assert!(master_status["address"]
        .as_str()
        .unwrap()
        .starts_with("127.0.0.1:"));
    assert_eq!(master_status["protocol"], "tcp");
    assert_eq!(master_status["rights"], "read_write");
    assert_eq!(master_status["role"], Value::Null);
    assert_eq!(master_status["requests"], 3);
    assert_eq!(
        status["writes"],
        serde_json::json!([]),
        "reads are no writes"
    );
    drop(master);
    within("the master that left is no longer listed", async {
        while !get_status(gateway.metrics_addr()).await["masters"]
            .as_array()
            .unwrap()
            .is_empty()
        {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    })
    .await;
    gateway.shutdown().await;
}

#[tokio::test]
async fn status_lists_the_last_writes_oldest_first_with_their_rule_and_how_each_ended() {
    let toml = format!(
        "{}\n[[rule]]\nname = \"unit 2 on trial\"\nunits = \"2\"\nfunctions = \"write\"\n\
         action = \"acknowledge\"\n",
        line().to_toml()
    );
    let gateway = start(&toml).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &WRITE_0010_2).await, WRITE_0010_2[..5]);
    assert_eq!(
        master.call(2, 2, &WRITE_2001).await,
        WRITE_2001,
        "acknowledged"
    );
    assert_eq!(
        master.call(3, 5, &WRITE_2001).await,
        [0x86, 0x0B],
        "slave 5 is silent"
    );
    assert_eq!(master.call(4, 1, &READ_2).await[0], 0x03);
    let status = within("the three writes, each with its outcome", async {
        loop {
            let status = get_status(gateway.metrics_addr()).await;
            let writes = status["writes"].as_array().expect("writes").clone();
            if writes.len() == 3 && writes.iter().all(|w| w["outcome"].is_object()) {
                return status;
            }
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    })
    .await;
    let writes = status["writes"].as_array().unwrap();
    let (answered, acknowledged, timed_out) = (&writes[0], &writes[1], &writes[2]);
    let write = &answered["write"];
    assert_eq!(write["id"], 1, "{status:#}");
    assert!(write["time"].as_str().unwrap().ends_with('Z'));
    assert!(write["master"].as_str().unwrap().starts_with("127.0.0.1:"));
    assert_eq!(write["protocol"], "tcp");
    assert_eq!(write["unit"], 1);
    assert_eq!(write["bus"], "sim");
    assert_eq!(write["slave"], 1);
    assert_eq!(write["function"], 0x10);
    assert_eq!(write["table"], "holding");
    assert_eq!(write["start"], 0x0010);
    assert_eq!(write["count"], 2);
    assert_eq!(write["values"], "00010002");
    assert_eq!(write["rule"], Value::Null);
    assert_eq!(write["action"], "allow");
    assert_eq!(answered["outcome"]["id"], 1);
    assert_eq!(answered["outcome"]["outcome"], "answered");
    assert_eq!(answered["outcome"]["carried_out"], "yes");

    assert_eq!(acknowledged["write"]["unit"], 2);
    assert_eq!(acknowledged["write"]["values"], "1388");
    assert_eq!(acknowledged["write"]["rule"], "unit 2 on trial");
    assert_eq!(acknowledged["write"]["action"], "acknowledge");
    assert_eq!(acknowledged["outcome"]["outcome"], "acknowledged");
    assert_eq!(acknowledged["outcome"]["carried_out"], "no");

    assert_eq!(timed_out["write"]["slave"], 5);
    assert_eq!(timed_out["outcome"]["outcome"], "timeout");
    assert_eq!(timed_out["outcome"]["carried_out"], "maybe");
    assert_eq!(timed_out["outcome"]["exception"], 0x0B);
    gateway.shutdown().await;
}

#[tokio::test]
async fn a_read_only_master_is_listed_with_its_rights() {
    let gateway = line().read_only(&["127.0.0.0/8"]).start().await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    master.call(1, 1, &READ_2).await;
    let status = get_status(gateway.metrics_addr()).await;
    assert_eq!(status["masters"][0]["rights"], "read_only", "{status:#}");
    gateway.shutdown().await;
}

#[tokio::test]
async fn the_status_page_is_one_html_page_that_loads_nothing_from_elsewhere() {
    let gateway = line().start().await;
    let (head, page) = request(gateway.metrics_addr(), "GET", "/").await;
    assert!(head.starts_with("http/1.1 200"), "{head}");
    assert!(
        head.contains("\r\ncontent-type: text/html; charset=utf-8\r\n"),
        "{head}"
    );
    let policy = head
        .lines()
        .find_map(|line| line.strip_prefix("content-security-policy: "))
        .unwrap_or_else(|| panic!("no CSP: {head}"));
    assert!(policy.contains("default-src 'none'"), "{policy}");
    assert!(policy.contains("connect-src 'self'"), "{policy}");
    assert!(policy.contains("script-src 'sha256-"), "{policy}");
    assert!(page.starts_with("<!DOCTYPE html>"));
    for external in ["http://", "https://", "//cdn", " src=", " href="] {
        assert!(!page.contains(external), "the page holds {external:?}");
    }
    // It reads its data and the plant values from this endpoint, and the trace from the trace
    // endpoint.
    assert!(page.contains("fetchJson(\"status\")"));
    assert!(page.contains("fetchJson(\"values?history=1\")"));
    assert!(page.contains("new EventSource(url)"));
    for table in ["buses", "slaves", "masters", "writes", "trace"] {
        assert!(page.contains(&format!("<tbody id=\"{table}\">")), "{table}");
    }
    assert!(page.contains("<div id=\"values\">"));
    let (head_only, nothing) = request(gateway.metrics_addr(), "HEAD", "/").await;
    assert!(head_only.starts_with("http/1.1 200"), "{head_only}");
    assert!(head_only.contains("content-security-policy: default-src 'none'"));
    assert_eq!(nothing, "");
    let (code, body) = http_get(gateway.metrics_addr(), "/nothing-here").await;
    assert_eq!(code, 404);
    assert!(body.contains("/ (the status page), /status"), "{body}");
    gateway.shutdown().await;
}

/// `/status` lists each virtual unit's registers with their source, value and age, and says
/// which are fresh: one polled every 100 ms, one whose slave never answers.
#[tokio::test]
async fn status_lists_a_virtual_units_registers_with_source_value_age_and_freshness() {
    let gateway = GatewayConfig::new()
        .bus(
            crate::support::Bus::sim("a")
                .baud(115_200)
                .parity("none")
                .sim_slaves("1")
                .sim_slave("2", &[("offline", true.into())])
                .response_timeout("20ms")
                .text(
                    "[[bus.slave]]\naddress = 1\npoll_interval = \"100ms\"\n\
                     [[bus.slave.value]]\nname = \"level\"\nregister = 0\n\
                     [[bus.slave]]\naddress = 2\npoll_interval = \"100ms\"\n\
                     [[bus.slave.value]]\nname = \"level\"\nregister = 0\n",
                ),
        )
        .route("1-2", "a", None)
        .tables(
            "[[virtual]]\nunit = 100\nname = \"pair\"\n\
             [[virtual.register]]\nregister = 0\nvalue = \"a/1/level\"\n\
             [[virtual.register]]\nregister = 1\nvalue = \"a/2/level\"\nwritable = true\n",
        )
        .start()
        .await;
    let metrics = gateway.metrics_addr();
    let units = crate::support::within("slave 1's level read", async {
        loop {
            let status = get_status(metrics).await;
            if status["virtual_units"][0]["registers"][0]["fresh"] == true {
                return status["virtual_units"].clone();
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    })
    .await;
    assert_eq!(units[0]["unit"], 100);
    assert_eq!(units[0]["name"], "pair");
    let registers = units[0]["registers"].as_array().unwrap();
    let fresh = &registers[0];
    assert_eq!(
        (
            &fresh["table"],
            &fresh["register"],
            &fresh["type"],
            &fresh["source"]
        ),
        (
            &"holding".into(),
            &0.into(),
            &"u16".into(),
            &"a/1/level".into()
        )
    );
    assert_eq!(fresh["value"], 0.0);
    assert!(fresh["age_seconds"].as_f64().unwrap() <= 0.3, "{fresh}");
    assert_eq!(fresh["max_age_seconds"], 0.3, "three of its 100 ms polls");
    let never = &registers[1];
    assert_eq!(never["source"], "a/2/level");
    assert_eq!(never["writable"], true);
    assert_eq!(
        (&never["value"], &never["age_seconds"], &never["fresh"]),
        (&Value::Null, &Value::Null, &false.into()),
        "never read: {never}"
    );
}
