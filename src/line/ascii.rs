//! Modbus ASCII frames as bytes (Modbus over Serial Line V1.02, 2.5.2): `:`, then the address,
//! the PDU and the LRC as hex pairs, then CR LF. The LRC is the two's complement of the byte sum
//! of address and PDU. Frames are delimited by their characters, not by silence: a frame ends at
//! CR LF, and a new `:` restarts it. Upper-case hex is sent; either case is read. Pure functions
//! over bytes; knows nothing of ports or time.

/// Starts every frame.
pub(crate) const START: u8 = b':';
/// Ends every frame.
pub(crate) const END: [u8; 2] = *b"\r\n";
/// `:`, 2 x (address + 253 PDU bytes + LRC) characters, CR LF.
pub(crate) const MAX_FRAME_LEN: usize = 1 + 2 * (1 + 253 + 1) + 2;

const HEX: &[u8; 16] = b"0123456789ABCDEF";

/// The LRC of `bytes`: the two's complement of their sum, modulo 256.
pub(crate) fn lrc(bytes: impl IntoIterator<Item = u8>) -> u8 {
    bytes
        .into_iter()
        .fold(0u8, |sum, b| sum.wrapping_add(b))
        .wrapping_neg()
}

fn push_hex(out: &mut Vec<u8>, byte: u8) {
    out.push(HEX[usize::from(byte >> 4)]);
    out.push(HEX[usize::from(byte & 0x0F)]);
}

/// Build the frame for `pdu` to `address` into `out` (cleared first).
pub(crate) fn encode_into(out: &mut Vec<u8>, address: u8, pdu: &[u8]) {
    out.clear();
    out.push(START);
    push_hex(out, address);
    for &byte in pdu {
        push_hex(out, byte);
    }
    push_hex(
        out,
        lrc(std::iter::once(address).chain(pdu.iter().copied())),
    );
    out.extend_from_slice(&END);
}

/// A whole frame of its own (for tests; the engine encodes into its buffer).
#[cfg(test)]
pub(crate) fn encode(address: u8, pdu: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(2 * pdu.len() + 7);
    encode_into(&mut out, address, pdu);
    out
}

/// Where the first whole frame in `received` ends (just past its CR LF), if one has.
pub(crate) fn frame_end(received: &[u8]) -> Option<usize> {
    received
        .windows(END.len())
        .position(|pair| pair == END)
        .map(|at| at + END.len())
}

fn nibble(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'A'..=b'F' => Some(c - b'A' + 10),
        b'a'..=b'f' => Some(c - b'a' + 10),
        _ => None,
    }
}

/// The address of a whole frame (up to and including its CR LF), with its PDU decoded into
/// `pdu`; `None` when it is no frame: no `:`, a character that is not hex, an odd count, too
/// short, or an LRC that does not check. The frame starts at its last `:`: whatever came before
/// (noise, a frame cut short by a new `:`) is not part of it.
pub(crate) fn decode_into(whole: &[u8], pdu: &mut Vec<u8>) -> Option<u8> {
    let body = whole.strip_suffix(&END)?;
    let start = body.iter().rposition(|&c| c == START)?;
    let hex = &body[start + 1..];
    // Address, function code and LRC at least.
    if hex.len() % 2 != 0 || hex.len() < 6 {
        return None;
    }
    pdu.clear();
    for pair in hex.chunks_exact(2) {
        pdu.push(nibble(pair[0])? << 4 | nibble(pair[1])?);
    }
    let sent_lrc = pdu.pop()?;
    if lrc(pdu.iter().copied()) != sent_lrc {
        return None;
    }
    let address = pdu.remove(0);
    Some(address)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lrc_is_the_twos_complement_of_the_manuals_worked_sum() {
        // Goodrive manuals, "ASCII mode check (LRC Check)": 0x02+0x06+0x00+0x08+0x13+0x88 = 0xAB,
        // LRC 0x55. (Their C function returns the one's complement, 0x54; the spec and the
        // worked figure agree on 0x55.)
        assert_eq!(lrc([0x02, 0x06, 0x00, 0x08, 0x13, 0x88]), 0x55);
        assert_eq!(lrc([]), 0x00);
    }

    #[test]
    fn the_manuals_ascii_read_of_two_words_from_0004h_comes_out_byte_for_byte() {
        // Goodrive manuals, "ASCII mode", command code 03H: slave 01H, start 0004H, two words.
        let request = encode(0x01, &[0x03, 0x00, 0x04, 0x00, 0x02]);
        assert_eq!(request, b":010300040002F6\r\n");
        // The inverter's answer: 0004H = 1388H, 0005H = 0000H.
        let reply = encode(0x01, &[0x03, 0x04, 0x13, 0x88, 0x00, 0x00]);
        assert_eq!(reply, b":010304138800005D\r\n");
        let mut pdu = Vec::new();
        assert_eq!(decode_into(&reply, &mut pdu), Some(0x01));
        assert_eq!(pdu, [0x03, 0x04, 0x13, 0x88, 0x00, 0x00]);
    }

    #[test]
    fn lower_case_hex_reads_the_same_and_a_bad_lrc_or_character_reads_as_nothing() {
        let mut pdu = Vec::new();
        assert_eq!(decode_into(b":010304138800005d\r\n", &mut pdu), Some(1));
        assert_eq!(pdu, [0x03, 0x04, 0x13, 0x88, 0x00, 0x00]);
        assert_eq!(decode_into(b":010304138800005C\r\n", &mut pdu), None, "LRC");
        assert_eq!(
            decode_into(b":01030413880G005D\r\n", &mut pdu),
            None,
            "not hex"
        );
        assert_eq!(decode_into(b":010304138800005\r\n", &mut pdu), None, "odd");
        assert_eq!(decode_into(b":01FF\r\n", &mut pdu), None, "short");
        assert_eq!(
            decode_into(b":0103FC\r\n", &mut pdu),
            Some(1),
            "the shortest"
        );
        assert_eq!(
            decode_into(b":010304138800005D", &mut pdu),
            None,
            "no CR LF"
        );
        assert_eq!(
            decode_into(b"010304138800005D\r\n", &mut pdu),
            None,
            "no colon"
        );
    }

    #[test]
    fn a_new_colon_restarts_the_frame_and_noise_before_it_is_dropped() {
        let mut pdu = Vec::new();
        let restarted = b"\x00\xff:0103:010304138800005D\r\n";
        assert_eq!(decode_into(restarted, &mut pdu), Some(1));
        assert_eq!(pdu, [0x03, 0x04, 0x13, 0x88, 0x00, 0x00]);
    }

    #[test]
    fn a_frame_ends_just_past_its_cr_lf() {
        assert_eq!(frame_end(b":0103"), None);
        assert_eq!(frame_end(b":01\r"), None);
        assert_eq!(frame_end(b":01\r\n:02"), Some(5));
        assert_eq!(MAX_FRAME_LEN, 513);
    }
}
