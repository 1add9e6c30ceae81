//! `[bus.rs485]`: whether the gateway drives an RS-485 transceiver's driver enable itself (through
//! the kernel's RS-485 mode, or by switching RTS around each frame), and whether the line echoes
//! every byte sent. Plain values with their effective defaults; knows nothing of ioctls or ports.

use super::defaults;
use super::serde_adapters::{duration, is_false, is_true, is_zero};
use super::serde_adapters::{words, Choice};
use crate::line::framing::TransportKind;
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Who switches the transceiver's driver enable.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Rs485Mode {
    /// Nobody: the adapter switches it (USB adapters with automatic direction), or the line is
    /// not RS-485.
    #[default]
    Off,
    /// The UART's driver, through `TIOCSRS485`.
    Kernel,
    /// The gateway, raising RTS before each frame and dropping it once the frame is out.
    Rts,
}

impl Choice for Rs485Mode {
    const ALL: &'static [Self] = &[Rs485Mode::Off, Rs485Mode::Kernel, Rs485Mode::Rts];
    fn word(self) -> &'static str {
        self.as_str()
    }
}

words!(Rs485Mode);

impl Rs485Mode {
    pub fn as_str(self) -> &'static str {
        match self {
            Rs485Mode::Off => "off",
            Rs485Mode::Kernel => "kernel",
            Rs485Mode::Rts => "rts",
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rs485 {
    #[serde(default)]
    pub mode: Rs485Mode,
    /// RTS level while sending (default on); `kernel` and `rts` modes.
    #[serde(default = "defaults::rts_on_send", skip_serializing_if = "is_true")]
    pub rts_on_send: bool,
    /// RTS level once the frame is sent (default off); `kernel` and `rts` modes.
    #[serde(default, skip_serializing_if = "is_false")]
    pub rts_after_send: bool,
    /// From raising RTS to the first byte.
    #[serde(default, with = "duration", skip_serializing_if = "is_zero")]
    pub delay_before_send: Duration,
    /// From the last byte leaving the wire to dropping RTS.
    #[serde(default, with = "duration", skip_serializing_if = "is_zero")]
    pub delay_after_send: Duration,
    /// Keep the receiver on while sending (`kernel` mode).
    #[serde(default, skip_serializing_if = "is_false")]
    pub rx_during_tx: bool,
    /// The line hands back every byte sent: read it back and drop it before the reply.
    #[serde(default, skip_serializing_if = "is_false")]
    pub echo: bool,
}

impl Default for Rs485 {
    fn default() -> Rs485 {
        Rs485 {
            mode: Rs485Mode::default(),
            rts_on_send: defaults::rts_on_send(),
            rts_after_send: false,
            delay_before_send: Duration::ZERO,
            delay_after_send: Duration::ZERO,
            rx_during_tx: false,
            echo: false,
        }
    }
}

impl Rs485 {
    pub(crate) fn is_default(&self) -> bool {
        *self == Rs485::default()
    }
}

/// Longest `delay_before_send` or `delay_after_send`: longer than any transceiver needs, and the
/// line would stand still for it on every frame.
pub(super) const MAX_DELAY: Duration = Duration::from_secs(1);
/// The range of a USB serial driver's latency timer, in whole milliseconds.
pub(super) const LATENCY_TIMER_MS: std::ops::RangeInclusive<u128> = 1..=255;

impl Rs485 {
    /// What is wrong with these settings on a line that is (`sim`) or is not simulated, as
    /// (key under `rs485`, reason) pairs.
    pub(super) fn problems(&self, transport: TransportKind) -> Vec<(&'static str, String)> {
        let mut problems = Vec::new();
        let mut fail = |key, reason: &str| problems.push((key, reason.to_owned()));
        if transport != TransportKind::Serial && self.mode != Rs485Mode::Off {
            let why = match transport {
                TransportKind::Sim => "a simulated line has no transceiver to drive".to_owned(),
                _ => format!(
                    "the transceiver behind {} is the device server's to drive",
                    transport.name()
                ),
            };
            fail("mode", &format!("{why}: only \"off\""));
        }
        if transport == TransportKind::Sim && self.echo {
            fail("echo", "a simulated line does not echo");
        }
        let driven = self.mode != Rs485Mode::Off;
        // A key left at its default changes nothing, so it is accepted in any mode: every
        // commented default of config/gateway.toml can be uncommented.
        for (key, set) in [
            ("rts_on_send", !self.rts_on_send),
            ("rts_after_send", self.rts_after_send),
            ("delay_before_send", !self.delay_before_send.is_zero()),
            ("delay_after_send", !self.delay_after_send.is_zero()),
            ("rx_during_tx", self.rx_during_tx),
        ] {
            if set && !driven {
                fail(key, "only with mode = \"kernel\" or \"rts\"");
            }
        }
        if self.rx_during_tx && self.mode == Rs485Mode::Rts {
            fail("rx_during_tx", "only with mode = \"kernel\"");
        }
        if driven && self.rts_on_send == self.rts_after_send {
            fail(
                "rts_after_send",
                "must differ from rts_on_send, or RTS never switches the driver",
            );
        }
        for (key, delay) in [
            ("delay_before_send", self.delay_before_send),
            ("delay_after_send", self.delay_after_send),
        ] {
            if delay > MAX_DELAY {
                fail(key, "must not be longer than 1s");
            } else if self.mode == Rs485Mode::Kernel && delay.subsec_nanos() % 1_000_000 != 0 {
                fail(key, "the kernel takes whole milliseconds");
            }
        }
        problems
    }
}

#[cfg(test)]
mod tests {
    use crate::config::testing::{errors, MINIMAL};
    use crate::config::{Config, Rs485Mode};

    const SIM: &str = "[[bus]]\nname = \"sim\"\ndevice = \"sim\"\n";

    #[test]
    fn rs485_settings_that_cannot_work_are_refused_naming_the_key() {
        for (keys, expected) in [
            (
                "rts_on_send = false",
                "bus[0].rs485.rts_on_send: only with mode = \"kernel\" or \"rts\"",
            ),
            (
                "rts_after_send = true",
                "bus[0].rs485.rts_after_send: only with mode = \"kernel\" or \"rts\"",
            ),
            (
                "delay_after_send = \"1ms\"",
                "bus[0].rs485.delay_after_send: only with mode = \"kernel\" or \"rts\"",
            ),
            (
                "mode = \"rts\"\nrx_during_tx = true",
                "bus[0].rs485.rx_during_tx: only with mode = \"kernel\"",
            ),
            (
                "mode = \"kernel\"\nrts_on_send = false",
                "bus[0].rs485.rts_after_send: must differ from rts_on_send, or RTS never \
                 switches the driver",
            ),
            (
                "mode = \"rts\"\ndelay_before_send = \"2s\"",
                "bus[0].rs485.delay_before_send: must not be longer than 1s",
            ),
            (
                "mode = \"kernel\"\ndelay_after_send = \"500us\"",
                "bus[0].rs485.delay_after_send: the kernel takes whole milliseconds",
            ),
        ] {
            let e = errors(&format!("{MINIMAL}\n[bus.rs485]\n{keys}"));
            assert_eq!(e, [expected], "{keys}");
        }
        let e = errors(&format!("{MINIMAL}\n[bus.rs485]\nmode = \"half\""));
        assert!(e[0].starts_with("bus[0].rs485.mode"), "{e:?}");
    }

    #[test]
    fn every_rs485_key_at_its_default_value_is_accepted_with_mode_off() {
        let defaults = "[bus.rs485]\nmode = \"off\"\nrts_on_send = true\n\
                        rts_after_send = false\ndelay_before_send = \"0s\"\n\
                        delay_after_send = \"0s\"\nrx_during_tx = false\necho = false";
        let c = Config::from_toml_str(&format!("{MINIMAL}\n{defaults}")).unwrap();
        assert_eq!(c.bus[0].rs485.mode, Rs485Mode::Off);
    }

    #[test]
    fn a_simulated_line_refuses_rs485_direction_control_echo_and_a_latency_timer() {
        let e = errors(&format!(
            "{SIM}latency_timer = \"1ms\"\n[bus.rs485]\nmode = \"rts\"\necho = true"
        ));
        assert_eq!(
            e,
            [
                "bus[0].rs485.mode: a simulated line has no transceiver to drive: only \"off\"",
                "bus[0].rs485.echo: a simulated line does not echo",
                "bus[0].latency_timer: a simulated line has no USB adapter",
            ]
        );
        assert!(Config::from_toml_str(&format!("{SIM}[bus.rs485]\nmode = \"off\"")).is_ok());
    }

    #[test]
    fn a_latency_timer_outside_1_to_255_whole_milliseconds_is_refused() {
        for value in ["0s", "256ms", "1500us"] {
            let e = errors(&format!("{MINIMAL}\nlatency_timer = \"{value}\""));
            assert_eq!(
                e,
                ["bus[0].latency_timer: must be whole milliseconds, 1ms to 255ms"],
                "{value}"
            );
        }
        let c = Config::from_toml_str(&format!("{MINIMAL}\nlatency_timer = \"1ms\"")).unwrap();
        assert_eq!(
            c.bus[0].latency_timer,
            Some(std::time::Duration::from_millis(1))
        );
    }

    /// Echo is allowed without direction control; mode `rts` defaults to RTS high on send.
    #[test]
    fn echo_needs_no_direction_control_and_rts_mode_defaults_to_high_on_send() {
        let c = Config::from_toml_str(&format!(
            "{MINIMAL}\n[bus.rs485]\necho = true\n\
             [[bus]]\nname = \"b\"\ndevice = \"/dev/ttyS1\"\n[bus.rs485]\nmode = \"rts\""
        ))
        .unwrap();
        assert!(c.bus[0].rs485.echo);
        assert_eq!(c.bus[0].rs485.mode, Rs485Mode::Off);
        let rts = &c.bus[1].rs485;
        assert_eq!(rts.mode, Rs485Mode::Rts);
        assert!(rts.rts_on_send && !rts.rts_after_send);
        assert!(
            c.to_toml().contains("[bus.rs485]\nmode = \"rts\""),
            "{}",
            c.to_toml()
        );
    }
}
