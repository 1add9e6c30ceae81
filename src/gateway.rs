//! Wires a validated configuration into running parts: the metrics, the simulated lines, one task
//! per bus, the dispatcher, the Modbus TCP listeners and the metrics endpoint; applies the
//! `ConfigDiff` of a reloaded configuration to them without closing connections; stops them
//! gracefully. Owns their tasks: dropping the gateway stops them. Also where a configuration is
//! loaded with its simulated drives checked ([`load_config`]): the one place that knows both.

use crate::audit::Audit;
use crate::bus::{BusHandle, BusTask, BusUpdates, Device, Reconfigure, SerialDriver, TlsDevice};
use crate::config::{self, BusChange, Config, ConfigDiff, ConfigError, ConfigErrors, DeviceName};
use crate::dispatch::Dispatcher;
use crate::master::Protocol;
use crate::metrics::Metrics;
use crate::net::server::Shared;
use crate::net::tls::TlsServer;
use crate::net::{self, ListenAddrs, Policy};
use crate::routing::Router;
use crate::shutdown::{self, Stop};
use crate::sim::{self, SimLine};
use crate::values::{Exported, Values};
use crate::web;
use inspected::Inspected;
use std::io;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::task::{JoinHandle, JoinSet};
use tokio::time::Instant;
use tracing::{info, warn};

mod inspected;

#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error("{key}: cannot listen on {addr}: {source}")]
    Listen {
        key: &'static str,
        addr: SocketAddr,
        source: io::Error,
    },
    #[error("{0}")]
    Tls(ConfigErrors),
    #[error("audit.path: cannot open the audit journal `{path}`: {source}")]
    Journal { path: String, source: io::Error },
    #[error("bus {bus}: simulated slave {address}: {reason}")]
    SimSlave {
        bus: String,
        address: u8,
        reason: String,
    },
}

/// Slack on top of the last transaction's own bound, for the sessions to write their answers.
const LAST_TRANSACTION_MARGIN: Duration = Duration::from_secs(1);

/// One bus as the gateway runs it.
struct Running {
    settings: config::Bus,
    device: Device,
    handle: BusHandle,
    updates: BusUpdates,
    stop: Stop,
    task: JoinHandle<()>,
}

pub struct Gateway {
    listen_addrs: ListenAddrs,
    metrics_addr: SocketAddr,
    metrics: Arc<Metrics>,
    /// The configuration in force: the one started with, or the last reloaded. Shared with the
    /// status page, which shows the buses' settings.
    config: Arc<Mutex<Config>>,
    /// In configuration order, which the router's bus indices follow.
    buses: Mutex<Vec<Running>>,
    /// Buses removed by a reload that are still serving what they had queued.
    retired: Mutex<Vec<JoinHandle<()>>>,
    /// Tells the sessions to stop.
    stop: Stop,
    listeners: JoinSet<()>,
    shared: Arc<Shared>,
    /// The plant values and their pollers.
    values: Values,
    /// Their publisher to `[mqtt]`'s broker.
    mqtt: Option<crate::mqtt::Publishing>,
    tasks: JoinSet<()>,
}

/// What a reload did.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Reloaded {
    /// One line per change applied: bus added, removed, reconfigured or reopened; routes; limits.
    pub applied: Vec<String>,
    /// Keys that changed but take a restart to apply (`log.level` is not the gateway's to apply).
    pub need_restart: Vec<String>,
    /// Changes that could not be applied, each saying what was kept instead and why.
    pub kept: Vec<String>,
}

/// A new simulated line for a `device = "sim"` bus, with its slaves powered on and its other
/// master, if it has one (`[bus.sim_master]`, which runs while the line is listened to).
pub fn power_on_line(bus: &config::Bus) -> Result<SimLine, StartError> {
    let line = SimLine::with_framing(bus.line_timing(), bus.framing);
    for slaves in &bus.sim_slave {
        for address in slaves.address.iter() {
            let slave = sim::build(slaves, address, bus.format(), bus.framing).map_err(|e| {
                StartError::SimSlave {
                    bus: bus.name.clone(),
                    address,
                    reason: e.to_string(),
                }
            })?;
            line.add_slave(address, slave);
        }
    }
    if let Some(master) = &bus.sim_master {
        line.set_master(master);
    }
    Ok(line)
}

/// Read `path` with the `MBGW__` variables among `env` over it, and check it through and
/// through: the configuration's own checks, the simulated drives' parameters, which only the
/// simulator knows, and the `[server.tls]` files. What the daemon runs, checks (`check-config`)
/// and reloads.
pub fn load_config(
    path: &Path,
    env: impl IntoIterator<Item = (String, String)>,
) -> Result<Config, ConfigErrors> {
    Config::load_with(path, env, &sim::Drives, &TlsFiles)
}

/// The `[server.tls]` files, read as the TLS listeners will read them.
struct TlsFiles;

impl config::TlsFilesCheck for TlsFiles {
    fn read_files(&self, tls: &config::Tls) -> Result<(), ConfigErrors> {
        TlsServer::load(tls).map(|_| ())
    }
}

/// [`load_config`] for TOML text, with no environment, and the `[server.tls]` files left for
/// [`Gateway::start`] to read.
pub fn config_from_toml(text: &str) -> Result<Config, ConfigErrors> {
    Config::from_toml_str_with(text, &sim::Drives)
}

/// The TLS server of `[server.tls]`, read from its files now, with its certificate's expiry
/// exported and warned of; `None` without that table.
fn load_tls(
    server: &config::Server,
    metrics: &Metrics,
) -> Result<Option<Arc<TlsServer>>, StartError> {
    let Some(settings) = &server.tls else {
        return Ok(None);
    };
    let tls = TlsServer::load(settings).map_err(StartError::Tls)?;
    let certificate = &tls.certificate;
    metrics.tls.certificate_expires(certificate.expires);
    let now = std::time::SystemTime::now();
    let expires = certificate.expiry(now);
    let subject = &certificate.subject;
    let file = settings.certificate.display().to_string();
    match certificate.expiry_warning(now) {
        Some(warning) => warn!(file, subject, expires, "{warning}"),
        None => info!(file, subject, expires, "TLS server certificate loaded"),
    }
    Ok(Some(Arc::new(tls)))
}

/// The operator's HTTP listener on `metrics.listen`, and the address it got.
async fn bind_metrics(listen: SocketAddr) -> Result<(TcpListener, SocketAddr), StartError> {
    let listen_error = |source| StartError::Listen {
        key: "metrics.listen",
        addr: listen,
        source,
    };
    let listener = TcpListener::bind(listen).await.map_err(listen_error)?;
    let addr = listener.local_addr().map_err(listen_error)?;
    Ok((listener, addr))
}

/// One task per bound listener in `tasks`, accepting masters.
fn serve_listeners(
    listeners: Vec<net::listener::Listener>,
    shared: &Arc<Shared>,
    tasks: &mut JoinSet<()>,
) {
    for listener in listeners {
        info!(listen = %listener.addr, protocol = listener.protocol.name(), "accepting masters");
        tasks.spawn(net::serve(listener, shared.clone()));
    }
}

/// The writes' record, with the journal of `[audit]` open; one that cannot be opened is a start
/// error naming `audit.path`.
fn open_audit(config: &Config, metrics: &Arc<Metrics>) -> Result<Arc<Audit>, StartError> {
    let audit = Audit::new(metrics.clone());
    audit
        .open(config.audit.as_ref())
        .map_err(|source| StartError::Journal {
            path: config
                .audit
                .as_ref()
                .map(|a| a.path.display().to_string())
                .unwrap_or_default(),
            source,
        })?;
    Ok(audit)
}

/// The running bus named `name`, taken out of `buses` (the last one takes its place, which is
/// the order [`ConfigDiff::removed`] follows).
fn take(buses: &mut Vec<Running>, name: &str) -> Option<Running> {
    let at = buses.iter().position(|r| r.settings.name == name)?;
    Some(buses.swap_remove(at))
}

/// The device `bus[index]`'s settings name (the one place a `device` key becomes a transport); a
/// simulated line is kept when its format, slaves and other master are unchanged (`current`), so
/// its slaves keep their state.
fn device_for(
    index: usize,
    settings: &config::Bus,
    current: Option<(&config::Bus, &Device)>,
) -> Result<Device, StartError> {
    match settings.device_name() {
        DeviceName::Serial(path) => {
            return Ok(Device::Serial {
                path,
                format: settings.format(),
                driver: SerialDriver::of(index, settings),
            })
        }
        DeviceName::Server(addr) => {
            // A `tls://` device's files are read now: a bad one is an error naming its key.
            let tls = settings
                .tls
                .as_ref()
                .map(|tls| {
                    TlsDevice::load(tls, &addr.host).map_err(|problems| {
                        let errors = problems.into_iter().map(|(key, reason)| ConfigError {
                            key: format!("bus[{index}].tls.{key}"),
                            reason,
                        });
                        StartError::Tls(ConfigErrors(errors.collect()))
                    })
                })
                .transpose()?;
            return Ok(Device::Server {
                addr,
                format: settings.format(),
                tls,
            });
        }
        DeviceName::Sim => {}
    }
    if let Some((old, device @ Device::Sim(_))) = current {
        if old.is_sim()
            && old.format() == settings.format()
            && old.framing == settings.framing
            && old.sim_slave == settings.sim_slave
            && old.sim_master == settings.sim_master
        {
            return Ok(device.clone());
        }
    }
    power_on_line(settings).map(Device::Sim)
}

impl Gateway {
    /// Bind every listener and start every bus. Fails only if a listen address cannot be bound;
    /// a serial port that cannot be opened yet is retried by its bus while the rest serves.
    pub async fn start(config: &Config) -> Result<Gateway, StartError> {
        let metrics = Arc::new(Metrics::new());
        let tls = load_tls(&config.server, &metrics)?;
        let listeners = net::bind_all(&config.server)
            .await
            .map_err(|(key, addr, source)| StartError::Listen { key, addr, source })?;
        let (metrics_listener, metrics_addr) = bind_metrics(config.metrics.listen).await?;
        let buses = Self::start_buses(config, &metrics).await?;
        let handles: Vec<BusHandle> = buses.iter().map(|b| b.handle.clone()).collect();
        let values = Values::new();
        metrics.collect_also(Box::new(Exported(values.store().clone())));
        values.apply(config, &handles);
        let audit = open_audit(config, &metrics)?;
        let router = Router::new(config);
        let decided = Dispatcher::decided(config, &router, values.store(), &metrics);
        let dispatcher = Dispatcher::with_rules(router, handles, decided, audit, metrics.clone());
        let (stop, stopping) = shutdown::channel();
        let shared = Arc::new(Shared::new(
            dispatcher,
            Policy::of(&config.server, tls),
            config.server.max_connections,
            metrics.clone(),
            stopping,
        ));
        let mut listener_tasks = JoinSet::new();
        let ports = crate::port::start(&config.server.serial, &shared, &mut listener_tasks);
        let mqtt = crate::mqtt::Publishing::start(config, values.store(), &shared, &metrics);
        let config = Arc::new(Mutex::new(config.clone()));
        let inspected = Inspected {
            shared: shared.clone(),
            ports,
            config: config.clone(),
            values: values.store().clone(),
        };
        let mut tasks = JoinSet::new();
        info!(listen = %metrics_addr, "serving the status page (/), /status, /values, /trace, /metrics, /healthz and /readyz");
        tasks.spawn(web::serve(
            metrics_listener,
            metrics.clone(),
            Arc::new(inspected),
        ));
        let listen_addrs = ListenAddrs::of(&listeners);
        serve_listeners(listeners, &shared, &mut listener_tasks);
        Ok(Gateway {
            listen_addrs,
            metrics_addr,
            metrics,
            config,
            buses: Mutex::new(buses),
            retired: Mutex::new(Vec::new()),
            stop,
            listeners: listener_tasks,
            shared,
            values,
            mqtt,
            tasks,
        })
    }

    /// Every configured bus started, each having tried its port once: so what is reported
    /// next is true.
    async fn start_buses(config: &Config, metrics: &Metrics) -> Result<Vec<Running>, StartError> {
        let mut buses = Vec::with_capacity(config.bus.len());
        for (index, settings) in config.bus.iter().enumerate() {
            let device = device_for(index, settings, None)?;
            buses.push(Self::start_bus(settings, device, metrics));
        }
        for bus in &buses {
            bus.handle.first_open_attempt().await;
        }
        for bus in &buses {
            bus.handle.set_priority_share(config.server.priority_share);
        }
        Ok(buses)
    }

    fn start_bus(settings: &config::Bus, device: Device, metrics: &Metrics) -> Running {
        let mut bus = BusTask::new(settings.clone(), device.clone(), metrics);
        let updates = bus.updates();
        let handle = bus.handle();
        let (stop, stopping) = shutdown::channel();
        let task = tokio::spawn(bus.run(stopping));
        Running {
            settings: settings.clone(),
            device,
            handle,
            updates,
            stop,
            task,
        }
    }

    /// Apply `new` (validated) without closing any TCP connection: routes, timeouts, per-slave
    /// settings, queue and connection limits change between transactions; a bus whose device or
    /// serial format changed reopens its port; added buses start; removed ones serve what they
    /// had queued (until `shutdown_timeout`) and stop. Listen addresses and the log format take
    /// a restart. On error nothing has changed.
    pub fn reload(&self, new: &Config) -> Result<Reloaded, StartError> {
        let mut config = self.config.lock().unwrap_or_else(PoisonError::into_inner);
        let mut running = self.buses.lock().unwrap_or_else(PoisonError::into_inner);
        let diff = ConfigDiff::new(&config, new);
        // The TLS files and every device first, so that a failure leaves everything as it was.
        let tls = load_tls(&new.server, &self.metrics)?;
        let devices = new
            .bus
            .iter()
            .enumerate()
            .map(|(index, settings)| {
                let current = running.iter().find(|r| r.settings.name == settings.name);
                device_for(index, settings, current.map(|r| (&r.settings, &r.device)))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let mut done = Reloaded::default();
        self.reload_buses(new, &diff, &mut running, devices, &mut done);
        let handles: Vec<BusHandle> = running.iter().map(|r| r.handle.clone()).collect();
        self.reload_requests(new, &config, &diff, handles, &mut done);
        self.reload_server(new, &diff, tls, &mut done);
        done.need_restart = diff
            .need_restart
            .iter()
            .map(|&key| key.to_owned())
            .collect();
        *config = new.clone();
        Ok(done)
    }

    /// The buses `new` lists, each updated, added or kept, in `running`; the removed ones
    /// retired, serving what they had queued until `shutdown_timeout`.
    fn reload_buses(
        &self,
        new: &Config,
        diff: &ConfigDiff,
        running: &mut Vec<Running>,
        devices: Vec<Device>,
        done: &mut Reloaded,
    ) {
        let mut old = std::mem::take(running);
        for ((settings, (_, change)), device) in new.bus.iter().zip(&diff.buses).zip(devices) {
            let bus = match take(&mut old, &settings.name) {
                Some(bus) => Self::update_bus(bus, *change, settings, device, done),
                None => {
                    done.applied.push(format!("bus {}: added", settings.name));
                    Self::start_bus(settings, device, &self.metrics)
                }
            };
            running.push(bus);
        }
        let deadline = Instant::now() + new.server.shutdown_timeout;
        let removed: Vec<Running> = diff
            .removed
            .iter()
            .filter_map(|name| take(&mut old, name))
            .collect();
        let names = removed.iter().map(|bus| &bus.settings.name);
        done.applied
            .extend(names.map(|name| format!("bus {name}: removed")));
        self.retire(removed, deadline);
        for bus in running.iter() {
            bus.handle.set_priority_share(new.server.priority_share);
        }
    }

    /// What decides a request from `new`: routes, plant values, rules, the journal.
    fn reload_requests(
        &self,
        new: &Config,
        old: &Config,
        diff: &ConfigDiff,
        handles: Vec<BusHandle>,
        done: &mut Reloaded,
    ) {
        if diff.routes {
            done.applied.push("routes".to_owned());
        }
        self.values.apply(new, &handles);
        if let Some(mqtt) = &self.mqtt {
            mqtt.apply(new);
        }
        if diff.values {
            done.applied.push("plant values".to_owned());
        }
        // A rule's units are the slaves they route to: new routes make new rules of old ones.
        let router = Router::new(new);
        let decided = Dispatcher::decided(new, &router, self.values.store(), &self.shared.metrics);
        self.shared.dispatcher.replace(router, handles, decided);
        if new.rule != old.rule {
            done.applied.push("rules".to_owned());
        }
        if new.virtual_units != old.virtual_units {
            done.applied.push("virtual units".to_owned());
        }
        match self.shared.dispatcher.audit().apply(new.audit.as_ref()) {
            Ok(Some(what)) => done.applied.push(what),
            Ok(None) => {}
            Err(why) => done.kept.push(why),
        }
    }

    /// The listeners' policy and TLS files from `new`, for new connections.
    fn reload_server(
        &self,
        new: &Config,
        diff: &ConfigDiff,
        tls: Option<Arc<TlsServer>>,
        done: &mut Reloaded,
    ) {
        if diff.connection_policy {
            done.applied
                .push("connection limits and access (for new connections)".to_owned());
        }
        if tls.is_some() {
            done.applied
                .push("TLS certificate, key, client CA and roles (for new connections)".to_owned());
        }
        self.shared
            .set_policy(Policy::of(&new.server, tls), new.server.max_connections);
        if diff.shutdown_timeout {
            done.applied.push("server.shutdown_timeout".to_owned());
        }
    }

    /// A running bus as a reload leaves it: told its new settings if they `change`d.
    fn update_bus(
        mut bus: Running,
        change: BusChange,
        settings: &config::Bus,
        device: Device,
        done: &mut Reloaded,
    ) -> Running {
        if change == BusChange::Changed {
            let reopen = bus.updates.send(Reconfigure {
                settings: settings.clone(),
                device: device.clone(),
            });
            let what = if reopen { "reopened" } else { "reconfigured" };
            done.applied.push(format!("bus {}: {what}", settings.name));
            bus.settings = settings.clone();
            bus.device = device;
        }
        bus
    }

    /// Stop the buses a reload removed once they have served what they had queued (until
    /// `deadline`), then drop their series.
    fn retire(&self, buses: Vec<Running>, deadline: Instant) {
        let mut retired = self.retired.lock().unwrap_or_else(PoisonError::into_inner);
        retired.retain(|task| !task.is_finished());
        for bus in buses {
            bus.stop.stop(deadline);
            let metrics = self.metrics.clone();
            let handle = bus.handle.clone();
            let task = bus.task;
            retired.push(tokio::spawn(async move {
                shutdown::log_end("retired bus", task.await);
                metrics.forget_bus(handle.metrics());
            }));
        }
    }

    /// The bound addresses of the `protocol` masters' listeners, in configuration order (port 0
    /// in the configuration becomes the real port here).
    fn addrs(&self, protocol: Protocol) -> &[SocketAddr] {
        self.listen_addrs.of_protocol(protocol)
    }

    /// The bound `server.listen` addresses (Modbus TCP).
    pub fn tcp_addrs(&self) -> &[SocketAddr] {
        self.addrs(Protocol::Tcp)
    }

    /// The bound `server.listen_rtu_over_tcp` addresses.
    pub fn rtu_over_tcp_addrs(&self) -> &[SocketAddr] {
        self.addrs(Protocol::RtuOverTcp)
    }

    /// The bound `server.listen_tls` addresses.
    pub fn tls_addrs(&self) -> &[SocketAddr] {
        self.addrs(Protocol::Tls)
    }

    /// The bound `server.listen_udp` addresses.
    pub fn udp_addrs(&self) -> &[SocketAddr] {
        self.addrs(Protocol::Udp)
    }

    /// The bound address of the metrics endpoint.
    pub fn metrics_addr(&self) -> SocketAddr {
        self.metrics_addr
    }

    /// The simulated line of bus `name`, for tests and demos.
    pub fn sim_line(&self, name: &str) -> Option<SimLine> {
        let buses = self.buses.lock().unwrap_or_else(PoisonError::into_inner);
        match &buses.iter().find(|b| b.settings.name == name)?.device {
            Device::Sim(line) => Some(line.clone()),
            Device::Serial { .. } | Device::Server { .. } => None,
        }
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
        shutdown::abort_all(&mut self.listeners, "listener").await;
        let config = self
            .config
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone();
        let deadline = Instant::now() + config.server.shutdown_timeout;
        let buses = std::mem::take(self.buses.get_mut().unwrap_or_else(PoisonError::into_inner));
        let mut retired = std::mem::take(
            self.retired
                .get_mut()
                .unwrap_or_else(PoisonError::into_inner),
        );
        for bus in &buses {
            bus.stop.stop(deadline);
        }
        self.stop.stop(deadline);
        let shared = self.shared.clone();
        let mut tasks: Vec<JoinHandle<()>> = buses.into_iter().map(|b| b.task).collect();
        tasks.append(&mut retired);
        let aborts: Vec<_> = tasks.iter().map(JoinHandle::abort_handle).collect();
        let drained = async {
            for task in tasks {
                shutdown::log_end("bus", task.await);
            }
            shared.sessions_ended().await;
        };
        // A request started just before the deadline may take the longest transaction its bus
        // allows.
        let longest = config
            .bus
            .iter()
            .map(crate::bus::longest_transaction)
            .max()
            .unwrap_or_default();
        let limit = deadline + longest + LAST_TRANSACTION_MARGIN;
        if tokio::time::timeout_at(limit, drained).await.is_err() {
            warn!("shutdown: sessions still open after the shutdown timeout; closing them");
        }
        for abort in aborts {
            abort.abort();
        }
        if let Some(mqtt) = self.mqtt.take() {
            mqtt.stop().await;
        }
        shutdown::abort_all(&mut self.tasks, "metrics endpoint").await;
    }
}

impl Drop for Gateway {
    /// Bus tasks are spawned on their own (a reload replaces them one by one): stop them with
    /// the gateway.
    fn drop(&mut self) {
        let buses = self.buses.get_mut().unwrap_or_else(PoisonError::into_inner);
        for bus in buses.iter() {
            bus.task.abort();
        }
        let retired = self
            .retired
            .get_mut()
            .unwrap_or_else(PoisonError::into_inner);
        for task in retired.iter() {
            task.abort();
        }
    }
}
