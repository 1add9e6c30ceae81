//! RTU frames as bytes: CRC-16, encoding, how long a frame is from its first bytes (the PDU
//! lengths of [`crate::pdu`] plus the address and CRC), and whether a received frame answers a
//! given request (the CRC, then `crate::line::reply`). Pure functions; knows nothing of ports
//! or time.

#[cfg(test)]
use super::reply::Verdict;
use super::reply::{self, ReplyForm};
use crate::pdu::{self, PduLen};
use crc::{Crc, CRC_16_MODBUS};

const CRC: Crc<u16> = Crc::<u16>::new(&CRC_16_MODBUS);

/// The address before the PDU and the CRC after it.
const OVERHEAD: usize = 3;
/// Address, at most 253 bytes of PDU, two bytes of CRC.
pub const MAX_FRAME_LEN: usize = pdu::MAX_PDU_LEN + OVERHEAD;
/// Address, function code and CRC: nothing shorter is a frame.
pub const MIN_FRAME_LEN: usize = 1 + OVERHEAD;
/// Exception replies: address, function | 0x80, exception code, CRC.
#[cfg(any(test, feature = "test-util"))]
pub const EXCEPTION_FRAME_LEN: usize = pdu::EXCEPTION_PDU_LEN + OVERHEAD;

pub fn crc16(bytes: &[u8]) -> u16 {
    CRC.checksum(bytes)
}

/// Build the frame for `pdu` to `address` into `out` (cleared first). The CRC goes low byte first.
pub fn encode_into(out: &mut Vec<u8>, address: u8, pdu: &[u8]) {
    out.clear();
    out.push(address);
    out.extend_from_slice(pdu);
    let crc = crc16(out);
    out.extend_from_slice(&crc.to_le_bytes());
}

pub fn encode(address: u8, pdu: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(pdu.len() + OVERHEAD);
    encode_into(&mut out, address, pdu);
    out
}

/// True if the last two bytes are the CRC of the rest.
pub fn crc_ok(frame: &[u8]) -> bool {
    match frame.len().checked_sub(2) {
        Some(body) if frame.len() >= MIN_FRAME_LEN => {
            crc16(&frame[..body]) == u16::from_le_bytes([frame[body], frame[body + 1]])
        }
        _ => false,
    }
}

/// The PDU inside a frame whose CRC has been checked.
pub fn pdu_of(frame: &[u8]) -> &[u8] {
    &frame[1..frame.len() - 2]
}

/// What the first bytes of a frame say about its length.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameLen {
    /// The length is known once at least this many bytes are in.
    Need(usize),
    /// The frame is exactly this many bytes long.
    Exact(usize),
    /// The bytes cannot tell: the frame ends with t3.5 of silence.
    BySilence,
    /// The header announces more than a frame can hold: these bytes are not a frame.
    Invalid,
}

/// The frame around a PDU of `len`: one address byte before it, two CRC bytes after it.
fn frame_len(len: PduLen) -> FrameLen {
    match len {
        PduLen::Need(n) => FrameLen::Need(n + 1),
        PduLen::Exact(n) => FrameLen::Exact(n + OVERHEAD),
        PduLen::Unknown => FrameLen::BySilence,
        PduLen::Invalid => FrameLen::Invalid,
    }
}

/// Length of a reply frame starting at `buf[0]`, as far as its bytes tell. `slave` and `request`
/// (the PDU sent) settle the lengths that only the request knows, and only for a frame that
/// claims to answer it.
#[cfg(any(test, feature = "test-util"))]
pub fn reply_len(buf: &[u8], slave: u8, request: &[u8]) -> FrameLen {
    reply_len_as(buf, slave, request, ReplyForm::Standard)
}

/// [`reply_len`] for a slave whose replies take `form`.
pub fn reply_len_as(buf: &[u8], slave: u8, request: &[u8], form: ReplyForm) -> FrameLen {
    let Some(&function) = buf.get(1) else {
        return FrameLen::Need(2);
    };
    let answers_request = buf[0] == slave && request.first() == Some(&function);
    frame_len(reply::reply_len(
        &buf[1..],
        answers_request.then_some(request),
        form,
    ))
}

/// Length of a request frame starting at `buf[0]`, as a slave sees it.
pub fn request_len(buf: &[u8]) -> FrameLen {
    let Some(&function) = buf.get(1) else {
        return FrameLen::Need(2);
    };
    frame_len(
        pdu::function(function).map_or(PduLen::Unknown, |row| row.request.of(&buf[1..], None)),
    )
}

/// Judge a complete frame received after sending `request` (a PDU) to `slave`.
#[cfg(test)]
pub(crate) fn check_reply(frame: &[u8], slave: u8, request: &[u8]) -> Verdict {
    check_reply_as(frame, slave, request, ReplyForm::Standard)
}

/// The PDU of a frame that [`check_reply_as`] found to be the answer, in standard form.
#[cfg(test)]
pub(crate) fn answer_pdu(frame: &[u8], form: ReplyForm) -> Vec<u8> {
    reply::answer_pdu(pdu_of(frame), form)
}

/// [`check_reply`] for a slave whose replies take `form`.
#[cfg(test)]
pub(crate) fn check_reply_as(frame: &[u8], slave: u8, request: &[u8], form: ReplyForm) -> Verdict {
    if !crc_ok(frame) {
        return Verdict::Corrupt;
    }
    reply::judge(frame[0], pdu_of(frame), slave, request, form)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_late_echo_of_another_value_written_to_the_same_register_does_not_fit_the_write() {
        // Write 1388H to register 0004H; an earlier write of 0001H there is echoed late.
        let request = [0x06, 0x00, 0x04, 0x13, 0x88];
        let earlier = encode(2, &[0x06, 0x00, 0x04, 0x00, 0x01]);
        assert_eq!(check_reply(&earlier, 2, &request), Verdict::Malformed);
        assert_eq!(
            check_reply(&encode(2, &request), 2, &request),
            Verdict::Answer
        );
    }

    /// Goodrive300 manual 10.4.1: read 2 words from 0004H of slave 01H.
    const READ_REQUEST: [u8; 8] = [
        0x01, // slave address
        0x03, // read holding registers
        0x00, 0x04, // start address 0004H
        0x00, 0x02, // two words
        0x85, 0xCA, // CRC, low byte first
    ];
    /// Its reply: 0004H = 1388H, 0005H = 0000H.
    const READ_REPLY: [u8; 9] = [
        0x01, // slave address
        0x03, // read holding registers
        0x04, // four data bytes
        0x13, 0x88, // 0004H = 1388H (5000)
        0x00, 0x00, // 0005H = 0000H
        0x7E, 0x9D, // CRC
    ];
    /// Goodrive300 manual 10.4.2: write 1388H to 0004H of slave 02H; the reply is the echo.
    const WRITE_REQUEST: [u8; 8] = [
        0x02, // slave address
        0x06, // write single register
        0x00, 0x04, // register 0004H
        0x13, 0x88, // value 5000
        0xC5, 0x6E, // CRC
    ];
    /// Goodrive300 manual 10.4.3: diagnostics, return query data 12ABH to slave 01H.
    const ECHO_REQUEST: [u8; 8] = [
        0x01, // slave address
        0x08, // diagnostics
        0x00, 0x00, // sub-function 0000: return query data
        0x12, 0xAB, // data
        0xAD, 0x14, // CRC
    ];

    #[test]
    fn encoding_reproduces_the_manual_frames_byte_for_byte() {
        assert_eq!(encode(0x01, &READ_REQUEST[1..6]), READ_REQUEST);
        assert_eq!(encode(0x01, &READ_REPLY[1..7]), READ_REPLY);
        assert_eq!(encode(0x02, &WRITE_REQUEST[1..6]), WRITE_REQUEST);
        assert_eq!(encode(0x01, &ECHO_REQUEST[1..6]), ECHO_REQUEST);
    }

    #[test]
    fn the_manuals_fc10_example_carries_the_fc06_crc_by_mistake() {
        // Goodrive300 10.4.4 (and the GD20/GD10 manuals): write 1388H, 0032H to 0004H-0005H of
        // slave 02H, printed with CRC C5 6E, which belongs to the FC 06 example. Not a fixture.
        let printed = [
            0x02, 0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32, 0xC5, 0x6E,
        ];
        assert!(!crc_ok(&printed));
        let request = encode(0x02, &printed[1..11]);
        assert_eq!(&request[11..], &[0xF8, 0x63]);
        assert_eq!(
            encode(0x02, &[0x10, 0x00, 0x04, 0x00, 0x02]),
            [0x02, 0x10, 0x00, 0x04, 0x00, 0x02, 0x00, 0x3A]
        );
    }

    #[test]
    fn crc_rejects_any_flipped_bit_and_frames_too_short() {
        assert!(crc_ok(&READ_REPLY));
        for i in 0..READ_REPLY.len() {
            let mut bad = READ_REPLY;
            bad[i] ^= 0x10;
            assert!(!crc_ok(&bad), "flipped byte {i} passed");
        }
        assert!(!crc_ok(&[0x01, 0x03, 0x00]));
        assert!(!crc_ok(&[]));
    }

    #[test]
    fn reply_length_is_known_from_the_byte_count_byte_by_byte() {
        let request = &READ_REQUEST[1..6];
        assert_eq!(reply_len(&READ_REPLY[..0], 1, request), FrameLen::Need(2));
        assert_eq!(reply_len(&READ_REPLY[..1], 1, request), FrameLen::Need(2));
        assert_eq!(reply_len(&READ_REPLY[..2], 1, request), FrameLen::Need(3));
        for n in 3..=READ_REPLY.len() {
            assert_eq!(reply_len(&READ_REPLY[..n], 1, request), FrameLen::Exact(9));
        }
    }

    #[test]
    fn exception_replies_are_five_bytes_for_any_function() {
        assert_eq!(reply_len(&[0x01, 0x83], 1, &[0x03]), FrameLen::Exact(5));
        assert_eq!(reply_len(&[0x01, 0xC1], 1, &[0x41]), FrameLen::Exact(5));
    }

    #[test]
    fn fixed_length_replies() {
        for function in [0x05, 0x06, 0x0B, 0x0F, 0x10] {
            assert_eq!(
                reply_len(&[1, function], 1, &[function]),
                FrameLen::Exact(8)
            );
        }
        assert_eq!(reply_len(&[1, 0x07], 1, &[0x07]), FrameLen::Exact(5));
        assert_eq!(reply_len(&[1, 0x16], 1, &[0x16]), FrameLen::Exact(10));
    }

    #[test]
    fn diagnostics_replies_echo_the_request_length_only_when_they_answer_it() {
        let request = &ECHO_REQUEST[1..6];
        assert_eq!(
            reply_len(&ECHO_REQUEST[..2], 1, request),
            FrameLen::Exact(8)
        );
        assert_eq!(reply_len(&[0x05, 0x08], 1, request), FrameLen::BySilence);
    }

    #[test]
    fn fifo_replies_carry_a_two_byte_count() {
        assert_eq!(reply_len(&[1, 0x18, 0x00], 1, &[0x18]), FrameLen::Need(4));
        assert_eq!(
            reply_len(&[1, 0x18, 0x00, 0x06], 1, &[0x18]),
            FrameLen::Exact(12)
        );
        assert_eq!(
            reply_len(&[1, 0x18, 0x01, 0x00], 1, &[0x18]),
            FrameLen::Invalid
        );
    }

    #[test]
    fn device_identification_length_follows_its_objects() {
        // Reply header, then objects (id, length, value): "AB" and "C".
        let reply = [
            0x01, 0x2B, 0x0E, // slave, MEI transport, read device identification
            0x01, 0x01, // read code basic, conformity basic
            0x00, 0x00, // no more follows, next object 0
            0x02, // two objects
            0x00, 0x02, b'A', b'B', // object 0, two bytes
            0x01, 0x01, b'C', // object 1, one byte
        ];
        let request = [0x2B, 0x0E, 0x01, 0x00];
        assert_eq!(reply_len(&reply[..7], 1, &request), FrameLen::Need(8));
        assert_eq!(reply_len(&reply[..8], 1, &request), FrameLen::Need(10));
        assert_eq!(reply_len(&reply[..10], 1, &request), FrameLen::Need(14));
        assert_eq!(reply_len(&reply[..14], 1, &request), FrameLen::Exact(17));
        assert_eq!(reply_len(&reply, 1, &request), FrameLen::Exact(17));
    }

    #[test]
    fn user_defined_functions_end_by_silence() {
        assert_eq!(reply_len(&[1, 0x41, 9, 9], 1, &[0x41]), FrameLen::BySilence);
        assert_eq!(request_len(&[1, 0x41, 9]), FrameLen::BySilence);
    }

    #[test]
    fn byte_counts_past_the_frame_limit_are_invalid() {
        assert_eq!(reply_len(&[1, 0x03, 0xFF], 1, &[0x03]), FrameLen::Invalid);
        assert_eq!(
            reply_len(&[1, 0x03, 0xFB], 1, &[0x03]),
            FrameLen::Exact(256)
        );
    }

    #[test]
    fn request_lengths_as_a_slave_sees_them() {
        assert_eq!(request_len(&READ_REQUEST), FrameLen::Exact(8));
        assert_eq!(request_len(&[2, 0x10, 0, 4, 0, 2]), FrameLen::Need(7));
        assert_eq!(request_len(&[2, 0x10, 0, 4, 0, 2, 4]), FrameLen::Exact(13));
        assert_eq!(
            request_len(&[1, 0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2]),
            FrameLen::Exact(15)
        );
        assert_eq!(request_len(&[1, 0x2B, 0x0E]), FrameLen::Exact(7));
        assert_eq!(request_len(&[1, 0x11]), FrameLen::Exact(4));
        assert_eq!(request_len(&[1]), FrameLen::Need(2));
    }

    #[test]
    fn the_manual_reply_answers_its_request() {
        assert_eq!(
            check_reply(&READ_REPLY, 1, &READ_REQUEST[1..6]),
            Verdict::Answer
        );
        assert_eq!(
            check_reply(&WRITE_REQUEST, 2, &WRITE_REQUEST[1..6]),
            Verdict::Answer
        );
        assert_eq!(
            check_reply(&ECHO_REQUEST, 1, &ECHO_REQUEST[1..6]),
            Verdict::Answer
        );
    }

    #[test]
    fn another_slaves_frame_is_foreign() {
        assert_eq!(
            check_reply(&READ_REPLY, 2, &READ_REQUEST[1..6]),
            Verdict::Foreign
        );
    }

    #[test]
    fn a_reply_of_the_wrong_shape_is_malformed_and_of_the_wrong_function_foreign() {
        // Asked for three words; a two-word reply is a late answer to something else, or the
        // slave's own short answer.
        assert_eq!(
            check_reply(&READ_REPLY, 1, &[0x03, 0, 4, 0, 3]),
            Verdict::Malformed
        );
        // A write echo for another register.
        assert_eq!(
            check_reply(&WRITE_REQUEST, 2, &[0x06, 0x00, 0x05, 0x13, 0x88]),
            Verdict::Malformed
        );
        // A multiple write's echo of another quantity.
        let wrote_three = encode(2, &[0x10, 0x00, 0x04, 0x00, 0x03]);
        let request = [0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32];
        assert_eq!(check_reply(&wrote_three, 2, &request), Verdict::Malformed);
        // Asked for input registers; holding-register reply.
        assert_eq!(
            check_reply(&READ_REPLY, 1, &[0x04, 0, 4, 0, 2]),
            Verdict::Foreign
        );
    }

    #[test]
    fn exceptions_answer_only_their_own_function() {
        let exception = encode(1, &[0x83, 0x02]);
        assert_eq!(
            check_reply(&exception, 1, &[0x03, 0, 0, 0, 1]),
            Verdict::Answer
        );
        assert_eq!(
            check_reply(&exception, 1, &[0x04, 0, 0, 0, 1]),
            Verdict::Foreign
        );
        // Vendor exception codes pass as they are.
        let vendor = encode(1, &[0x86, 0x07]);
        assert_eq!(
            check_reply(&vendor, 1, &[0x06, 0, 0, 0, 1]),
            Verdict::Answer
        );
    }

    #[test]
    fn a_bad_crc_is_corrupt_whatever_else_it_says() {
        let mut bad = READ_REPLY;
        bad[4] ^= 0xFF;
        assert_eq!(check_reply(&bad, 1, &READ_REQUEST[1..6]), Verdict::Corrupt);
    }

    #[test]
    fn a_wide_read_count_is_read_whole_and_handed_on_in_standard_form() {
        let request = [0x03, 0x30, 0x00, 0x00, 0x02];
        let wide = encode(
            4,
            &[
                0x03, // read holding registers
                0x00, 0x04, // byte count as two bytes
                0x13, 0x88, 0x00, 0x32, // two words
            ],
        );
        let form = ReplyForm::WideReadCount;
        assert_eq!(
            reply_len_as(&wide[..2], 4, &request, form),
            FrameLen::Need(3)
        );
        assert_eq!(
            reply_len_as(&wide[..3], 4, &request, form),
            FrameLen::Need(4)
        );
        assert_eq!(
            reply_len_as(&wide[..4], 4, &request, form),
            FrameLen::Exact(10)
        );
        assert_eq!(check_reply_as(&wide, 4, &request, form), Verdict::Answer);
        assert_eq!(
            answer_pdu(&wide, form),
            [0x03, 0x04, 0x13, 0x88, 0x00, 0x32]
        );
        // The same slave switched to the standard form is still understood.
        let standard = encode(4, &[0x03, 0x04, 0x13, 0x88, 0x00, 0x32]);
        assert_eq!(
            reply_len_as(&standard, 4, &request, form),
            FrameLen::Exact(9)
        );
        assert_eq!(
            check_reply_as(&standard, 4, &request, form),
            Verdict::Answer
        );
        assert_eq!(answer_pdu(&standard, form), pdu_of(&standard));
        // Without the option the wide reply is a malformed frame, never an answer.
        assert_ne!(check_reply(&wide, 4, &request), Verdict::Answer);
        // A wide reply with the wrong count does not fit the request.
        let short = encode(4, &[0x03, 0x00, 0x02, 0x13, 0x88]);
        assert_eq!(
            check_reply_as(&short, 4, &request, form),
            Verdict::Malformed
        );
    }

    mod properties {
        use super::*;
        use crate::pdu::EXCEPTION_BIT;
        use proptest::prelude::*;

        /// A request PDU, a well-formed normal or exception reply PDU to it, and the form the
        /// slave replies in.
        #[derive(Clone, Debug)]
        struct Exchange {
            request: Vec<u8>,
            reply: Vec<u8>,
            form: ReplyForm,
        }

        impl Exchange {
            /// What the master on TCP gets: the reply in standard form.
            fn standard_reply(&self) -> Vec<u8> {
                match self.reply.as_slice() {
                    [0x03, 0x00, count, data @ ..] if self.form == ReplyForm::WideReadCount => {
                        [&[0x03, *count], data].concat()
                    }
                    reply => reply.to_vec(),
                }
            }
        }

        fn bytes(len: impl Into<prop::collection::SizeRange>) -> impl Strategy<Value = Vec<u8>> {
            prop::collection::vec(any::<u8>(), len)
        }

        fn form() -> impl Strategy<Value = ReplyForm> {
            prop_oneof![Just(ReplyForm::Standard), Just(ReplyForm::WideReadCount)]
        }

        /// `function`, then `fields` (address, quantity, ...) as big-endian words.
        fn pdu(function: u8, fields: &[u16]) -> Vec<u8> {
            let mut pdu = vec![function];
            fields.iter().for_each(|f| pdu.extend(f.to_be_bytes()));
            pdu
        }

        fn with_count(mut head: Vec<u8>, data: &[u8]) -> Vec<u8> {
            head.push(data.len() as u8);
            head.extend_from_slice(data);
            head
        }

        /// Normal replies for every function code whose reply length the frame layer knows.
        fn normal_exchange() -> impl Strategy<Value = Exchange> {
            let read_bits =
                (0x01u8..=0x02, any::<u16>(), 1u16..=2000).prop_flat_map(|(f, at, q)| {
                    bytes(usize::from(q).div_ceil(8))
                        .prop_map(move |data| (pdu(f, &[at, q]), with_count(vec![f], &data)))
                });
            let read_registers =
                (0x03u8..=0x04, any::<u16>(), 1u16..=125).prop_flat_map(|(f, at, q)| {
                    bytes(usize::from(q) * 2)
                        .prop_map(move |data| (pdu(f, &[at, q]), with_count(vec![f], &data)))
                });
            let write_single = (prop_oneof![Just(0x05u8), Just(0x06)], any::<[u16; 2]>())
                .prop_map(|(f, fields)| (pdu(f, &fields), pdu(f, &fields)));
            let status = (any::<u8>()).prop_map(|status| (vec![0x07], vec![0x07, status]));
            // Sub-functions with one data word have a length of their own (five bytes), which
            // other tests pin; these are the ones only silence ends.
            let by_silence = any::<u16>().prop_filter(
                "a sub-function with one data word",
                |s| !matches!(s, 0x0001..=0x0004 | 0x000A..=0x0012 | 0x0014),
            );
            let diagnostics = (by_silence, bytes(0..=250)).prop_map(|(sub, data)| {
                let echo = [pdu(0x08, &[sub]), data].concat();
                (echo.clone(), echo)
            });
            let event_counter =
                any::<[u16; 2]>().prop_map(|fields| (vec![0x0B], pdu(0x0B, &fields)));
            let counted_reply = (prop_oneof![Just(0x0Cu8), Just(0x11)], bytes(0..=251))
                .prop_map(|(f, data)| (vec![f], with_count(vec![f], &data)));
            let write_coils = (any::<u16>(), 1u16..=1968).prop_flat_map(|(at, q)| {
                bytes(usize::from(q).div_ceil(8)).prop_map(move |data| {
                    (with_count(pdu(0x0F, &[at, q]), &data), pdu(0x0F, &[at, q]))
                })
            });
            let write_registers = (any::<u16>(), 1u16..=123).prop_flat_map(|(at, q)| {
                bytes(usize::from(q) * 2).prop_map(move |data| {
                    (with_count(pdu(0x10, &[at, q]), &data), pdu(0x10, &[at, q]))
                })
            });
            let read_file = (
                prop::collection::vec(any::<[u16; 3]>(), 1..=35),
                bytes(0..=251),
            )
                .prop_map(|(records, data)| {
                    let sub: Vec<u8> = records.iter().flat_map(|r| pdu(0x06, r)).collect();
                    (with_count(vec![0x14], &sub), with_count(vec![0x14], &data))
                });
            let write_file = bytes(0..=251).prop_map(|data| {
                let echo = with_count(vec![0x15], &data);
                (echo.clone(), echo)
            });
            let mask_write =
                any::<[u16; 3]>().prop_map(|fields| (pdu(0x16, &fields), pdu(0x16, &fields)));
            let read_write =
                (any::<[u16; 2]>(), 1u16..=125, 1u16..=121).prop_flat_map(|(at, rq, wq)| {
                    (bytes(usize::from(rq) * 2), bytes(usize::from(wq) * 2)).prop_map(
                        move |(read, written)| {
                            let request = with_count(pdu(0x17, &[at[0], rq, at[1], wq]), &written);
                            (request, with_count(vec![0x17], &read))
                        },
                    )
                });
            let fifo = (any::<u16>(), prop::collection::vec(any::<u16>(), 0..=31)).prop_map(
                |(at, values)| {
                    let count = values.len() as u16;
                    let reply = [
                        pdu(0x18, &[2 + 2 * count, count]),
                        pdu(0, &values)[1..].to_vec(),
                    ]
                    .concat();
                    (pdu(0x18, &[at]), reply)
                },
            );
            let device_id = (
                any::<[u8; 6]>(),
                prop::collection::vec((any::<u8>(), bytes(0..60)), 0..8),
            )
                .prop_map(|(head, mut objects)| {
                    // Whole objects while the frame stays within 256 bytes.
                    let mut room = MAX_FRAME_LEN - 10;
                    objects.retain(|(_, value)| {
                        let fits = value.len() + 2 <= room;
                        room -= if fits { value.len() + 2 } else { 0 };
                        fits
                    });
                    let mut reply = vec![
                        0x2B,
                        0x0E,
                        head[0],
                        head[1],
                        head[2],
                        head[3],
                        objects.len() as u8,
                    ];
                    for (id, value) in &objects {
                        reply.push(*id);
                        reply.extend(with_count(vec![], value));
                    }
                    (vec![0x2B, 0x0E, head[4], head[5]], reply)
                });
            let standard = prop_oneof![
                read_bits,
                read_registers,
                write_single,
                status,
                diagnostics,
                event_counter,
                counted_reply,
                write_coils,
                write_registers,
                read_file,
                write_file,
                mask_write,
                read_write,
                fifo,
                device_id,
            ];
            let wide = (any::<u16>(), 1u16..=125).prop_flat_map(|(at, q)| {
                bytes(usize::from(q) * 2).prop_map(move |data| {
                    let reply = [pdu(0x03, &[2 * q]), data].concat();
                    Exchange {
                        request: pdu(0x03, &[at, q]),
                        reply,
                        form: ReplyForm::WideReadCount,
                    }
                })
            });
            prop_oneof![
                4 => (standard, form())
                    .prop_map(|((request, reply), form)| Exchange { request, reply, form }),
                1 => wide,
            ]
        }

        /// A normal reply, or an exception to any request whatever.
        fn exchange() -> impl Strategy<Value = Exchange> {
            let exception =
                (1u8..0x80, bytes(0..8), any::<u8>(), form()).prop_map(|(f, rest, code, form)| {
                    Exchange {
                        request: [vec![f], rest].concat(),
                        reply: vec![f | EXCEPTION_BIT, code],
                        form,
                    }
                });
            prop_oneof![4 => normal_exchange(), 1 => exception]
        }

        fn slave() -> impl Strategy<Value = u8> {
            1u8..=247
        }

        /// Frames with a good CRC are rare among random bytes: half the inputs are encoded.
        fn frame_like() -> impl Strategy<Value = Vec<u8>> {
            prop_oneof![
                bytes(0..=300),
                (any::<u8>(), bytes(0..=260)).prop_map(|(address, pdu)| encode(address, &pdu)),
            ]
        }

        proptest! {
            #[test]
            fn no_bytes_whatever_make_the_frame_functions_panic_or_talk_nonsense(
                frame in frame_like(),
                request in prop_oneof![bytes(0..12), exchange().prop_map(|e| e.request)],
                slave in prop::option::of(any::<u8>()),
                form in form(),
            ) {
                // Mostly the sender's own address, so the checks past the address run.
                let slave = slave.unwrap_or(frame.first().copied().unwrap_or(0));
                let _ = crc16(&frame);
                for len in [
                    request_len(&frame),
                    reply_len(&frame, slave, &request),
                    reply_len_as(&frame, slave, &request, form),
                ] {
                    match len {
                        FrameLen::Need(n) => prop_assert!(n > frame.len(), "{:?}", len),
                        FrameLen::Exact(n) => {
                            prop_assert!((MIN_FRAME_LEN..=MAX_FRAME_LEN).contains(&n), "{:?}", len)
                        }
                        FrameLen::BySilence | FrameLen::Invalid => {}
                    }
                }
                let crc = crc_ok(&frame);
                for verdict in [
                    check_reply(&frame, slave, &request),
                    check_reply_as(&frame, slave, &request, form),
                ] {
                    prop_assert_eq!(verdict == Verdict::Corrupt, !crc);
                    if matches!(verdict, Verdict::Answer | Verdict::Malformed) {
                        prop_assert_eq!(frame[0], slave);
                        prop_assert_eq!(request[0], pdu_of(&frame)[0] & !EXCEPTION_BIT);
                    }
                }
                if crc {
                    prop_assert_eq!(pdu_of(&frame), &frame[1..frame.len() - 2]);
                    let _ = answer_pdu(&frame, form);
                }
            }

            #[test]
            fn every_encoded_frame_has_a_good_crc_and_gives_back_its_pdu(
                address in any::<u8>(),
                pdu in bytes(1..=253),
                mut out in bytes(0..8),
            ) {
                let frame = encode(address, &pdu);
                prop_assert_eq!(frame.len(), pdu.len() + 3);
                prop_assert_eq!(frame[0], address);
                prop_assert!(crc_ok(&frame));
                prop_assert_eq!(pdu_of(&frame), &pdu[..]);
                encode_into(&mut out, address, &pdu);
                prop_assert_eq!(out, frame);
            }

            #[test]
            fn any_single_flipped_bit_fails_the_crc(
                exchange in exchange(),
                slave in slave(),
                bit in any::<prop::sample::Index>(),
            ) {
                let mut frame = encode(slave, &exchange.reply);
                let bit = bit.index(frame.len() * 8);
                frame[bit / 8] ^= 1 << (bit % 8);
                prop_assert!(!crc_ok(&frame));
                prop_assert_eq!(
                    check_reply_as(&frame, slave, &exchange.request, exchange.form),
                    Verdict::Corrupt
                );
            }

            #[test]
            fn a_well_formed_reply_is_complete_at_exactly_its_length_and_answers_its_request(
                exchange in exchange(),
                slave in slave(),
                next in bytes(0..8),
            ) {
                let Exchange { request, form, .. } = &exchange;
                let frame = encode(slave, &exchange.reply);
                for k in 0..frame.len() {
                    match reply_len_as(&frame[..k], slave, request, *form) {
                        FrameLen::Need(n) => {
                            prop_assert!(k < n && n <= frame.len(), "Need({}) at {}", n, k)
                        }
                        FrameLen::Exact(n) => prop_assert_eq!(n, frame.len(), "at {}", k),
                        other => {
                            let why = format!("{other:?} at {k} of {frame:02X?}");
                            return Err(TestCaseError::fail(why));
                        }
                    }
                }
                // The next frame's first bytes, already in, change nothing.
                let stream = [frame.clone(), next].concat();
                let whole = FrameLen::Exact(frame.len());
                prop_assert_eq!(reply_len_as(&stream, slave, request, *form), whole);
                prop_assert_eq!(check_reply_as(&frame, slave, request, *form), Verdict::Answer);
                prop_assert_eq!(answer_pdu(&frame, *form), exchange.standard_reply());
                if *form == ReplyForm::Standard {
                    prop_assert_eq!(reply_len(&stream, slave, request), whole);
                    prop_assert_eq!(check_reply(&frame, slave, request), Verdict::Answer);
                }
            }

            #[test]
            fn a_request_is_complete_at_exactly_its_length_unless_only_silence_can_tell(
                exchange in normal_exchange(),
                slave in slave(),
            ) {
                let frame = encode(slave, &exchange.request);
                let whole = if exchange.request[0] == 0x08 {
                    FrameLen::BySilence
                } else {
                    FrameLen::Exact(frame.len())
                };
                prop_assert_eq!(request_len(&frame), whole);
                for k in 0..frame.len() {
                    match request_len(&frame[..k]) {
                        FrameLen::Need(n) => {
                            prop_assert!(k < n && n <= frame.len(), "Need({}) at {}", n, k)
                        }
                        len => prop_assert!(len == whole || k < 2, "{:?} at {}", len, k),
                    }
                }
            }

            #[test]
            fn a_reply_from_another_address_is_foreign(
                exchange in exchange(),
                (slave, other) in (slave(), any::<u8>())
                    .prop_filter("another address", |(s, o)| s != o),
            ) {
                let frame = encode(other, &exchange.reply);
                prop_assert_eq!(
                    check_reply_as(&frame, slave, &exchange.request, exchange.form),
                    Verdict::Foreign
                );
            }

            #[test]
            fn a_reply_to_another_function_is_foreign(
                (asked, answered) in (exchange(), exchange())
                    .prop_filter("another function", |(a, b)| a.request[0] != b.request[0]),
                slave in slave(),
            ) {
                let frame = encode(slave, &answered.reply);
                prop_assert_eq!(
                    check_reply_as(&frame, slave, &asked.request, asked.form),
                    Verdict::Foreign
                );
            }

            #[test]
            fn an_echo_of_another_address_quantity_or_sub_function_is_malformed(
                exchange in normal_exchange().prop_filter("an echo", |e| {
                    matches!(e.request[0], 0x05 | 0x06 | 0x08 | 0x0F | 0x10 | 0x16)
                }),
                at in any::<prop::sample::Index>(),
                flip in 1u8..,
                slave in slave(),
            ) {
                // The bytes the reply must echo: the address (and quantity), or the sub-function.
                let echoed = if matches!(exchange.request[0], 0x0F | 0x10) { 4 } else { 2 };
                let mut reply = exchange.reply.clone();
                reply[1 + at.index(echoed)] ^= flip;
                let frame = encode(slave, &reply);
                prop_assert_eq!(
                    check_reply_as(&frame, slave, &exchange.request, exchange.form),
                    Verdict::Malformed
                );
            }

            #[test]
            fn a_read_reply_for_another_quantity_is_malformed(
                function in 0x01u8..=0x04,
                (asked, sent) in (1u16..=125, 1u16..=125)
                    .prop_filter("another quantity", |(a, s)| a != s),
                slave in slave(),
                form in form(),
            ) {
                let bytes_for = |q: u16| if function <= 0x02 { q.div_ceil(8) } else { q * 2 };
                prop_assume!(bytes_for(asked) != bytes_for(sent));
                let count = bytes_for(sent) as usize;
                let frame = encode(slave, &with_count(vec![function], &vec![0; count]));
                prop_assert_eq!(
                    check_reply_as(&frame, slave, &pdu(function, &[0, asked]), form),
                    Verdict::Malformed
                );
            }
        }
    }
}
