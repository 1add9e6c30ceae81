//! RS-485 timing per Modbus over Serial Line V1.02 §2.5.1.1: character time from the serial
//! format, t1.5 and t3.5, and the fixed values above 19200 baud. Pure arithmetic over values.

use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Above this baud rate the spec fixes t1.5 and t3.5 instead of scaling them.
const FIXED_TIMING_ABOVE_BAUD: u32 = 19_200;
const FIXED_T15: Duration = Duration::from_micros(750);
const FIXED_T35: Duration = Duration::from_micros(1_750);
const NANOS_PER_SEC: u64 = 1_000_000_000;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Parity {
    None,
    Even,
    Odd,
}

impl Parity {
    /// Each parity, its word in the configuration and its letter in `8E1`: the one place they
    /// are spelled.
    const SPELLINGS: [(Parity, &'static str, char); 3] = [
        (Parity::None, "none", 'N'),
        (Parity::Even, "even", 'E'),
        (Parity::Odd, "odd", 'O'),
    ];

    fn spelling(self) -> (&'static str, char) {
        let row = Self::SPELLINGS.iter().find(|(parity, ..)| *parity == self);
        row.map_or(("none", 'N'), |&(_, name, letter)| (name, letter))
    }

    /// As the configuration writes it: `none`, `even` or `odd`.
    pub fn name(self) -> &'static str {
        self.spelling().0
    }

    /// As a serial format writes it: `N`, `E` or `O`.
    pub fn letter(self) -> char {
        self.spelling().1
    }
}

impl Serialize for Parity {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for Parity {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        let row = Parity::SPELLINGS.iter().find(|(_, name, _)| *name == text);
        row.map(|&(parity, ..)| parity)
            .ok_or_else(|| serde::de::Error::custom(format!("`{text}` is not none, even or odd")))
    }
}

/// How characters are framed on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SerialFormat {
    pub baud: u32,
    pub data_bits: u8,
    pub parity: Parity,
    pub stop_bits: u8,
}

/// As the manuals write it: `9600 baud 8E1`.
impl std::fmt::Display for SerialFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} baud {}{}{}",
            self.baud,
            self.data_bits,
            self.parity.letter(),
            self.stop_bits
        )
    }
}

impl SerialFormat {
    /// Start bit, data bits, parity bit if any, stop bits.
    pub(crate) fn bits_per_char(&self) -> u32 {
        1 + u32::from(self.data_bits)
            + u32::from(self.parity != Parity::None)
            + u32::from(self.stop_bits)
    }
}

/// The times a line at a given format imposes on every frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LineTiming {
    /// Time one character occupies the wire.
    pub char_time: Duration,
    /// Longest silence allowed inside a frame.
    pub t15: Duration,
    /// Silence that separates frames.
    pub t35: Duration,
}

impl LineTiming {
    /// No wire: frames take no time (a Modbus TCP device's line).
    pub const NONE: LineTiming = LineTiming {
        char_time: Duration::ZERO,
        t15: Duration::ZERO,
        t35: Duration::ZERO,
    };

    pub fn new(format: &SerialFormat) -> Self {
        let bits = u64::from(format.bits_per_char());
        let baud = u64::from(format.baud.max(1));
        let char_time = Duration::from_nanos(bits * NANOS_PER_SEC / baud);
        let (t15, t35) = if format.baud > FIXED_TIMING_ABOVE_BAUD {
            (FIXED_T15, FIXED_T35)
        } else {
            // 1.5 and 3.5 character times, computed from the exact ratio rather than the
            // rounded character time.
            (
                Duration::from_nanos(bits * 3 * NANOS_PER_SEC / (2 * baud)),
                Duration::from_nanos(bits * 7 * NANOS_PER_SEC / (2 * baud)),
            )
        };
        LineTiming {
            char_time,
            t15,
            t35,
        }
    }

    /// Time `bytes` characters occupy the wire, back to back.
    pub fn frame_time(&self, bytes: usize) -> Duration {
        self.char_time * u32::try_from(bytes).unwrap_or(u32::MAX)
    }

    /// The physical minimum of one transaction (docs/performance.md, the yardstick): request and
    /// reply on the wire, the slave's turnaround, and the t3.5 before the next request.
    pub fn transaction_minimum(
        &self,
        request_bytes: usize,
        reply_bytes: usize,
        slave_turnaround: Duration,
    ) -> Duration {
        self.frame_time(request_bytes + reply_bytes) + slave_turnaround + self.t35
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_parity_reads_back_from_its_word_and_shows_its_letter_in_the_format() {
        for (parity, word, letter) in [
            (Parity::None, "none", "8N2"),
            (Parity::Even, "even", "8E1"),
            (Parity::Odd, "odd", "8O1"),
        ] {
            let text = toml::to_string(
                &[("parity", parity)]
                    .into_iter()
                    .collect::<std::collections::BTreeMap<_, _>>(),
            )
            .unwrap();
            assert_eq!(text.trim(), format!("parity = \"{word}\""));
            let back: std::collections::BTreeMap<String, Parity> = toml::from_str(&text).unwrap();
            assert_eq!(back["parity"], parity);
            let stop_bits = if parity == Parity::None { 2 } else { 1 };
            let shown = format(9600, parity, stop_bits).to_string();
            assert_eq!(shown, format!("9600 baud {letter}"));
        }
        let refused =
            toml::from_str::<std::collections::BTreeMap<String, Parity>>("parity = \"mark\"");
        assert!(refused
            .unwrap_err()
            .to_string()
            .contains("`mark` is not none, even or odd"));
    }

    fn format(baud: u32, parity: Parity, stop_bits: u8) -> SerialFormat {
        SerialFormat {
            baud,
            data_bits: 8,
            parity,
            stop_bits,
        }
    }

    #[test]
    fn t35_at_19200_8n2_is_2_005_ms_as_the_spec_says() {
        let t = LineTiming::new(&format(19_200, Parity::None, 2));
        assert_eq!(t.t35.as_micros(), 2_005);
        assert_eq!(t.char_time.as_nanos(), 572_916);
    }

    #[test]
    fn a_9600_8e1_character_is_11_bits_long() {
        let f = format(9_600, Parity::Even, 1);
        assert_eq!(f.bits_per_char(), 11);
        let t = LineTiming::new(&f);
        assert_eq!(t.char_time.as_nanos(), 1_145_833);
        assert_eq!(t.t35.as_nanos(), 4_010_416);
        assert_eq!(t.t15.as_nanos(), 1_718_750);
        assert_eq!(t.frame_time(8), t.char_time * 8);
        // Read 10 registers from a slave that answers t3.5 after the request.
        assert_eq!(
            t.transaction_minimum(8, 25, t.t35),
            t.char_time * 33 + t.t35 * 2
        );
    }

    #[test]
    fn above_19200_baud_the_gaps_are_fixed() {
        let t = LineTiming::new(&format(115_200, Parity::None, 1));
        assert_eq!(t.t15, Duration::from_micros(750));
        assert_eq!(t.t35, Duration::from_micros(1_750));
        assert_eq!(t.char_time.as_nanos(), 86_805);
    }

    #[test]
    fn at_exactly_19200_baud_the_gaps_still_scale() {
        let t = LineTiming::new(&format(19_200, Parity::Even, 1));
        assert!(t.t35 > Duration::from_micros(1_750));
    }
}
