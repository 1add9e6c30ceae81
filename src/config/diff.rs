//! What changed from one configuration to the next, for a reload to apply: buses added, changed
//! or removed, routes, the connection policy, and the keys that only a restart applies. Pure:
//! computed from two configurations; knows nothing of how the running gateway applies it.

use super::{Bus, Config, Server, Slave, Value};
use std::time::Duration;

/// What happens to a bus of the new configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum BusChange {
    /// No bus of that name ran before.
    Added,
    /// Its settings differ from the running bus of that name.
    Changed,
    /// Exactly as before.
    Same,
}

/// The difference between the configuration in force and a new one.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct ConfigDiff {
    /// Each bus of the new configuration, in its order, by name.
    pub buses: Vec<(String, BusChange)>,
    /// Buses of the old configuration that the new one does not have, in the order a reload has
    /// always named them: what is left of the old list once each kept bus has been swapped out
    /// of it (`Vec::swap_remove`).
    pub removed: Vec<String>,
    /// The `[[route]]` sections differ.
    pub routes: bool,
    /// The plant values to poll differ: a slave's values, template, interval or read limit, a
    /// bus's `poll_share`, or a template's file.
    pub values: bool,
    /// Something in `[server]` that new connections follow changed: everything but the listen
    /// addresses and `shutdown_timeout`.
    pub(crate) connection_policy: bool,
    pub shutdown_timeout: bool,
    /// The logger applies it, not the gateway.
    pub(crate) log_level: bool,
    /// Keys that changed but only take effect after a restart, in a fixed order.
    pub need_restart: Vec<&'static str>,
}

impl ConfigDiff {
    /// What it takes to go from `old` to `new`.
    pub(crate) fn new(old: &Config, new: &Config) -> ConfigDiff {
        let mut left: Vec<&str> = old.bus.iter().map(|b| b.name.as_str()).collect();
        let buses = new
            .bus
            .iter()
            .map(|bus| {
                let change = match left.iter().position(|&name| name == bus.name) {
                    None => BusChange::Added,
                    Some(at) => {
                        left.swap_remove(at);
                        match old.bus.iter().find(|b| b.name == bus.name) {
                            Some(was) if line_of(was) == line_of(bus) => BusChange::Same,
                            _ => BusChange::Changed,
                        }
                    }
                };
                (bus.name.clone(), change)
            })
            .collect();
        let mut need_restart = Vec::new();
        if new.server.listen != old.server.listen {
            need_restart.push("server.listen");
        }
        if new.server.listen_rtu_over_tcp != old.server.listen_rtu_over_tcp {
            need_restart.push("server.listen_rtu_over_tcp");
        }
        if new.server.listen_udp != old.server.listen_udp {
            need_restart.push("server.listen_udp");
        }
        if new.server.listen_tls != old.server.listen_tls {
            need_restart.push("server.listen_tls");
        }
        // A line's mode is its task's for life: a listen line must never become a master's by a
        // reload, nor the other way.
        let mode_of = |config: &Config, name: &str| {
            config.bus.iter().find(|b| b.name == name).map(|b| b.mode)
        };
        if new
            .bus
            .iter()
            .any(|b| mode_of(old, &b.name).is_some_and(|m| m != b.mode))
        {
            need_restart.push("bus.mode");
        }
        if new.server.serial != old.server.serial {
            need_restart.push("server.serial");
        }
        if new.metrics != old.metrics {
            need_restart.push("metrics.listen");
        }
        // The broker's session is the client's from its start; the values it publishes follow
        // a reload.
        if new.mqtt != old.mqtt {
            need_restart.push("mqtt");
        }
        // The level is the logger's own business; the format is fixed when the logger starts.
        if new.log.format != old.log.format {
            need_restart.push("log.format");
        }
        ConfigDiff {
            buses,
            removed: left.into_iter().map(str::to_owned).collect(),
            routes: new.route != old.route,
            values: new.templates != old.templates
                || old
                    .bus
                    .iter()
                    .filter_map(values_of)
                    .ne(new.bus.iter().filter_map(values_of)),
            connection_policy: policy(&new.server) != policy(&old.server),
            shutdown_timeout: new.server.shutdown_timeout != old.server.shutdown_timeout,
            log_level: new.log.level != old.log.level,
            need_restart,
        }
    }
}

/// A bus's settings but those of its plant values, which its poller follows, not its line.
fn line_of(bus: &Bus) -> Bus {
    let mut line = bus.clone();
    line.poll_share = 0.0;
    for slave in &mut line.slave {
        slave.template = None;
        slave.poll_interval = None;
        slave.max_read_registers = None;
        slave.value.clear();
    }
    line
}

/// The plant values' settings of a bus: what [`line_of`] leaves out; `None` for a bus with no
/// values, whose coming and going changes no poll.
type ValuesOf<'a> = (
    &'a str,
    f64,
    Vec<(
        u8,
        &'a Option<String>,
        Option<Duration>,
        Option<u16>,
        &'a [Value],
    )>,
);

fn values_of(bus: &Bus) -> Option<ValuesOf<'_>> {
    let polled = |s: &&Slave| s.template.is_some() || !s.value.is_empty();
    let slaves: Vec<_> = bus
        .slave
        .iter()
        .filter(polled)
        .map(|s| {
            let own = s.value.as_slice();
            (
                s.address,
                &s.template,
                s.poll_interval,
                s.max_read_registers,
                own,
            )
        })
        .collect();
    (!slaves.is_empty()).then_some((&bus.name, bus.poll_share, slaves))
}

/// Everything in `[server]` but the listen addresses and the stop's timeout.
fn policy(server: &Server) -> Server {
    let mut server = server.clone();
    server.listen.clear();
    server.listen_rtu_over_tcp.clear();
    server.listen_udp.clear();
    server.listen_tls.clear();
    server.serial.clear();
    server.shutdown_timeout = Duration::ZERO;
    server
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(text: &str) -> Config {
        Config::from_toml_str(text).unwrap_or_else(|e| panic!("test config: {e}"))
    }

    fn buses(names: &[&str]) -> String {
        names
            .iter()
            .map(|name| format!("[[bus]]\nname = \"{name}\"\ndevice = \"sim\"\n"))
            .collect()
    }

    #[test]
    fn the_same_configuration_changes_nothing() {
        let c = config(&buses(&["a", "b"]));
        let diff = ConfigDiff::new(&c, &c);
        assert_eq!(
            diff.buses,
            [
                ("a".to_owned(), BusChange::Same),
                ("b".to_owned(), BusChange::Same)
            ]
        );
        assert!(diff.removed.is_empty());
        assert!(!diff.routes && !diff.connection_policy && !diff.shutdown_timeout);
        assert!(!diff.log_level);
        assert!(diff.need_restart.is_empty());
    }

    #[test]
    fn buses_are_added_changed_or_kept_in_the_new_order() {
        let old = config(&buses(&["a", "b"]));
        let new = config(&format!(
            "{}baud = 9600\n{}",
            buses(&["b"]),
            buses(&["c", "a"])
        ));
        let diff = ConfigDiff::new(&old, &new);
        assert_eq!(
            diff.buses,
            [
                ("b".to_owned(), BusChange::Changed),
                ("c".to_owned(), BusChange::Added),
                ("a".to_owned(), BusChange::Same)
            ]
        );
        assert!(diff.removed.is_empty());
    }

    #[test]
    fn removed_buses_are_named_in_the_order_the_reload_has_always_retired_them() {
        let old = config(&buses(&["a", "b", "c", "d"]));
        let new = config(&buses(&["a"]));
        // Swapping `a` out of [a, b, c, d] leaves [d, b, c].
        assert_eq!(ConfigDiff::new(&old, &new).removed, ["d", "b", "c"]);
    }

    #[test]
    fn listen_addresses_and_the_log_format_need_a_restart_in_a_fixed_order() {
        let old = config(&buses(&["a"]));
        let new = config(&format!(
            "[server]\nlisten = \"127.0.0.1:5020\"\nlisten_rtu_over_tcp = \"127.0.0.1:5021\"\n\
             listen_udp = \"127.0.0.1:5022\"\n\
             [metrics]\nlisten = \"127.0.0.1:9020\"\n\
             [log]\nformat = \"json\"\nlevel = \"debug\"\n{}",
            buses(&["a"])
        ));
        let diff = ConfigDiff::new(&old, &new);
        assert_eq!(
            diff.need_restart,
            [
                "server.listen",
                "server.listen_rtu_over_tcp",
                "server.listen_udp",
                "metrics.listen",
                "log.format"
            ]
        );
        assert!(diff.log_level);
        assert!(!diff.connection_policy, "listen is not part of the policy");
    }

    #[test]
    fn the_connection_policy_and_the_shutdown_timeout_are_told_apart() {
        let old = config(&buses(&["a"]));
        let timeout = config(&format!(
            "[server]\nshutdown_timeout = \"3s\"\n{}",
            buses(&["a"])
        ));
        let diff = ConfigDiff::new(&old, &timeout);
        assert!(diff.shutdown_timeout && !diff.connection_policy);
        let limits = config(&format!("[server]\nmax_connections = 3\n{}", buses(&["a"])));
        let diff = ConfigDiff::new(&old, &limits);
        assert!(diff.connection_policy && !diff.shutdown_timeout);
    }

    #[test]
    fn a_changed_route_is_noticed() {
        let old = config(&buses(&["a"]));
        let new = config(&format!(
            "{}[[route]]\nunits = \"1\"\nbus = \"a\"\naddress = 2\n",
            buses(&["a"])
        ));
        assert!(ConfigDiff::new(&old, &new).routes);
    }

    /// Such a change leaves the bus as it was.
    #[test]
    fn only_a_change_of_what_is_polled_changes_the_values_and_not_the_bus() {
        let value = "[[bus.slave]]\naddress = 1\n[[bus.slave.value]]\nname = \"v\"\nregister = 0\n";
        let old = config(&format!("{}{value}", buses(&["a"])));
        // Another bus, with nothing to poll: the values stay as they are.
        let more = config(&format!("{}{value}{}", buses(&["a"]), buses(&["b"])));
        let diff = ConfigDiff::new(&old, &more);
        assert!(!diff.values);
        let moved = config(&format!("{}{}", buses(&["a"]), value.replace("= 0", "= 1")));
        let diff = ConfigDiff::new(&old, &moved);
        assert!(diff.values);
        assert_eq!(diff.buses, [("a".to_owned(), BusChange::Same)]);
    }
}
