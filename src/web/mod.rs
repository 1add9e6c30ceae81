//! The operator's HTTP surface on `metrics.listen`: the status page (`/`) and its data
//! (`/status`, [`status`]), the plant values as JSON (`/values`, `values`), the live trace as
//! server-sent events (`/trace`, `sse`), the
//! Prometheus text format (`/metrics`) and the health checks (`/healthz`, `/readyz`), served by
//! [`endpoint`]. It reads the running gateway only through [`Inspect`] and the metrics' registry
//! and trace hub; it changes nothing, and knows nothing of how listeners, sessions or the line
//! work.

mod endpoint;
mod sse;
pub(crate) mod status;
mod values;

pub(crate) use endpoint::serve;

use crate::bus::BusHandle;
use crate::config;
use crate::net::server::Connected;
use status::{BusStatus, LinkStatus, MasterStatus, SlaveStatus, Status, Utilisation};
use std::borrow::Cow;
use std::time::SystemTime;
use tokio::time::Instant;

/// What the operator's pages read of the running gateway, and nothing more.
pub(crate) trait Inspect: Send + Sync + 'static {
    /// The buses in service, in configuration order.
    fn buses(&self) -> Vec<BusHandle>;
    /// The settings bus `name` runs with now.
    fn settings(&self, name: &str) -> Option<config::Bus>;
    /// The masters connected now, longest connected first.
    fn masters(&self) -> Vec<Connected>;
    /// The serial master ports.
    fn ports(&self) -> &[std::sync::Arc<crate::port::PortView>] {
        &[]
    }
    /// The plant values as last read.
    fn values(&self) -> &crate::values::Store;
    /// The virtual units and their registers, as they stand now.
    fn virtual_units(&self) -> Vec<crate::virtuals::ShownUnit> {
        Vec::new()
    }
    /// The last writes, newest last.
    fn writes(&self) -> Vec<crate::audit::Recent>;
}

/// A query string's `key=value` pairs, decoded, in order (a key alone has an empty value).
type Pairs<'a> = Vec<(Cow<'a, str>, Cow<'a, str>)>;

/// The pairs of `query`, decoded as the URL standard's `application/x-www-form-urlencoded` (what
/// an HTML form sends: `%2F` is `/`, `+` a space, bytes that are no UTF-8 become U+FFFD); or the
/// 400 and message that refuse it, for a `%` that two hex digits do not follow, which the
/// standard would keep as it is.
fn query_pairs(query: Option<&str>) -> Result<Pairs<'_>, (hyper::StatusCode, String)> {
    let query = query.unwrap_or_default();
    let bytes = query.as_bytes();
    let escape = |at: usize| bytes.get(at + 1..at + 3);
    let bad = (0..bytes.len()).find(|&at| {
        bytes[at] == b'%' && !escape(at).is_some_and(|hex| hex.iter().all(u8::is_ascii_hexdigit))
    });
    if let Some(at) = bad {
        let escape: String = query[at..].chars().take(3).collect();
        return Err((
            hyper::StatusCode::BAD_REQUEST,
            format!("bad escape `{escape}` in the query: a `%` takes two hex digits\n"),
        ));
    }
    Ok(form_urlencoded::parse(bytes).collect())
}

/// The bus a `bus=` parameter names, or the 404 and message that list the buses there are.
fn bus_named(value: &str, buses: &[String]) -> Result<String, (hyper::StatusCode, String)> {
    if buses.iter().any(|b| b == value) {
        return Ok(value.to_owned());
    }
    let known = buses.join(", ");
    Err((
        hyper::StatusCode::NOT_FOUND,
        format!("no bus named `{value}`; the buses are: {known}\n"),
    ))
}

/// The buses whose port is not open, for `/readyz`.
fn not_ready(gateway: &dyn Inspect) -> Vec<String> {
    let buses = gateway.buses();
    let down = buses.iter().filter(|bus| !bus.is_up());
    down.map(|bus| bus.name().to_owned()).collect()
}

/// What the status page shows, read when asked, and the lines' busy time of a moment ago that
/// their recent utilisation needs.
pub(crate) struct StatusSource {
    started: (Instant, SystemTime),
    utilisation: Utilisation,
}

impl StatusSource {
    /// The status of a gateway started now.
    pub(crate) fn new() -> StatusSource {
        StatusSource {
            started: (Instant::now(), SystemTime::now()),
            utilisation: Utilisation::default(),
        }
    }

    /// The buses as their handles and metrics have them, and the masters connected.
    fn read(&self, gateway: &dyn Inspect) -> Status {
        let (now, wall) = (Instant::now(), SystemTime::now());
        let handles = gateway.buses();
        let names: Vec<&str> = handles.iter().map(BusHandle::name).collect();
        self.utilisation.keep_only(&names);
        let buses = handles
            .iter()
            .filter_map(|handle| {
                let settings = gateway.settings(handle.name())?;
                let metrics = handle.metrics();
                let busy =
                    self.utilisation
                        .of(handle.name(), metrics.busy_seconds(), now, self.started.0);
                Some(bus_status(handle, &settings, busy, wall))
            })
            .collect();
        Status {
            version: env!("CARGO_PKG_VERSION"),
            time: status::rfc3339(wall),
            uptime_seconds: status::seconds_between(self.started.1, wall),
            buses,
            masters: gateway
                .masters()
                .iter()
                .map(|m| master_status(m, wall))
                .collect(),
            serial_ports: gateway.ports().iter().map(|p| port_status(p)).collect(),
            virtual_units: gateway.virtual_units(),
            writes: gateway.writes(),
        }
    }
}

/// One serial master port on the status page.
fn port_status(port: &crate::port::PortView) -> status::SerialPortStatus {
    status::SerialPortStatus {
        name: port.name.to_string(),
        device: port.device.clone(),
        format: port.format.clone(),
        framing: port.framing,
        up: port.metrics.is_up(),
        requests: crate::metrics::PortOutcome::ALL
            .iter()
            .map(|&o| (o.label(), port.metrics.counted(o)))
            .collect(),
    }
}

/// One master on the status page, at `now`.
fn master_status(master: &Connected, now: SystemTime) -> MasterStatus {
    MasterStatus {
        address: master.peer.to_string(),
        protocol: master.protocol.label(),
        rights: master.rights.name(),
        role: master.role.clone(),
        priority: master.priority,
        connected_since: status::rfc3339(master.since),
        connected_seconds: status::seconds_between(master.since, now),
        requests: master.requests,
    }
}

/// One bus on the status page, with its recent `utilisation`, at `now`.
fn bus_status(
    handle: &BusHandle,
    settings: &config::Bus,
    utilisation: f64,
    now: SystemTime,
) -> BusStatus {
    let metrics = handle.metrics();
    let model = |address: u8| {
        let sim = settings.sim_slave.iter();
        let mut slaves = sim.filter(|s| s.address.iter().any(|a| a == address));
        slaves.next().map(|s| s.model.name())
    };
    let slaves = metrics
        .slaves()
        .into_iter()
        .map(|slave| {
            let errors = slave
                .requests
                .iter()
                // A write an `acknowledge` rule answered ended as the master expects.
                .filter(|(outcome, _)| !matches!(outcome.as_str(), "ok" | "acknowledged"))
                .map(|(_, count)| count)
                .sum();
            SlaveStatus {
                address: slave.address,
                model: model(slave.address),
                up: slave.up,
                last_answer: slave.last_answer.map(status::rfc3339),
                last_answer_seconds_ago: slave
                    .last_answer
                    .map(|at| status::seconds_between(at, now)),
                round_trip_p50_seconds: slave.round_trip_p50.map(|d| d.as_secs_f64()),
                requests: slave.requests,
                errors,
                polls: slave.polls,
            }
        })
        .collect();
    BusStatus {
        name: settings.name.clone(),
        device: if settings.is_sim() {
            "simulated".to_owned()
        } else {
            settings.device.clone()
        },
        framing: settings.framing.name(),
        format: settings.format_label(),
        transport: settings.transport().label(),
        mode: if handle.shadow().is_some() {
            config::BusMode::Listen.name()
        } else {
            config::BusMode::Master.name()
        },
        port_up: handle.is_up(),
        link: metrics.link_snapshot().map(|link| LinkStatus {
            peer: link.peer,
            round_trip_seconds: link.round_trip.map(|rtt| rtt.as_secs_f64()),
            budget_seconds: link.budget.as_secs_f64(),
        }),
        utilisation,
        queue_depth: handle.queue_depth(),
        queue_capacity: settings.queue_depth,
        transactions: metrics.transactions(),
        slaves,
    }
}
