//! Fault knobs for any simulated slave, so timeouts, late replies and noise can be tested without
//! hardware: a slave that is offline, slow, late, corrupts its CRC, wraps its reply in garbage,
//! answers with the wrong address or function code, stops its reply short or pauses in the middle
//! of it. Wraps a model and bends what it puts on the wire; the model
//! itself stays correct. On an ASCII line it also puts the model's replies, which are RTU frames,
//! into ASCII first, and the knobs bend the ASCII: a CRC error becomes an LRC error, garbage and
//! cuts count characters. Random choices come from a generator seeded by the slave's address, so
//! a run repeats exactly.

use super::{Pause, Simulated, Transmission};
use crate::config;
use crate::line::{ascii, Framing, BROADCAST};
use crate::pdu::EXCEPTION_BIT;
use std::time::Duration;
use tokio::time::Instant;

/// What is wrong with a slave. The default is nothing.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Faults {
    /// Never answers and carries nothing out, as if unpowered or disconnected.
    pub offline: bool,
    /// Added to every reply's delay.
    pub extra_delay: Duration,
    /// Every reply starts this long after the slave recognised the request, whatever its own
    /// delay: set it past the gateway's response timeout to get replies that arrive late.
    pub late_reply: Option<Duration>,
    /// Fraction of replies (0 to 1) whose CRC is corrupted.
    pub crc_error_rate: f64,
    /// Random bytes sent straight before every reply, as part of the same transmission.
    pub garbage_before: usize,
    /// Random bytes sent straight after every reply.
    pub garbage_after: usize,
    /// Replies carry this address instead of the slave's own (with a valid CRC).
    pub reply_address: Option<u8>,
    /// Replies carry this function code instead of the request's (with a valid CRC); an
    /// exception reply keeps its exception bit.
    pub reply_function: Option<u8>,
    /// Only the first this many bytes of every reply are sent.
    pub truncate_reply: Option<usize>,
    /// Every reply stops after some bytes and goes on after a silence.
    pub reply_gap: Option<Pause>,
}

/// The fault knobs of a configured simulated slave.
impl From<&config::SimSlave> for Faults {
    fn from(slave: &config::SimSlave) -> Self {
        Faults {
            offline: slave.offline,
            extra_delay: slave.extra_delay,
            late_reply: slave.late_reply,
            crc_error_rate: slave.crc_error_rate,
            garbage_before: slave.garbage_before,
            garbage_after: slave.garbage_after,
            reply_address: slave.reply_address,
            reply_function: slave.reply_function,
            truncate_reply: slave.truncate_reply,
            reply_gap: slave
                .reply_gap
                .zip(slave.reply_gap_after)
                .map(|(gap, after)| Pause { after, gap }),
        }
    }
}

impl Faults {
    pub fn is_none(&self) -> bool {
        *self == Faults::default()
    }
}

/// A slave with [`Faults`], on a line of some framing.
pub struct Faulty<S> {
    inner: S,
    faults: Faults,
    framing: Framing,
    rng: fastrand::Rng,
}

impl<S: Simulated> Faulty<S> {
    /// `inner` with `faults` on an RTU line.
    #[cfg(any(test, feature = "test-util"))]
    pub fn new(inner: S, faults: Faults, address: u8) -> Self {
        Self::framed(inner, faults, address, Framing::Rtu)
    }

    /// `inner` with `faults` on a line of `framing`.
    pub(crate) fn framed(inner: S, faults: Faults, address: u8, framing: Framing) -> Self {
        Faulty {
            inner,
            faults,
            framing,
            rng: fastrand::Rng::with_seed(u64::from(address)),
        }
    }

    /// Break the frame's check: the last CRC byte, or the last LRC character (MBAP has no check:
    /// its last byte).
    fn corrupt_check(&self, bytes: &mut [u8]) {
        let from_end = match self.framing {
            Framing::Rtu | Framing::Tcp => 1,
            Framing::Ascii => 1 + ascii::END.len(),
        };
        if let Some(at) = bytes.len().checked_sub(from_end) {
            bytes[at] ^= 0x01;
        }
    }

    fn garbage(&mut self, n: usize) -> impl Iterator<Item = u8> + '_ {
        (0..n).map(|_| self.rng.u8(..))
    }
}

impl<S: Simulated> Simulated for Faulty<S> {
    fn handle(&mut self, address: u8, request: &[u8], at: Instant) -> Option<Transmission> {
        if self.faults.offline {
            return None;
        }
        let mut reply = self.inner.handle(address, request, at)?;
        if address == BROADCAST {
            return Some(reply);
        }
        // The model's reply is an intact RTU frame: take its PDU, to frame again as the line
        // does and as the knobs want.
        if let Some(pdu) = reply.bytes.get(1..reply.bytes.len().saturating_sub(2)) {
            let address = self.faults.reply_address.unwrap_or(address);
            let mut pdu = pdu.to_vec();
            if let (Some(function), Some(wrong)) = (pdu.first_mut(), self.faults.reply_function) {
                *function = wrong | (*function & EXCEPTION_BIT);
            }
            self.framing.encode_into(&mut reply.bytes, 0, address, &pdu);
        }
        if self.faults.crc_error_rate > 0.0 && self.rng.f64() < self.faults.crc_error_rate {
            self.corrupt_check(&mut reply.bytes);
        }
        if let Some(keep) = self.faults.truncate_reply {
            reply.bytes.truncate(keep);
        }
        if self.faults.garbage_before > 0 || self.faults.garbage_after > 0 {
            let mut bytes: Vec<u8> = self.garbage(self.faults.garbage_before).collect();
            bytes.append(&mut reply.bytes);
            bytes.extend(self.garbage(self.faults.garbage_after).collect::<Vec<_>>());
            reply.bytes = bytes;
        }
        reply.delay = match self.faults.late_reply {
            Some(late) => late,
            None => reply.delay + self.faults.extra_delay,
        };
        reply.pause = reply.pause.or(self.faults.reply_gap);
        Some(reply)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::rtu;
    use crate::sim::RegisterBank;

    const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];
    const DELAY: Duration = Duration::from_millis(3);

    fn slave(faults: Faults) -> Faulty<RegisterBank> {
        Faulty::new(RegisterBank::new(DELAY), faults, 7)
    }

    fn answer(faults: Faults) -> Option<Transmission> {
        slave(faults).handle(7, &READ, Instant::now())
    }

    #[test]
    fn no_faults_leave_the_reply_alone() {
        let clean = RegisterBank::new(DELAY).handle(7, &READ, Instant::now());
        assert_eq!(answer(Faults::default()), clean);
    }

    #[test]
    fn an_offline_slave_neither_answers_nor_carries_out_writes() {
        let mut slave = slave(Faults {
            offline: true,
            ..Faults::default()
        });
        assert_eq!(slave.handle(7, &[0x06, 0, 0, 0, 9], Instant::now()), None);
        assert_eq!(slave.inner.respond(7, &READ), Ok(vec![0x03, 0x02, 0, 0]));
    }

    #[test]
    fn delays_add_up_unless_the_reply_is_late() {
        let extra = Duration::from_millis(40);
        let slow = answer(Faults {
            extra_delay: extra,
            ..Faults::default()
        });
        assert_eq!(slow.unwrap().delay, DELAY + extra);
        let late = answer(Faults {
            extra_delay: extra,
            late_reply: Some(Duration::from_secs(2)),
            ..Faults::default()
        });
        assert_eq!(late.unwrap().delay, Duration::from_secs(2));
    }

    #[test]
    fn a_wrong_address_comes_with_a_valid_crc() {
        let reply = answer(Faults {
            reply_address: Some(9),
            ..Faults::default()
        })
        .unwrap();
        assert_eq!(reply.bytes[0], 9);
        assert!(rtu::crc_ok(&reply.bytes));
    }

    #[test]
    fn a_wrong_function_code_comes_with_a_valid_crc_and_exceptions_stay_exceptions() {
        let wrong = Faults {
            reply_function: Some(0x04),
            ..Faults::default()
        };
        let reply = answer(wrong.clone()).unwrap().bytes;
        assert_eq!(reply, rtu::encode(7, &[0x04, 0x02, 0x00, 0x00]));
        // 126 registers are more than a read may ask for: exception 03, now under function 04.
        let refused = slave(wrong)
            .handle(7, &[0x03, 0x00, 0x00, 0x00, 0x7E], Instant::now())
            .unwrap();
        assert_eq!(refused.bytes, rtu::encode(7, &[0x84, 0x03]));
    }

    #[test]
    fn a_truncated_reply_is_the_first_bytes_of_the_intact_one() {
        let clean = answer(Faults::default()).unwrap().bytes;
        let cut = answer(Faults {
            truncate_reply: Some(4),
            ..Faults::default()
        })
        .unwrap();
        assert_eq!(cut.bytes, clean[..4]);
        let longer = answer(Faults {
            truncate_reply: Some(100),
            ..Faults::default()
        });
        assert_eq!(longer.unwrap().bytes, clean, "nothing to cut");
    }

    #[test]
    fn a_reply_gap_is_handed_to_the_line_with_the_intact_reply() {
        let gap = Pause {
            after: 3,
            gap: Duration::from_millis(30),
        };
        let reply = answer(Faults {
            reply_gap: Some(gap),
            ..Faults::default()
        })
        .unwrap();
        assert_eq!(reply.pause, Some(gap));
        assert_eq!(reply.bytes, answer(Faults::default()).unwrap().bytes);
    }

    #[test]
    fn the_crc_error_rate_corrupts_that_share_of_replies_repeatably() {
        let faults = Faults {
            crc_error_rate: 0.25,
            ..Faults::default()
        };
        let run = || {
            let mut slave = slave(faults.clone());
            (0..400)
                .map(|_| rtu::crc_ok(&slave.handle(7, &READ, Instant::now()).unwrap().bytes))
                .collect::<Vec<_>>()
        };
        let first = run();
        let corrupt = first.iter().filter(|ok| !**ok).count();
        assert!((70..=130).contains(&corrupt), "{corrupt} of 400 corrupt");
        assert_eq!(first, run(), "the same seed gives the same run");
        let always = answer(Faults {
            crc_error_rate: 1.0,
            ..Faults::default()
        });
        assert!(!rtu::crc_ok(&always.unwrap().bytes));
    }

    #[test]
    fn garbage_surrounds_an_intact_frame() {
        let clean = answer(Faults::default()).unwrap().bytes;
        let noisy = answer(Faults {
            garbage_before: 3,
            garbage_after: 2,
            ..Faults::default()
        })
        .unwrap()
        .bytes;
        assert_eq!(noisy.len(), clean.len() + 5);
        assert_eq!(&noisy[3..noisy.len() - 2], &clean[..]);
    }

    #[test]
    fn broadcasts_stay_unanswered_whatever_the_faults() {
        let mut slave = slave(Faults {
            reply_address: Some(9),
            garbage_before: 4,
            ..Faults::default()
        });
        assert_eq!(
            slave.handle(BROADCAST, &[0x06, 0, 1, 0, 5], Instant::now()),
            None
        );
    }

    #[test]
    fn the_new_fault_knobs_reach_the_slave_and_read_back_the_same() {
        const SIM_BUS: &str =
            "[[bus]]\nname = \"sim\"\ndevice = \"sim\"\n[[bus.sim_slave]]\naddress = 2\n";
        let text = format!(
            "{SIM_BUS}reply_function = 4\ntruncate_reply = 5\nreply_gap = \"30ms\"\nreply_gap_after = 3\n"
        );
        let c = config::Config::from_toml_str(&text).unwrap();
        let faults = Faults::from(&c.bus[0].sim_slave[0]);
        assert_eq!(faults.reply_function, Some(4));
        assert_eq!(faults.truncate_reply, Some(5));
        assert_eq!(
            faults.reply_gap,
            Some(Pause {
                after: 3,
                gap: Duration::from_millis(30)
            })
        );
        assert_eq!(config::Config::from_toml_str(&c.to_toml()).unwrap(), c);
    }
}
