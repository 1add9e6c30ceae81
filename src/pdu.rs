//! Facts about Modbus PDUs that both sides of the gateway share: exception codes, which requests
//! only read, which may be broadcast, and what a broadcast write is answered with.
//! Knows nothing of MBAP, RTU framing, sockets or serial ports.

/// Largest PDU a Modbus ADU can carry (256-byte RTU frame minus address and CRC).
pub const MAX_PDU_LEN: usize = 253;

/// Set in the function code of a reply that is an exception.
pub const EXCEPTION_BIT: u8 = 0x80;

/// Exception codes the gateway itself sends. Slave exceptions pass through as raw bytes and are
/// never converted to this type, so vendor codes (05-09 on the reference drives) survive.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum ExceptionCode {
    IllegalFunction = 0x01,
    IllegalDataAddress = 0x02,
    IllegalDataValue = 0x03,
    ServerDeviceFailure = 0x04,
    Acknowledge = 0x05,
    ServerDeviceBusy = 0x06,
    GatewayPathUnavailable = 0x0A,
    GatewayTargetFailedToRespond = 0x0B,
}

/// The public function codes of the Modbus Application Protocol V1.1b3, by the spec's names.
pub mod code {
    pub const READ_COILS: u8 = 0x01;
    pub const READ_DISCRETE_INPUTS: u8 = 0x02;
    pub const READ_HOLDING_REGISTERS: u8 = 0x03;
    pub const READ_INPUT_REGISTERS: u8 = 0x04;
    pub const WRITE_SINGLE_COIL: u8 = 0x05;
    pub const WRITE_SINGLE_REGISTER: u8 = 0x06;
    pub const READ_EXCEPTION_STATUS: u8 = 0x07;
    pub const DIAGNOSTICS: u8 = 0x08;
    pub const GET_COMM_EVENT_COUNTER: u8 = 0x0B;
    pub const GET_COMM_EVENT_LOG: u8 = 0x0C;
    pub const WRITE_MULTIPLE_COILS: u8 = 0x0F;
    pub const WRITE_MULTIPLE_REGISTERS: u8 = 0x10;
    pub const REPORT_SERVER_ID: u8 = 0x11;
    pub const READ_FILE_RECORD: u8 = 0x14;
    pub const WRITE_FILE_RECORD: u8 = 0x15;
    pub const MASK_WRITE_REGISTER: u8 = 0x16;
    pub const READ_WRITE_MULTIPLE_REGISTERS: u8 = 0x17;
    pub const READ_FIFO_QUEUE: u8 = 0x18;
    pub const ENCAPSULATED_INTERFACE: u8 = 0x2B;
}

/// The two-byte exception PDU for a request with function code `function`.
pub fn exception_pdu(function: u8, code: ExceptionCode) -> [u8; 2] {
    [function | EXCEPTION_BIT, code as u8]
}

/// A function code a master may send: 1..=127. Codes with the high bit set only exist in replies.
pub fn is_valid_request_function(function: u8) -> bool {
    function != 0 && function & EXCEPTION_BIT == 0
}

/// Requests that change nothing on the slave, so repeating them after a lost reply is harmless.
/// Anything not known to be a read (user-defined codes included) counts as a write.
pub fn is_read_only(pdu: &[u8]) -> bool {
    match pdu.first() {
        Some(0x01..=0x04 | 0x07 | 0x0B | 0x0C | 0x11 | 0x14 | 0x18) => true,
        // Diagnostics: echo, diagnostic register and the counters read; the rest restart or clear.
        Some(0x08) => matches!(sub_function(pdu), Some(0x0000 | 0x0002 | 0x000B..=0x0012)),
        // Encapsulated interface: only Read Device Identification is known to be a read.
        Some(0x2B) => pdu.get(1) == Some(&0x0E),
        _ => false,
    }
}

fn sub_function(pdu: &[u8]) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(1)?, *pdu.get(2)?]))
}

/// Function codes the serial line spec allows to address 0: the writes. Everything else sent to
/// the broadcast address is refused by the gateway and never reaches the line.
pub fn is_broadcastable(function: u8) -> bool {
    matches!(function, 0x05 | 0x06 | 0x0F | 0x10 | 0x15 | 0x16)
}

/// The normal response to a broadcast write, which the gateway makes itself because no slave
/// answers a broadcast. `None` for requests that cannot be broadcast or are too short to answer.
pub fn broadcast_response(pdu: &[u8]) -> Option<Vec<u8>> {
    match *pdu.first()? {
        // Write single coil/register, write file record, mask write: the response echoes the request.
        0x05 | 0x06 | 0x15 | 0x16 => Some(pdu.to_vec()),
        // Write multiple coils/registers: function, starting address, quantity.
        0x0F | 0x10 => pdu.get(..5).map(<[u8]>::to_vec),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gateway_exceptions_set_the_high_bit_of_the_request_function() {
        assert_eq!(
            exception_pdu(0x03, ExceptionCode::GatewayTargetFailedToRespond),
            [0x83, 0x0B]
        );
        assert_eq!(
            exception_pdu(0x41, ExceptionCode::GatewayPathUnavailable),
            [0xC1, 0x0A]
        );
    }

    #[test]
    fn reads_are_recognised_and_everything_unknown_counts_as_a_write() {
        assert!(is_read_only(&[0x03, 0, 0, 0, 1]));
        assert!(is_read_only(&[0x08, 0x00, 0x00, 0x12, 0xAB]));
        assert!(
            !is_read_only(&[0x08, 0x00, 0x01, 0x00, 0x00]),
            "restart comms"
        );
        assert!(
            !is_read_only(&[0x08, 0x00, 0x0A, 0x00, 0x00]),
            "clear counters"
        );
        assert!(is_read_only(&[0x2B, 0x0E, 0x01, 0x00]));
        assert!(!is_read_only(&[0x2B, 0x0D]));
        assert!(!is_read_only(&[0x06, 0, 1, 0, 1]));
        assert!(!is_read_only(&[0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0, 0]));
        assert!(!is_read_only(&[0x41, 1, 2]));
        assert!(!is_read_only(&[]));
    }

    #[test]
    fn broadcast_writes_are_answered_like_the_slave_would() {
        // Write multiple registers 0004H..0005H (the Goodrive300 manual's FC 10 example).
        let pdu = [0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32];
        assert_eq!(
            broadcast_response(&pdu),
            Some(vec![0x10, 0x00, 0x04, 0x00, 0x02])
        );
        let pdu = [0x06, 0x00, 0x04, 0x13, 0x88];
        assert_eq!(broadcast_response(&pdu), Some(pdu.to_vec()));
        assert_eq!(broadcast_response(&[0x03, 0, 0, 0, 1]), None);
        assert_eq!(broadcast_response(&[0x10, 0x00]), None);
    }

    #[test]
    fn only_user_visible_function_codes_are_valid_in_requests() {
        assert!(!is_valid_request_function(0x00));
        assert!(is_valid_request_function(0x41));
        assert!(!is_valid_request_function(0x83));
    }
}
