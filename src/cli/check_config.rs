//! `check-config`: the resolved configuration, preceded by what it means on each line (timing
//! worked out from the baud and format). Knows nothing of serving.

use crate::bus::device::net::{MAX_LINK_BUDGET, MIN_LINK_BUDGET};
use crate::config::UnitSet;
use crate::config::{Action, Bus, Config, DeviceName, Rs485Mode, Rule, ServerAddr, ServerMode};
use crate::line::{Framing, BROADCAST};
use crate::net::tls::TlsServer;
use crate::routing::Router;
use crate::rules::Reach;
use std::path::Path;
use std::process::ExitCode;
use std::time::{Duration, SystemTime};

/// Print the description of the valid configuration `config` read from `path`, unless `quiet`;
/// warn on standard error of a TLS server certificate that expires within 30 days.
pub fn check_config(path: &Path, config: &Config, quiet: bool) -> ExitCode {
    let tls = match config.server.tls.as_ref().map(TlsServer::load).transpose() {
        Ok(tls) => tls,
        // The files changed since they were checked a moment ago.
        Err(errors) => {
            for e in &errors.0 {
                eprintln!("modbus-gateway: {}: {e}", path.display());
            }
            return ExitCode::from(super::EXIT_CONFIG);
        }
    };
    let now = SystemTime::now();
    if let Some(warning) = tls.as_ref().and_then(|t| t.certificate.expiry_warning(now)) {
        eprintln!(
            "modbus-gateway: {}: warning: server.tls.certificate: {warning}",
            path.display()
        );
    }
    if !quiet {
        match super::print_out(&describe(path, config, tls.as_ref(), now)) {
            Err(e) if !super::reader_gone(&e) => {
                eprintln!("modbus-gateway: cannot write to stdout: {e}");
                return ExitCode::FAILURE;
            }
            _ => {}
        }
    }
    ExitCode::SUCCESS
}

/// What the TLS listeners will serve: the certificate, its expiry, the CA, the roles.
fn describe_tls(config: &Config, tls: &TlsServer, now: SystemTime) -> String {
    let certificate = &tls.certificate;
    let expires = humantime::format_rfc3339_seconds(certificate.expires);
    let expiry = certificate.expiry(now);
    let mut roles: Vec<String> = Vec::new();
    if let Some(settings) = &config.server.tls {
        roles.extend(settings.roles.iter().map(|(name, role)| match role.units {
            None => format!("{name} {}", role.access.name()),
            Some(units) => format!("{name} {} on units {units}", role.access.name()),
        }));
        roles.push(format!(
            "any other certificate {}",
            settings.default_role_access.name()
        ));
    }
    format!(
        "# TLS: server certificate {}, expires {expires} ({expiry}); client certificates \
         must chain to {} CA certificate(s); roles: {}.\n",
        certificate.subject,
        certificate.client_cas,
        roles.join(", ")
    )
}

fn ms(d: std::time::Duration) -> String {
    format!("{:.3} ms", d.as_secs_f64() * 1e3)
}

/// Who drives the bus's RS-485 transceiver, whether the line echoes, and the latency timer.
fn describe_driver(bus: &Bus) -> String {
    let rs485 = &bus.rs485;
    let mode = match rs485.mode {
        Rs485Mode::Off => "off (the adapter switches the transceiver)".to_owned(),
        Rs485Mode::Kernel => "kernel (TIOCSRS485)".to_owned(),
        Rs485Mode::Rts => format!(
            "rts (the gateway raises RTS for each frame, drops it {} after the last character)",
            ms(rs485.delay_after_send)
        ),
    };
    let echo = if rs485.echo {
        "; each frame is read back (echo)"
    } else {
        ""
    };
    let latency = bus.latency_timer.map_or_else(
        || "left as it is".to_owned(),
        |timer| format!("set to {}", ms(timer)),
    );
    format!(
        "# bus {}: rs485.mode {mode}{echo}; a USB adapter's latency timer is {latency}.\n",
        bus.name
    )
}

/// What a line behind a device server adds to its timing (docs/device-servers.md). Not measured
/// here: connecting to check would take the converter's one connection from a running gateway.
fn describe_link(name: &str, addr: &ServerAddr, packing: Duration) -> String {
    let how = match addr.mode {
        ServerMode::Raw => "raw TCP",
        ServerMode::Rfc2217 => "RFC 2217, which sets the format above on the far port at connect",
        ServerMode::Tls => "Modbus/TCP Security",
    };
    let packing = if packing.is_zero() {
        String::new()
    } else {
        format!(
            " plus packing_delay {} (also silence a reply may hold mid-way)",
            ms(packing)
        )
    };
    format!(
        "# bus {name}: behind the device server at {addr} ({how}), connected at start; a reply's \
         deadline counts from the frame's time on the wire plus the link budget (twice the least \
         round trip the kernel measures on the connection, {} to {}; live on the status page and \
         as modbus_gateway_link_budget_seconds){packing}.\n",
        ms(MIN_LINK_BUDGET),
        ms(MAX_LINK_BUDGET),
    )
}

/// The resolved configuration, preceded by what it means on each line and for TLS masters.
fn describe(path: &Path, config: &Config, tls: Option<&TlsServer>, now: SystemTime) -> String {
    let mut out = format!("# {} is valid.\n", path.display());
    for bus in &config.bus {
        let format = bus.format();
        let master = bus.master_timing();
        let line = master.line;
        if bus.mode == crate::config::BusMode::Listen {
            out += &format!(
                "# bus {}: listen-only at {format} ({}): the gateway never transmits on it; a \
                 frame ends by its length or {} of silence, a reply is paired with the request \
                 before it within {}; masters' reads are answered from what was heard in the \
                 last {} (else 0x0B), anything else 0x01; its values are never polled.\n",
                bus.name,
                bus.framing.name(),
                ms(master.silence),
                humantime::format_duration(bus.response_timeout),
                humantime::format_duration(bus.max_age),
            );
            match bus.device_name() {
                DeviceName::Server(addr) => {
                    out += &describe_link(&bus.name, &addr, master.packing);
                }
                DeviceName::Serial(_) => out += &describe_driver(bus),
                DeviceName::Sim => {}
            }
            continue;
        }
        out += &match bus.framing {
            Framing::Rtu => format!(
                "# bus {}: {format}, character {}, t3.5 {}; frames start {} after the line \
                 falls silent; replies of unknown length end after {} of silence.\n",
                bus.name,
                ms(line.char_time),
                ms(line.t35),
                ms(master.gap),
                ms(master.silence),
            ),
            Framing::Ascii => format!(
                "# bus {}: Modbus ASCII at {format}, character {}; frames start {} after the \
                 line falls silent; a reply that stops for {} before its CR LF is dropped.\n",
                bus.name,
                ms(line.char_time),
                ms(master.gap),
                ms(master.silence),
            ),
            Framing::Tcp => format!(
                "# bus {}: a Modbus TCP device at {}, connected at start; one request at a time, \
                 each {} after the last reply, its reply matched by transaction id; unit 0 is a \
                 unit, not a broadcast.\n",
                bus.name,
                bus.device,
                ms(master.gap),
            ),
        };
        match bus.device_name() {
            DeviceName::Sim => {}
            DeviceName::Serial(_) => out += &describe_driver(bus),
            DeviceName::Server(_) if bus.framing == Framing::Tcp => {}
            DeviceName::Server(addr) => out += &describe_link(&bus.name, &addr, master.packing),
        }
    }
    out += &describe_ports(config);
    out += &describe_virtual_units(config);
    out += &describe_mqtt(config);
    if let Some(tls) = tls {
        out += &describe_tls(config, tls, now);
    }
    out += &describe_writes(config);
    out + "\n" + &config.to_toml()
}

/// What each serial master port answers, and when (docs/serial-ports.md).
fn describe_ports(config: &Config) -> String {
    let mut out = String::new();
    for port in &config.server.serial {
        let format = port.format();
        let line = crate::line::LineTiming::new(&format);
        let when = match port.framing {
            Framing::Ascii => "at the request's LF".to_owned(),
            Framing::Rtu | Framing::Tcp => format!("t3.5 ({}) after the request", ms(line.t35)),
        };
        let mut rights = String::new();
        if port.read_only {
            rights += ", read only";
        }
        if port.priority {
            rights += ", served before the other masters";
        }
        out += &format!(
            "# serial port {}: the gateway is the slave of units {} on {} at {format} ({}); it \
             answers no sooner than {when} and never later than {} after it; unit 0 is a \
             broadcast, forwarded and never answered; its master is serial:{} (protocol \
             serial{rights}).\n",
            port.name,
            port.units,
            port.device,
            port.framing.name().to_ascii_uppercase(),
            ms(port.answer_within),
            port.name,
        );
    }
    out
}

/// What `[mqtt]` publishes, and which values a `set` writes (docs/mqtt.md).
fn describe_mqtt(config: &Config) -> String {
    let Some(mqtt) = &config.mqtt else {
        return String::new();
    };
    let mut values = 0;
    let mut slaves = 0;
    let mut writable = Vec::new();
    for bus in &config.bus {
        for slave in &bus.slave {
            let listed = config
                .values_of(&bus.name, slave.address)
                .unwrap_or_default();
            slaves += usize::from(!listed.is_empty());
            values += listed.len();
            for (value, _) in listed.iter().filter(|(v, _)| v.writable) {
                writable.push(format!("{}/{}/{}", bus.name, slave.address, value.name));
            }
        }
    }
    let retained = if mqtt.retain {
        "retained"
    } else {
        "not retained"
    };
    let mut out = format!(
        "# mqtt: {values} values of {slaves} slaves published to {} at {}/BUS/SLAVE/NAME \
         ({retained}, QoS {}) when they change, and again every {} unchanged",
        mqtt.url,
        mqtt.topic_prefix,
        mqtt.qos(),
        humantime::format_duration(mqtt.publish_interval),
    );
    if mqtt.home_assistant {
        out += &format!("; Home Assistant discovery under {}", mqtt.discovery_prefix);
    }
    out += ".\n";
    match (mqtt.writes, writable.is_empty()) {
        (false, _) => out += "# mqtt: writes = false: no set topic is subscribed to.\n",
        (true, true) => {
            out += "# mqtt: writes = true, but no value is writable: no set is ever carried out.\n"
        }
        (true, false) => {
            out += "# mqtt: a set writes (master mqtt, protocol mqtt, under the rules):\n";
            for value in writable {
                out += &format!("#   {}/{value}/set\n", mqtt.topic_prefix);
            }
        }
    }
    out
}

/// Each virtual unit's layout: every register, how it holds its value, where the value comes
/// from and how old it may be (docs/virtual-units.md).
fn describe_virtual_units(config: &Config) -> String {
    let mut out = String::new();
    for (at, unit) in config.virtual_units.iter().enumerate() {
        let (slots, _) = config.virtual_layout(at);
        out += &format!(
            "# virtual unit {} ({}): answered from memory, never from a line; a read touching a \
             register not laid out is 0x02, one whose value is too old, never read or failed \
             0x0B.\n",
            unit.unit, unit.name
        );
        let mut slots: Vec<_> = slots.iter().collect();
        slots.sort_by_key(|s| (s.encoding.table, s.first(), s.encoding.bit));
        for slot in slots {
            let encoding = &slot.encoding;
            let mut held = encoding.kind().name().to_owned();
            if let Some(bit) = encoding.bit {
                held += &format!(" bit {bit}");
            }
            if encoding.width() > 1 && encoding.word_order == crate::config::Order::Little {
                held += " word order little";
            }
            if encoding.byte_order == crate::config::Order::Little {
                held += " byte order little";
            }
            if encoding.scale != 1.0 || encoding.offset != 0.0 {
                held += &format!(" x {} + {}", encoding.scale, encoding.offset);
            }
            let source = match &slot.source {
                Some(found) => format!(
                    "{}, max age {}",
                    found.at,
                    humantime::format_duration(slot.max_age)
                ),
                None => "not in its source: always 0x0B".to_owned(),
            };
            let range = match encoding.width() {
                1 => slot.first().to_string(),
                _ => format!("{}-{}", slot.first(), slot.last()),
            };
            out += &format!(
                "#   {} {range}: {held} <- {source}{}\n",
                encoding.table.name(),
                if slot.writable { ", writable" } else { "" }
            );
        }
    }
    out
}

/// The slaves a rule's `units` hold, whichever unit id a master reaches them by.
fn describe_slaves(
    config: &Config,
    rule: &Rule,
    slaves: &Reach,
    at: usize,
    units: UnitSet,
) -> String {
    let mut held = Vec::new();
    for (bus, addresses) in slaves.by_bus() {
        let bus = &config.bus[bus];
        let broadcasts = bus.framing.broadcasts();
        let mut slaves = addresses;
        if broadcasts {
            slaves.remove(BROADCAST);
        }
        match slaves.iter().count() {
            0 => {}
            1 => held.push(format!("slave {slaves} of {}", bus.name)),
            _ => held.push(format!("slaves {slaves} of {}", bus.name)),
        }
        let by_broadcast = match rule.action {
            Action::Allow => addresses.contains(BROADCAST),
            Action::Deny | Action::Acknowledge => true,
        };
        if broadcasts && by_broadcast {
            held.push(format!("broadcasts on {}", bus.name));
        }
    }
    for unit in slaves.virtual_units().iter() {
        held.push(format!("virtual unit {unit}"));
    }
    let name = rule.display_name(at);
    if held.is_empty() {
        return format!(
            "# {name} (units {units}): no slave, since none of these units has a route; it \
             matches nothing.\n"
        );
    }
    format!(
        "# {name} (units {units}): {}, whatever unit id a master reaches them by.\n",
        held.join(", ")
    )
}

/// How writes are decided and recorded: the rules in their order, the journal.
fn describe_writes(config: &Config) -> String {
    let mut out = String::new();
    if !config.rule.is_empty() {
        let names: Vec<String> = config
            .rule
            .iter()
            .enumerate()
            .map(|(at, rule)| format!("{} ({})", rule.display_name(at), rule.action.label()))
            .collect();
        out += &format!(
            "# rules, first match deciding, after server.read_only and the TLS roles: {}; a \
             request no rule matches goes on.\n",
            names.join(", ")
        );
        let router = Router::new(config);
        for (at, rule) in config.rule.iter().enumerate() {
            if let Some(units) = rule.units {
                out += &describe_slaves(config, rule, &Reach::of(units, &router), at, units);
            }
        }
    }
    out +=
        &match &config.audit {
            None => "# writes are not journaled (no [audit]).\n".to_owned(),
            Some(audit) => {
                format!(
            "# every write is journaled in {} before it is sent{}; rotated at {}, {} older \
             files kept; if an entry cannot be written, {} (not opened here: the running \
             gateway opens it).\n",
            audit.path.display(),
            if audit.fsync { ", synced to the disk" } else { "" },
            audit.max_size,
            audit.keep,
            match audit.on_error {
                crate::config::OnError::DenyWrites => "writes get 0x0A",
                crate::config::OnError::Allow => "writes go on unrecorded",
            }
        )
            }
        };
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_config_says_which_slaves_a_rule_on_units_holds() {
        let config = Config::from_toml_str(
            r#"
            [[bus]]
            name = "line1"
            device = "sim"
            [[bus]]
            name = "inverter"
            device = "tcp://127.0.0.1:502"
            framing = "tcp"
            [[route]]
            units = "1-4,200"
            bus = "line1"
            [[route]]
            units = "101-104"
            bus = "line1"
            offset = -100
            [[route]]
            units = "10"
            bus = "inverter"
            address = 0
            [[rule]]
            name = "drive parameters"
            units = "101-104"
            action = "deny"
            [[rule]]
            name = "setpoints"
            units = "1-2,10"
            action = "allow"
            [[rule]]
            units = "50"
            action = "deny"
            "#,
        )
        .expect("a valid configuration");
        let out = describe_writes(&config);
        let lines: Vec<&str> = out.lines().skip(1).take(3).collect();
        assert_eq!(
            lines,
            [
                "# drive parameters (units 101-104): slaves 1-4 of line1, broadcasts on line1, \
                 whatever unit id a master reaches them by.",
                "# setpoints (units 1-2,10): slaves 1-2 of line1, slave 0 of inverter, whatever \
                 unit id a master reaches them by.",
                "# rule 3 (units 50): no slave, since none of these units has a route; it matches \
                 nothing.",
            ]
        );
    }
}
