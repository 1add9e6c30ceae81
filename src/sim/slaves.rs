//! The simulated slaves of one line by address, and what becomes of a request frame among them:
//! the one place a simulated slave hears a frame, for the simulated line and for the responder on
//! a real serial port alike, in the line's framing (RTU or ASCII). A frame whose check (CRC, LRC)
//! fails is ignored, as a slave must; a broadcast is carried out by every slave and answered by
//! none; any other frame goes to the slave at its address, whose answer, if any, the caller puts
//! on its wire. The slaves answer in the line's framing (see [`super::faults::Faulty`]).

use super::{Simulated, Transmission};
use crate::line::{Framing, BROADCAST};
use std::collections::BTreeMap;
use tokio::time::Instant;

/// What became of a request frame.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Heard {
    /// The CRC fails (or it is too short to be a frame): nobody acts on it.
    Corrupt,
    /// Every slave carried it out; nobody answers.
    Broadcast,
    /// No slave here has its address.
    NotHere,
    /// The slave at `address` acted on it and says nothing.
    Unanswered { address: u8, function: u8 },
    /// The slave at `address` answers with `reply`.
    Answered {
        address: u8,
        function: u8,
        reply: Transmission,
    },
}

/// The slaves on one line, by address, and the line's framing.
#[derive(Default)]
pub(crate) struct Slaves {
    slaves: BTreeMap<u8, Box<dyn Simulated>>,
    framing: Framing,
    /// The PDU of the frame being heard.
    pdu: Vec<u8>,
}

impl Slaves {
    /// No slaves yet, on a line of `framing`.
    pub(crate) fn new(framing: Framing) -> Self {
        Slaves {
            framing,
            ..Slaves::default()
        }
    }

    pub(crate) fn framing(&self) -> Framing {
        self.framing
    }

    /// Put `slave` at `address`, replacing any slave there.
    pub(crate) fn insert(&mut self, address: u8, slave: Box<dyn Simulated>) {
        self.slaves.insert(address, slave);
    }

    /// Hand `frame`, a whole request frame that ended on the wire at `at`, to the slaves.
    pub(crate) fn hear(&mut self, frame: &[u8], at: Instant) -> Heard {
        let Some(address) = self.framing.decode_into(frame, &mut self.pdu) else {
            return Heard::Corrupt;
        };
        let pdu = &self.pdu;
        if address == BROADCAST {
            for slave in self.slaves.values_mut() {
                slave.handle(BROADCAST, pdu, at);
            }
            return Heard::Broadcast;
        }
        let Some(slave) = self.slaves.get_mut(&address) else {
            return Heard::NotHere;
        };
        let function = pdu[0];
        match slave.handle(address, pdu, at) {
            Some(reply) => Heard::Answered {
                address,
                function,
                reply,
            },
            None => Heard::Unanswered { address, function },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::{ascii, rtu};
    use crate::sim::faults::{Faults, Faulty};
    use crate::sim::RegisterBank;
    use std::time::Duration;

    fn slaves() -> Slaves {
        let mut slaves = Slaves::default();
        slaves.insert(1, Box::new(RegisterBank::new(Duration::ZERO)));
        slaves.insert(2, Box::new(RegisterBank::new(Duration::ZERO)));
        slaves
    }

    #[test]
    fn a_broadcast_write_is_carried_out_by_every_slave_and_answered_by_none() {
        let mut slaves = slaves();
        let now = Instant::now();
        let write = rtu::encode(BROADCAST, &[0x06, 0x00, 0x03, 0x12, 0x34]);
        assert_eq!(slaves.hear(&write, now), Heard::Broadcast);
        let read = [0x03, 0x00, 0x03, 0x00, 0x01];
        for address in [1, 2] {
            let Heard::Answered { reply, .. } = slaves.hear(&rtu::encode(address, &read), now)
            else {
                panic!("slave {address} does not answer");
            };
            assert_eq!(reply.bytes, rtu::encode(address, &[0x03, 0x02, 0x12, 0x34]));
        }
    }

    #[test]
    fn a_bad_crc_or_a_foreign_address_gets_nothing() {
        let mut slaves = slaves();
        let now = Instant::now();
        let mut bad = rtu::encode(1, &[0x03, 0x00, 0x00, 0x00, 0x01]);
        bad[2] ^= 0x01;
        assert_eq!(slaves.hear(&bad, now), Heard::Corrupt);
        assert_eq!(slaves.hear(&[0x01, 0x03], now), Heard::Corrupt);
        let other = rtu::encode(9, &[0x03, 0x00, 0x00, 0x00, 0x01]);
        assert_eq!(slaves.hear(&other, now), Heard::NotHere);
    }

    #[test]
    fn on_an_ascii_line_the_slaves_hear_ascii_and_answer_in_ascii() {
        let mut slaves = Slaves::new(Framing::Ascii);
        let bank = RegisterBank::new(Duration::ZERO);
        let slave = Faulty::framed(bank, Faults::default(), 1, Framing::Ascii);
        slaves.insert(1, Box::new(slave));
        let now = Instant::now();
        let write = ascii::encode(1, &[0x06, 0x00, 0x04, 0x13, 0x88]);
        let Heard::Answered { reply, .. } = slaves.hear(&write, now) else {
            panic!("no answer to an ASCII write");
        };
        assert_eq!(reply.bytes, b":0106000413885A\r\n");
        let read = b":010300040002F6\r\n";
        let Heard::Answered { reply, .. } = slaves.hear(read, now) else {
            panic!("no answer to an ASCII read");
        };
        assert_eq!(reply.bytes, b":010304138800005D\r\n");
        let rtu_read = rtu::encode(1, &[0x03, 0x00, 0x04, 0x00, 0x02]);
        assert_eq!(
            slaves.hear(&rtu_read, now),
            Heard::Corrupt,
            "RTU on an ASCII line"
        );
    }
}
