//! A line's `mode`: `master` (the gateway drives it) or `listen` (another master does, and the
//! gateway only hears it), with the keys only a listen line has (`max_age`, and on a simulated
//! line the other master, `[bus.sim_master]`), and the check that refuses on a listen line every
//! key that would make the gateway transmit or that means nothing where it never does. Plain
//! values; knows nothing of ports or of what is heard.

use super::defaults;
use super::serde_adapters::{duration, words, Choice};
use super::{Bus, ConfigError, Rs485Mode, Table};
use crate::line::framing::TransportKind;
use crate::line::Framing;
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Who masters the line.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BusMode {
    /// The gateway: it sends the masters' requests and its own polls.
    #[default]
    Master,
    /// Another master: the gateway never transmits, decodes what it hears and answers reads of
    /// what it saw.
    Listen,
}

impl Choice for BusMode {
    const ALL: &'static [Self] = &[BusMode::Master, BusMode::Listen];
    fn word(self) -> &'static str {
        self.name()
    }
}

words!(BusMode);

impl BusMode {
    /// As the configuration and `modbus_gateway_bus_info`'s `mode` label spell it.
    pub fn name(self) -> &'static str {
        match self {
            BusMode::Master => "master",
            BusMode::Listen => "listen",
        }
    }

    /// For serde: the default mode is left out.
    #[allow(clippy::trivially_copy_pass_by_ref)] // serde's signature
    pub(super) fn is_master(&self) -> bool {
        *self == BusMode::Master
    }
}

/// The other master of a simulated listen line: it reads `read` in turn, for ever, as a PLC
/// polling its slaves would.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimMaster {
    /// Silence after each of its transactions, on top of t3.5 (0: back to back).
    #[serde(default, with = "duration")]
    pub pause: Duration,
    /// How long it waits for a reply before its next request.
    #[serde(default = "defaults::response_timeout", with = "duration")]
    pub response_timeout: Duration,
    pub read: Vec<SimRead>,
}

/// One read of the simulated other master.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimRead {
    pub slave: u8,
    #[serde(default)]
    pub table: Table,
    pub register: u16,
    pub count: u16,
}

/// `bus`'s listen-only keys, as `key` names them: on a master line, none; on a listen line, no
/// key that would transmit or that only a line the gateway masters uses.
pub(super) fn check(bus: &Bus, key: &dyn Fn(&str) -> String, out: &mut Vec<ConfigError>) {
    let mut fail = |field: &str, reason: &str| {
        out.push(ConfigError {
            key: key(field),
            reason: reason.to_owned(),
        });
    };
    if bus.mode == BusMode::Master {
        if bus.max_age != defaults::listen_max_age() {
            fail(
                "max_age",
                "only a line with mode = \"listen\" has shadow data to age",
            );
        }
        if bus.sim_master.is_some() {
            fail(
                "sim_master",
                "only a simulated line with mode = \"listen\" has another master",
            );
        }
        return;
    }
    if bus.framing == Framing::Tcp {
        fail(
            "mode",
            "a Modbus TCP device's connection has no other master to listen to: \
             only framing = \"rtu\" or \"ascii\" listen",
        );
    }
    if bus.max_age.is_zero() {
        fail("max_age", "must be longer than 0");
    }
    if bus.sim_master.is_some() && bus.transport() != TransportKind::Sim {
        fail(
            "sim_master",
            "only a simulated line (device = \"sim\") has one",
        );
    }
    if let Some(master) = &bus.sim_master {
        check_sim_master(master, &mut fail);
    }
    for (field, why) in transmitting_keys(bus) {
        fail(field, why);
    }
    for (j, slave) in bus.slave.iter().enumerate() {
        let unused = [
            ("cache", !slave.cache.is_zero()),
            ("coalesce_reads", slave.coalesce_reads.is_some()),
            ("poll_interval", slave.poll_interval.is_some()),
            ("max_read_registers", slave.max_read_registers.is_some()),
        ];
        for (field, set) in unused {
            if set {
                fail(&format!("slave[{j}].{field}"), NOT_POLLED);
            }
        }
        for (k, value) in slave.value.iter().enumerate() {
            if value.poll_interval.is_some() {
                fail(&format!("slave[{j}].value[{k}].poll_interval"), NOT_POLLED);
            }
            if value.writable {
                fail(&format!("slave[{j}].value[{k}].writable"), NEVER_SENT);
            }
        }
    }
}

const NEVER_SENT: &str = "the line is listen-only (mode = \"listen\"): nothing is ever sent on it";
const NOT_POLLED: &str = "the line is listen-only (mode = \"listen\"): its values come from what \
                          its own master reads, and nothing is polled, cached or coalesced";

/// The keys of `bus` set to anything but their default that would transmit on a listen line, or
/// shape what the gateway sends on a line it masters, with why each is refused.
fn transmitting_keys(bus: &Bus) -> Vec<(&'static str, &'static str)> {
    let rs485 = &bus.rs485;
    let driven_by_kernel = "the kernel's RS-485 mode switches the transmitter on to send: a \
                            listen line holds RTS at its receive level (mode = \"rts\", \
                            rts_after_send) or leaves it alone (\"off\")";
    let set = [
        ("retries", bus.retries != 0, NEVER_SENT),
        ("retry_writes", bus.retry_writes, NEVER_SENT),
        (
            "inter_frame_delay",
            bus.inter_frame_delay.is_some(),
            NEVER_SENT,
        ),
        (
            "turnaround_delay",
            bus.turnaround_delay != defaults::turnaround_delay(),
            NEVER_SENT,
        ),
        (
            "broadcast_reply",
            bus.broadcast_reply != defaults::broadcast_reply(),
            NEVER_SENT,
        ),
        ("max_in_flight", bus.max_in_flight != 1, NEVER_SENT),
        ("connect_delay", !bus.connect_delay.is_zero(), NEVER_SENT),
        (
            "slave_down_after",
            bus.slave_down_after != defaults::slave_down_after(),
            NEVER_SENT,
        ),
        (
            "slave_probe_interval",
            bus.slave_probe_interval != defaults::slave_probe_interval(),
            NEVER_SENT,
        ),
        (
            "coalesce_reads",
            bus.coalesce_reads != defaults::coalesce_reads(),
            NOT_POLLED,
        ),
        (
            "poll_share",
            bus.poll_share != defaults::poll_share(),
            NOT_POLLED,
        ),
        (
            "rs485.mode",
            rs485.mode == Rs485Mode::Kernel,
            driven_by_kernel,
        ),
        (
            "rs485.delay_before_send",
            !rs485.delay_before_send.is_zero(),
            NEVER_SENT,
        ),
        (
            "rs485.delay_after_send",
            !rs485.delay_after_send.is_zero(),
            NEVER_SENT,
        ),
        ("rs485.echo", rs485.echo, NEVER_SENT),
    ];
    set.into_iter()
        .filter(|(_, set, _)| *set)
        .map(|(field, _, why)| (field, why))
        .collect()
}

fn check_sim_master(master: &SimMaster, fail: &mut dyn FnMut(&str, &str)) {
    if master.read.is_empty() {
        fail(
            "sim_master.read",
            "the simulated master needs at least one read",
        );
    }
    if master.response_timeout.is_zero() {
        fail("sim_master.response_timeout", "must be longer than 0");
    }
    for (k, read) in master.read.iter().enumerate() {
        let most = if read.table.is_bits() {
            super::MAX_READ_BITS
        } else {
            super::MAX_READ_REGISTERS
        };
        if read.slave == 0 || read.slave > super::MAX_SLAVE_ADDRESS {
            fail(
                &format!("sim_master.read[{k}].slave"),
                "is not a slave address 1-247",
            );
        }
        if read.count == 0 || read.count > most {
            fail(
                &format!("sim_master.read[{k}].count"),
                &format!("must be 1 to {most} for a {} read", read.table.name()),
            );
        } else if u32::from(read.register) + u32::from(read.count) > 0x1_0000 {
            fail(
                &format!("sim_master.read[{k}].count"),
                "reads past register 65535",
            );
        }
    }
}
