//! Properties of the whole loader: no text makes it panic; whatever loads prints back the same;
//! every generated valid configuration loads back; every bad value is refused naming its key.

use super::check::{MAX_GARBAGE, MAX_RETRIES};
use super::*;
use crate::gateway::config_from_toml;
use crate::line::{Framing, Parity};
use crate::master::Protocol;
use ipnet::IpNet;
use proptest::prelude::*;
use std::collections::BTreeMap;
use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr};
use std::time::Duration;

fn duration() -> impl Strategy<Value = Duration> {
    prop_oneof![
        (1u64..=60_000).prop_map(Duration::from_millis),
        (1u64..=10_000_000).prop_map(Duration::from_micros),
        (1u64..=100_000).prop_map(Duration::from_secs),
    ]
}

fn socket_addr() -> impl Strategy<Value = SocketAddr> {
    prop_oneof![
        any::<([u8; 4], u16)>().prop_map(SocketAddr::from),
        any::<([u16; 8], u16)>()
            .prop_map(|(ip, port)| SocketAddr::from((Ipv6Addr::from(ip), port))),
    ]
}

fn server() -> impl Strategy<Value = Server> {
    let limits = (
        // Each address once: a second listener on one could not be bound.
        prop::collection::btree_set(socket_addr(), 1..4).prop_map(Vec::from_iter),
        1usize..=100_000,
        prop_oneof![Just(Duration::ZERO), duration()],
        1usize..=64,
        prop_oneof![Just(Duration::ZERO), duration()],
    );
    let guard = (
        prop::sample::select(vec![WhenFull::CloseOldestIdle, WhenFull::Refuse]),
        duration(),
        prop_oneof![
            Just(Duration::ZERO),
            (1u64..=7200).prop_map(Duration::from_secs)
        ],
        prop::collection::vec(net(), 0..4),
        prop::collection::vec(net(), 0..4),
    );
    let tls = (
        prop::collection::vec(socket_addr(), 0..3),
        prop::option::of(tls()),
        prop::collection::vec(net(), 0..3),
        prop::sample::select(vec![0.25, 0.9, 1.0]),
        // Resolved: the loader fills in the default.
        (0usize..=100_000).prop_map(Some),
    );
    (limits, guard, tls).prop_map(
        |(
            (listen, max_connections, idle, depth, shutdown),
            (when_full, frame_timeout, keepalive, allow, read_only),
            (mut listen_tls, tls, priority, priority_share, per_address),
        )| Server {
            listen_tls: if tls.is_some() {
                listen_tls.sort();
                listen_tls.dedup();
                listen_tls.retain(|addr| !listen.contains(addr));
                listen_tls
            } else {
                Vec::new()
            },
            listen,
            listen_rtu_over_tcp: Vec::new(),
            listen_udp: Vec::new(),
            max_connections,
            max_connections_per_address: per_address,
            idle_timeout: idle,
            pipeline_depth: depth,
            shutdown_timeout: shutdown,
            when_full,
            frame_timeout,
            keepalive,
            allow,
            read_only,
            priority,
            priority_share,
            tls,
            serial: Vec::new(),
        },
    )
}

fn role_access() -> impl Strategy<Value = RoleAccess> {
    prop::sample::select(vec![
        RoleAccess::ReadWrite,
        RoleAccess::ReadOnly,
        RoleAccess::None,
    ])
}

fn tls() -> impl Strategy<Value = Tls> {
    let roles = prop::collection::btree_map(
        prop::sample::select(vec!["operator", "viewer", "Engineering", "historian-2"])
            .prop_map(str::to_owned),
        (
            role_access(),
            prop::option::of(prop::sample::select(vec!["1", "10-19,30", "0-255"])),
        )
            .prop_map(|(access, units)| Role {
                access,
                units: units.map(|units| units.parse().expect("a unit set")),
            }),
        0..4,
    );
    (roles, role_access(), duration()).prop_map(|(roles, default_role_access, handshake)| Tls {
        certificate: "/etc/modbus-gateway/tls/server.crt".into(),
        private_key: "/etc/modbus-gateway/tls/server.key".into(),
        client_ca: "/etc/modbus-gateway/tls/client-ca.crt".into(),
        crl: None,
        roles,
        default_role_access,
        handshake_timeout: handshake,
    })
}

/// An IPv4 or IPv6 network, host bits cleared as the loader clears them.
fn net() -> impl Strategy<Value = IpNet> {
    prop_oneof![
        (any::<u32>(), 0u8..=32).prop_map(|(ip, len)| {
            IpNet::from(ipnet::Ipv4Net::new(Ipv4Addr::from(ip), len).unwrap()).trunc()
        }),
        (any::<u128>(), 0u8..=128).prop_map(|(ip, len)| {
            IpNet::from(ipnet::Ipv6Net::new(Ipv6Addr::from(ip), len).unwrap()).trunc()
        }),
    ]
}

fn log() -> impl Strategy<Value = Log> {
    let levels = [
        "info",
        "debug",
        "warn",
        "error",
        "modbus_gateway=trace",
        "info,tokio=warn",
    ];
    let formats = [LogFormat::Text, LogFormat::Json];
    (
        prop::sample::select(levels.to_vec()),
        prop::sample::select(formats.to_vec()),
    )
        .prop_map(|(level, format)| Log {
            level: level.into(),
            format,
        })
}

/// Disjoint sets of addresses 1-247.
fn address_sets(n: usize) -> impl Strategy<Value = Vec<UnitSet>> {
    prop::collection::vec(prop::collection::vec((1u8..=247, 0u8..4), 1..3), 0..=n).prop_map(
        |sets| {
            let mut taken = UnitSet::default();
            let mut out = Vec::new();
            for ranges in sets {
                let mut set = UnitSet::default();
                for (low, span) in ranges {
                    for a in low..=low.saturating_add(span).min(MAX_SLAVE_ADDRESS) {
                        if !taken.contains(a) {
                            taken.insert(a);
                            set.insert(a);
                        }
                    }
                }
                if !set.is_empty() {
                    out.push(set);
                }
            }
            out
        },
    )
}

fn slaves() -> impl Strategy<Value = Vec<Slave>> {
    (
        prop::collection::btree_set(1u8..=MAX_SLAVE_ADDRESS, 0..4),
        prop::collection::vec(
            (
                prop::option::of(duration()),
                any::<bool>(),
                prop::option::of(any::<bool>()),
                prop_oneof![Just(Duration::ZERO), duration()],
            ),
            4,
        ),
    )
        .prop_map(|(addresses, knobs)| {
            addresses
                .into_iter()
                .zip(knobs)
                .map(
                    |(address, (response_timeout, wide_read_count, coalesce_reads, cache))| Slave {
                        address,
                        response_timeout,
                        wide_read_count,
                        coalesce_reads,
                        cache,
                        template: None,
                        poll_interval: None,
                        max_read_registers: None,
                        value: Vec::new(),
                    },
                )
                .collect()
        })
}

fn sim_slaves() -> impl Strategy<Value = Vec<SimSlave>> {
    // Every model the file may name, as its key reads them.
    let models = <SimModel as super::serde_adapters::Choice>::ALL;
    let knobs = (
        prop::sample::select(models.to_vec()),
        prop_oneof![Just(Duration::ZERO), duration()],
        any::<bool>(),
        prop::option::of(duration()),
        prop_oneof![Just(0.0), 0.0..=1.0, Just(1.0)],
        (0..=MAX_GARBAGE, 0..=MAX_GARBAGE),
        prop::option::of(any::<u8>()),
    );
    let bends = (
        prop::option::of(1u8..=127),
        prop::option::of(1usize..=300),
        prop::option::of((duration(), 1usize..=300)),
    );
    let knobs = (knobs, bends);
    (address_sets(3), prop::collection::vec(knobs, 3)).prop_map(|(sets, knobs)| {
        sets.into_iter()
            .zip(knobs)
            .map(
                |(
                    address,
                    (
                        (model, delay, offline, late, rate, garbage, reply),
                        (function, truncate, gap),
                    ),
                )| SimSlave {
                    address,
                    model,
                    processing_delay: delay,
                    params: BTreeMap::new(),
                    trip: None,
                    offline,
                    extra_delay: delay / 2,
                    late_reply: late,
                    crc_error_rate: rate,
                    garbage_before: garbage.0,
                    garbage_after: garbage.1,
                    reply_address: reply,
                    reply_function: function,
                    truncate_reply: truncate,
                    reply_gap: gap.map(|(gap, _)| gap),
                    reply_gap_after: gap.map(|(_, after)| after),
                },
            )
            .collect()
    })
}

fn bus() -> impl Strategy<Value = Bus> {
    let bauds = [1200, 2400, 4800, 9600, 19_200, 38_400, 57_600, 115_200];
    let parities = [Parity::None, Parity::Even, Parity::Odd];
    let line = (
        "[a-zA-Z0-9_.-]{0,8}",
        prop_oneof![
            Just(SIM_DEVICE.to_owned()),
            "/dev/tty(USB|S|AMA)[0-9]",
            "(tcp|rfc2217)://(nport[0-9]|10\\.0\\.0\\.[0-9]|\\[::1\\]):[1-9][0-9]{0,3}",
        ],
        prop::sample::select(bauds.to_vec()),
        // RTU needs 8 data bits; ASCII takes 7 or 8; either may leave them to its default.
        prop_oneof![
            Just((Framing::Rtu, Some(8u8))),
            Just((Framing::Rtu, None)),
            Just((Framing::Ascii, Some(7u8))),
            Just((Framing::Ascii, Some(8u8))),
            Just((Framing::Ascii, None)),
        ],
        prop::sample::select(parities.to_vec()),
        prop::option::of(1u8..=2),
    );
    let timing = (
        duration(),
        (0..=MAX_RETRIES, any::<bool>()),
        prop::option::of(duration()),
        prop::option::of(duration()),
        prop_oneof![Just(Duration::ZERO), duration()],
        any::<bool>(),
    );
    let queue = (1usize..=4096, duration(), duration(), duration());
    let down = (0u32..=10, duration(), any::<bool>(), duration());
    (line, timing, queue, down, slaves(), sim_slaves()).prop_map(
        |(line, timing, queue, down, slave, sim_slave)| {
            let (name, device, baud, (framing, data_bits), parity, stop_bits) = line;
            let (response_timeout, retry, inter_frame, byte, turn, reply) = timing;
            let (retries, retry_writes) = retry;
            let (queue_depth, queue_timeout, reopen_delay, reopen_extra) = queue;
            let sim_slave = if device == SIM_DEVICE {
                sim_slave
            } else {
                Vec::new()
            };
            let mut bus = Bus {
                name,
                device,
                baud,
                framing,
                data_bits,
                parity,
                stop_bits,
                response_timeout,
                retries,
                retry_writes,
                inter_frame_delay: inter_frame,
                byte_timeout: byte,
                turnaround_delay: turn,
                broadcast_reply: reply,
                queue_depth,
                queue_timeout,
                reopen_delay,
                reopen_delay_max: reopen_delay + reopen_extra,
                slave_down_after: down.0,
                slave_probe_interval: down.1,
                coalesce_reads: down.2,
                rs485: Rs485::default(),
                latency_timer: None,
                slave,
                sim_slave,
                packing_delay: Duration::ZERO,
                connect_delay: Duration::ZERO,
                match_transaction_id: true,
                max_in_flight: 1,
                tls: None,
                poll_share: crate::config::defaults::poll_share(),
                mode: crate::config::BusMode::Master,
                max_age: crate::config::defaults::listen_max_age(),
                sim_master: None,
            };
            if bus.transport().is_network() {
                bus.packing_delay = down.3;
            }
            bus
        },
    )
}

/// How a route picks its slave: the unit itself, a fixed address, or an offset (a point
/// in the range of offsets that keep every unit on the line).
#[derive(Clone, Debug)]
enum Target {
    Same,
    Address(u8),
    Offset(f64),
}

fn routes(buses: usize) -> impl Strategy<Value = Vec<(UnitSet, usize, Target)>> {
    let target = prop_oneof![
        Just(Target::Same),
        (0..=MAX_SLAVE_ADDRESS).prop_map(Target::Address),
        (0.0..=1.0).prop_map(Target::Offset),
    ];
    let units = prop::collection::vec((any::<u8>(), 0u8..16), 1..3).prop_map(|ranges| {
        let mut set = UnitSet::default();
        for (low, span) in ranges {
            (low..=low.saturating_add(span)).for_each(|u| set.insert(u));
        }
        set
    });
    prop::collection::vec((units, 0..buses, target), 0..4)
}

/// A configuration that validates: every section, a few buses (some simulated), slaves,
/// simulated slaves and routes.
/// Up to three rules, each with some of the match keys (names unique by position).
fn rules() -> impl Strategy<Value = Vec<Rule>> {
    use crate::config::{Action, Functions, Registers};
    let function = prop_oneof![
        (1u8..=0x7F).prop_map(Functions::Code),
        Just(Functions::Read),
        Just(Functions::Write),
        Just(Functions::Diagnostic),
        Just(Functions::DiagnosticWrite),
    ];
    let registers = (any::<u16>(), any::<u16>()).prop_map(|(a, b)| Registers {
        first: a.min(b),
        last: a.max(b),
    });
    let protocol = prop_oneof![
        Just(Protocol::Tcp),
        Just(Protocol::RtuOverTcp),
        Just(Protocol::Udp),
        Just(Protocol::Tls),
    ];
    let rule = (
        any::<bool>(),
        prop::collection::vec(net(), 0..3),
        prop::collection::vec("[a-z]{1,8}", 0..2),
        prop::collection::vec(protocol, 0..3),
        address_sets(1).prop_map(|sets| sets.into_iter().next()),
        prop::collection::vec(function, 0..3),
        prop::collection::vec(registers, 0..3),
        prop_oneof![
            Just(Action::Allow),
            Just(Action::Deny),
            Just(Action::Acknowledge)
        ],
    )
        .prop_map(
            |(named, masters, roles, protocols, units, functions, registers, action)| Rule {
                name: named.then(String::new),
                masters,
                roles,
                protocols,
                buses: Vec::new(),
                units: units.filter(|u| !u.is_empty()),
                functions,
                registers,
                action,
            },
        );
    prop::collection::vec(rule, 0..3).prop_map(|mut rules| {
        for (i, rule) in rules.iter_mut().enumerate() {
            if rule.name.is_some() {
                rule.name = Some(format!("rule-{i}"));
            }
        }
        rules
    })
}

fn audit() -> impl Strategy<Value = crate::config::Audit> {
    use crate::config::{Audit, ByteSize, OnError};
    (
        "/var/lib/[a-z]{1,8}\\.jsonl",
        4096u64..(1 << 40),
        1u32..=1000,
        any::<bool>(),
        any::<bool>(),
    )
        .prop_map(|(path, size, keep, allow, fsync)| Audit {
            path: path.into(),
            max_size: ByteSize(size),
            keep,
            on_error: if allow {
                OnError::Allow
            } else {
                OnError::DenyWrites
            },
            fsync,
        })
}

fn config() -> impl Strategy<Value = Config> {
    let parts = (
        server(),
        socket_addr(),
        log(),
        prop::collection::vec(bus(), 1..4),
    );
    parts
        .prop_flat_map(|(server, metrics, log, buses)| {
            let n = buses.len();
            (
                Just((server, metrics, log, buses)),
                routes(n),
                rules(),
                prop::option::of(audit()),
            )
        })
        .prop_map(
            |((server, metrics, log, mut bus), wanted, mut rule, audit)| {
                // Unique names: the generated prefix plus the position; a serial device, or a device
                // server's port, once.
                let mut devices = std::collections::BTreeSet::new();
                for (i, b) in bus.iter_mut().enumerate() {
                    b.name = format!("{}{i}", b.name);
                    let owned = match b.device_name() {
                        crate::config::DeviceName::Server(addr) => {
                            format!("{}:{}", addr.host, addr.port)
                        }
                        _ => b.device.clone(),
                    };
                    if !b.is_sim() && !devices.insert(owned) {
                        b.device = match b.device_name() {
                            crate::config::DeviceName::Server(addr) => {
                                format!("{}://uniq{i}:{}", addr.mode.scheme(), addr.port)
                            }
                            _ => format!("{}-{i}", b.device),
                        };
                        devices.insert(b.device.clone());
                    }
                }
                let mut routed = UnitSet::default();
                let mut route = Vec::new();
                for (units, b, target) in wanted {
                    let mut fresh = UnitSet::default();
                    units
                        .iter()
                        .filter(|&u| !routed.contains(u))
                        .for_each(|u| fresh.insert(u));
                    let (Some(low), Some(high)) = (fresh.iter().next(), fresh.iter().last()) else {
                        continue;
                    };
                    let (low, high) = (i32::from(low), i32::from(high));
                    let max = i32::from(MAX_SLAVE_ADDRESS);
                    let (address, offset) = match target {
                        Target::Same if high <= max => (None, None),
                        Target::Offset(at) if high - low <= max => {
                            let span = f64::from(max - high + low);
                            (None, Some(-low + (at * span) as i32))
                        }
                        Target::Address(a) => (Some(a), None),
                        _ => (Some(1), None),
                    };
                    fresh.iter().for_each(|u| routed.insert(u));
                    route.push(Route {
                        units: fresh,
                        bus: bus[b].name.clone(),
                        address,
                        offset,
                    });
                }
                // Rules name buses that exist, and roles only where TLS masters have them.
                for r in &mut rule {
                    r.buses.extend(bus.first().map(|b| b.name.clone()));
                    if server.tls.is_none() {
                        r.roles.clear();
                    }
                }
                Config {
                    template_dir: None,
                    server,
                    metrics: Metrics { listen: metrics },
                    log,
                    bus,
                    route,
                    rule,
                    audit,
                    virtual_units: Vec::new(),
                    mqtt: None,
                    templates: crate::config::Templates::load(None, "template_dir")
                        .expect("the shipped templates"),
                }
            },
        )
}

/// Where a key sits in the TOML document: `bus[1].slave[0].address`.
fn at<'a>(doc: &'a mut toml::Value, path: &str) -> Option<&'a mut toml::Value> {
    let mut here = doc;
    for part in path.split('.') {
        let mut pieces = part.split('[');
        let key = pieces.next()?;
        here = here
            .as_table_mut()?
            .entry(key)
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        for index in pieces {
            let index: usize = index.trim_end_matches(']').parse().ok()?;
            here = here.as_array_mut()?.get_mut(index)?;
        }
    }
    Some(here)
}

/// Keys of `config` set to values the loader must refuse, each with the key the error
/// must name.
fn mutations(config: &Config) -> Vec<(String, toml::Value)> {
    use toml::Value::{Float, Integer, String as Text};
    let text = |s: &str| Text(s.to_owned());
    let table =
        |key: &str, value| toml::Value::Table(toml::Table::from_iter([(key.to_owned(), value)]));
    let mut out = vec![
        ("server.max_connections".to_owned(), Integer(0)),
        ("server.max_connections_per_address".to_owned(), Integer(-1)),
        ("server.pipeline_depth".to_owned(), Integer(0)),
        ("server.listen".to_owned(), text("localhost")),
        ("server.listen".to_owned(), toml::Value::Array(vec![])),
        ("server.idle_timeout".to_owned(), text("soon")),
        ("server.frame_timeout".to_owned(), text("0s")),
        ("server.keepalive".to_owned(), text("10ms")),
        ("server.when_full".to_owned(), text("oldest")),
        ("server.allow".to_owned(), text("10.0.0.0/40")),
        ("server.read_only".to_owned(), text("plc")),
        ("metrics.listen".to_owned(), text("127.0.0.1")),
        ("log.level".to_owned(), text("[")),
        ("log.format".to_owned(), text("xml")),
    ];
    for (i, bus) in config.bus.iter().enumerate() {
        let mut key = |field: &str, value| out.push((format!("bus[{i}].{field}"), value));
        key("baud", Integer(0));
        key("baud", Integer(-9600));
        key("data_bits", Integer(6));
        key("framing", text("modbus"));
        key("stop_bits", Integer(3));
        key("parity", text("evn"));
        key("response_timeout", text("0s"));
        key("queue_timeout", text("0s"));
        key("reopen_delay", text("0s"));
        key("reopen_delay_max", text("0s"));
        key("slave_probe_interval", text("0s"));
        key("turnaround_delay", text("later"));
        key("retries", Integer(11));
        key("queue_depth", Integer(0));
        key("name", text("line one"));
        key("device", text(""));
        key("broadcast_reply", text("maybe"));
        if i > 0 {
            key("name", text(&config.bus[0].name));
        }
        if !bus.is_sim() {
            key(
                "sim_slave",
                toml::Value::Array(vec![table("address", Integer(1))]),
            );
        }
        for j in 0..bus.slave.len() {
            let mut key =
                |field: &str, value| out.push((format!("bus[{i}].slave[{j}].{field}"), value));
            key("address", Integer(0));
            key("address", Integer(248));
            key("address", Integer(256));
            key("response_timeout", text("0s"));
            if j > 0 {
                key("address", Integer(i64::from(bus.slave[0].address)));
            }
        }
        for (j, sim) in bus.sim_slave.iter().enumerate() {
            let mut key =
                |field: &str, value| out.push((format!("bus[{i}].sim_slave[{j}].{field}"), value));
            key("address", text("0-3"));
            key("address", text("240-248"));
            key("address", text("4-1"));
            key("model", text("gd2000"));
            key("crc_error_rate", Float(1.5));
            key("crc_error_rate", Float(-0.1));
            key("garbage_before", Integer(MAX_GARBAGE as i64 + 1));
            key("garbage_after", Integer(MAX_GARBAGE as i64 + 1));
            if sim.model.is_drive() {
                key("trip", Integer(0xFFFF));
            } else {
                key("trip", Integer(35));
                key("params", table("P00.01", Integer(2)));
            }
            if j > 0 {
                let first = bus.sim_slave[0].address.iter().next().unwrap_or(1);
                key("address", Integer(i64::from(first)));
            }
        }
    }
    for (k, route) in config.route.iter().enumerate() {
        let mut key = |field: &str, value| out.push((format!("route[{k}].{field}"), value));
        key("bus", text("nowhere"));
        key("units", text("9-1"));
        if route.offset.is_none() {
            key("address", Integer(248));
        }
        if k > 0 {
            key("units", text(&config.route[0].units.to_string()));
        }
    }
    for (k, rule) in config.rule.iter().enumerate() {
        let mut key = |field: &str, value| out.push((format!("rule[{k}].{field}"), value));
        key("action", text("block"));
        key("buses", text("nowhere"));
        key("functions", Integer(0x80));
        key("functions", text("writes"));
        key("registers", text("0x2001-0x2000"));
        key("registers", text("65536"));
        key("protocols", text("modbus"));
        key("masters", text("plc"));
        key("units", text("300"));
        if k > 0 && rule.name.is_some() && config.rule[0].name.is_some() {
            key(
                "name",
                text(config.rule[0].name.as_deref().unwrap_or_default()),
            );
        }
    }
    if config.audit.is_some() {
        out.push(("audit.max_size".to_owned(), Integer(4095)));
        out.push(("audit.max_size".to_owned(), text("10 mb")));
        out.push(("audit.keep".to_owned(), Integer(0)));
        out.push(("audit.on_error".to_owned(), text("ignore")));
        out.push(("audit.path".to_owned(), text("")));
    }
    out
}

/// A TOML value of any type, mostly one that some key takes.
fn toml_value() -> impl Strategy<Value = String> {
    let words = [
        "sim",
        "/dev/ttyUSB0",
        "1s",
        "0s",
        "250ms",
        "2h",
        "1-4",
        "1,5-7",
        "0-255",
        "4-1",
        "127.0.0.1:502",
        "[::1]:502",
        "0.0.0.0:502,[::]:502",
        "even",
        "odd",
        "none",
        "text",
        "json",
        "info",
        "registers",
        "gd20",
        "gd300",
        "gd10",
        "pd-inverter",
        "line1",
        "yes",
        "",
    ];
    let scalar = prop_oneof![
        prop::sample::select(words.to_vec()).prop_map(|w| format!("\"{w}\"")),
        "\"[ -~]{0,12}\"",
        prop_oneof![-2i64..=260, Just(9600), Just(65_536), any::<i64>()]
            .prop_map(|n| n.to_string()),
        prop_oneof![
            Just("true"),
            Just("false"),
            Just("0.5"),
            Just("1e9"),
            Just("-0.0")
        ]
        .prop_map(str::to_owned),
    ];
    scalar.prop_recursive(2, 8, 4, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..4)
                .prop_map(|items| format!("[{}]", items.join(", "))),
            prop::collection::vec(("[A-Za-z0-9.]{1,7}", inner), 0..3).prop_map(|pairs| {
                let pairs: Vec<String> = pairs
                    .iter()
                    .map(|(k, v)| format!("\"{k}\" = {v}"))
                    .collect();
                format!("{{ {} }}", pairs.join(", "))
            }),
        ]
    })
}

/// Sections and keys of the real layout, each key with a value it takes or a value of
/// any type, a rare garbage line, and buses that mostly have a name and a device, so
/// that some documents load.
const BUS_KEYS: &[&str] = &[
    "baud",
    "data_bits",
    "parity",
    "stop_bits",
    "response_timeout",
    "retries",
    "retry_writes",
    "inter_frame_delay",
    "byte_timeout",
    "queue_depth",
    "reopen_delay_max",
];
const SIM_SLAVE_KEYS: &[&str] = &[
    "address",
    "model",
    "params",
    "trip",
    "offline",
    "late_reply",
    "crc_error_rate",
    "garbage_before",
    "reply_address",
];

fn toml_document() -> impl Strategy<Value = String> {
    // Headers with the keys they take, [[bus]] and its parts more likely; the last two
    // are the wrong kind of table.
    let sections: &[(&str, &[&str])] = &[
        (
            "[server]",
            &[
                "listen",
                "max_connections",
                "max_connections_per_address",
                "idle_timeout",
                "pipeline_depth",
            ],
        ),
        ("[metrics]", &["listen"]),
        ("[log]", &["level", "format"]),
        ("[[bus]]", BUS_KEYS),
        ("[[bus]]", BUS_KEYS),
        ("[[bus]]", BUS_KEYS),
        (
            "[[bus.slave]]",
            &["address", "response_timeout", "wide_read_count"],
        ),
        ("[[bus.sim_slave]]", SIM_SLAVE_KEYS),
        ("[[route]]", &["units", "bus", "address", "offset"]),
        (
            "[[bus.slave]]",
            &["address", "response_timeout", "wide_read_count"],
        ),
        ("[[bus.sim_slave]]", SIM_SLAVE_KEYS),
        ("[[route]]", &["units", "bus", "address", "offset"]),
        ("[bus]", &["baud"]),
        ("[[server]]", &["listen"]),
    ];
    let keys: &[(&str, &[&str])] = &[
        (
            "listen",
            &["\"127.0.0.1:5020\"", "[\"[::1]:502\", \"0.0.0.0:502\"]"],
        ),
        ("max_connections", &["1", "64"]),
        ("max_connections_per_address", &["0", "4"]),
        ("idle_timeout", &["\"0s\"", "\"10m\""]),
        ("pipeline_depth", &["1", "16"]),
        ("level", &["\"debug\""]),
        ("format", &["\"json\""]),
        ("baud", &["9600", "115200"]),
        ("data_bits", &["8"]),
        ("framing", &["\"rtu\"", "\"ascii\""]),
        ("parity", &["\"none\"", "\"odd\""]),
        ("stop_bits", &["1", "2"]),
        ("response_timeout", &["\"20ms\"", "\"1s 500ms\""]),
        ("retries", &["0", "3"]),
        ("retry_writes", &["true"]),
        ("inter_frame_delay", &["\"5ms\""]),
        ("byte_timeout", &["\"3ms\""]),
        ("queue_depth", &["1", "500"]),
        ("reopen_delay_max", &["\"1m\""]),
        ("address", &["3", "247"]),
        ("wide_read_count", &["true"]),
        (
            "model",
            &["\"registers\"", "\"gd20\"", "\"pd-inverter\"", "\"sdm120\""],
        ),
        ("params", &["{ \"P00.01\" = 2 }", "{ \"Pd-00\" = 3 }"]),
        ("trip", &["35"]),
        ("offline", &["true"]),
        ("late_reply", &["\"2s\""]),
        ("crc_error_rate", &["0.25", "1.0"]),
        ("garbage_before", &["0", "256"]),
        ("reply_address", &["9"]),
        ("units", &["\"1-10\"", "[20, 21]", "255"]),
        ("bus", &["\"b0\"", "\"b1\""]),
        ("offset", &["-1", "100"]),
    ];
    let section = prop::sample::select(sections.to_vec()).prop_flat_map(|(header, names)| {
        let known: Vec<_> = keys
            .iter()
            .filter(|(k, _)| names.contains(k))
            .copied()
            .collect();
        let key_value = prop::sample::select(known).prop_flat_map(|(key, good)| {
            let good = prop::sample::select(good.to_vec()).prop_map(str::to_owned);
            (Just(key), prop_oneof![2 => good, 1 => toml_value()])
        });
        // A map: a key twice is a TOML error, and those are plenty already.
        let lines = prop::collection::vec(key_value, 0..5).prop_map(|lines| {
            let lines: BTreeMap<_, _> = lines.into_iter().collect();
            lines
                .into_iter()
                .map(|(k, v)| format!("{k} = {v}\n"))
                .collect::<String>()
        });
        (
            Just(header),
            prop::bool::weighted(0.9),
            lines,
            prop::option::weighted(
                0.05,
                prop_oneof![Just("bogus = 1".to_owned()), "[ -~]{0,16}"],
            ),
        )
    });
    let first_bus = prop::bool::weighted(0.8);
    (first_bus, prop::collection::vec(section, 0..6)).prop_map(|(first_bus, sections)| {
        let mut text = String::new();
        let mut seen = Vec::new();
        let mut buses = 0;
        if first_bus {
            text.push_str("[[bus]]\nname = \"b0\"\ndevice = \"sim\"\n");
            buses += 1;
        }
        for (header, named, lines, garbage) in sections {
            // A table opened twice is a TOML error, and those are plenty already.
            if !header.starts_with("[[") && seen.contains(&header) {
                continue;
            }
            seen.push(header);
            text.extend([header, "\n"]);
            if named && header == "[[bus]]" {
                text.push_str(&format!("name = \"b{buses}\"\ndevice = \"sim\"\n"));
                buses += 1;
            }
            text.push_str(&lines);
            text.extend(garbage.map(|g| g + "\n"));
        }
        text
    })
}

proptest! {
    #[test]
    fn no_text_whatever_makes_the_loader_panic(text in "\\PC*") {
        let _ = config_from_toml(&text);
    }

    #[test]
    fn any_document_is_refused_with_named_keys_or_loads_and_prints_back_the_same(
        text in toml_document(),
    ) {
        match config_from_toml(&text) {
            Ok(config) => {
                let printed = config.to_toml();
                let again = config_from_toml(&printed);
                prop_assert_eq!(again, Ok(config), "{}\n---\n{}", text, printed);
            }
            Err(errors) => {
                prop_assert!(!errors.0.is_empty());
                // Each error names its key, but for the one of a text that is no TOML.
                let syntax = matches!(&errors.0[..], [only] if only.key.is_empty()
                    && only.reason.starts_with("TOML parse error"));
                prop_assert!(syntax || errors.0.iter().all(|e| !e.key.is_empty()), "{:?}", errors);
            }
        }
    }

    #[test]
    fn every_valid_configuration_printed_loads_back_the_same(config in config()) {
        let mut config = config;
        // Fills in the stop bits, as loading does.
        let valid = config.validate();
        prop_assert!(valid.is_ok(), "the generator made an invalid config: {:?}", valid);
        let text = config.to_toml();
        let again = config_from_toml(&text);
        prop_assert_eq!(again, Ok(config), "{}", text);
    }

    #[test]
    fn a_bad_value_is_refused_with_an_error_naming_its_key(
        config in config(),
        // A few of the config's mutations each: loading all of them takes seconds.
        picks in prop::collection::vec(any::<prop::sample::Index>(), 4),
    ) {
        let mut config = config;
        prop_assert!(config.validate().is_ok());
        let printed: toml::Table = config.to_toml().parse().map_err(|e| {
            TestCaseError::fail(format!("to_toml printed bad TOML: {e}"))
        })?;
        let mutations = mutations(&config);
        for pick in picks {
            let (key, value) = &mutations[pick.index(mutations.len())];
            let mut doc = toml::Value::Table(printed.clone());
            let Some(slot) = at(&mut doc, key) else {
                return Err(TestCaseError::fail(format!("no {key} in the document")));
            };
            *slot = value.clone();
            let text =
                toml::to_string(&doc).map_err(|e| TestCaseError::fail(e.to_string()))?;
            match config_from_toml(&text) {
                Ok(_) => prop_assert!(false, "{} = {} was accepted", key, value),
                Err(errors) => prop_assert!(
                    errors.0.iter().any(|e| &e.key == key),
                    "{} = {} gave {:?}",
                    key,
                    value,
                    errors.0
                ),
            }
        }
    }
}
