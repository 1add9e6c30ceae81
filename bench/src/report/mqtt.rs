//! The `mqtt-` scenarios' figures (`MqttFigures`), made of what their two gateways saw: the one
//! with `[mqtt]` and the same without it.

use super::{count, percentile, slowest};
use crate::mqtt::{self, MqttWindow, Side};
use serde::Serialize;

/// The `mqtt-` scenarios': the plant values of the `values-` scenario published through a local
/// mosquitto, beside the same gateway without `[mqtt]` (the `_without_mqtt` figures, measured
/// first, the same way). `masters`, `transactions`, `tx_per_s`, `p50_ms`, `p99_ms` and `max_ms`
/// are the masters' beside the gateway with MQTT; `rss_mb` its memory at the end.
#[derive(Serialize)]
pub(crate) struct MqttFigures {
    /// The values configured, and `[mqtt] publish_interval`: with values that never change, the
    /// steady rate is the one over the other.
    pub(crate) plant_values: u64,
    pub(crate) publish_interval_s: f64,
    /// From the gateway listening until every value had been read once (`GET /values`, to
    /// within 250 ms).
    pub(crate) first_pass_s: f64,
    pub(crate) first_pass_s_without_mqtt: f64,
    /// From the gateway listening until the subscriber had the first message, every discovery
    /// config, and the whole first publication (every value, discovery config and availability,
    /// and the status; null if it never came within a minute of the first pass), and the
    /// messages it had received by then.
    pub(crate) first_message_s: Option<f64>,
    pub(crate) discovery_s: Option<f64>,
    pub(crate) first_publication_s: Option<f64>,
    pub(crate) first_publication_messages: Option<u64>,
    /// The burst at the connection: the messages received from the first to the last discovery
    /// config, a second; and the most received in any one second of the run.
    pub(crate) discovery_msgs_per_s: Option<f64>,
    pub(crate) peak_received_per_s: u64,
    /// Distinct topics received: values, discovery configs, availabilities.
    pub(crate) value_topics: u64,
    /// Over the run, the time between two messages of one value, each time one came again: the
    /// mean and the longest (against `publish_interval_s`: a value unchanged is due again after
    /// the interval, and goes at the publisher's next look at the store).
    pub(crate) value_gap_mean_s: Option<f64>,
    pub(crate) value_gap_max_s: Option<f64>,
    pub(crate) discovery_topics: u64,
    pub(crate) availability_topics: u64,
    /// The window (`--seconds`) after the first publication in which the gateway only polls
    /// and publishes: its polls a second, the messages the subscriber received a second and the
    /// gateway's own count of those it sent (`modbus_gateway_mqtt_messages_total{kind=
    /// "published"}`), its CPU a second with MQTT and without, the difference per message
    /// sent, and the broker's CPU a second.
    pub(crate) polls_per_s: f64,
    pub(crate) received_per_s: f64,
    pub(crate) published_per_s: f64,
    pub(crate) poll_cpu_ms_per_s: f64,
    pub(crate) poll_cpu_ms_per_s_without_mqtt: f64,
    pub(crate) mqtt_cpu_us_per_message: Option<f64>,
    pub(crate) broker_cpu_ms_per_s: Option<f64>,
    /// The gateway's memory after that window, with MQTT and without; and at the end, without
    /// (`rss_mb` is with).
    pub(crate) rss_polling_mb: f64,
    pub(crate) rss_polling_mb_without_mqtt: f64,
    pub(crate) rss_mb_without_mqtt: f64,
    /// The masters' window (`--seconds`, after theirs): each master reads every
    /// `master_period_ms`; their rate and latency without MQTT, the gateway's CPU a second with
    /// and without, and the messages received a second meanwhile.
    pub(crate) master_period_ms: f64,
    pub(crate) tx_per_s_without_mqtt: f64,
    pub(crate) p50_ms_without_mqtt: Option<f64>,
    pub(crate) p99_ms_without_mqtt: Option<f64>,
    pub(crate) max_ms_without_mqtt: Option<f64>,
    pub(crate) masters_cpu_ms_per_s: Option<f64>,
    pub(crate) masters_cpu_ms_per_s_without_mqtt: Option<f64>,
    pub(crate) masters_received_per_s: Option<f64>,
    /// At the end: the gateway's counters (`modbus_gateway_mqtt_messages_total` by kind,
    /// `modbus_gateway_mqtt_connection_failures_total`, `modbus_gateway_mqtt_connected`) and the
    /// messages the subscriber had received in all when the bench asked for them.
    pub(crate) published: u64,
    pub(crate) received: u64,
    pub(crate) dropped: u64,
    pub(crate) set_received: u64,
    pub(crate) set_refused: u64,
    pub(crate) connection_failures: u64,
    pub(crate) mqtt_connected: u64,
}

impl MqttFigures {
    pub(super) fn of(w: &MqttWindow) -> MqttFigures {
        let (with, without, p) = (&w.with, &w.without, &w.published);
        let polling = with.polling.as_secs_f64();
        let per_s = |n: f64| n / polling;
        let ((cpu, masters_cpu), (cpu_without, masters_cpu_without)) =
            (cpu_ms_per_s(with), cpu_ms_per_s(without));
        let published_per_s = per_s(p.published_polling);
        let c = &p.counters;
        let discovery_span = p
            .discovery
            .zip(p.first_message)
            .map(|(done, first)| (done - first).as_secs_f64());
        MqttFigures {
            plant_values: w.values as u64,
            publish_interval_s: w.publish_interval.as_secs_f64(),
            first_pass_s: with.first_pass.as_secs_f64(),
            first_pass_s_without_mqtt: without.first_pass.as_secs_f64(),
            first_message_s: p.first_message.map(|d| d.as_secs_f64()),
            discovery_s: p.discovery.map(|d| d.as_secs_f64()),
            first_publication_s: p.complete.map(|(d, _)| d.as_secs_f64()),
            first_publication_messages: p.complete.map(|(_, n)| n as u64),
            discovery_msgs_per_s: discovery_span
                .filter(|span| *span > 0.0)
                .map(|span| p.discovery_messages as f64 / span),
            peak_received_per_s: p.peak_per_s as u64,
            value_topics: p.value_topics as u64,
            value_gap_mean_s: p.value_gap_mean.map(|d| d.as_secs_f64()),
            value_gap_max_s: p.value_gap_max.map(|d| d.as_secs_f64()),
            discovery_topics: p.discovery_topics as u64,
            availability_topics: p.availability_topics as u64,
            polls_per_s: per_s(with.polls),
            received_per_s: per_s(p.received_polling as f64),
            published_per_s,
            poll_cpu_ms_per_s: cpu,
            poll_cpu_ms_per_s_without_mqtt: cpu_without,
            mqtt_cpu_us_per_message: (published_per_s > 0.0)
                .then(|| (cpu - cpu_without) * 1e3 / published_per_s),
            broker_cpu_ms_per_s: p.broker_cpu.map(|cpu| cpu.as_secs_f64() * 1e3 / polling),
            rss_polling_mb: with.rss_polling_mb,
            rss_polling_mb_without_mqtt: without.rss_polling_mb,
            rss_mb_without_mqtt: without.rss_mb,
            master_period_ms: mqtt::PERIOD.as_secs_f64() * 1e3,
            tx_per_s_without_mqtt: without.masters.tx_per_s,
            p50_ms_without_mqtt: percentile(&without.masters.latencies, 0.5),
            p99_ms_without_mqtt: percentile(&without.masters.latencies, 0.99),
            max_ms_without_mqtt: slowest(&without.masters.latencies),
            masters_cpu_ms_per_s: masters_cpu,
            masters_cpu_ms_per_s_without_mqtt: masters_cpu_without,
            masters_received_per_s: with
                .masters
                .window
                .map(|(start, end)| p.received_masters as f64 / (end - start).as_secs_f64()),
            published: count(c.published),
            received: p.received as u64,
            dropped: count(c.dropped),
            set_received: count(c.set_received),
            set_refused: count(c.set_refused),
            connection_failures: count(c.connection_failures),
            mqtt_connected: count(c.connected),
        }
    }
}

/// The gateway's CPU a second across `side`'s polling window and across its masters' window.
fn cpu_ms_per_s(side: &Side) -> (f64, Option<f64>) {
    let polling = side.polling_cpu.as_secs_f64() * 1e3 / side.polling.as_secs_f64();
    let masters = side
        .masters
        .window
        .zip(side.masters.cpu)
        .map(|((start, end), cpu)| cpu.as_secs_f64() * 1e3 / (end - start).as_secs_f64());
    (polling, masters)
}
