//! MBAP as the gateway writes it to a Modbus TCP device and reads the device's replies (the
//! listeners' side, with masters, is `net::mbap`): the 7-byte header (transaction id, protocol
//! id 0, length, unit id) before the PDU. Pure functions over bytes.

use super::framing::Completion;

/// The header's bytes: transaction id, protocol id, length, unit id.
pub(crate) const HEADER_LEN: usize = 7;
/// The length field counts the unit id and the PDU: at least a function code.
pub(crate) const MIN_LENGTH: u16 = 2;
/// The unit id and the longest PDU (253 bytes).
pub(crate) const MAX_LENGTH: u16 = 254;
/// The longest frame: the header's first six bytes and the longest length.
pub(crate) const MAX_FRAME_LEN: usize = 6 + MAX_LENGTH as usize;

/// Build the frame for `pdu` to `unit` with `transaction` into `out` (cleared first).
pub(crate) fn encode_into(out: &mut Vec<u8>, transaction: u16, unit: u8, pdu: &[u8]) {
    out.clear();
    let length = u16::try_from(pdu.len() + 1).unwrap_or(u16::MAX);
    out.extend_from_slice(&transaction.to_be_bytes());
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(&length.to_be_bytes());
    out.push(unit);
    out.extend_from_slice(pdu);
}

/// How far `received` makes a frame: whole at the header's length, invalid with a protocol id
/// other than Modbus's or a length no frame has.
pub(crate) fn completion(received: &[u8]) -> Completion {
    if received.len() >= 4 && received[2..4] != [0, 0] {
        return Completion::Invalid;
    }
    let Some(length) = received.get(4..6) else {
        return Completion::AtLeast(HEADER_LEN + 1);
    };
    let length = u16::from_be_bytes([length[0], length[1]]);
    if !(MIN_LENGTH..=MAX_LENGTH).contains(&length) {
        return Completion::Invalid;
    }
    let whole = 6 + usize::from(length);
    if received.len() >= whole {
        Completion::Whole(whole)
    } else {
        Completion::AtLeast(whole)
    }
}

/// The unit id of a whole frame, with its PDU decoded into `pdu`.
pub(crate) fn decode_into(whole: &[u8], pdu: &mut Vec<u8>) -> Option<u8> {
    let unit = *whole.get(HEADER_LEN - 1)?;
    pdu.clear();
    pdu.extend_from_slice(whole.get(HEADER_LEN..)?);
    Some(unit)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_is_whole_at_its_length_and_a_foreign_protocol_or_length_is_no_frame() {
        let mut frame = Vec::new();
        encode_into(&mut frame, 0x1234, 0xFF, &[0x03, 0x00, 0x00, 0x00, 0x02]);
        assert_eq!(
            frame,
            [0x12, 0x34, 0, 0, 0, 6, 0xFF, 0x03, 0x00, 0x00, 0x00, 0x02]
        );
        assert_eq!(completion(&frame[..3]), Completion::AtLeast(8));
        assert_eq!(completion(&frame[..9]), Completion::AtLeast(12));
        assert_eq!(completion(&frame), Completion::Whole(12));
        let mut two = frame.clone();
        two.extend_from_slice(&frame);
        assert_eq!(completion(&two), Completion::Whole(12));
        let mut pdu = Vec::new();
        assert_eq!(decode_into(&frame, &mut pdu), Some(0xFF));
        assert_eq!(pdu, [0x03, 0x00, 0x00, 0x00, 0x02]);
        let mut other_protocol = frame.clone();
        other_protocol[3] = 1;
        assert_eq!(completion(&other_protocol), Completion::Invalid);
        let mut too_short = frame;
        too_short[5] = 1;
        assert_eq!(completion(&too_short), Completion::Invalid);
    }
}
