//! MBAP, the framing of Modbus TCP (Modbus Messaging on TCP/IP Implementation Guide V1.0b,
//! 3.1.3), both ways: masters' requests in and replies out (`net`), and the gateway's requests
//! to a Modbus TCP device and its replies (`line`). The 7-byte header (transaction id, protocol
//! id 0, length, unit id) before the PDU: each field read in one place, one encoder, one length
//! rule. Pure functions over bytes; knows nothing of sockets, sessions or lines.
//!
//! Written here rather than taken from tokio-modbus: the gateway forwards raw PDU bytes for
//! every function code (user-defined ones included), and tokio-modbus's server decodes requests
//! into typed values and does not hand back the bytes.

use bytes::{Buf, BytesMut};

/// The header's bytes: transaction id, protocol id, length, unit id.
pub(crate) const HEADER_LEN: usize = 7;
/// The length field counts the unit id and the PDU: at least a function code.
pub(crate) const MIN_LENGTH: u16 = 2;
/// The unit id and the longest PDU (253 bytes).
pub(crate) const MAX_LENGTH: u16 = 254;
/// The longest frame: the header's first six bytes and the longest length.
pub(crate) const MAX_FRAME_LEN: usize = HEADER_LEN - 1 + MAX_LENGTH as usize;
const MODBUS_PROTOCOL: u16 = 0;

/// What a reply must echo.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Header {
    pub transaction: u16,
    pub unit: u8,
}

/// A whole frame, taken off a stream.
#[derive(Debug, PartialEq, Eq)]
pub(crate) struct Request {
    pub header: Header,
    pub pdu: Vec<u8>,
}

/// A header that is not Modbus TCP's: the stream cannot be followed.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum HeaderError {
    #[error("protocol id {0} is not 0 (Modbus)")]
    Protocol(u16),
    #[error("length field {0} is outside {MIN_LENGTH}-{MAX_LENGTH}")]
    Length(u16),
}

fn field(frame: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*frame.get(at)?, *frame.get(at + 1)?]))
}

/// The transaction id, once its two bytes are in.
pub(crate) fn transaction(frame: &[u8]) -> Option<u16> {
    field(frame, 0)
}

/// The protocol id, once its two bytes are in.
pub(crate) fn protocol(frame: &[u8]) -> Option<u16> {
    field(frame, 2)
}

/// The length field (unit id and PDU), once its two bytes are in.
pub(crate) fn length(frame: &[u8]) -> Option<u16> {
    field(frame, 4)
}

/// The unit id, once it is in.
pub(crate) fn unit(frame: &[u8]) -> Option<u8> {
    frame.get(HEADER_LEN - 1).copied()
}

/// The PDU's bytes so far: all after the header.
pub(crate) fn pdu(frame: &[u8]) -> Option<&[u8]> {
    frame.get(HEADER_LEN..)
}

/// How long the frame at the front of `received` is, once its length field is in (`Ok(None)`
/// before). The protocol id is judged as soon as its bytes are in, the length when it is.
pub(crate) fn frame_len(received: &[u8]) -> Result<Option<usize>, HeaderError> {
    match protocol(received) {
        Some(id) if id != MODBUS_PROTOCOL => return Err(HeaderError::Protocol(id)),
        _ => {}
    }
    let Some(length) = length(received) else {
        return Ok(None);
    };
    if !(MIN_LENGTH..=MAX_LENGTH).contains(&length) {
        return Err(HeaderError::Length(length));
    }
    Ok(Some(HEADER_LEN - 1 + usize::from(length)))
}

/// The header and the PDU of a whole frame.
pub(crate) fn split(whole: &[u8]) -> Option<(Header, &[u8])> {
    let header = Header {
        transaction: transaction(whole)?,
        unit: unit(whole)?,
    };
    Some((header, pdu(whole)?))
}

/// Take one frame off the front of a master's stream in `buf`: `Ok(None)` until a whole one is
/// in. Its header is judged once the length field is in, protocol id and length together.
pub(crate) fn decode(buf: &mut BytesMut) -> Result<Option<Request>, HeaderError> {
    if buf.len() < HEADER_LEN - 1 {
        return Ok(None);
    }
    let Some(total) = frame_len(buf)? else {
        return Ok(None);
    };
    let Some((header, pdu)) = buf.get(..total).and_then(split) else {
        return Ok(None);
    };
    let request = Request {
        header,
        pdu: pdu.to_vec(),
    };
    buf.advance(total);
    Ok(Some(request))
}

/// Append the frame carrying `pdu` under `header` to `out`.
pub(crate) fn encode(header: Header, pdu: &[u8], out: &mut Vec<u8>) {
    out.extend_from_slice(&header.transaction.to_be_bytes());
    out.extend_from_slice(&MODBUS_PROTOCOL.to_be_bytes());
    // A PDU is at most 253 bytes; the length field counts it and the unit id.
    let length = u16::try_from(pdu.len() + 1).unwrap_or(u16::MAX);
    out.extend_from_slice(&length.to_be_bytes());
    out.push(header.unit);
    out.extend_from_slice(pdu);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Read holding registers 0004H-0005H of unit 1, transaction 0x1234.
    const READ: [u8; 12] = [
        0x12, 0x34, // transaction id
        0x00, 0x00, // protocol id: Modbus
        0x00, 0x06, // length: unit + 5 PDU bytes
        0x01, // unit id
        0x03, 0x00, 0x04, 0x00, 0x02, // PDU: read 2 registers from 0004H
    ];

    fn expected() -> Request {
        Request {
            header: Header {
                transaction: 0x1234,
                unit: 1,
            },
            pdu: READ[7..].to_vec(),
        }
    }

    #[test]
    fn a_whole_frame_decodes() {
        let mut buf = BytesMut::from(&READ[..]);
        assert_eq!(decode(&mut buf), Ok(Some(expected())));
        assert!(buf.is_empty());
    }

    #[test]
    fn a_frame_fed_byte_by_byte_decodes_once_complete() {
        let mut buf = BytesMut::new();
        for (i, &byte) in READ.iter().enumerate() {
            buf.extend_from_slice(&[byte]);
            let result = decode(&mut buf);
            if i + 1 < READ.len() {
                assert_eq!(result, Ok(None), "after {} bytes", i + 1);
            } else {
                assert_eq!(result, Ok(Some(expected())));
            }
        }
    }

    #[test]
    fn two_frames_in_one_buffer_come_out_in_order() {
        let mut second = READ;
        second[1] = 0x35;
        let mut buf = BytesMut::from(&READ[..]);
        buf.extend_from_slice(&second);
        assert_eq!(
            decode(&mut buf).unwrap().unwrap().header.transaction,
            0x1234
        );
        assert_eq!(
            decode(&mut buf).unwrap().unwrap().header.transaction,
            0x1235
        );
        assert_eq!(decode(&mut buf), Ok(None));
    }

    #[test]
    fn a_wrong_protocol_id_or_length_is_an_error() {
        let mut bad = READ;
        bad[3] = 1;
        assert_eq!(
            decode(&mut BytesMut::from(&bad[..])),
            Err(HeaderError::Protocol(1))
        );
        for length in [0u16, 1, 255, 0xFFFF] {
            let mut bad = READ;
            bad[4..6].copy_from_slice(&length.to_be_bytes());
            assert_eq!(
                decode(&mut BytesMut::from(&bad[..])),
                Err(HeaderError::Length(length))
            );
        }
    }

    #[test]
    fn the_largest_frame_decodes() {
        let mut frame = vec![0, 1, 0, 0, 0, 254, 9, 0x10];
        frame.extend(std::iter::repeat_n(0xAB, 252));
        let request = decode(&mut BytesMut::from(&frame[..])).unwrap().unwrap();
        assert_eq!(request.pdu.len(), 253);
    }

    #[test]
    fn replies_echo_the_header_with_their_own_length() {
        let mut out = Vec::new();
        let header = Header {
            transaction: 0xBEEF,
            unit: 0x11,
        };
        encode(header, &[0x83, 0x0B], &mut out);
        assert_eq!(out, [0xBE, 0xEF, 0, 0, 0, 3, 0x11, 0x83, 0x0B]);
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;

        fn header() -> impl Strategy<Value = Header> {
            (any::<u16>(), any::<u8>()).prop_map(|(transaction, unit)| Header { transaction, unit })
        }

        fn request() -> impl Strategy<Value = Request> {
            (header(), prop::collection::vec(any::<u8>(), 1..=253))
                .prop_map(|(header, pdu)| Request { header, pdu })
        }

        /// Length fields, crowded at the edges of the valid range: proptest picks uniformly.
        fn length_field() -> impl Strategy<Value = u16> {
            prop_oneof![
                0u16..=MIN_LENGTH + 1,
                MAX_LENGTH - 1..=MAX_LENGTH + 2,
                any::<u16>()
            ]
        }

        fn framed(request: &Request) -> Vec<u8> {
            let mut out = Vec::new();
            encode(request.header, &request.pdu, &mut out);
            out
        }

        proptest! {
            #[test]
            fn any_bytes_give_one_frame_more_bytes_needed_or_a_typed_error(
                bytes in prop::collection::vec(any::<u8>(), 0..300),
                // Mostly Modbus, with a plausible length, so whole frames come out too.
                protocol_zero in any::<bool>(),
                length in prop::option::of(length_field()),
            ) {
                let mut bytes = bytes;
                match (protocol_zero, bytes.get_mut(2..4)) {
                    (true, Some(id)) => id.fill(0),
                    // Protocol id 1 is as near Modbus as a stranger gets.
                    (false, Some(id)) if id[0] & 1 == 0 => id.copy_from_slice(&[0, 1]),
                    _ => {}
                }
                if let (Some(length), true) = (length, bytes.len() >= 6) {
                    bytes[4..6].copy_from_slice(&length.to_be_bytes());
                }
                let mut buf = BytesMut::from(&bytes[..]);
                match decode(&mut buf) {
                    Ok(Some(request)) => {
                        let length = u16::from_be_bytes([bytes[4], bytes[5]]);
                        let total = HEADER_LEN - 1 + usize::from(length);
                        prop_assert_eq!(&bytes[2..4], &[0, 0]);
                        prop_assert!((MIN_LENGTH..=MAX_LENGTH).contains(&length));
                        prop_assert!(bytes.len() >= total);
                        prop_assert_eq!(
                            request.header,
                            Header {
                                transaction: u16::from_be_bytes([bytes[0], bytes[1]]),
                                unit: bytes[6],
                            }
                        );
                        prop_assert_eq!(&request.pdu[..], &bytes[HEADER_LEN..total]);
                        prop_assert_eq!(&buf[..], &bytes[total..], "one frame is consumed");
                    }
                    Ok(None) => {
                        prop_assert_eq!(&buf[..], &bytes[..], "nothing is consumed");
                        if bytes.len() >= HEADER_LEN - 1 {
                            let length = u16::from_be_bytes([bytes[4], bytes[5]]);
                            prop_assert_eq!(&bytes[2..4], &[0, 0]);
                            prop_assert!((MIN_LENGTH..=MAX_LENGTH).contains(&length));
                            prop_assert!(bytes.len() < HEADER_LEN - 1 + usize::from(length));
                        }
                    }
                    Err(HeaderError::Protocol(id)) => {
                        prop_assert_ne!(id, 0);
                        prop_assert_eq!(id, u16::from_be_bytes([bytes[2], bytes[3]]));
                    }
                    Err(HeaderError::Length(length)) => {
                        prop_assert_eq!(&bytes[2..4], &[0, 0]);
                        prop_assert_eq!(length, u16::from_be_bytes([bytes[4], bytes[5]]));
                        prop_assert!(!(MIN_LENGTH..=MAX_LENGTH).contains(&length));
                    }
                }
            }

            #[test]
            fn every_valid_frame_decodes_to_what_was_encoded(request in request()) {
                let frame = framed(&request);
                let mut buf = BytesMut::from(&frame[..]);
                prop_assert_eq!(decode(&mut buf), Ok(Some(request)));
                prop_assert!(buf.is_empty());
            }

            #[test]
            fn every_valid_frame_fed_byte_by_byte_decodes_only_once_complete(
                request in request(),
            ) {
                let frame = framed(&request);
                let mut buf = BytesMut::new();
                for (i, &byte) in frame.iter().enumerate() {
                    buf.extend_from_slice(&[byte]);
                    if i + 1 < frame.len() {
                        prop_assert_eq!(decode(&mut buf), Ok(None), "after {} bytes", i + 1);
                    }
                }
                prop_assert_eq!(decode(&mut buf), Ok(Some(request)));
                prop_assert!(buf.is_empty());
            }

            #[test]
            fn frames_sharing_a_buffer_come_out_in_order_however_the_stream_is_cut(
                requests in prop::collection::vec(request(), 1..5),
                cuts in prop::collection::vec(1usize..300, 0..8),
            ) {
                let stream: Vec<u8> = requests.iter().flat_map(framed).collect();
                let mut buf = BytesMut::new();
                let mut decoded = Vec::new();
                let mut rest = &stream[..];
                let mut cuts = cuts.into_iter();
                while !rest.is_empty() {
                    let n = cuts.next().unwrap_or(rest.len()).min(rest.len());
                    buf.extend_from_slice(&rest[..n]);
                    rest = &rest[n..];
                    while let Some(request) =
                        decode(&mut buf).map_err(|e| TestCaseError::fail(e.to_string()))?
                    {
                        decoded.push(request);
                    }
                }
                prop_assert_eq!(decoded, requests);
                prop_assert!(buf.is_empty());
            }

            #[test]
            fn a_protocol_id_other_than_modbus_is_refused_by_its_value(
                request in request(),
                protocol in prop_oneof![1u16..=2, 1u16..],
                keep in 6usize..=260,
            ) {
                let mut frame = framed(&request);
                frame[2..4].copy_from_slice(&protocol.to_be_bytes());
                frame.truncate(keep);
                let mut buf = BytesMut::from(&frame[..]);
                prop_assert_eq!(decode(&mut buf), Err(HeaderError::Protocol(protocol)));
            }

            #[test]
            fn a_length_outside_2_to_254_is_refused_by_its_value(
                request in request(),
                length in length_field()
                    .prop_filter("a valid length", |l| !(MIN_LENGTH..=MAX_LENGTH).contains(l)),
                keep in 6usize..=260,
            ) {
                let mut frame = framed(&request);
                frame[4..6].copy_from_slice(&length.to_be_bytes());
                frame.truncate(keep);
                let mut buf = BytesMut::from(&frame[..]);
                prop_assert_eq!(decode(&mut buf), Err(HeaderError::Length(length)));
            }
        }
    }
}
