//! Checks what serde cannot: ranges, names, references between sections, and (through
//! [`DriveCheck`]) whether a simulated drive accepts its parameters. Reads the configuration and
//! changes nothing (deriving values is [`resolve`](super::resolve)'s); reports every problem, in
//! the order of the file, each with its key path. Knows nothing of how a drive is simulated.

use super::audit::{MAX_AUDIT_KEEP, MIN_AUDIT_SIZE};
use super::defaults;
use super::rs485::LATENCY_TIMER_MS;
use super::values;
use super::DeviceName;
use super::UnitSet;
use super::OTHER_ROLE;
use super::{Audit, Bus, Config, ConfigError, ConfigErrors, Route, Rule, Server, SimSlave};
use super::{Templates, Tls};
use super::{MAX_SLAVE_ADDRESS, SIM_DEVICE};
use crate::line::framing::TransportKind;
use crate::line::{Framing, SerialFormat};
use crate::pdu::EXCEPTION_BIT;
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::time::Duration;

pub(super) const MAX_RETRIES: u32 = 10;
const MIN_KEEPALIVE: Duration = Duration::from_secs(1);
/// Most garbage a simulated slave may wrap a reply in: a frame's worth.
pub(super) const MAX_GARBAGE: usize = 256;

/// Powers on a simulated drive to see whether it accepts its configured parameters and trip.
/// Only the simulator knows its drives' parameter tables, so it implements this; the check asks
/// it, and the configuration needs nothing of the simulator's.
pub trait DriveCheck {
    /// Power on the drive `slave` describes at `address`, on a line of `format`.
    fn power_on(
        &self,
        slave: &SimSlave,
        address: u8,
        format: SerialFormat,
    ) -> Result<(), DriveRefusal>;
}

/// Reads the files `[server.tls]` names, so that one that cannot be used is reported with every
/// other problem. Only the TLS code knows how to read them, so it implements this.
pub(crate) trait TlsFilesCheck {
    /// Every problem with the files `tls` names, each with its key path.
    fn read_files(&self, tls: &Tls) -> Result<(), ConfigErrors>;
}

/// A setting a drive refused: the parameter by the manual's name (or `trip`), and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DriveRefusal {
    pub param: String,
    pub reason: String,
}

/// The problems found so far, in the order they were found.
#[derive(Default)]
struct Report(Vec<ConfigError>);

impl Report {
    fn fail(&mut self, key: impl Into<String>, reason: impl Into<String>) {
        self.0.push(ConfigError {
            key: key.into(),
            reason: reason.into(),
        });
    }
}

impl Config {
    /// Every problem serde cannot see, each with its key path. With `drives`, the simulated
    /// drives are powered on to check their parameters; without, those are left unchecked.
    pub fn check(&self, drives: Option<&dyn DriveCheck>) -> Result<(), ConfigErrors> {
        let mut report = Report::default();
        check_server(&self.server, &mut report);
        check_listen_once(&self.server, self.metrics.listen, &mut report);
        check_log_level(&self.log.level, &mut report);
        if self.bus.is_empty() {
            report.fail("bus", "at least one [[bus]] is needed");
        }
        let mut names = BTreeMap::new();
        for (i, bus) in self.bus.iter().enumerate() {
            check_bus(i, bus, &mut names, drives, &mut report);
            check_values(i, bus, &self.templates, &mut report);
        }
        let values = self.bus.iter().enumerate().flat_map(|(i, bus)| {
            bus.slave.iter().enumerate().flat_map(move |(j, slave)| {
                let template = slave
                    .template
                    .as_deref()
                    .and_then(|name| self.templates.get(name));
                let from_template = template.into_iter().flat_map(move |t| {
                    t.value.iter().enumerate().map(move |(k, v)| {
                        (format!("bus[{i}].slave[{j}].template (its value[{k}])"), v)
                    })
                });
                let own = slave
                    .value
                    .iter()
                    .enumerate()
                    .map(move |(k, v)| (format!("bus[{i}].slave[{j}].value[{k}]"), v));
                from_template.chain(own)
            })
        });
        values::check_families(values, &mut report.0);
        check_devices_once(&self.bus, &mut report);
        check_routes(&self.route, &self.bus, &names, &mut report);
        check_rules(&self.rule, &self.server, &names, &mut report);
        super::serial_port::check(&self.server.serial, &self.bus, &mut report.0);
        super::virtual_unit::check(self, &mut report.0);
        super::mqtt::check(self, &mut report.0);
        if let Some(audit) = &self.audit {
            check_audit(audit, &mut report);
        }
        if report.0.is_empty() {
            Ok(())
        } else {
            Err(ConfigErrors(report.0))
        }
    }
}

fn check_server(server: &Server, report: &mut Report) {
    if server.listen.is_empty() {
        report.fail("server.listen", "needs at least one address");
    }
    if server.max_connections == 0 {
        report.fail("server.max_connections", "must be at least 1");
    }
    if server.pipeline_depth == 0 {
        report.fail("server.pipeline_depth", "must be at least 1");
    }
    if server.frame_timeout.is_zero() {
        report.fail("server.frame_timeout", "must be longer than 0");
    }
    if !server.keepalive.is_zero() && server.keepalive < MIN_KEEPALIVE {
        report.fail(
            "server.keepalive",
            "must be \"0s\" (off) or at least 1s (TCP counts it in seconds)",
        );
    }
    if !(server.priority_share > 0.0 && server.priority_share <= 1.0) {
        report.fail(
            "server.priority_share",
            format!(
                "{} must be more than 0 and at most 1 (a share of the line's transactions)",
                server.priority_share
            ),
        );
    }
    match &server.tls {
        None if !server.listen_tls.is_empty() => report.fail(
            "server.tls",
            "server.listen_tls needs a [server.tls] table: certificate, private_key and client_ca",
        ),
        None => {}
        Some(tls) => check_tls(tls, report),
    }
}

fn check_tls(tls: &Tls, report: &mut Report) {
    for (name, role) in &tls.roles {
        if role.units.is_some_and(|units| units.is_empty()) {
            report.fail(
                format!("server.tls.roles.{name}.units"),
                "names no unit: leave it out for any unit, or give access = \"none\"",
            );
        }
        if name.is_empty() {
            report.fail("server.tls.roles", "a role needs a name");
        } else if name == OTHER_ROLE {
            report.fail(
                format!("server.tls.roles.{name}"),
                format!(
                    "`{OTHER_ROLE}` is the role label of certificates whose role is not in the \
                     table; give the role another name"
                ),
            );
        }
    }
    if tls.handshake_timeout.is_zero() {
        report.fail("server.tls.handshake_timeout", "must be longer than 0");
    }
}

/// Every serial device, and every device server's port, is one bus's: two buses on one port would
/// fight over it at run time (a device server takes one connection to its port, or mixes two
/// masters' frames on one line).
fn check_devices_once(buses: &[Bus], report: &mut Report) {
    let mut owners: BTreeMap<String, usize> = BTreeMap::new();
    for (i, bus) in buses.iter().enumerate() {
        let (owned, what) = match DeviceName::parse(&bus.device) {
            Ok(DeviceName::Serial(path)) => (path, "a serial port"),
            // rfc2217:// and tcp:// to one host and port are one port of the server.
            Ok(DeviceName::Server(addr)) => (
                format!("{}:{}", addr.host.to_ascii_lowercase(), addr.port),
                "a device server's port",
            ),
            Ok(DeviceName::Sim) | Err(_) => continue,
        };
        if let Some(&first) = owners.get(&owned) {
            report.fail(
                format!("bus[{i}].device"),
                format!(
                    "`{}` is already bus[{first}].device: two buses cannot share {what}",
                    bus.device
                ),
            );
        } else {
            owners.insert(owned, i);
        }
    }
}

/// Every address is listened on once per transport, the metrics endpoint's included: the second
/// listener could not be bound. Port 0 asks the system for a free port each time, so it may repeat.
fn check_listen_once(server: &Server, metrics: SocketAddr, report: &mut Report) {
    let keyed = |key: &str, addrs: &[SocketAddr]| -> Vec<(String, SocketAddr)> {
        let key = |k| format!("server.{key}[{k}]");
        addrs
            .iter()
            .enumerate()
            .map(|(k, a)| (key(k), *a))
            .collect()
    };
    let mut tcp = keyed("listen", &server.listen);
    tcp.extend(keyed("listen_rtu_over_tcp", &server.listen_rtu_over_tcp));
    tcp.extend(keyed("listen_tls", &server.listen_tls));
    tcp.push(("metrics.listen".to_owned(), metrics));
    for transport in [tcp, keyed("listen_udp", &server.listen_udp)] {
        let mut first: BTreeMap<SocketAddr, String> = BTreeMap::new();
        for (here, addr) in transport.into_iter().filter(|(_, a)| a.port() != 0) {
            match first.get(&addr) {
                Some(there) => report.fail(&here, format!("{addr} is already {there}")),
                None => {
                    first.insert(addr, here);
                }
            }
        }
    }
}

fn check_log_level(level: &str, report: &mut Report) {
    if let Err(e) = tracing_subscriber::EnvFilter::try_new(level) {
        report.fail("log.level", format!("`{level}` is not a log filter: {e}"));
    }
}

/// `bus[i]`; a valid name goes into `names`, which the routes refer to.
fn check_bus(
    i: usize,
    bus: &Bus,
    names: &mut BTreeMap<String, usize>,
    drives: Option<&dyn DriveCheck>,
    report: &mut Report,
) {
    let key = |field: &str| format!("bus[{i}].{field}");
    if bus.name.is_empty()
        || !bus
            .name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"_-.".contains(&b))
    {
        report.fail(
            key("name"),
            format!("`{}` must be letters, digits, `_`, `-` or `.`", bus.name),
        );
    } else if let Some(first) = names.insert(bus.name.clone(), i) {
        report.fail(
            key("name"),
            format!("`{}` is already the name of bus[{first}]", bus.name),
        );
    }
    check_device(bus, &key, report);
    check_line(bus, &key, report);
    check_serial_driver(bus, &key, report);
    super::listen::check(bus, &key, &mut report.0);
    check_slaves(i, bus, report);
    if !bus.sim_slave.is_empty() && !bus.is_sim() {
        report.fail(
            key("sim_slave"),
            format!("only a bus with device = \"{SIM_DEVICE}\" has simulated slaves"),
        );
    }
    let mut seen = UnitSet::default();
    let format = bus.format();
    for (j, sim) in bus.sim_slave.iter().enumerate() {
        let key = |field: &str| format!("bus[{i}].sim_slave[{j}].{field}");
        check_sim_addresses(sim, &mut seen, &key, report);
        check_fault_knobs(sim, &key, report);
        check_drive(sim, format, drives, &key, report);
    }
}

/// The line's format, timing, retries and queue.
fn check_line(bus: &Bus, key: &dyn Fn(&str) -> String, report: &mut Report) {
    if bus.baud == 0 {
        report.fail(key("baud"), "must be more than 0");
    }
    match bus.data_bits {
        Some(n) if !matches!(n, 7 | 8) => {
            report.fail(key("data_bits"), format!("{n} is not 7 or 8"))
        }
        Some(7) if bus.framing == Framing::Rtu => report.fail(
            key("data_bits"),
            "RTU frames carry 8-bit bytes: 7 data bits need framing = \"ascii\"",
        ),
        _ => {}
    }
    if let Some(n) = bus.stop_bits.filter(|n| !matches!(n, 1 | 2)) {
        report.fail(key("stop_bits"), format!("{n} is not 1 or 2"));
    }
    for (field, value) in [
        ("response_timeout", bus.response_timeout),
        ("queue_timeout", bus.queue_timeout),
        ("reopen_delay", bus.reopen_delay),
        ("slave_probe_interval", bus.slave_probe_interval),
    ] {
        if value.is_zero() {
            report.fail(key(field), "must be longer than 0");
        }
    }
    if bus.reopen_delay_max < bus.reopen_delay {
        report.fail(
            key("reopen_delay_max"),
            "must not be shorter than reopen_delay",
        );
    }
    if bus.retries > MAX_RETRIES {
        report.fail(
            key("retries"),
            format!("{} is more than {MAX_RETRIES}", bus.retries),
        );
    }
    if bus.queue_depth == 0 {
        report.fail(key("queue_depth"), "must be at least 1");
    }
}

/// `device`: a name the gateway can open, carrying the bus's framing (the framing table), and
/// `packing_delay` only where a device server's packing timer can delay replies.
fn check_device(bus: &Bus, key: &dyn Fn(&str) -> String, report: &mut Report) {
    let kind = match DeviceName::parse(&bus.device) {
        Ok(name) => name.kind(),
        Err(why) => return report.fail(key("device"), why),
    };
    if !bus.framing.runs_over(kind) {
        report.fail(
            key("framing"),
            format!("\"{}\" cannot run over {}", bus.framing.name(), kind.name()),
        );
    }
    if !bus.packing_delay.is_zero() && (!kind.is_network() || bus.framing == Framing::Tcp) {
        report.fail(
            key("packing_delay"),
            "only a line behind a serial device server (tcp:// or rfc2217://) has a packing timer",
        );
    }
    match (kind == TransportKind::Tls, &bus.tls) {
        (true, None) => report.fail(
            key("tls"),
            "a tls:// device needs [bus.tls] with certificate, private_key and ca",
        ),
        (false, Some(_)) => report.fail(key("tls"), "only a tls:// device takes [bus.tls]"),
        _ => {}
    }
    if !bus.connect_delay.is_zero() && !kind.is_network() {
        report.fail(
            key("connect_delay"),
            "only a line on the network (tcp:// or rfc2217://) is connected to",
        );
    }
    if bus.max_in_flight != 1 && bus.framing != Framing::Tcp {
        report.fail(
            key("max_in_flight"),
            "only a Modbus TCP device (framing = \"tcp\") pipelines: a serial line has one \
             request at a time",
        );
    } else if !(1..=defaults::MAX_IN_FLIGHT).contains(&bus.max_in_flight) {
        report.fail(
            key("max_in_flight"),
            format!(
                "{} is not 1 to {}",
                bus.max_in_flight,
                defaults::MAX_IN_FLIGHT
            ),
        );
    } else if bus.max_in_flight > 1 && !bus.match_transaction_id {
        report.fail(
            key("max_in_flight"),
            "pipelined replies are told apart by transaction id: not with match_transaction_id = false",
        );
    }
    if !bus.match_transaction_id && bus.framing != Framing::Tcp {
        report.fail(
            key("match_transaction_id"),
            "only a Modbus TCP device (framing = \"tcp\") has transaction ids",
        );
    }
    if bus.framing == Framing::Tcp && bus.rs485.echo {
        report.fail(
            key("rs485.echo"),
            "a Modbus TCP device has no line of the gateway's to echo",
        );
    }
}

/// `[bus.rs485]` and `latency_timer`: what the gateway asks of the serial driver.
fn check_serial_driver(bus: &Bus, key: &dyn Fn(&str) -> String, report: &mut Report) {
    let kind = bus.transport();
    for (field, reason) in bus.rs485.problems(kind) {
        report.fail(key(&format!("rs485.{field}")), reason);
    }
    if let Some(timer) = bus.latency_timer {
        if kind != TransportKind::Serial {
            let why = match kind {
                TransportKind::Sim => "a simulated line has no USB adapter",
                _ => "a line behind a serial device server has no USB adapter of the gateway's",
            };
            report.fail(key("latency_timer"), why);
        } else if !LATENCY_TIMER_MS.contains(&timer.as_millis())
            || timer.subsec_nanos() % 1_000_000 != 0
        {
            report.fail(
                key("latency_timer"),
                "must be whole milliseconds, 1ms to 255ms",
            );
        }
    }
}

/// `bus[i]`'s plant values: each slave's own and its template's, and the share of the line
/// their polls may take.
fn check_values(i: usize, bus: &Bus, templates: &Templates, report: &mut Report) {
    for (j, slave) in bus.slave.iter().enumerate() {
        values::check_slave(
            &format!("bus[{i}].slave[{j}]"),
            slave,
            templates,
            &mut report.0,
        );
    }
    if !(bus.poll_share > 0.0 && bus.poll_share <= 1.0) {
        report.fail(
            format!("bus[{i}].poll_share"),
            format!(
                "{} must be more than 0 and at most 1 (a share of the line's time)",
                bus.poll_share
            ),
        );
    }
}

/// `bus[i].slave`: addresses on the line, each once, and their overrides.
fn check_slaves(i: usize, bus: &Bus, report: &mut Report) {
    let mut seen = UnitSet::default();
    for (j, slave) in bus.slave.iter().enumerate() {
        let key = format!("bus[{i}].slave[{j}]");
        let serial = bus.framing.broadcasts();
        if serial && (slave.address == 0 || slave.address > MAX_SLAVE_ADDRESS) {
            report.fail(
                format!("{key}.address"),
                format!("{} is not a slave address 1-247", slave.address),
            );
        } else if seen.contains(slave.address) {
            report.fail(
                format!("{key}.address"),
                format!("slave {} is configured twice", slave.address),
            );
        }
        seen.insert(slave.address);
        if slave.response_timeout.is_some_and(|t| t.is_zero()) {
            report.fail(format!("{key}.response_timeout"), "must be longer than 0");
        }
    }
}

/// A simulated slave's addresses: on the line, and none simulated twice (`seen` holds those of
/// the slaves before it).
fn check_sim_addresses(
    sim: &SimSlave,
    seen: &mut UnitSet,
    key: &dyn Fn(&str) -> String,
    report: &mut Report,
) {
    if sim.address.is_empty() {
        report.fail(key("address"), "names no address");
    }
    for address in sim.address.iter() {
        if address == 0 || address > MAX_SLAVE_ADDRESS {
            report.fail(
                key("address"),
                format!("{address} is not a slave address 1-247"),
            );
            break;
        }
        if seen.contains(address) {
            report.fail(
                key("address"),
                format!("slave {address} is simulated twice"),
            );
            break;
        }
        seen.insert(address);
    }
}

fn check_fault_knobs(sim: &SimSlave, key: &dyn Fn(&str) -> String, report: &mut Report) {
    if !(0.0..=1.0).contains(&sim.crc_error_rate) {
        report.fail(key("crc_error_rate"), "must be from 0 to 1");
    }
    for (field, bytes) in [
        ("garbage_before", sim.garbage_before),
        ("garbage_after", sim.garbage_after),
    ] {
        if bytes > MAX_GARBAGE {
            report.fail(
                key(field),
                format!("{bytes} is more than {MAX_GARBAGE} bytes"),
            );
        }
    }
    if sim
        .reply_function
        .is_some_and(|f| f == 0 || f & EXCEPTION_BIT != 0)
    {
        report.fail(key("reply_function"), "must be a function code 1-127");
    }
    if sim.truncate_reply == Some(0) {
        report.fail(
            key("truncate_reply"),
            "must be at least 1 byte (a slave that sends nothing is `offline`)",
        );
    }
    match (sim.reply_gap, sim.reply_gap_after) {
        (Some(_), None) => report.fail(key("reply_gap_after"), "is required with reply_gap"),
        (None, Some(_)) => report.fail(key("reply_gap"), "is required with reply_gap_after"),
        (_, Some(0)) => report.fail(key("reply_gap_after"), "must be at least 1 byte"),
        _ => {}
    }
}

/// Parameters and a trip only on a drive model; a drive's own parameter check through `drives`.
fn check_drive(
    sim: &SimSlave,
    format: SerialFormat,
    drives: Option<&dyn DriveCheck>,
    key: &dyn Fn(&str) -> String,
    report: &mut Report,
) {
    if !sim.model.is_drive() {
        for (field, set) in [
            ("params", !sim.params.is_empty()),
            ("trip", sim.trip.is_some()),
        ] {
            if set {
                report.fail(key(field), "only drive models have parameters and faults");
            }
        }
        return;
    }
    // The drive checks its own parameters; one power-on tells for every address.
    let (Some(drives), Some(address)) = (drives, sim.address.iter().next()) else {
        return;
    };
    if let Err(e) = drives.power_on(sim, address, format) {
        let field = if e.param == "trip" {
            e.param
        } else {
            format!("params.\"{}\"", e.param)
        };
        report.fail(key(&field), e.reason);
    }
}

/// `route`: every route to a bus by a valid name (`names`, indexes into `buses`), each unit
/// routed once and to an address on the line (0-247 on a serial line, 0-255 on a Modbus TCP
/// device).
fn check_routes(
    routes: &[Route],
    buses: &[Bus],
    names: &BTreeMap<String, usize>,
    report: &mut Report,
) {
    let mut routed: BTreeMap<u8, usize> = BTreeMap::new();
    for (i, route) in routes.iter().enumerate() {
        let key = |field: &str| format!("route[{i}].{field}");
        let highest = names
            .get(&route.bus)
            .map_or(MAX_SLAVE_ADDRESS, |&at| buses[at].framing.highest_address());
        if !names.contains_key(&route.bus) {
            let known: Vec<String> = names.keys().map(|n| format!("`{n}`")).collect();
            let known = match known.len() {
                0 => "no bus has a valid name".to_owned(),
                _ => format!("the buses are {}", known.join(", ")),
            };
            report.fail(
                key("bus"),
                format!("there is no bus named `{}`: {known}", route.bus),
            );
        }
        if route.address.is_some() && route.offset.is_some() {
            report.fail(key("offset"), "give `address` or `offset`, not both");
        }
        if route.address.is_some_and(|a| a > highest) {
            report.fail(
                key("address"),
                format!("must be a slave address 0-{highest}"),
            );
        }
        if route.units.is_empty() {
            report.fail(key("units"), "names no unit");
        }
        for unit in route.units.iter() {
            if let Some(first) = routed.insert(unit, i) {
                report.fail(
                    key("units"),
                    format!("unit {unit} is already routed by route[{first}]"),
                );
                break;
            }
            if route.target(unit, highest).is_none() {
                report.fail(
                    key("offset"),
                    format!("sends unit {unit} outside slave addresses 0-{highest}"),
                );
                break;
            }
        }
    }
}

/// Rules name buses that exist, roles only where masters have certificates, and unique names.
fn check_rules(
    rules: &[Rule],
    server: &Server,
    buses: &BTreeMap<String, usize>,
    report: &mut Report,
) {
    let mut named: BTreeMap<&str, usize> = BTreeMap::new();
    for (i, rule) in rules.iter().enumerate() {
        let key = |field: &str| format!("rule[{i}].{field}");
        if let Some(name) = &rule.name {
            if name.trim().is_empty() {
                report.fail(key("name"), "is empty: leave it out to be called `rule N`");
            } else if let Some(first) = named.insert(name, i) {
                report.fail(
                    key("name"),
                    format!("`{name}` is already rule[{first}].name: the journal could not tell them apart"),
                );
            }
        }
        for bus in &rule.buses {
            if !buses.contains_key(bus) {
                report.fail(key("buses"), format!("there is no bus named `{bus}`"));
            }
        }
        if !rule.roles.is_empty() && server.tls.is_none() {
            report.fail(
                key("roles"),
                "no master has a role without [server.tls]: roles come from TLS masters' \
                 certificates",
            );
        }
        if rule.units.is_some_and(|units| units.is_empty()) {
            report.fail(key("units"), "names no unit: leave it out for any unit");
        }
    }
}

fn check_audit(audit: &Audit, report: &mut Report) {
    if audit.path.as_os_str().is_empty() {
        report.fail("audit.path", "is empty: name the journal's file");
    }
    if audit.max_size.0 < MIN_AUDIT_SIZE {
        report.fail(
            "audit.max_size",
            format!("{} is below the smallest journal, 4KiB", audit.max_size),
        );
    }
    if !(1..=MAX_AUDIT_KEEP).contains(&audit.keep) {
        report.fail(
            "audit.keep",
            format!(
                "{} rotated files: keep 1 to {MAX_AUDIT_KEEP} (the journal is never thrown away whole)",
                audit.keep
            ),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::testing::{errors, MINIMAL};

    const SIM_BUS: &str =
        "[[bus]]\nname = \"sim\"\ndevice = \"sim\"\n[[bus.sim_slave]]\naddress = 2\n";

    #[test]
    fn bad_server_access_and_connection_keys_are_named() {
        for (keys, key, reason) in [
            ("allow = [\"10.0.0.0/33\"]", "server.allow", "10.0.0.0/33"),
            ("read_only = \"plc.local\"", "server.read_only", "plc.local"),
            ("when_full = \"drop\"", "server.when_full", "drop"),
            (
                "frame_timeout = \"0s\"",
                "server.frame_timeout",
                "longer than 0",
            ),
            ("keepalive = \"500ms\"", "server.keepalive", "at least 1s"),
            (
                "max_connections_per_address = -1",
                "server.max_connections_per_address",
                "-1",
            ),
        ] {
            let e = errors(&format!("[server]\n{keys}\n{MINIMAL}"));
            assert_eq!(e.len(), 1, "{e:?}");
            assert!(e[0].starts_with(key), "{keys}: {e:?}");
            assert!(e[0].contains(reason), "{keys}: {e:?}");
        }
        let c = Config::from_toml_str(&format!("[server]\nkeepalive = \"0s\"\n{MINIMAL}"));
        assert!(c.is_ok(), "0s turns keepalive off");
    }

    /// A line behind a device server takes its framing and packing delay.
    #[test]
    fn a_device_server_line_takes_framing_and_packing_delay_but_no_local_driver() {
        let ok = Config::from_toml_str(
            "[[bus]]\nname = \"a\"\ndevice = \"tcp://nport:4001\"\nframing = \"ascii\"\n\
             packing_delay = \"40ms\"\n[bus.rs485]\necho = true\n\
             [[bus]]\nname = \"b\"\ndevice = \"rfc2217://[::1]:2217\"\n",
        )
        .expect("both lines are good");
        assert_eq!(ok.bus[0].packing_delay, Duration::from_millis(40));
        for (keys, key, reason) in [
            (
                "device = \"ser2net://box:2000\"",
                "bus[0].device",
                "`ser2net://` is not a kind of device",
            ),
            (
                "device = \"tcp://box\"",
                "bus[0].device",
                "`tcp://box`: needs HOST:PORT",
            ),
            (
                "device = \"/dev/ttyS0\"\npacking_delay = \"10ms\"",
                "bus[0].packing_delay",
                "only a line behind a serial device server",
            ),
            (
                "device = \"tcp://box:4001\"\nlatency_timer = \"1ms\"",
                "bus[0].latency_timer",
                "no USB adapter",
            ),
            (
                "device = \"tcp://box:4001\"\n[bus.rs485]\nmode = \"rts\"",
                "bus[0].rs485.mode",
                "the device server's to drive",
            ),
        ] {
            let e = errors(&format!("[[bus]]\nname = \"a\"\n{keys}\n"));
            assert_eq!(e.len(), 1, "{keys}: {e:?}");
            assert!(e[0].starts_with(key), "{keys}: {e:?}");
            assert!(e[0].contains(reason), "{keys}: {e:?}");
        }
    }

    #[test]
    fn a_modbus_tcp_device_takes_units_0_to_255_and_no_serial_line_key() {
        let ok = Config::from_toml_str(
            "[[bus]]\nname = \"inverter\"\ndevice = \"tcp://10.0.0.9:502\"\nframing = \"tcp\"\n\
             connect_delay = \"2s\"\n[[bus.slave]]\naddress = 0\n[[bus.slave]]\naddress = 255\n\
             [[route]]\nunits = \"1\"\nbus = \"inverter\"\naddress = 255\n",
        );
        assert!(ok.is_ok(), "{ok:?}");
        for (keys, key, reason) in [
            (
                "device = \"/dev/ttyS0\"\nframing = \"tcp\"",
                "bus[0].framing",
                "\"tcp\" cannot run over a serial port",
            ),
            (
                "device = \"rfc2217://box:2217\"\nframing = \"tcp\"",
                "bus[0].framing",
                "cannot run over a serial device server's RFC 2217 socket",
            ),
            (
                "device = \"tcp://box:502\"\nframing = \"tcp\"\npacking_delay = \"10ms\"",
                "bus[0].packing_delay",
                "only a line behind a serial device server",
            ),
            (
                "device = \"/dev/ttyS0\"\nconnect_delay = \"1s\"",
                "bus[0].connect_delay",
                "only a line on the network",
            ),
            (
                "device = \"tcp://box:4001\"\nmax_in_flight = 2",
                "bus[0].max_in_flight",
                "a serial line has one request at a time",
            ),
            (
                "device = \"tcp://box:502\"\nframing = \"tcp\"\nmax_in_flight = 17",
                "bus[0].max_in_flight",
                "17 is not 1 to 16",
            ),
            (
                "device = \"tcp://box:4001\"\nmatch_transaction_id = false",
                "bus[0].match_transaction_id",
                "only a Modbus TCP device",
            ),
            (
                "device = \"tcp://box:502\"\nframing = \"tcp\"\n[bus.rs485]\necho = true",
                "bus[0].rs485.echo",
                "no line of the gateway's to echo",
            ),
        ] {
            let e = errors(&format!("[[bus]]\nname = \"a\"\n{keys}\n"));
            assert_eq!(e.len(), 1, "{keys}: {e:?}");
            assert!(e[0].starts_with(key), "{keys}: {e:?}");
            assert!(e[0].contains(reason), "{keys}: {e:?}");
        }
    }

    #[test]
    fn two_buses_on_one_device_server_port_are_refused_whichever_scheme_names_it() {
        let e = errors(
            "[[bus]]\nname = \"a\"\ndevice = \"tcp://NPort:4001\"\n\
             [[bus]]\nname = \"b\"\ndevice = \"tcp://nport:4002\"\n\
             [[bus]]\nname = \"c\"\ndevice = \"rfc2217://nport:4001\"\n",
        );
        assert_eq!(
            e,
            [
                "bus[2].device: `rfc2217://nport:4001` is already bus[0].device: two buses cannot \
              share a device server's port"
            ]
        );
    }

    #[test]
    fn two_buses_on_one_serial_device_are_refused_naming_both() {
        let e = errors(
            "[[bus]]\nname = \"a\"\ndevice = \"/dev/ttyUSB0\"\n\
             [[bus]]\nname = \"b\"\ndevice = \"sim\"\n\
             [[bus]]\nname = \"c\"\ndevice = \"sim\"\n\
             [[bus]]\nname = \"d\"\ndevice = \"/dev/ttyUSB0\"\n",
        );
        assert_eq!(
            e,
            [
                "bus[3].device: `/dev/ttyUSB0` is already bus[0].device: two buses cannot share a \
              serial port"
            ]
        );
    }

    /// UDP may share an address with TCP.
    #[test]
    fn a_tcp_address_listened_on_twice_is_refused_naming_both_keys() {
        let e = errors(&format!(
            "[server]\nlisten = [\"0.0.0.0:502\", \"127.0.0.1:5020\"]\n\
             listen_rtu_over_tcp = \"127.0.0.1:5020\"\nlisten_udp = [\"0.0.0.0:502\", \
             \"0.0.0.0:502\"]\n{MINIMAL}"
        ));
        assert_eq!(
            e,
            [
                "server.listen_rtu_over_tcp[0]: 127.0.0.1:5020 is already server.listen[1]",
                "server.listen_udp[1]: 0.0.0.0:502 is already server.listen_udp[0]",
            ]
        );
    }

    #[test]
    fn a_metrics_listen_address_a_server_listens_on_is_refused_naming_both_keys() {
        let e = errors(&format!(
            "[server]\nlisten = [\"0.0.0.0:502\", \"127.0.0.1:5020\"]\n\
             [metrics]\nlisten = \"127.0.0.1:5020\"\n{MINIMAL}"
        ));
        assert_eq!(
            e,
            ["metrics.listen: 127.0.0.1:5020 is already server.listen[1]"]
        );
    }

    #[test]
    fn a_route_to_a_missing_bus_lists_the_buses_that_exist() {
        let e = errors(
            "[[bus]]\nname = \"east\"\ndevice = \"sim\"\n\
             [[bus]]\nname = \"west\"\ndevice = \"sim2\"\n\
             [[route]]\nunits = \"1\"\nbus = \"north\"\n",
        );
        assert_eq!(
            e,
            ["route[0].bus: there is no bus named `north`: the buses are `east`, `west`"]
        );
    }

    #[test]
    fn a_zero_slave_probe_interval_is_refused() {
        let e = errors(&format!("{MINIMAL}\nslave_probe_interval = \"0s\""));
        assert!(e[0].starts_with("bus[0].slave_probe_interval"), "{e:?}");
    }

    #[test]
    fn semantic_errors_are_all_reported_with_their_keys() {
        let e = errors(
            r#"
            [[bus]]
            name = "a"
            device = "sim"
            data_bits = 6
            stop_bits = 3
            [[bus.slave]]
            address = 248
            [[bus]]
            name = "a"
            device = ""
            [[route]]
            units = "1-3"
            bus = "nope"
            "#,
        );
        let keys: Vec<&str> = e.iter().map(|s| s.split(':').next().unwrap()).collect();
        assert_eq!(
            keys,
            [
                "bus[0].data_bits",
                "bus[0].stop_bits",
                "bus[0].slave[0].address",
                "bus[1].name",
                "bus[1].device",
                "route[0].bus"
            ],
            "{e:#?}"
        );
    }

    #[test]
    fn a_config_without_buses_is_refused() {
        assert_eq!(errors("")[0], "bus: at least one [[bus]] is needed");
    }

    #[test]
    fn routes_may_not_overlap_or_leave_the_address_range() {
        let e = errors(&format!(
            "{MINIMAL}\n[[route]]\nunits = \"1-10\"\nbus = \"line1\"\noffset = 240\n\
             [[route]]\nunits = [5, 6]\nbus = \"line1\"\naddress = 3\n"
        ));
        assert_eq!(e.len(), 2, "{e:?}");
        assert!(e[0].starts_with("route[0].offset: sends unit 8"), "{e:?}");
        assert!(
            e[1].starts_with("route[1].units: unit 5 is already routed by route[0]"),
            "{e:?}"
        );
    }

    #[test]
    fn sim_slaves_only_live_on_a_sim_bus() {
        let e = errors(&format!(
            "{MINIMAL}\n[[bus.sim_slave]]\naddress = \"1-4\"\n"
        ));
        assert!(e[0].starts_with("bus[0].sim_slave:"), "{e:?}");
    }

    #[test]
    fn bad_fault_knobs_are_refused_by_key() {
        for (knobs, key, reason) in [
            (
                "reply_function = 0",
                "reply_function",
                "must be a function code 1-127",
            ),
            (
                "reply_function = 131",
                "reply_function",
                "must be a function code 1-127",
            ),
            (
                "truncate_reply = 0",
                "truncate_reply",
                "must be at least 1 byte",
            ),
            (
                "reply_gap = \"30ms\"",
                "reply_gap_after",
                "is required with reply_gap",
            ),
            (
                "reply_gap_after = 3",
                "reply_gap",
                "is required with reply_gap_after",
            ),
            (
                "reply_gap = \"30ms\"\nreply_gap_after = 0",
                "reply_gap_after",
                "must be at least 1 byte",
            ),
        ] {
            let e = errors(&format!("{SIM_BUS}{knobs}\n"));
            let expected = format!("bus[0].sim_slave[0].{key}: {reason}");
            assert!(
                e.len() == 1 && e[0].starts_with(&expected),
                "{knobs}: {e:?}"
            );
        }
    }
}
