//! The connection to the broker: rumqttc's event loop on a task of its own, connecting with the
//! configured login, TLS and last will (`PREFIX/status` `offline`, retained), reconnecting with
//! back-off (1 s doubling to 30 s) while the rest of the gateway serves Modbus. It tells the
//! publisher when the broker is up or down and hands it the messages that arrive; it counts the
//! messages that leave and why a connection failed, and logs a failure once until it changes
//! or a minute has passed.

use crate::config::{Broker, Mqtt};
use crate::metrics::{MqttFailure, MqttMessage, MqttMetrics};
use crate::pem;
use rumqttc::{
    AsyncClient, ConnectReturnCode, ConnectionError, Event, EventLoop, LastWill, MqttOptions,
    Outgoing, Packet, Publish, QoS, TlsConfiguration, Transport,
};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::time::Instant;
use tracing::{debug, warn};

/// What the publisher hears from the connection.
#[derive(Debug)]
pub(super) enum FromBroker {
    Up,
    Down,
    Message(Publish),
}

/// Requests waiting for the event loop (publishes, subscriptions); the publisher keeps the rest.
pub(super) const REQUESTS: usize = 256;
/// Messages from the broker waiting for the publisher (a large Home Assistant's discovery
/// configs all come at once at a connection); more are dropped, a set among them refused.
const MESSAGES: usize = 4096;
const BACKOFF_FIRST: Duration = Duration::from_secs(1);
const BACKOFF_MAX: Duration = Duration::from_secs(30);
/// A failure like the last one is logged again after this.
const LOG_AGAIN: Duration = Duration::from_secs(60);
const KEEP_ALIVE: Duration = Duration::from_secs(30);
/// The largest message the client takes or sends.
const MAX_PACKET: usize = 1 << 20;

pub(super) fn qos(settings: &Mqtt) -> QoS {
    if settings.qos() == 1 {
        QoS::AtLeastOnce
    } else {
        QoS::AtMostOnce
    }
}

/// The client of `settings`' broker, its event loop, and the broker as the logs name it; or
/// why it cannot be made (a file that cannot be read since the configuration was checked).
pub(super) fn client(settings: &Mqtt) -> Result<(AsyncClient, EventLoop, String), String> {
    let broker: Broker = settings.broker()?;
    let mut options = MqttOptions::new(settings.client_id(), broker.host.clone(), broker.port);
    options.set_keep_alive(KEEP_ALIVE);
    // rumqttc closes the connection on a bigger message (it reconnects); other integrations'
    // discovery configs arrive on the subscription too, and are rarely past a few KiB.
    options.set_max_packet_size(MAX_PACKET, MAX_PACKET);
    options.set_clean_session(true);
    let status = format!("{}/status", settings.topic_prefix);
    options.set_last_will(LastWill::new(status, "offline", qos(settings), true));
    if let Some(user) = &settings.username {
        let password = settings.read_password()?.unwrap_or_default();
        options.set_credentials(user.clone(), password);
    }
    if broker.tls {
        options.set_transport(Transport::tls_with_config(TlsConfiguration::Rustls(
            Arc::new(tls(settings)?),
        )));
    }
    let (client, events) = AsyncClient::new(options, REQUESTS);
    let scheme = if broker.tls { "mqtts" } else { "mqtt" };
    Ok((
        client,
        events,
        format!("{scheme}://{}:{}", broker.host, broker.port),
    ))
}

/// The TLS client of an `mqtts` broker: its CA, and the gateway's certificate for mutual TLS.
fn tls(settings: &Mqtt) -> Result<rustls::ClientConfig, String> {
    let ca = settings.ca_file.as_deref().ok_or("mqtt.ca_file: not set")?;
    let roots = pem::roots(ca).map_err(|e| format!("mqtt.ca_file: {e}"))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13, &rustls::version::TLS12])
        .map_err(|e| e.to_string())?
        .with_root_certificates(roots);
    match (&settings.cert_file, &settings.key_file) {
        (Some(cert), Some(key)) => {
            let chain = pem::certificates(cert).map_err(|e| format!("mqtt.cert_file: {e}"))?;
            let key = pem::private_key(key).map_err(|e| format!("mqtt.key_file: {e}"))?;
            builder
                .with_client_auth_cert(chain, key)
                .map_err(|e| format!("mqtt.key_file: does not fit the certificate: {e}"))
        }
        _ => Ok(builder.with_no_client_auth()),
    }
}

/// Why a connection failed, as counted.
fn failure(error: &ConnectionError) -> MqttFailure {
    match error {
        ConnectionError::ConnectionRefused(
            ConnectReturnCode::BadUserNamePassword | ConnectReturnCode::NotAuthorized,
        ) => MqttFailure::Login,
        ConnectionError::ConnectionRefused(_) => MqttFailure::Refused,
        ConnectionError::Tls(_) => MqttFailure::Tls,
        _ => MqttFailure::Network,
    }
}

/// Drive `events` for as long as the gateway runs, telling `publisher`.
pub(super) async fn run(
    mut events: EventLoop,
    broker: String,
    publisher: mpsc::Sender<FromBroker>,
    metrics: MqttMetrics,
    stopped: Arc<tokio::sync::Notify>,
) {
    let mut backoff = BACKOFF_FIRST;
    let mut logged: Option<(String, Instant)> = None;
    loop {
        match events.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                metrics.connected(&broker);
                backoff = BACKOFF_FIRST;
                logged = None;
                if publisher.send(FromBroker::Up).await.is_err() {
                    return;
                }
            }
            Ok(Event::Incoming(Packet::Publish(message))) => {
                let set = message.topic.ends_with("/set");
                if publisher.try_send(FromBroker::Message(message)).is_err() {
                    if set {
                        metrics.count(MqttMessage::SetReceived, 1);
                        metrics.count(MqttMessage::SetRefused, 1);
                    }
                    debug!(target: "modbus_gateway::mqtt", set, "a message from the broker dropped: the publisher is behind");
                }
            }
            Ok(Event::Outgoing(Outgoing::Publish(_))) => metrics.count(MqttMessage::Published, 1),
            Ok(Event::Outgoing(Outgoing::Disconnect)) => {
                metrics.stopped(&broker);
                stopped.notify_one();
                return;
            }
            Ok(_) => {}
            Err(error) => {
                let why = error.to_string();
                metrics.failed(failure(&error));
                let again = logged
                    .as_ref()
                    .is_none_or(|(last, at)| *last != why || at.elapsed() >= LOG_AGAIN);
                if again {
                    warn!(target: "modbus_gateway::mqtt", broker = %broker, error = %why, retry_in = ?backoff, "cannot reach the MQTT broker; Modbus is served meanwhile");
                    logged = Some((why.clone(), Instant::now()));
                }
                metrics.disconnected(&broker, &why);
                if publisher.send(FromBroker::Down).await.is_err() {
                    return;
                }
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(BACKOFF_MAX);
            }
        }
    }
}

/// Messages from the broker waiting for the publisher.
pub(super) fn channel() -> (mpsc::Sender<FromBroker>, mpsc::Receiver<FromBroker>) {
    mpsc::channel(MESSAGES)
}
