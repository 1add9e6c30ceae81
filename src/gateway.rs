//! Wires a validated configuration into running parts: the metrics, the simulated lines, one task
//! per bus, the dispatcher, the Modbus TCP listeners and the metrics endpoint. Owns their tasks:
//! dropping the gateway stops them.

use crate::bus::{Bus, BusHandle, Device};
use crate::config::Config;
use crate::dispatch::Dispatcher;
use crate::metrics::{self, Metrics};
use crate::routing::Router;
use crate::shutdown::{self, Stop};
use crate::sim::{self, SimLine};
use crate::tcp::server::Shared;
use crate::tcp::{self, SessionLimits};
use std::collections::BTreeMap;
use std::io;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::task::JoinSet;
use tracing::{info, warn};

#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error("cannot listen on {addr}: {source}")]
    Listen { addr: SocketAddr, source: io::Error },
    #[error("bus {bus}: simulated slave {address}: {reason}")]
    SimSlave {
        bus: String,
        address: u8,
        reason: String,
    },
}

/// Slack on top of the last transaction's own bound, for the sessions to write their answers.
const LAST_TRANSACTION_MARGIN: Duration = Duration::from_secs(1);

pub struct Gateway {
    local_addrs: Vec<SocketAddr>,
    metrics_addr: SocketAddr,
    metrics: Arc<Metrics>,
    stop: Stop,
    shutdown_timeout: Duration,
    /// How long the transaction on the wire at the shutdown deadline may still take.
    last_transaction: Duration,
    listeners: JoinSet<()>,
    buses: JoinSet<()>,
    sim_lines: BTreeMap<String, SimLine>,
    shared: Arc<Shared>,
    tasks: JoinSet<()>,
}

/// The simulated line of a `device = "sim"` bus, with its slaves powered on.
pub fn sim_line(bus: &crate::config::Bus) -> Result<SimLine, StartError> {
    let line = SimLine::new(bus.line_timing());
    for slaves in &bus.sim_slave {
        for address in slaves.address.iter() {
            let slave =
                sim::build(slaves, address, bus.format()).map_err(|e| StartError::SimSlave {
                    bus: bus.name.clone(),
                    address,
                    reason: e.to_string(),
                })?;
            line.add_slave(address, slave);
        }
    }
    Ok(line)
}

impl Gateway {
    /// Bind every listener and start every bus. Fails only if a listen address cannot be bound;
    /// a serial port that cannot be opened yet is retried by its bus while the rest serves.
    pub async fn start(config: &Config) -> Result<Gateway, StartError> {
        let listeners = tcp::bind(&config.server.listen)
            .await
            .map_err(|(addr, source)| StartError::Listen { addr, source })?;
        let metrics_listen = config.metrics.listen;
        let listen_error = |source| StartError::Listen {
            addr: metrics_listen,
            source,
        };
        let metrics_listener = TcpListener::bind(metrics_listen)
            .await
            .map_err(listen_error)?;
        let metrics_addr = metrics_listener.local_addr().map_err(listen_error)?;
        let metrics = Arc::new(Metrics::new());
        let (stop, stopping) = shutdown::channel();
        let mut tasks = JoinSet::new();
        let mut bus_tasks = JoinSet::new();
        let mut listener_tasks = JoinSet::new();
        let mut sim_lines = BTreeMap::new();
        let mut handles = Vec::with_capacity(config.bus.len());
        for settings in &config.bus {
            let device = if settings.is_sim() {
                let line = sim_line(settings)?;
                sim_lines.insert(settings.name.clone(), line.clone());
                Device::Sim(line)
            } else {
                Device::Serial {
                    path: settings.device.clone(),
                    format: settings.format(),
                }
            };
            let bus = Bus::new(settings.clone(), device, &metrics);
            handles.push(bus.handle());
            bus_tasks.spawn(bus.run(stopping.clone()));
        }
        let limits = SessionLimits {
            pipeline_depth: config.server.pipeline_depth,
            idle_timeout: Some(config.server.idle_timeout).filter(|t| !t.is_zero()),
        };
        // Started means each bus has tried its port once, so what is reported next is true.
        for handle in &handles {
            handle.first_open_attempt().await;
        }
        let buses = handles.clone();
        let not_ready: metrics::http::Readiness = Arc::new(move || {
            let down = buses.iter().filter(|bus| !bus.is_up());
            down.map(|bus| bus.name().to_owned()).collect()
        });
        info!(listen = %metrics_addr, "serving /metrics, /healthz and /readyz");
        tasks.spawn(metrics::http::serve(
            metrics_listener,
            metrics.clone(),
            not_ready,
        ));
        let dispatcher = Dispatcher::new(Router::new(config), handles, metrics.clone());
        let shared = Arc::new(Shared::new(
            dispatcher,
            limits,
            config.server.max_connections,
            metrics.clone(),
            stopping,
        ));
        let local_addrs = listeners.iter().map(|l| l.addr).collect();
        for listener in listeners {
            info!(listen = %listener.addr, "accepting Modbus TCP masters");
            listener_tasks.spawn(tcp::serve(listener, shared.clone()));
        }
        // A request started just before the deadline may wait its slave's timeout, after a
        // gap the line may keep busy for as long again.
        let longest_timeout = config
            .bus
            .iter()
            .flat_map(|b| {
                std::iter::once(b.response_timeout)
                    .chain(b.slave.iter().filter_map(|s| s.response_timeout))
            })
            .max()
            .unwrap_or_default();
        Ok(Gateway {
            local_addrs,
            metrics_addr,
            metrics,
            stop,
            shutdown_timeout: config.server.shutdown_timeout,
            last_transaction: longest_timeout * 2 + LAST_TRANSACTION_MARGIN,
            listeners: listener_tasks,
            buses: bus_tasks,
            sim_lines,
            shared,
            tasks,
        })
    }

    /// The bound listen addresses (port 0 in the configuration becomes the real port here).
    pub fn local_addrs(&self) -> &[SocketAddr] {
        &self.local_addrs
    }

    /// The bound address of the metrics endpoint.
    pub fn metrics_addr(&self) -> SocketAddr {
        self.metrics_addr
    }

    /// The gateway's metrics, as `/metrics` serves them.
    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// The simulated line of bus `name`, for tests and demos.
    pub fn sim_line(&self, name: &str) -> Option<&SimLine> {
        self.sim_lines.get(name)
    }

    /// The buses whose task has stopped making progress, with how long it has been silent.
    pub fn stalled_buses(&self) -> Vec<(String, Duration)> {
        let buses = self.shared.dispatcher.buses();
        buses
            .iter()
            .filter_map(|b| Some((b.name().to_owned(), b.stalled_for()?)))
            .collect()
    }

    /// A one-line health summary for the service manager: connections, buses up and down.
    pub fn status(&self) -> String {
        let buses = self.shared.dispatcher.buses();
        let (up, down): (Vec<&BusHandle>, Vec<&BusHandle>) = buses.iter().partition(|b| b.is_up());
        let names =
            |list: &[&BusHandle]| list.iter().map(|b| b.name()).collect::<Vec<_>>().join(", ");
        let mut status = format!("{} masters connected", self.shared.connections_open());
        if !up.is_empty() {
            status += &format!("; serving {}", names(&up));
        }
        if !down.is_empty() {
            status += &format!("; port down: {}", names(&down));
        }
        status
    }

    /// Whether bus `name` has its port open.
    pub fn bus_up(&self, name: &str) -> Option<bool> {
        let buses = self.shared.dispatcher.buses();
        buses.iter().find(|b| b.name() == name).map(|b| b.is_up())
    }

    /// Stop gracefully: accept no more masters; finish the transaction on the wire; serve the
    /// queued requests until `shutdown_timeout` and answer the rest 0x0A; let every session
    /// write its answers and close; then stop every task.
    pub async fn shutdown(mut self) {
        self.listeners.shutdown().await;
        let deadline = tokio::time::Instant::now() + self.shutdown_timeout;
        self.stop.stop(deadline);
        let shared = self.shared.clone();
        let buses = &mut self.buses;
        let drained = async {
            while buses.join_next().await.is_some() {}
            shared.sessions_ended().await;
        };
        let limit = deadline + self.last_transaction;
        if tokio::time::timeout_at(limit, drained).await.is_err() {
            warn!("shutdown: sessions still open after the shutdown timeout; closing them");
        }
        self.buses.shutdown().await;
        self.tasks.shutdown().await;
    }
}
