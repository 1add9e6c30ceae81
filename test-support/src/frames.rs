//! Frames as masters and slaves put them on the wire: a Modbus TCP ADU (MBAP header and PDU) and
//! an RTU frame (address, PDU, CRC-16). The RTU frame is the product's own encoder, so a test
//! checks the gateway against the codec it ships, whose CRC the worked frames of the spec pin.

use modbus_gateway::testing::line::rtu;

/// The Modbus TCP ADU carrying `pdu` to `unit`: transaction id, protocol id 0, the length of
/// what follows (unit id and PDU), the unit id, the PDU.
///
/// # Panics
/// If `pdu` is longer than an MBAP length field can say (65,534 bytes).
pub fn mbap(transaction: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let length = u16::try_from(pdu.len() + 1).expect("a PDU an MBAP header can carry");
    let mut adu = Vec::with_capacity(7 + pdu.len());
    adu.extend_from_slice(&transaction.to_be_bytes());
    adu.extend_from_slice(&[0, 0]);
    adu.extend_from_slice(&length.to_be_bytes());
    adu.push(unit);
    adu.extend_from_slice(pdu);
    adu
}

/// The RTU frame carrying `pdu` to or from slave `address`: address, PDU, CRC-16 (low byte first).
pub fn rtu(address: u8, pdu: &[u8]) -> Vec<u8> {
    rtu::encode(address, pdu)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_mbap_adu_counts_the_unit_id_in_its_length() {
        assert_eq!(
            mbap(0x0102, 0x11, &[0x03, 0x00, 0x6B, 0x00, 0x03]),
            // transaction, protocol 0, length 6, unit 0x11, read 3 registers from 0x006B
            [0x01, 0x02, 0x00, 0x00, 0x00, 0x06, 0x11, 0x03, 0x00, 0x6B, 0x00, 0x03]
        );
    }

    #[test]
    fn an_rtu_frame_ends_with_its_crc_low_byte_first() {
        // Slave 1, read 2 holding registers from 0: the frame of the trace tests (CRC C40B).
        assert_eq!(
            rtu(1, &[0x03, 0x00, 0x00, 0x00, 0x02]),
            [0x01, 0x03, 0x00, 0x00, 0x00, 0x02, 0xC4, 0x0B]
        );
    }
}
