//! A plain simulated slave: four register banks and the standard function codes, answered per the
//! Modbus Application Protocol V1.1b3 (quantity limits, exception codes, broadcast writes).
//! Storage is sparse, so a line of 247 such slaves costs little.
//!
//! Contents: coils and holding registers start at 0 and keep what is written. Input register `a`
//! reads `a`, and discrete input `a` is on when `a` is odd, so tests know what to expect.

use super::{Simulated, Transmission};
use crate::pdu::code;
use crate::pdu::exception_pdu;
use crate::pdu::ExceptionCode::{self, IllegalDataAddress, IllegalDataValue, IllegalFunction};
use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;
use tokio::time::Instant;

/// FC 2B's MEI type for Read Device Identification.
const READ_DEVICE_ID: u8 = 0x0E;

const MAX_READ_BITS: usize = 2000;
const MAX_READ_REGISTERS: usize = 125;
const MAX_WRITE_BITS: usize = 1968;
const MAX_WRITE_REGISTERS: usize = 123;
const MAX_READ_WRITE_REGISTERS: usize = 121;

const VENDOR_NAME: &[u8] = b"modbus-gateway";
const PRODUCT_CODE: &[u8] = b"SIM-REGISTERS";
const REVISION: &[u8] = env!("CARGO_PKG_VERSION").as_bytes();

#[derive(Debug, Default)]
pub struct RegisterBank {
    coils: BTreeSet<u16>,
    holding: BTreeMap<u16, u16>,
    processing_delay: Duration,
}

type Reply = Result<Vec<u8>, ExceptionCode>;

fn word(pdu: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]))
}

/// Start address and quantity at bytes 1..5, checked against `max` and the end of the address space.
fn range(pdu: &[u8], max: usize) -> Result<(u16, usize), ExceptionCode> {
    let (start, quantity) = match (word(pdu, 1), word(pdu, 3)) {
        (Some(start), Some(quantity)) => (start, usize::from(quantity)),
        _ => return Err(IllegalDataValue),
    };
    if quantity == 0 || quantity > max {
        return Err(IllegalDataValue);
    }
    if usize::from(start) + quantity > 0x1_0000 {
        return Err(IllegalDataAddress);
    }
    Ok((start, quantity))
}

fn addresses(start: u16, quantity: usize) -> impl Iterator<Item = u16> {
    // `range` has checked that start + quantity fits the address space, so every offset is a u16.
    (0..quantity).map_while(move |i| u16::try_from(i).ok().map(|i| start.wrapping_add(i)))
}

fn pack_bits(bits: impl Iterator<Item = bool>, quantity: usize) -> Vec<u8> {
    let mut bytes = vec![0u8; quantity.div_ceil(8)];
    for (i, on) in bits.enumerate() {
        if on {
            bytes[i / 8] |= 1 << (i % 8);
        }
    }
    bytes
}

/// The quantity limits keep every reply's data under 256 bytes; were one not to, the request
/// asked for too much.
fn with_count(function: u8, data: Vec<u8>) -> Reply {
    let count = u8::try_from(data.len()).map_err(|_| IllegalDataValue)?;
    let mut reply = Vec::with_capacity(data.len() + 2);
    reply.push(function);
    reply.push(count);
    reply.extend(data);
    Ok(reply)
}

fn input_register(address: u16) -> u16 {
    address
}

fn discrete_input(address: u16) -> bool {
    address % 2 == 1
}

impl RegisterBank {
    pub fn new(processing_delay: Duration) -> Self {
        RegisterBank {
            processing_delay,
            ..RegisterBank::default()
        }
    }

    fn holding(&self, address: u16) -> u16 {
        self.holding.get(&address).copied().unwrap_or(0)
    }

    fn set_holding(&mut self, address: u16, value: u16) {
        if value == 0 {
            self.holding.remove(&address);
        } else {
            self.holding.insert(address, value);
        }
    }

    fn set_coil(&mut self, address: u16, on: bool) {
        if on {
            self.coils.insert(address);
        } else {
            self.coils.remove(&address);
        }
    }

    fn read_registers(&self, pdu: &[u8], read: impl Fn(&Self, u16) -> u16) -> Reply {
        let (start, quantity) = range(pdu, MAX_READ_REGISTERS)?;
        let data = addresses(start, quantity)
            .flat_map(|a| read(self, a).to_be_bytes())
            .collect();
        with_count(pdu[0], data)
    }

    fn read_bits(&self, pdu: &[u8], read: impl Fn(&Self, u16) -> bool) -> Reply {
        let (start, quantity) = range(pdu, MAX_READ_BITS)?;
        let bits = addresses(start, quantity).map(|a| read(self, a));
        with_count(pdu[0], pack_bits(bits, quantity))
    }

    fn write_coil(&mut self, pdu: &[u8]) -> Reply {
        let (Some(address), Some(value)) = (word(pdu, 1), word(pdu, 3)) else {
            return Err(IllegalDataValue);
        };
        match value {
            0xFF00 => self.set_coil(address, true),
            0x0000 => self.set_coil(address, false),
            _ => return Err(IllegalDataValue),
        }
        Ok(pdu[..5].to_vec())
    }

    fn write_register(&mut self, pdu: &[u8]) -> Reply {
        let (Some(address), Some(value)) = (word(pdu, 1), word(pdu, 3)) else {
            return Err(IllegalDataValue);
        };
        self.set_holding(address, value);
        Ok(pdu[..5].to_vec())
    }

    fn write_coils(&mut self, pdu: &[u8]) -> Reply {
        let (start, quantity) = range(pdu, MAX_WRITE_BITS)?;
        let values = pdu.get(6..).ok_or(IllegalDataValue)?;
        if usize::from(pdu[5]) != quantity.div_ceil(8) || values.len() != usize::from(pdu[5]) {
            return Err(IllegalDataValue);
        }
        for (i, address) in addresses(start, quantity).enumerate() {
            self.set_coil(address, values[i / 8] & (1 << (i % 8)) != 0);
        }
        Ok(pdu[..5].to_vec())
    }

    fn write_registers_at(
        &mut self,
        start: u16,
        quantity: usize,
        values: &[u8],
    ) -> Result<(), ExceptionCode> {
        if values.len() != quantity * 2 {
            return Err(IllegalDataValue);
        }
        for (address, value) in addresses(start, quantity).zip(values.chunks_exact(2)) {
            self.set_holding(address, u16::from_be_bytes([value[0], value[1]]));
        }
        Ok(())
    }

    fn write_registers(&mut self, pdu: &[u8]) -> Reply {
        let (start, quantity) = range(pdu, MAX_WRITE_REGISTERS)?;
        let count = *pdu.get(5).ok_or(IllegalDataValue)?;
        if usize::from(count) != quantity * 2 {
            return Err(IllegalDataValue);
        }
        self.write_registers_at(start, quantity, &pdu[6..])?;
        Ok(pdu[..5].to_vec())
    }

    fn mask_write_register(&mut self, pdu: &[u8]) -> Reply {
        let (Some(address), Some(and), Some(or)) = (word(pdu, 1), word(pdu, 3), word(pdu, 5))
        else {
            return Err(IllegalDataValue);
        };
        let current = self.holding(address);
        self.set_holding(address, (current & and) | (or & !and));
        Ok(pdu[..7].to_vec())
    }

    fn read_write_registers(&mut self, pdu: &[u8]) -> Reply {
        let (read_start, read_quantity) = range(pdu, MAX_READ_REGISTERS)?;
        let (write_start, write_quantity) = range(&pdu[4..], MAX_READ_WRITE_REGISTERS)?;
        let count = *pdu.get(9).ok_or(IllegalDataValue)?;
        if usize::from(count) != write_quantity * 2 {
            return Err(IllegalDataValue);
        }
        // The spec performs the write before the read.
        self.write_registers_at(write_start, write_quantity, &pdu[10..])?;
        let data = addresses(read_start, read_quantity)
            .flat_map(|a| self.holding(a).to_be_bytes())
            .collect();
        with_count(pdu[0], data)
    }

    fn diagnostics(&self, pdu: &[u8]) -> Reply {
        match word(pdu, 1) {
            // Return query data: the request comes back unchanged.
            Some(0x0000) => Ok(pdu.to_vec()),
            _ => Err(IllegalFunction),
        }
    }

    fn report_server_id(&self, address: u8) -> Reply {
        let mut data = vec![address, 0xFF];
        data.extend_from_slice(PRODUCT_CODE);
        with_count(code::REPORT_SERVER_ID, data)
    }

    fn read_device_identification(&self, pdu: &[u8]) -> Reply {
        let objects: [&[u8]; 3] = [VENDOR_NAME, PRODUCT_CODE, REVISION];
        let (Some(&read_code), Some(&object_id)) = (pdu.get(2), pdu.get(3)) else {
            return Err(IllegalDataValue);
        };
        let wanted: Vec<u8> = match read_code {
            // Basic stream: every object from the one asked for.
            0x01 => (object_id..3).collect(),
            0x04 if usize::from(object_id) < objects.len() => vec![object_id],
            0x04 => return Err(IllegalDataAddress),
            _ => return Err(IllegalDataValue),
        };
        let count = u8::try_from(wanted.len()).map_err(|_| IllegalDataValue)?;
        let mut reply = vec![
            code::ENCAPSULATED_INTERFACE,
            READ_DEVICE_ID,
            read_code,
            0x01,
            0x00,
            0x00,
            count,
        ];
        for id in wanted {
            let value = objects[usize::from(id)];
            reply.push(id);
            reply.push(u8::try_from(value.len()).map_err(|_| IllegalDataValue)?);
            reply.extend_from_slice(value);
        }
        Ok(reply)
    }

    /// Answer a request PDU; `Err` carries the exception code.
    pub fn respond(&mut self, address: u8, pdu: &[u8]) -> Reply {
        let Some(&function) = pdu.first() else {
            return Err(IllegalFunction);
        };
        match function {
            code::READ_COILS => self.read_bits(pdu, |bank, a| bank.coils.contains(&a)),
            code::READ_DISCRETE_INPUTS => self.read_bits(pdu, |_, a| discrete_input(a)),
            code::READ_HOLDING_REGISTERS => self.read_registers(pdu, RegisterBank::holding),
            code::READ_INPUT_REGISTERS => self.read_registers(pdu, |_, a| input_register(a)),
            code::WRITE_SINGLE_COIL => self.write_coil(pdu),
            code::WRITE_SINGLE_REGISTER => self.write_register(pdu),
            code::READ_EXCEPTION_STATUS => Ok(vec![code::READ_EXCEPTION_STATUS, 0x00]),
            code::DIAGNOSTICS => self.diagnostics(pdu),
            code::WRITE_MULTIPLE_COILS => self.write_coils(pdu),
            code::WRITE_MULTIPLE_REGISTERS => self.write_registers(pdu),
            code::REPORT_SERVER_ID => self.report_server_id(address),
            code::MASK_WRITE_REGISTER => self.mask_write_register(pdu),
            code::READ_WRITE_MULTIPLE_REGISTERS => self.read_write_registers(pdu),
            code::ENCAPSULATED_INTERFACE if pdu.get(1) == Some(&READ_DEVICE_ID) => {
                self.read_device_identification(pdu)
            }
            _ => Err(IllegalFunction),
        }
    }
}

impl Simulated for RegisterBank {
    fn handle(&mut self, address: u8, request: &[u8], _at: Instant) -> Option<Transmission> {
        let reply = self.respond(address, request);
        if address == crate::line::BROADCAST {
            return None;
        }
        let function = request.first().copied().unwrap_or(0);
        let pdu = reply.unwrap_or_else(|e| exception_pdu(function, e).to_vec());
        Some(Transmission::frame(address, &pdu, self.processing_delay))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::rtu;

    fn bank() -> RegisterBank {
        RegisterBank::new(Duration::ZERO)
    }

    #[test]
    fn holding_registers_keep_what_is_written() {
        let mut b = bank();
        assert_eq!(
            b.respond(1, &[0x06, 0x00, 0x04, 0x13, 0x88]),
            Ok(vec![0x06, 0x00, 0x04, 0x13, 0x88])
        );
        assert_eq!(
            b.respond(1, &[0x10, 0x00, 0x05, 0x00, 0x01, 0x02, 0x00, 0x32]),
            Ok(vec![0x10, 0x00, 0x05, 0x00, 0x01])
        );
        assert_eq!(
            b.respond(1, &[0x03, 0x00, 0x04, 0x00, 0x02]),
            Ok(vec![0x03, 0x04, 0x13, 0x88, 0x00, 0x32])
        );
    }

    #[test]
    fn input_registers_and_discrete_inputs_follow_their_address() {
        let mut b = bank();
        assert_eq!(
            b.respond(1, &[0x04, 0x01, 0x00, 0x00, 0x02]),
            Ok(vec![0x04, 0x04, 0x01, 0x00, 0x01, 0x01])
        );
        // Inputs 0..9: odd ones on -> 0b1010_1010, 0b10.
        assert_eq!(
            b.respond(1, &[0x02, 0x00, 0x00, 0x00, 0x0A]),
            Ok(vec![0x02, 0x02, 0xAA, 0x02])
        );
    }

    #[test]
    fn coils_pack_lsb_first() {
        let mut b = bank();
        assert_eq!(
            b.respond(1, &[0x05, 0x00, 0x02, 0xFF, 0x00]),
            Ok(vec![0x05, 0x00, 0x02, 0xFF, 0x00])
        );
        assert_eq!(
            b.respond(1, &[0x0F, 0x00, 0x08, 0x00, 0x02, 0x01, 0x03]),
            Ok(vec![0x0F, 0x00, 0x08, 0x00, 0x02])
        );
        assert_eq!(
            b.respond(1, &[0x01, 0x00, 0x00, 0x00, 0x0A]),
            Ok(vec![0x01, 0x02, 0x04, 0x03])
        );
        assert_eq!(
            b.respond(1, &[0x05, 0x00, 0x02, 0x12, 0x34]),
            Err(IllegalDataValue)
        );
    }

    #[test]
    fn mask_write_and_read_write_follow_the_spec_examples() {
        let mut b = bank();
        b.respond(1, &[0x06, 0x00, 0x04, 0x00, 0x12]).unwrap();
        // Spec 6.16: current 0x12, AND 0xF2, OR 0x25 -> 0x17.
        b.respond(1, &[0x16, 0x00, 0x04, 0x00, 0xF2, 0x00, 0x25])
            .unwrap();
        assert_eq!(b.holding(4), 0x17);
        assert_eq!(
            b.respond(
                1,
                &[0x17, 0x00, 0x04, 0x00, 0x01, 0x00, 0x04, 0x00, 0x01, 0x02, 0xAB, 0xCD]
            ),
            Ok(vec![0x17, 0x02, 0xAB, 0xCD])
        );
    }

    #[test]
    fn misuse_gets_the_spec_exception() {
        let mut b = bank();
        assert_eq!(
            b.respond(1, &[0x03, 0x00, 0x00, 0x00, 0x7E]),
            Err(IllegalDataValue)
        );
        assert_eq!(
            b.respond(1, &[0x03, 0x00, 0x00, 0x00, 0x00]),
            Err(IllegalDataValue)
        );
        assert_eq!(
            b.respond(1, &[0x03, 0xFF, 0xFF, 0x00, 0x02]),
            Err(IllegalDataAddress)
        );
        assert_eq!(
            b.respond(1, &[0x10, 0x00, 0x00, 0x00, 0x02, 0x02, 0, 1]),
            Err(IllegalDataValue)
        );
        assert_eq!(b.respond(1, &[0x41, 0x01]), Err(IllegalFunction));
        assert_eq!(
            b.respond(1, &[0x08, 0x00, 0x01, 0x00, 0x00]),
            Err(IllegalFunction)
        );
        assert_eq!(b.respond(1, &[0x03]), Err(IllegalDataValue));
    }

    #[test]
    fn identification_answers_report_server_id_and_device_id() {
        let mut b = bank();
        let id = b.respond(7, &[0x11]).unwrap();
        assert_eq!(
            &id[..4],
            &[0x11, 2 + u8::try_from(PRODUCT_CODE.len()).unwrap(), 7, 0xFF]
        );
        let device = b.respond(7, &[0x2B, 0x0E, 0x04, 0x01]).unwrap();
        assert_eq!(
            &device[..9],
            &[
                0x2B,
                0x0E,
                0x04,
                0x01,
                0x00,
                0x00,
                0x01,
                0x01,
                u8::try_from(PRODUCT_CODE.len()).unwrap()
            ]
        );
        let framed = rtu::encode(7, &device);
        assert_eq!(
            rtu::reply_len(&framed, 7, &[0x2B, 0x0E, 0x04, 0x01]),
            rtu::FrameLen::Exact(framed.len())
        );
    }

    #[test]
    fn broadcast_writes_are_applied_and_never_answered() {
        let mut b = bank();
        let now = Instant::now();
        assert_eq!(b.handle(0, &[0x06, 0x00, 0x01, 0x00, 0x09], now), None);
        assert_eq!(b.holding(1), 9);
        let answer = b.handle(3, &[0x03, 0x00, 0x01, 0x00, 0x01], now).unwrap();
        assert_eq!(answer.bytes, rtu::encode(3, &[0x03, 0x02, 0x00, 0x09]));
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;

        const FUNCTIONS: [u8; 12] = [
            0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x08, 0x0F, 0x10, 0x16, 0x17, 0x2B,
        ];

        /// Mostly a known function, then the words it takes (an address, then quantities or
        /// values, near their limits), a byte count and as many data bytes as the last word asks
        /// for, so the handlers run past their first check.
        fn request() -> impl Strategy<Value = Vec<u8>> {
            let function = prop_oneof![3 => prop::sample::select(&FUNCTIONS[..]), 1 => any::<u8>()];
            let shaped = function.prop_flat_map(|function| {
                let words = match function {
                    0x08 => 1..=1,
                    0x01..=0x06 | 0x0F | 0x10 | 0x2B => 2..=2,
                    0x16 => 3..=3,
                    0x17 => 4..=4,
                    _ => 1..=4,
                };
                let address = prop_oneof![0u16..=8, 0x0E00u16..=0x0E04, 0xFFF0u16.., any::<u16>()];
                // Quantities at the spec's limits, and the value that switches a coil on.
                let edges = vec![0u16, 121, 123, 126, 1968, 1969, 2000, 2001, 0xFF00];
                let quantity = prop_oneof![
                    3 => 1u16..=125,
                    1 => prop::sample::select(edges),
                    1 => any::<u16>(),
                ];
                let more = words.start() - 1..=words.end() - 1;
                (
                    Just(function),
                    address,
                    prop::collection::vec(quantity, more),
                )
            });
            let shaped = shaped.prop_flat_map(|(function, address, mut words)| {
                words.insert(0, address);
                let last = usize::from(words[words.len() - 1]);
                let fitting = prop::sample::select(vec![last * 2, last.div_ceil(8)]);
                let len = prop_oneof![1 => 0usize..12, 3 => fitting];
                let cut = prop_oneof![3 => Just(0usize), 1 => 1usize..3];
                (len, prop::bool::weighted(0.75), cut).prop_flat_map(move |(len, counted, cut)| {
                    let words = words.clone();
                    prop::collection::vec(any::<u8>(), len.min(240)).prop_map(move |data| {
                        let mut pdu = vec![function];
                        words.iter().for_each(|w| pdu.extend(w.to_be_bytes()));
                        if counted {
                            pdu.push(u8::try_from(data.len()).unwrap());
                        }
                        pdu.extend(data);
                        pdu.truncate(pdu.len().saturating_sub(cut));
                        pdu
                    })
                })
            });
            prop_oneof![3 => shaped, 1 => prop::collection::vec(any::<u8>(), 0..24)]
        }

        proptest! {
            #[test]
            fn every_answer_to_any_request_is_a_frame_the_master_reads_whole_and_accepts(
                requests in prop::collection::vec((request(), any::<bool>()), 1..16),
            ) {
                let mut b = bank();
                for (request, broadcast) in requests {
                    let address = if broadcast { crate::line::BROADCAST } else { 7 };
                    let answer = b.handle(address, &request, Instant::now());
                    prop_assert_eq!(answer.is_none(), broadcast, "{:02X?}", request);
                    let (Some(answer), false) = (answer, request.is_empty()) else {
                        continue;
                    };
                    let bytes = &answer.bytes;
                    prop_assert_eq!(
                        rtu::reply_len(bytes, 7, &request),
                        rtu::FrameLen::Exact(bytes.len()),
                        "{:02X?} -> {:02X?}", request, bytes
                    );
                    // A code with the exception bit is no request (the gateway never sends one),
                    // so nothing is its answer.
                    let expected = if request[0] & crate::pdu::EXCEPTION_BIT == 0 {
                        crate::line::Verdict::Answer
                    } else {
                        crate::line::Verdict::Foreign
                    };
                    prop_assert_eq!(
                        rtu::check_reply(bytes, 7, &request),
                        expected,
                        "{:02X?} -> {:02X?}", request, bytes
                    );
                }
            }
        }
    }
}
