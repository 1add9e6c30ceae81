//! The MQTT client's metrics (`[mqtt]`): whether the broker is connected, and its messages by
//! kind. Defined when the client starts, so a gateway without `[mqtt]` has none of them.

use super::Definer;
use prometheus::{IntCounter, IntGauge, Registry};
use tracing::{info, warn};

/// What became of one message: the `kind` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum MqttMessage {
    /// Handed to the broker (a value, an availability, a discovery config, a set's result).
    Published,
    /// Replaced, unsent, by a newer message on its topic (the broker down or slow).
    Dropped,
    /// A `.../set` message received.
    SetReceived,
    /// A `.../set` refused before any write: not writable, a payload that is no value of it,
    /// a retained message, a value no longer configured.
    SetRefused,
}

impl MqttMessage {
    pub(crate) const ALL: [MqttMessage; 4] = [
        MqttMessage::Published,
        MqttMessage::Dropped,
        MqttMessage::SetReceived,
        MqttMessage::SetRefused,
    ];

    pub(crate) fn label(self) -> &'static str {
        match self {
            MqttMessage::Published => "published",
            MqttMessage::Dropped => "dropped",
            MqttMessage::SetReceived => "set_received",
            MqttMessage::SetRefused => "set_refused",
        }
    }
}

/// Why a connection to the broker failed: the `reason` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum MqttFailure {
    /// The broker refused the user name and password (or the client is not authorized).
    Login,
    /// The broker refused the connection for another reason.
    Refused,
    /// The TLS handshake failed.
    Tls,
    /// No connection, a lost one, or a broker that did not answer in time.
    Network,
}

impl MqttFailure {
    const ALL: [MqttFailure; 4] = [
        MqttFailure::Login,
        MqttFailure::Refused,
        MqttFailure::Tls,
        MqttFailure::Network,
    ];

    fn label(self) -> &'static str {
        match self {
            MqttFailure::Login => "login",
            MqttFailure::Refused => "refused",
            MqttFailure::Tls => "tls",
            MqttFailure::Network => "network",
        }
    }
}

/// The MQTT client's series, resolved once.
#[derive(Clone)]
pub(crate) struct MqttMetrics {
    connected: IntGauge,
    messages: [IntCounter; 4],
    failures: [IntCounter; 4],
}

impl MqttMetrics {
    pub(super) fn new(registry: &Registry) -> Self {
        let define = Definer(registry);
        let connected = define.int_gauge(
            "modbus_gateway_mqtt_connected",
            "1 while the gateway is connected to the MQTT broker ([mqtt]), else 0.",
            &[],
        );
        let messages = define.int_counter(
            "modbus_gateway_mqtt_messages_total",
            "MQTT messages by kind: published to the broker, dropped (replaced unsent by a \
             newer one on its topic), set_received, set_refused (refused before any write).",
            &["kind"],
        );
        let failures = define.int_counter(
            "modbus_gateway_mqtt_connection_failures_total",
            "Connections to the MQTT broker that failed or were lost, by reason: login (user \
             name or password refused), refused (by the broker, another reason), tls, network.",
            &["reason"],
        );
        MqttMetrics {
            connected: connected.with_label_values::<&str>(&[]),
            messages: MqttMessage::ALL.map(|kind| messages.with_label_values(&[kind.label()])),
            failures: MqttFailure::ALL.map(|why| failures.with_label_values(&[why.label()])),
        }
    }

    pub(crate) fn failed(&self, why: MqttFailure) {
        self.failures[why as usize].inc();
    }

    pub(crate) fn count(&self, kind: MqttMessage, n: u64) {
        self.messages[kind as usize].inc_by(n);
    }

    /// Connected to `broker`, logged when it was not.
    pub(crate) fn connected(&self, broker: &str) {
        if self.connected.get() == 0 {
            info!(target: "modbus_gateway::mqtt", broker, "connected to the MQTT broker");
        }
        self.connected.set(1);
    }

    /// Disconnected from `broker` at the gateway's stop.
    pub(crate) fn stopped(&self, broker: &str) {
        info!(target: "modbus_gateway::mqtt", broker, "disconnected from the MQTT broker");
        self.connected.set(0);
    }

    /// No longer connected to `broker` (`why`), logged when it was.
    pub(crate) fn disconnected(&self, broker: &str, why: &str) {
        if self.connected.get() == 1 {
            warn!(target: "modbus_gateway::mqtt", broker, why, "lost the MQTT broker; reconnecting with back-off, Modbus served meanwhile");
        }
        self.connected.set(0);
    }
}
