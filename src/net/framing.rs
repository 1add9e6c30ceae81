//! The codec of a listener's [`UpstreamFraming`]: MBAP (Modbus TCP, `server.listen`; the same
//! inside TLS, `server.listen_tls`, and in datagrams, `server.listen_udp`) or plain RTU frames on
//! the stream (RTU over TCP, `server.listen_rtu_over_tcp`, as serial device servers and mbpoll's
//! `-m enc` send them). The session is the same for all; only the framing of requests and
//! replies differs. Pure functions over buffers; knows nothing of the transport.

use crate::line::rtu::{self, FrameLen};
pub(crate) use crate::master::UpstreamFraming;
use crate::mbap::{self, Header, HeaderError, Request};
use bytes::BytesMut;

/// A stream that is not Modbus TCP (or not RTU over TCP); the connection is closed.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error(transparent)]
    Mbap(#[from] HeaderError),
    #[error("RTU over TCP: bytes that are no request frame, longer than a frame")]
    RtuTooLong,
}

/// What the front of a connection's buffer holds.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Decoded {
    Request(Request),
    /// An RTU frame whose CRC fails, taken off the buffer and not answered, as a slave would.
    BadCrc,
}

impl UpstreamFraming {
    /// Take one request (or one bad frame) off the front of `buf`: `Ok(None)` until a whole one
    /// is in. An error closes the connection.
    pub(crate) fn decode(self, buf: &mut BytesMut) -> Result<Option<Decoded>, FrameError> {
        match self {
            UpstreamFraming::Mbap => Ok(mbap::decode(buf)?.map(Decoded::Request)),
            UpstreamFraming::Rtu => decode_rtu(buf),
        }
    }

    /// The reply to the request that came with `header`, carrying `pdu`, into `out` (cleared).
    pub(crate) fn encode(self, header: Header, pdu: &[u8], out: &mut Vec<u8>) {
        out.clear();
        match self {
            UpstreamFraming::Mbap => mbap::encode(header, pdu, out),
            UpstreamFraming::Rtu => rtu::encode_into(out, header.unit, pdu),
        }
    }
}

/// An RTU request on a stream is delimited by the RTU length rules. A function code whose
/// request length its bytes cannot tell (a user-defined one) has no silence to end it on TCP: the
/// bytes in the buffer are taken as the request once their CRC checks, and wait for more until
/// then (a connection that never frames is closed at `frame_timeout`, or once it holds more
/// than a frame).
fn decode_rtu(buf: &mut BytesMut) -> Result<Option<Decoded>, FrameError> {
    let len = match rtu::request_len(buf) {
        FrameLen::Exact(n) if buf.len() >= n => n,
        FrameLen::BySilence if buf.len() >= rtu::MIN_FRAME_LEN && rtu::crc_ok(buf) => buf.len(),
        FrameLen::Invalid => return Err(FrameError::RtuTooLong),
        _ if buf.len() > rtu::MAX_FRAME_LEN => return Err(FrameError::RtuTooLong),
        _ => return Ok(None),
    };
    let frame = buf.split_to(len);
    if !rtu::crc_ok(&frame) {
        return Ok(Some(Decoded::BadCrc));
    }
    let request = Request {
        header: Header {
            transaction: 0,
            unit: frame[0],
        },
        pdu: rtu::pdu_of(&frame).to_vec(),
    };
    Ok(Some(Decoded::Request(request)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Goodrive300 manual 10.4.1: read 2 words from 0004H of slave 01H.
    const READ: [u8; 8] = [0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA];

    fn rtu(bytes: &[u8]) -> Result<Option<Decoded>, FrameError> {
        UpstreamFraming::Rtu.decode(&mut BytesMut::from(bytes))
    }

    fn request(unit: u8, pdu: &[u8]) -> Option<Decoded> {
        Some(Decoded::Request(Request {
            header: Header {
                transaction: 0,
                unit,
            },
            pdu: pdu.to_vec(),
        }))
    }

    #[test]
    fn an_rtu_request_is_whole_at_its_length_and_not_before_byte_by_byte() {
        for n in 0..READ.len() {
            assert_eq!(rtu(&READ[..n]), Ok(None), "{n} bytes");
        }
        assert_eq!(rtu(&READ), Ok(request(1, &READ[1..6])));
    }

    #[test]
    fn two_rtu_requests_in_one_buffer_come_out_one_after_the_other() {
        let mut buf = BytesMut::from(&[READ, READ][..].concat()[..]);
        let framing = UpstreamFraming::Rtu;
        assert_eq!(framing.decode(&mut buf), Ok(request(1, &READ[1..6])));
        assert_eq!(framing.decode(&mut buf), Ok(request(1, &READ[1..6])));
        assert_eq!(framing.decode(&mut buf), Ok(None));
    }

    #[test]
    fn a_bad_crc_takes_the_frame_off_and_the_next_request_still_comes_through() {
        let mut bad = READ;
        bad[7] ^= 0x01;
        let mut buf = BytesMut::from(&[bad, READ][..].concat()[..]);
        let framing = UpstreamFraming::Rtu;
        assert_eq!(framing.decode(&mut buf), Ok(Some(Decoded::BadCrc)));
        assert_eq!(framing.decode(&mut buf), Ok(request(1, &READ[1..6])));
    }

    #[test]
    fn a_user_defined_function_is_taken_once_its_crc_checks() {
        let frame = rtu::encode(5, &[0x41, 0x01, 0x02]);
        assert_eq!(rtu(&frame[..4]), Ok(None));
        assert_eq!(rtu(&frame), Ok(request(5, &[0x41, 0x01, 0x02])));
    }

    #[test]
    fn bytes_that_cannot_be_an_rtu_request_close_the_connection() {
        // Write multiple registers announcing 255 data bytes: longer than a frame.
        assert_eq!(
            rtu(&[0x01, 0x10, 0x00, 0x00, 0x00, 0x7F, 0xFF]),
            Err(FrameError::RtuTooLong)
        );
        // A user-defined code whose bytes never check: more than a frame of them.
        let junk: Vec<u8> = std::iter::repeat_n([0x01, 0x41], 200).flatten().collect();
        assert_eq!(rtu(&junk), Err(FrameError::RtuTooLong));
    }

    #[test]
    fn replies_are_framed_as_the_request_was() {
        let header = Header {
            transaction: 7,
            unit: 1,
        };
        let mut out = vec![0xAA];
        UpstreamFraming::Rtu.encode(header, &[0x83, 0x0A], &mut out);
        assert_eq!(out, rtu::encode(1, &[0x83, 0x0A]));
        UpstreamFraming::Mbap.encode(header, &[0x83, 0x0A], &mut out);
        assert_eq!(out, [0, 7, 0, 0, 0, 3, 1, 0x83, 0x0A]);
    }
}
