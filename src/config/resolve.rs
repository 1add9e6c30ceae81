//! Every value that depends on other keys, derived here and nowhere else, once the configuration
//! has passed its check: a bus's data bits follow its framing and its stop bits its parity, its
//! gaps its format and where its line ends; the connections one address may hold follow
//! `max_connections`; a slave's poll interval is the default unless given. [`Config::resolve`]
//! writes the printable ones into the configuration, so what `check-config` prints is what runs,
//! and the rest of the gateway reads them through the methods below. Knows nothing of how the
//! values are used.

use super::{
    defaults, Bus, Config, Route, Server, ServerSerial, Slave, Template, Value, ValueType,
    MAX_READ_REGISTERS,
};
use crate::line::{Framing, MasterTiming, SerialFormat};
use std::time::Duration;

impl Config {
    /// Fill in what the file may leave to other keys.
    pub(crate) fn resolve(&mut self) {
        let server = &mut self.server;
        server.max_connections_per_address = Some(server.connections_per_address_setting());
        for port in &mut server.serial {
            let format = port.format();
            port.data_bits = Some(format.data_bits);
            port.stop_bits = Some(format.stop_bits);
        }
        for register in self.virtual_units.iter_mut().flat_map(|u| &mut u.register) {
            register.kind = Some(register.kind.unwrap_or(if register.table.is_bits() {
                ValueType::Bool
            } else {
                ValueType::U16
            }));
        }
        for route in &mut self.route {
            if route.address.is_none() {
                route.offset = Some(route.unit_offset());
            }
        }
        for bus in &mut self.bus {
            let format = bus.format();
            bus.data_bits = Some(format.data_bits);
            bus.stop_bits = Some(format.stop_bits);
            for slave in &mut bus.slave {
                let template = slave
                    .template
                    .as_deref()
                    .and_then(|t| self.templates.get(t));
                slave.poll_interval = Some(slave.poll_interval());
                slave.max_read_registers = Some(slave.read_limit(template));
                for value in &mut slave.value {
                    value.kind = Some(value.kind());
                }
            }
        }
    }

    /// [`Config::check`] without the drives, then [`Config::resolve`]: what
    /// [`Config::from_toml_str`] does after parsing (for the loader's property tests).
    #[cfg(test)]
    pub(crate) fn validate(&mut self) -> Result<(), super::ConfigErrors> {
        self.check(None)?;
        self.resolve();
        Ok(())
    }
}

impl Server {
    /// `max_connections_per_address` as given, else all but a few of `max_connections`.
    fn connections_per_address_setting(&self) -> usize {
        self.max_connections_per_address
            .unwrap_or_else(|| defaults::max_connections_per_address(self.max_connections))
    }

    /// Connections one address may hold; `None`: no limit but `max_connections` (one that
    /// allows every slot is none: at `max_connections`, `when_full` decides).
    pub(crate) fn connections_per_address(&self) -> Option<usize> {
        let limit = self.connections_per_address_setting();
        (limit > 0 && limit < self.max_connections).then_some(limit)
    }
}

impl Bus {
    /// The gaps the master keeps. RTU: t3.5, raised by `inter_frame_delay` and `byte_timeout`
    /// (whose default behind a device server allows for the link's jitter). ASCII has no t3.5:
    /// `inter_frame_delay` before a frame (default 1.5 characters of quiet, so the master never
    /// talks over a slave still sending), and `byte_timeout` (default 1 s) between the characters
    /// of a reply. A device server's `packing_delay` is silence a reply may hold on top, and
    /// comes on top of every reply's deadline.
    pub(crate) fn master_timing(&self) -> MasterTiming {
        let line = self.line_timing();
        let network = self.transport().is_network();
        let timing = match self.framing {
            Framing::Rtu => MasterTiming::new(
                line,
                self.inter_frame_delay.unwrap_or_default(),
                self.byte_timeout.unwrap_or(if network {
                    defaults::NETWORK_BYTE_TIMEOUT
                } else {
                    Duration::ZERO
                }),
            ),
            Framing::Ascii => MasterTiming {
                line,
                gap: self
                    .inter_frame_delay
                    .unwrap_or_else(|| defaults::ascii_gap(&line)),
                silence: self
                    .byte_timeout
                    .unwrap_or_else(defaults::ascii_byte_timeout),
                packing: Duration::ZERO,
            },
            // No wire of the gateway's and no silence rules: a request waits only for
            // `inter_frame_delay` after the last reply, and a reply's length is in its header.
            Framing::Tcp => MasterTiming {
                line,
                gap: self.inter_frame_delay.unwrap_or_default(),
                silence: self.byte_timeout.unwrap_or(defaults::NETWORK_BYTE_TIMEOUT),
                packing: Duration::ZERO,
            },
        };
        timing.with_packing(self.packing_delay)
    }

    pub fn format(&self) -> SerialFormat {
        line_format(
            self.baud,
            self.framing,
            self.data_bits,
            self.parity,
            self.stop_bits,
        )
    }
}

/// A line's format from its keys: data bits left out follow the framing, stop bits the parity.
fn line_format(
    baud: u32,
    framing: Framing,
    data_bits: Option<u8>,
    parity: crate::line::Parity,
    stop_bits: Option<u8>,
) -> SerialFormat {
    SerialFormat {
        baud,
        data_bits: data_bits.unwrap_or_else(|| defaults::data_bits(framing)),
        parity,
        stop_bits: stop_bits.unwrap_or_else(|| defaults::stop_bits(parity)),
    }
}

impl ServerSerial {
    /// The port's line format, its defaults as a bus's.
    pub fn format(&self) -> SerialFormat {
        line_format(
            self.baud,
            self.framing,
            self.data_bits,
            self.parity,
            self.stop_bits,
        )
    }

    /// RTU: the silence that breaks a request mid-frame or ends one of unknown length,
    /// `byte_timeout` if longer than t3.5; left out, t3.5, or behind a device server a network's
    /// jitter (a frame may come in segments). ASCII: the inter-character timeout.
    pub(crate) fn silence(&self, behind_a_server: bool) -> std::time::Duration {
        let t35 = crate::line::LineTiming::new(&self.format()).t35;
        let floor = if behind_a_server {
            defaults::NETWORK_BYTE_TIMEOUT
        } else {
            t35
        };
        match self.framing {
            Framing::Ascii => self
                .byte_timeout
                .unwrap_or_else(defaults::ascii_byte_timeout),
            Framing::Rtu | Framing::Tcp => self.byte_timeout.unwrap_or(floor).max(t35),
        }
    }
}

impl Route {
    /// What a route without `address` adds to a unit id: its `offset`, else 0.
    pub(crate) fn unit_offset(&self) -> i32 {
        self.offset.unwrap_or(0)
    }
}

impl Slave {
    /// How often the slave's plant values are read, unless a value gives its own.
    pub(crate) fn poll_interval(&self) -> Duration {
        self.poll_interval.unwrap_or(defaults::POLL_INTERVAL)
    }

    /// The most registers one poll of the slave reads: its own `max_read_registers`, else its
    /// template's, else a read's.
    pub(crate) fn read_limit(&self, template: Option<&Template>) -> u16 {
        self.max_read_registers
            .or(template.and_then(|t| t.max_read_registers))
            .unwrap_or(MAX_READ_REGISTERS)
    }
}

impl Value {
    /// Its type: as given, or the table's default.
    pub fn kind(&self) -> ValueType {
        self.kind.unwrap_or(if self.table.is_bits() {
            ValueType::Bool
        } else {
            ValueType::U16
        })
    }

    /// Its HELP text: as given, or its name.
    pub fn help_text(&self) -> &str {
        self.help.as_deref().unwrap_or(&self.name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::testing::MINIMAL;

    #[test]
    fn no_parity_defaults_to_two_stop_bits() {
        let c = Config::from_toml_str(&format!("{MINIMAL}\nparity = \"none\"")).unwrap();
        assert_eq!(c.bus[0].stop_bits, Some(2));
        assert_eq!(c.bus[0].format().bits_per_char(), 11);
    }

    #[test]
    fn connections_per_address_default_to_all_but_eight_slots_and_0_lifts_the_limit() {
        for (max, per_address) in [(1024, 1016), (20, 12), (5, 3), (2, 1)] {
            let c = Config::from_toml_str(&format!("[server]\nmax_connections = {max}\n{MINIMAL}"))
                .unwrap();
            assert_eq!(c.server.max_connections_per_address, Some(per_address));
            assert_eq!(c.server.connections_per_address(), Some(per_address));
        }
        let c = Config::from_toml_str(&format!(
            "[server]\nmax_connections_per_address = 0\n{MINIMAL}"
        ))
        .unwrap();
        assert_eq!(c.server.connections_per_address(), None);
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
        let c =
            Config::from_toml_str(&format!("[server]\nmax_connections = 1\n{MINIMAL}")).unwrap();
        assert_eq!(
            c.server.connections_per_address(),
            None,
            "one slot: no limit of its own"
        );
    }
}
