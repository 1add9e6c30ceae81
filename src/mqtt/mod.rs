//! The plant values over MQTT (`[mqtt]`): every polled value published at
//! `PREFIX/BUS/SLAVE/NAME` when it changes, each slave's availability, the gateway's status (its
//! last will says `offline`), Home Assistant's discovery configs, and with `writes` a value's
//! `set` topic carried out as a write of the master `mqtt`, under the rules and the journal.
//! By concern: `link` (the broker's connection, rumqttc's event loop), `catalogue` (the topics of
//! one configuration), `publish` (what is published when), `discovery` (Home Assistant's
//! configs), `set` (a write by MQTT). The broker is never in a bus's way: the publisher reads the
//! store the pollers fill and nothing waits on it but itself.

mod catalogue;
mod discovery;
mod link;
mod publish;
mod set;

use crate::config::{Config, Mqtt};
use crate::dispatch::Client;
use crate::master::{Peer, Protocol, Rights};
use crate::metrics::Metrics;
use crate::net::server::Shared;
use crate::values::Store;
use catalogue::Catalogue;
use rumqttc::AsyncClient;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{watch, Notify};
use tokio::task::JoinHandle;
use tracing::{error, info};

/// How long a stop waits for the gateway's `offline` to leave.
const STOP_WAIT: Duration = Duration::from_millis(500);

/// The running MQTT client of a gateway.
pub(crate) struct Publishing {
    settings: Mqtt,
    store: Arc<Store>,
    catalogues: watch::Sender<Arc<Catalogue>>,
    client: AsyncClient,
    stopped: Arc<Notify>,
    tasks: Vec<JoinHandle<()>>,
}

impl Publishing {
    /// Publish `config`'s values (read from `store`) to its `[mqtt]` broker, with sets written
    /// through `shared`'s dispatcher; `None` without `[mqtt]`, or if its client cannot be made
    /// (logged).
    pub(crate) fn start(
        config: &Config,
        store: &Arc<Store>,
        shared: &Arc<Shared>,
        metrics: &Metrics,
    ) -> Option<Publishing> {
        let settings = config.mqtt.clone()?;
        let (client, events, broker) = match link::client(&settings) {
            Ok(made) => made,
            Err(why) => {
                error!(target: "modbus_gateway::mqtt", %why, "the MQTT client cannot be made; nothing is published");
                return None;
            }
        };
        info!(target: "modbus_gateway::mqtt", %broker, prefix = %settings.topic_prefix, writes = settings.writes, "publishing the plant values over MQTT");
        let metrics = metrics.mqtt();
        let first = Catalogue::new(&settings, config, store.specs());
        let (catalogues, watched) = watch::channel(Arc::new(first));
        let (heard, hearing) = link::channel();
        let stopped = Arc::new(Notify::new());
        let master =
            Client::at(shared.new_master(), Peer::Mqtt, Rights::ReadWrite).speaking(Protocol::Mqtt);
        let parts = publish::Parts {
            settings: settings.clone(),
            client: client.clone(),
            store: store.clone(),
            catalogues: watched,
            shared: shared.clone(),
            master: Arc::new(master),
            metrics: metrics.clone(),
        };
        let tasks = vec![
            tokio::spawn(link::run(events, broker, heard, metrics, stopped.clone())),
            tokio::spawn(publish::run(parts, hearing)),
        ];
        Some(Publishing {
            settings,
            store: store.clone(),
            catalogues,
            client,
            stopped,
            tasks,
        })
    }

    /// Publish what `config` (reloaded, its values in the store already) has from now on; the
    /// `[mqtt]` table itself takes a restart.
    pub(crate) fn apply(&self, config: &Config) {
        let catalogue = Catalogue::new(&self.settings, config, self.store.specs());
        self.catalogues.send_replace(Arc::new(catalogue));
    }

    /// A clean stop: `PREFIX/status` says `offline` (the last will is only for a crash) and the
    /// client disconnects, waiting at most half a second for the broker.
    pub(crate) async fn stop(self) {
        let status = format!("{}/status", self.settings.topic_prefix);
        let qos = link::qos(&self.settings);
        let _ = self.client.try_publish(status, qos, true, "offline");
        let _ = self.client.try_disconnect();
        let _ = tokio::time::timeout(STOP_WAIT, self.stopped.notified()).await;
    }
}

impl Drop for Publishing {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
}
