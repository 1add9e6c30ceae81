//! What the status page and `/readyz` read of a running gateway (`web::Inspect`): the parts
//! the gateway holds, read through.

use crate::bus::BusHandle;
use crate::config::{self, Config};
use crate::net::{self, server::Shared};
use crate::values::Store;
use crate::web;
use std::sync::{Arc, Mutex, PoisonError};
use tokio::time::Instant;

/// What the status page and `/readyz` read of the gateway: the buses the dispatcher routes to,
/// the configuration in force, the masters the listeners serve.
pub(super) struct Inspected {
    pub(super) shared: Arc<Shared>,
    pub(super) ports: Vec<Arc<crate::port::PortView>>,
    pub(super) config: Arc<Mutex<Config>>,
    pub(super) values: Arc<Store>,
}

impl web::Inspect for Inspected {
    fn buses(&self) -> Vec<BusHandle> {
        self.shared.dispatcher.buses()
    }

    fn settings(&self, name: &str) -> Option<config::Bus> {
        let config = self.config.lock().unwrap_or_else(PoisonError::into_inner);
        config.bus.iter().find(|bus| bus.name == name).cloned()
    }

    fn masters(&self) -> Vec<net::server::Connected> {
        let mut masters = self.shared.masters();
        masters.extend(self.ports.iter().filter_map(|port| port.master()));
        masters
    }

    fn ports(&self) -> &[Arc<crate::port::PortView>] {
        &self.ports
    }

    fn values(&self) -> &Store {
        &self.values
    }

    fn virtual_units(&self) -> Vec<crate::virtuals::ShownUnit> {
        self.shared.dispatcher.virtual_units().shown(Instant::now())
    }

    fn writes(&self) -> Vec<crate::audit::Recent> {
        self.shared.dispatcher.audit().recent()
    }
}
