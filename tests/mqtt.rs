//! `[mqtt]` against a real broker (Debian's mosquitto) and a third-party subscriber
//! (mosquitto_sub), as a Home Assistant or Node-RED user sees it: the demo's drive 2 on its
//! topic as it ramps, deadband and publish_interval, retained flags, the status by the last
//! will, a slave's availability, discovery configs across restarts, writes by `set` under the
//! rules and the journal, bad payloads, the broker down and back while a master polls, mqtts
//! with a password file, a wrong password, and a publisher that sends what its rules forbid.

use crate::support::mosquitto::{publish, Broker, Message, Subscriber};
use crate::support::tls::Pki;
use crate::support::{
    addr, connect_when_listening, demo_path, demo_with_a_quick_drive_2, exit_status, free_addr,
    http_get, signal, until_logged, within, RawMaster, Scrape, TempDir,
};
use modbus_gateway::config::{Audit, Config, Mqtt, Rule, Value};
use modbus_gateway::testing::sim::{RegisterBank, Scripted};
use modbus_gateway::Gateway;
use std::process::{Command, Stdio};
use std::time::Duration;

const BINARY: &str = env!("CARGO_BIN_EXE_modbus-gateway");

const FREQUENCY: &str = "modbus-gateway/demo/2/drive_output_frequency_hertz";
const SETPOINT: &str = "modbus-gateway/demo/2/drive_frequency_setpoint_hertz";
/// 2001H = 5000 (50.00 Hz), then 2000H = 0001H (run forward): Goodrive300 manual 10.4.
const SET_50: [u8; 5] = [0x06, 0x20, 0x01, 0x13, 0x88];
const RUN: [u8; 5] = [0x06, 0x20, 0x00, 0x00, 0x01];

/// `config` publishing to `broker` with `[mqtt]` keys `extra` besides its url.
fn with_mqtt(mut config: Config, broker: &Broker, extra: &str) -> Config {
    let text = format!("url = \"{}\"\n{extra}", broker.url());
    config.mqtt = Some(toml::from_str::<Mqtt>(&text).expect("an [mqtt] table"));
    config.check(None).expect("a valid configuration");
    config
}

/// The payloads seen on `topic`, in order.
fn on<'a>(messages: &'a [Message], topic: &str) -> Vec<&'a str> {
    let on_topic = messages.iter().filter(|m| m.topic == topic);
    on_topic.map(|m| m.payload.as_str()).collect()
}

/// The last payload seen on `topic`.
fn last<'a>(messages: &'a [Message], topic: &str) -> Option<&'a str> {
    on(messages, topic).last().copied()
}

fn numbers(payloads: &[&str]) -> Vec<f64> {
    let parse = |p: &&str| {
        p.parse::<f64>()
            .unwrap_or_else(|_| panic!("not a number: {p:?}"))
    };
    payloads.iter().map(parse).collect()
}

async fn start(config: &Config) -> Gateway {
    Gateway::start(config).await.expect("the gateway starts")
}

/// Run the demo's drive 2 to 50 Hz.
async fn run_drive_2(gateway: &Gateway) {
    let mut master = RawMaster::connect(addr(gateway)).await;
    assert_eq!(master.call(1, 2, &SET_50).await, SET_50);
    assert_eq!(master.call(2, 2, &RUN).await, RUN);
}

async fn scrape(gateway: &Gateway) -> Scrape {
    Scrape::of(gateway).await
}

/// Holding register `register` of unit `unit`, read through the gateway.
async fn holding(gateway: &Gateway, unit: u8, register: u16) -> u16 {
    let mut master = RawMaster::connect(addr(gateway)).await;
    let [a, b] = register.to_be_bytes();
    let reply = master.call(1, unit, &[0x03, a, b, 0x00, 0x01]).await;
    assert_eq!(reply.len(), 4, "a read of {register:#06x}: {reply:02x?}");
    u16::from_be_bytes([reply[2], reply[3]])
}

#[tokio::test]
async fn the_demos_drive_2_run_to_50_hz_rises_on_its_topic_to_50_never_5000() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let live = Subscriber::start(&broker, &["modbus-gateway/#"]).await;
    let gateway = start(&with_mqtt(demo_with_a_quick_drive_2(), &broker, "")).await;
    live.until("drive 2 stopped at 0 Hz", |m| {
        last(m, FREQUENCY) == Some("0")
    })
    .await;
    run_drive_2(&gateway).await;
    let seen = live
        .until("drive 2 at 50 Hz", |m| last(m, FREQUENCY) == Some("50"))
        .await;
    let ramp = numbers(&on(&seen, FREQUENCY));
    assert!(
        ramp.iter().all(|&v| (0.0..=50.0).contains(&v)),
        "in Hz: {ramp:?}"
    );
    assert!(
        ramp.iter().any(|&v| v > 0.0 && v < 50.0),
        "on the way: {ramp:?}"
    );
    assert!(
        ramp.windows(2).all(|w| w[0] < w[1]),
        "rising, each a change: {ramp:?}"
    );
    assert!(
        seen.iter()
            .filter(|m| m.topic == FREQUENCY)
            .all(|m| !m.retained),
        "a live subscriber gets the messages as published"
    );
    assert_eq!(last(&seen, "modbus-gateway/status"), Some("online"));
    assert_eq!(
        last(&seen, "modbus-gateway/demo/2/availability"),
        Some("online")
    );
    // Retained: a subscriber arriving now is told the last of each at once.
    let late = Subscriber::start(&broker, &[FREQUENCY, "modbus-gateway/status"]).await;
    let frequency = late.first_on(FREQUENCY).await;
    assert_eq!(
        (frequency.payload.as_str(), frequency.retained),
        ("50", true)
    );
    let status = late.first_on("modbus-gateway/status").await;
    assert_eq!((status.payload.as_str(), status.retained), ("online", true));
    let scrape = scrape(&gateway).await;
    assert_eq!(scrape.value("modbus_gateway_mqtt_connected"), 1.0);
    let published = "modbus_gateway_mqtt_messages_total{kind=\"published\"}";
    assert!(scrape.value(published) > 100.0, "{}", scrape.text);
    crate::metrics::assert_promtool_finds_nothing_to_lint(&scrape.text).await;
}

/// The demo with a quick drive 2 whose output frequency is also its own value
/// `drive_output_frequency_banded_hertz`, with `deadband`.
fn banded(deadband: f64) -> (Config, &'static str) {
    let mut config = demo_with_a_quick_drive_2();
    let unit_2 = config.bus[0].slave.iter_mut().find(|s| s.address == 2);
    let value: Value = toml::from_str(&format!(
        "name = \"drive_output_frequency_banded_hertz\"\nregister = 0x3000\nscale = 0.01\n\
         unit = \"Hz\"\ndeadband = {deadband:?}"
    ))
    .unwrap();
    unit_2.expect("unit 2").value.push(value);
    (
        config,
        "modbus-gateway/demo/2/drive_output_frequency_banded_hertz",
    )
}

#[tokio::test]
async fn a_value_within_its_deadband_of_the_last_published_is_not_published() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let live = Subscriber::start(&broker, &["modbus-gateway/demo/2/#"]).await;
    let (config, topic) = banded(8.0);
    let gateway = start(&with_mqtt(config, &broker, "publish_interval = \"1h\"")).await;
    live.until("drive 2 stopped", |m| last(m, FREQUENCY) == Some("0"))
        .await;
    run_drive_2(&gateway).await;
    let seen = live
        .until("drive 2 at 50 Hz", |m| last(m, FREQUENCY) == Some("50"))
        .await;
    // The frequency's template value, with no deadband, shows every step the polls saw.
    let every = numbers(&on(&seen, FREQUENCY));
    let banded = numbers(&on(&seen, topic));
    assert_eq!(banded.first(), Some(&0.0));
    assert!(
        banded.windows(2).all(|w| w[1] - w[0] > 8.0),
        "each more than 8 Hz from the last published: {banded:?} (every step: {every:?})"
    );
    assert!(banded.len() < every.len(), "{banded:?} against {every:?}");
    assert!(*banded.last().unwrap() > 42.0, "{banded:?}");
}

#[tokio::test]
async fn an_unchanged_value_is_published_again_every_publish_interval() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let topic = "modbus-gateway/demo/2/drive_identifying_code";
    let live = Subscriber::start(&broker, &[topic]).await;
    let _gateway = start(&with_mqtt(
        demo_with_a_quick_drive_2(),
        &broker,
        "publish_interval = \"1s\"",
    ))
    .await;
    let seen = live
        .until("the identifying code three times", |m| {
            on(m, topic).len() >= 3
        })
        .await;
    assert!(on(&seen, topic).iter().all(|p| *p == "266"), "{seen:?}");
}

/// The demo binary publishing to `broker`, its log in `log`; the Modbus and metrics addresses.
fn demo_process(broker: &Broker, log: &std::path::Path, env: &[(&str, &str)]) -> DemoProcess {
    let listen = free_addr();
    let metrics = free_addr();
    let mut command = Command::new(BINARY);
    command
        .args(["--config", demo_path(), "run"])
        .env("MBGW__SERVER__LISTEN", listen.to_string())
        .env("MBGW__METRICS__LISTEN", metrics.to_string())
        .env("MBGW__MQTT__URL", broker.url())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap());
    for (key, value) in env {
        command.env(key, value);
    }
    DemoProcess {
        child: command.spawn().expect("the gateway runs"),
        listen,
        metrics,
    }
}

struct DemoProcess {
    child: std::process::Child,
    listen: std::net::SocketAddr,
    metrics: std::net::SocketAddr,
}

#[tokio::test]
async fn status_goes_offline_by_the_last_will_when_the_gateway_is_killed_9() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let dir = TempDir::new("mqtt-will");
    let status = "modbus-gateway/status";
    let live = Subscriber::start(&broker, &[status]).await;
    // Killed: the broker says offline for it.
    let gateway = demo_process(&broker, &dir.join("kill.log"), &[]);
    live.until("online", |m| last(m, status) == Some("online"))
        .await;
    signal(&gateway.child, "KILL");
    live.until("offline by the will", |m| {
        last(m, status) == Some("offline")
    })
    .await;
    exit_status(gateway.child).await;
    // Stopped: it says so itself before it goes.
    live.clear();
    let gateway = demo_process(&broker, &dir.join("term.log"), &[]);
    live.until("online again", |m| last(m, status) == Some("online"))
        .await;
    signal(&gateway.child, "TERM");
    assert_eq!(exit_status(gateway.child).await.code(), Some(0));
    live.until("offline at the stop", |m| {
        last(m, status) == Some("offline")
    })
    .await;
    let retained = Subscriber::start(&broker, &[status]).await;
    let said = retained.first_on(status).await;
    assert_eq!((said.payload.as_str(), said.retained), ("offline", true));
}

#[tokio::test]
async fn a_slave_that_stops_answering_turns_its_availability_offline_and_back() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let availability = "modbus-gateway/demo/2/availability";
    let live = Subscriber::start(&broker, &["modbus-gateway/demo/2/#"]).await;
    let gateway = start(&with_mqtt(demo_with_a_quick_drive_2(), &broker, "")).await;
    live.until("online", |m| last(m, availability) == Some("online"))
        .await;
    let line = gateway.sim_line("demo").expect("a simulated line");
    line.add_slave(2, Scripted::new([]));
    live.until("offline", |m| last(m, availability) == Some("offline"))
        .await;
    live.clear();
    // Nothing is published for the values whose polls fail: three more failed polls seen.
    let failures = |scrape: Scrape| {
        let of = |outcome: &str| {
            let series = format!("modbus_gateway_poll_errors_total{{bus=\"demo\",outcome=\"{outcome}\",slave=\"2\"}}");
            scrape.value(&series)
        };
        of("timeout") + of("slave_down")
    };
    let failed = failures(scrape(&gateway).await);
    within("three more failed polls", async {
        while failures(scrape(&gateway).await) < failed + 3.0 {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    assert!(
        live.messages().iter().all(|m| m.topic == availability),
        "{:?}",
        live.messages()
    );
    // Back on the line (a plain register bank: its registers hold 0).
    line.add_slave(2, RegisterBank::new(Duration::ZERO));
    let seen = live
        .until("online again", |m| last(m, availability) == Some("online"))
        .await;
    let retained = Subscriber::start(&broker, &[availability]).await;
    assert!(retained.first_on(availability).await.retained, "{seen:?}");
}

/// The discovery configs seen, by topic.
fn configs(messages: &[Message]) -> std::collections::BTreeMap<String, String> {
    let configs = messages
        .iter()
        .filter(|m| m.topic.starts_with("homeassistant/"));
    configs
        .map(|m| (m.topic.clone(), m.payload.clone()))
        .collect()
}

/// How many values the demo publishes: its templates' for its four drives.
async fn values_of(gateway: &Gateway) -> usize {
    let (_, body) = http_get(gateway.metrics_addr(), "/values").await;
    let listing: serde_json::Value = serde_json::from_str(&body).unwrap();
    listing["values"].as_array().unwrap().len()
}

#[tokio::test]
async fn discovery_configs_are_what_home_assistant_takes_and_survive_a_restart() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let config = with_mqtt(demo_with_a_quick_drive_2(), &broker, "");
    let first = Subscriber::start(&broker, &["homeassistant/#"]).await;
    let gateway = start(&config).await;
    let count = values_of(&gateway).await;
    let seen = configs(
        &first
            .until("every config", |m| configs(m).len() >= count)
            .await,
    );
    assert_eq!(seen.len(), count);
    let mut unique_ids = std::collections::BTreeSet::new();
    for (topic, payload) in &seen {
        let config: serde_json::Value = serde_json::from_str(payload)
            .unwrap_or_else(|e| panic!("{topic}: not JSON ({e}): {payload}"));
        let levels: Vec<&str> = topic.split('/').collect();
        assert_eq!(levels.len(), 5, "{topic}");
        assert!(["sensor", "binary_sensor"].contains(&levels[1]), "{topic}");
        let id_like = |s: &str| {
            s.chars()
                .all(|c| c.is_ascii_alphanumeric() || "_-".contains(c))
        };
        assert!(id_like(levels[2]) && id_like(levels[3]), "{topic}");
        assert_eq!(levels[4], "config");
        let state = config["state_topic"].as_str().expect("state_topic");
        assert!(state.starts_with("modbus-gateway/demo/"), "{payload}");
        assert!(unique_ids.insert(config["unique_id"].as_str().expect("unique_id").to_owned()));
        assert!(config["device"]["identifiers"][0].is_string(), "{payload}");
        assert!(config["name"].is_string(), "{payload}");
        let availability = config["availability"].as_array().expect("availability");
        assert_eq!(
            availability[0]["topic"], "modbus-gateway/status",
            "{payload}"
        );
    }
    let frequency =
        "homeassistant/sensor/modbus-gateway_demo_2/drive_output_frequency_hertz/config";
    let frequency: serde_json::Value = serde_json::from_str(&seen[frequency]).unwrap();
    assert_eq!(frequency["state_topic"], FREQUENCY);
    assert_eq!(frequency["unit_of_measurement"], "Hz");
    assert_eq!(frequency["device_class"], "frequency");
    assert_eq!(frequency["state_class"], "measurement");
    assert_eq!(frequency["device"]["model"], "goodrive300");
    assert_eq!(frequency["device"]["name"], "demo slave 2");
    assert_eq!(
        frequency["unique_id"],
        "modbus-gateway_demo_2_drive_output_frequency_hertz"
    );
    let ready = "homeassistant/binary_sensor/modbus-gateway_demo_2/drive_ready/config";
    let ready: serde_json::Value = serde_json::from_str(&seen[ready]).unwrap();
    assert_eq!(
        (ready["payload_on"].as_str(), ready["payload_off"].as_str()),
        (Some("1"), Some("0"))
    );
    gateway.shutdown().await;
    // The same again after a restart.
    let again = Subscriber::start(&broker, &["homeassistant/#"]).await;
    again.clear();
    let gateway = start(&config).await;
    let republished = configs(
        &again
            .until("every config again", |m| configs(m).len() >= count)
            .await,
    );
    assert_eq!(republished, seen, "identical after a restart");
    gateway.shutdown().await;
    // Unit 3 taken out of the configuration: its configs are cleared, the others stay.
    let mut without_3 = config.clone();
    without_3.bus[0].slave.retain(|s| s.address != 3);
    let cleared = Subscriber::start(&broker, &["homeassistant/#"]).await;
    cleared.clear();
    let _gateway = start(&without_3).await;
    let node_3 = "/modbus-gateway_demo_3/";
    let of_3 = seen.keys().filter(|t| t.contains(node_3)).count();
    assert!(of_3 > 0);
    let after = cleared
        .until("unit 3's configs cleared", |m| {
            m.iter()
                .filter(|m| m.topic.contains(node_3) && m.payload.is_empty())
                .count()
                >= of_3
        })
        .await;
    let retained = Subscriber::start(&broker, &["homeassistant/#"]).await;
    let left = configs(
        &retained
            .until("the retained configs", |m| configs(m).len() >= count - of_3)
            .await,
    );
    assert!(left.keys().all(|t| !t.contains(node_3)), "{after:?}");
}

/// The demo with writes by MQTT, journaled in `dir`, and unit 3 closed to MQTT's writes.
fn writing(broker: &Broker, dir: &TempDir) -> Config {
    let mut config = demo_with_a_quick_drive_2();
    let journal = dir.join("writes.jsonl");
    let audit = format!("path = {:?}", journal.display().to_string());
    config.audit = Some(toml::from_str::<Audit>(&audit).unwrap());
    let rule = "name = \"no MQTT writes to unit 3\"\nprotocols = [\"mqtt\"]\nunits = \"3\"\n\
                functions = [\"write\"]\naction = \"deny\"";
    config.rule.push(toml::from_str::<Rule>(rule).unwrap());
    with_mqtt(config, broker, "writes = true")
}

/// The result of a set of `topic` to `payload`.
async fn set(
    broker: &Broker,
    results: &Subscriber,
    topic: &str,
    payload: &str,
) -> serde_json::Value {
    results.clear();
    publish(broker, &format!("{topic}/set"), payload, false);
    let result = format!("{topic}/set/result");
    let seen = results
        .until(&format!("the result of {payload}"), |m| {
            last(m, &result).is_some()
        })
        .await;
    serde_json::from_str(last(&seen, &result).unwrap()).expect("a JSON result")
}

#[tokio::test]
async fn a_set_is_written_encoded_journaled_and_stopped_by_an_mqtt_deny_rule() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let dir = TempDir::new("mqtt-set");
    let results = Subscriber::start(&broker, &["modbus-gateway/+/+/+/set/result"]).await;
    let live = Subscriber::start(&broker, &[SETPOINT]).await;
    let gateway = start(&writing(&broker, &dir)).await;
    live.until("the setpoint", |m| last(m, SETPOINT) == Some("0"))
        .await;
    // 12.34 Hz is 1234 in 0.01 Hz.
    let ok = set(&broker, &results, SETPOINT, "12.34").await;
    assert_eq!(ok["result"], "ok", "{ok}");
    assert_eq!(ok["value"], 12.34);
    assert_eq!(holding(&gateway, 2, 0x2001).await, 1234);
    live.until("published back", |m| last(m, SETPOINT) == Some("12.34"))
        .await;
    // Rounded to the register's resolution.
    let rounded = set(&broker, &results, SETPOINT, " 25.006 ").await;
    assert_eq!(
        (rounded["result"].as_str(), rounded["value"].as_f64()),
        (Some("ok"), Some(25.01))
    );
    assert_eq!(holding(&gateway, 2, 0x2001).await, 2501);
    // The journal: master mqtt, protocol mqtt, FC 06 to 2001H.
    let journal = std::fs::read_to_string(dir.join("writes.jsonl")).unwrap();
    let entries: Vec<serde_json::Value> = journal
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let mqtt: Vec<&serde_json::Value> =
        entries.iter().filter(|e| e["protocol"] == "mqtt").collect();
    assert!(mqtt.len() >= 2, "{journal}");
    assert!(mqtt.iter().all(|e| e["master"] == "mqtt"), "{journal}");
    let fields = |e: &&serde_json::Value| {
        (
            e["function"].clone(),
            e["start"].clone(),
            e["values"].clone(),
        )
    };
    let written: Vec<_> = mqtt.iter().map(fields).collect();
    assert_eq!(
        written[0],
        (6.into(), 0x2001.into(), "04D2".into()),
        "{journal}"
    );
    // Unit 3 under the deny rule: never sent, the result names the rule.
    let setpoint_3 = "modbus-gateway/demo/3/drive_frequency_setpoint_hertz";
    let denied = set(&broker, &results, setpoint_3, "40").await;
    assert_eq!(denied["result"], "denied", "{denied}");
    assert_eq!(denied["rule"], "no MQTT writes to unit 3");
    assert_eq!(holding(&gateway, 3, 0x2001).await, 0, "not written");
    let journal = std::fs::read_to_string(dir.join("writes.jsonl")).unwrap();
    assert!(journal.contains("no MQTT writes to unit 3"), "{journal}");
    // Bad payloads: refused with a reason, nothing written.
    for (payload, says) in [
        ("fast", "not a decimal number"),
        ("NaN", "not a decimal number"),
        ("-1", "out of the range"),
        ("700", "out of the range"),
        ("", "not a decimal number"),
    ] {
        let refused = set(&broker, &results, SETPOINT, payload).await;
        assert_eq!(refused["result"], "refused", "{payload:?}: {refused}");
        assert!(
            refused["reason"].as_str().unwrap().contains(says),
            "{payload:?}: {refused}"
        );
    }
    assert_eq!(
        holding(&gateway, 2, 0x2001).await,
        2501,
        "none of those written"
    );
    let scrape = scrape(&gateway).await;
    assert!(scrape.value("modbus_gateway_mqtt_messages_total{kind=\"set_refused\"}") >= 5.0);
    assert!(scrape.value("modbus_gateway_mqtt_messages_total{kind=\"set_received\"}") >= 8.0);
}

#[tokio::test]
async fn a_retained_set_is_carried_out_once_never_again_at_a_reconnect() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let dir = TempDir::new("mqtt-retained-set");
    let results = Subscriber::start(&broker, &["modbus-gateway/+/+/+/set/result"]).await;
    let live = Subscriber::start(&broker, &[SETPOINT]).await;
    let config = writing(&broker, &dir);
    let gateway = start(&config).await;
    // Its values published: it has subscribed to the sets (in order on one connection).
    live.until("the setpoint", |m| last(m, SETPOINT).is_some())
        .await;
    let result = format!("{SETPOINT}/set/result");
    // MQTT 3.1.1 does not flag a retained message delivered live: it is carried out.
    let ok = set_retained(&broker, &results, &result).await;
    assert!(ok.contains("\"ok\""), "{ok}");
    assert_eq!(holding(&gateway, 2, 0x2001).await, 3000);
    gateway.shutdown().await;
    // The broker hands it over again at the next subscription, flagged: refused.
    results.clear();
    let gateway = start(&config).await;
    let seen = results
        .until("the redelivered set's result", |m| {
            last(m, &result).is_some()
        })
        .await;
    assert!(
        last(&seen, &result).unwrap().contains("retained"),
        "{seen:?}"
    );
    let journal = std::fs::read_to_string(dir.join("writes.jsonl")).unwrap();
    assert_eq!(
        journal.matches("\"values\":\"0BB8\"").count(),
        1,
        "written once: {journal}"
    );
    drop(gateway);
    publish(&broker, &format!("{SETPOINT}/set"), "", true);
}

/// Publish a retained set of 30 to the setpoint; its result.
async fn set_retained(broker: &Broker, results: &Subscriber, result: &str) -> String {
    results.clear();
    publish(broker, &format!("{SETPOINT}/set"), "30", true);
    let seen = results
        .until("the retained set's result", |m| last(m, result).is_some())
        .await;
    last(&seen, result).unwrap().to_owned()
}

#[tokio::test]
async fn a_publisher_gets_no_write_its_rules_and_writable_keys_forbid() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let dir = TempDir::new("mqtt-hostile");
    let results = Subscriber::start(&broker, &["modbus-gateway/#"]).await;
    let gateway = start(&writing(&broker, &dir)).await;
    results
        .until("the setpoint", |m| last(m, SETPOINT) == Some("0"))
        .await;
    let refused = "modbus_gateway_mqtt_messages_total{kind=\"set_refused\"}";
    let before = scrape(&gateway).await.value(refused);
    // Values that are not writable, values that do not exist, levels that are no value, a
    // wildcard-looking level, the status topic itself: every one refused, no result.
    let forbidden = [
        "modbus-gateway/demo/2/drive_output_frequency_hertz/set",
        "modbus-gateway/demo/2/drive_state/set",
        "modbus-gateway/demo/9/drive_frequency_setpoint_hertz/set",
        "modbus-gateway/other/2/drive_frequency_setpoint_hertz/set",
        "modbus-gateway/demo/2/availability/set",
        "modbus-gateway/demo/2/drive_frequency_setpoint_hertz/x/set",
        "modbus-gateway/demo/1/drive_frequency_setpoint_hertz/set",
    ];
    for topic in forbidden {
        publish(&broker, topic, "1", false);
    }
    within("every forbidden set refused", async {
        while scrape(&gateway).await.value(refused) < before + forbidden.len() as f64 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    // A flood of sets to unit 3, which a rule closes to MQTT: each denied, none sent.
    for _ in 0..50 {
        publish(
            &broker,
            "modbus-gateway/demo/3/drive_frequency_setpoint_hertz/set",
            "10",
            false,
        );
    }
    // A big payload: refused as no number, the connection kept.
    publish(
        &broker,
        &format!("{SETPOINT}/set"),
        &"9".repeat(50_000),
        false,
    );
    let result_3 = "modbus-gateway/demo/3/drive_frequency_setpoint_hertz/set/result";
    results
        .until("fifty denials", |m| {
            on(m, result_3)
                .iter()
                .filter(|r| r.contains("denied"))
                .count()
                >= 50
        })
        .await;
    let result_2 = format!("{SETPOINT}/set/result");
    results
        .until("the big payload refused", |m| {
            last(m, &result_2).is_some_and(|r| r.contains("refused"))
        })
        .await;
    let messages = results.messages();
    assert!(
        messages
            .iter()
            .all(|m| !m.topic.ends_with("/result") || m.topic == result_3 || m.topic == result_2),
        "no result for a topic that is no writable value"
    );
    assert_eq!(holding(&gateway, 3, 0x2001).await, 0);
    assert_eq!(
        holding(&gateway, 2, 0x3000).await,
        0,
        "the output frequency untouched"
    );
    let journal = std::fs::read_to_string(dir.join("writes.jsonl")).unwrap_or_default();
    let entries: Vec<serde_json::Value> = journal
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert!(
        entries
            .iter()
            .filter(|e| e["protocol"] == "mqtt")
            .all(|e| e["unit"] == 3),
        "only unit 3's denied writes are journaled: {journal}"
    );
    assert_eq!(
        scrape(&gateway)
            .await
            .value("modbus_gateway_mqtt_connected"),
        1.0
    );
}

/// A master reading unit 2 every 100 ms while `during` runs: the longest time between two
/// answers, and how many reads failed.
async fn polling_beside<F: std::future::Future>(gateway: &Gateway, during: F) -> (Duration, usize) {
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let addr = addr(gateway);
    let stopped = stop.clone();
    let master = tokio::spawn(async move {
        let mut master = RawMaster::connect(addr).await;
        let (mut longest, mut failed) = (Duration::ZERO, 0);
        let mut answered = tokio::time::Instant::now();
        let mut tid = 0u16;
        while !stopped.load(std::sync::atomic::Ordering::Relaxed) {
            tid = tid.wrapping_add(1);
            let reply = master
                .try_call(tid, 2, &[0x03, 0x21, 0x03, 0x00, 0x01])
                .await;
            if reply.as_deref() == Some(&[0x03, 0x02, 0x01, 0x0A][..]) {
                longest = longest.max(answered.elapsed());
                answered = tokio::time::Instant::now();
            } else {
                failed += 1;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        (longest, failed)
    });
    during.await;
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    master.await.unwrap()
}

#[tokio::test]
async fn the_broker_down_at_start_and_killed_mid_run_never_stalls_modbus() {
    let Some(mut broker) = Broker::start().await else {
        return;
    };
    broker.kill();
    let gateway = start(&with_mqtt(demo_with_a_quick_drive_2(), &broker, "")).await;
    let metrics = gateway.metrics_addr();
    let (longest, failed) = polling_beside(&gateway, async {
        // Down at the start: Modbus served, the failures counted.
        within("a failed connection counted", async {
            loop {
                let (_, text) = http_get(metrics, "/metrics").await;
                let scrape = Scrape::parse(text);
                if scrape.get("modbus_gateway_mqtt_connection_failures_total{reason=\"network\"}")
                    >= Some(1.0)
                {
                    assert_eq!(scrape.get("modbus_gateway_mqtt_connected"), Some(0.0));
                    return;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        })
        .await;
        broker.start_again().await;
        let live = Subscriber::start(&broker, &[FREQUENCY, "modbus-gateway/status"]).await;
        live.until("published once the broker is up", |m| {
            last(m, FREQUENCY).is_some()
        })
        .await;
        // Killed mid-run, and back: publishing resumes, everything again.
        broker.kill();
        tokio::time::sleep(Duration::from_millis(1500)).await;
        broker.start_again().await;
        live.until_subscribed().await;
        live.clear();
        live.until("published again after the reconnect", |m| {
            last(m, FREQUENCY).is_some() && last(m, "modbus-gateway/status") == Some("online")
        })
        .await;
    })
    .await;
    assert_eq!(failed, 0, "every read answered");
    assert!(
        longest < Duration::from_secs(1),
        "a gap of {longest:?} between answers"
    );
}

#[tokio::test]
async fn mqtts_with_a_ca_and_a_password_file_publishes() {
    let pki = Pki::new("mqtts");
    let Some(broker) = Broker::with_tls(&pki, "gateway", "s3cret").await else {
        return;
    };
    let dir = TempDir::new("mqtts");
    let password = dir.join("mqtt.password");
    std::fs::write(&password, "s3cret\n").unwrap();
    let extra = format!(
        "ca_file = {:?}\nusername = \"gateway\"\npassword_file = {:?}",
        broker.ca_file().unwrap().display().to_string(),
        password.display().to_string()
    );
    let live = Subscriber::start(&broker, &[FREQUENCY]).await;
    let gateway = start(&with_mqtt(demo_with_a_quick_drive_2(), &broker, &extra)).await;
    live.until("the frequency over TLS", |m| {
        last(m, FREQUENCY) == Some("0")
    })
    .await;
    assert_eq!(
        scrape(&gateway)
            .await
            .value("modbus_gateway_mqtt_connected"),
        1.0
    );
}

#[tokio::test]
async fn a_wrong_password_is_logged_and_counted_and_modbus_still_served() {
    let Some(broker) = Broker::with_password("gateway", "right").await else {
        return;
    };
    let dir = TempDir::new("mqtt-wrong");
    let password = dir.join("mqtt.password");
    std::fs::write(&password, "wrong\n").unwrap();
    let log = dir.join("gateway.log");
    let password = password.display().to_string();
    let env = [
        ("MBGW__MQTT__USERNAME", "gateway"),
        ("MBGW__MQTT__PASSWORD_FILE", password.as_str()),
    ];
    let gateway = demo_process(&broker, &log, &env);
    until_logged(&log, "cannot reach the MQTT broker").await;
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(
        text.contains("NotAuthorized") || text.contains("BadUserNamePassword"),
        "{text}"
    );
    let mut master = connect_when_listening(gateway.listen).await;
    assert_eq!(
        master.call(1, 2, &[0x03, 0x21, 0x03, 0x00, 0x01]).await,
        [0x03, 0x02, 0x01, 0x0A]
    );
    let (_, metrics) = http_get(gateway.metrics, "/metrics").await;
    let scrape = Scrape::parse(metrics);
    assert!(scrape.value("modbus_gateway_mqtt_connection_failures_total{reason=\"login\"}") >= 1.0);
    assert_eq!(scrape.value("modbus_gateway_mqtt_connected"), 0.0);
    signal(&gateway.child, "TERM");
    assert_eq!(exit_status(gateway.child).await.code(), Some(0));
}

#[tokio::test]
async fn a_reload_publishes_the_new_values_and_clears_the_removed_ones() {
    let Some(broker) = Broker::start().await else {
        return;
    };
    let config = with_mqtt(demo_with_a_quick_drive_2(), &broker, "");
    let live = Subscriber::start(&broker, &["modbus-gateway/demo/3/#", "homeassistant/#"]).await;
    let gateway = start(&config).await;
    let state = "modbus-gateway/demo/3/drive_state";
    let discovery = "homeassistant/sensor/modbus-gateway_demo_3/drive_state/config";
    live.until("unit 3 published", |m| {
        last(m, state).is_some() && last(m, discovery).is_some()
    })
    .await;
    // Unit 3 out: its values, availability and discovery configs are cleared (empty, retained).
    let mut without_3 = config.clone();
    without_3.bus[0].slave.retain(|s| s.address != 3);
    live.clear();
    let done = gateway.reload(&without_3).expect("the reload applies");
    assert!(done.applied.iter().any(|a| a == "plant values"), "{done:?}");
    assert!(done.need_restart.is_empty(), "{done:?}");
    let availability = "modbus-gateway/demo/3/availability";
    let cleared = |m: &[Message]| {
        [state, availability, discovery]
            .iter()
            .all(|t| last(m, t) == Some(""))
    };
    live.until("unit 3 cleared", cleared).await;
    let retained = Subscriber::start(&broker, &["modbus-gateway/demo/3/#"]).await;
    assert!(retained.messages().is_empty(), "{:?}", retained.messages());
    // Back: published again. A change to [mqtt] itself takes a restart.
    live.clear();
    let mut moved = config.clone();
    moved.mqtt.as_mut().unwrap().topic_prefix = "plant".to_owned();
    let done = gateway.reload(&moved).expect("the reload applies");
    assert_eq!(done.need_restart, ["mqtt"], "{done:?}");
    live.until("unit 3 again, under the prefix it started with", |m| {
        last(m, state).is_some_and(|p| !p.is_empty())
    })
    .await;
}
