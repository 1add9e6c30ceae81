//! How frames look on the wire of one line, for the [`engine`](super::engine): encoding a PDU to
//! an address, telling when a received frame is complete, and checking and unwrapping it: Modbus
//! RTU ([`rtu`]), Modbus ASCII ([`ascii`]), or MBAP towards a Modbus TCP device (`tcp`: a
//! header with the gateway's own transaction id, no check, no silence rules). Pure functions over
//! bytes; knows nothing of ports, time or what a reply means. Also the one table of which
//! framing may run over which kind of transport ([`Framing::runs_over`]).
//!
//! An enum rather than a trait: the spec defines exactly two serial framings, and MBAP is the
//! third a line can have; a line's framing is chosen by its configuration at run time, and the
//! master stays one type (`LineMaster<Port>`) whichever framing its line uses.

use super::ascii;
use super::reply::ReplyForm;
use super::rtu::{self, FrameLen};
use super::timing::LineTiming;
use crate::mbap::{self, Header};
use std::time::Duration;

/// A line's framing, as `[[bus]] framing` names it.
/// Its serde is the configuration's (`config/bus.rs`), by [`Framing::name`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Framing {
    /// Modbus RTU: address, PDU, CRC-16; frames are delimited by silence, and most announce
    /// their length in their first bytes.
    #[default]
    Rtu,
    /// Modbus ASCII: `:`, hex pairs of address, PDU and LRC, CR LF; frames are delimited by
    /// their characters, and silence mid-frame (the inter-character timeout) fails one.
    Ascii,
    /// Modbus TCP towards a device that speaks it (MBAP): transaction id, protocol id 0, length,
    /// unit id, PDU; frames are delimited by their length, and a reply is the request's by its
    /// transaction id. Unit 0 is a unit like any other: there is no broadcast.
    Tcp,
}

/// How far the bytes received so far make a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Completion {
    /// The first this many bytes are a whole frame (more may follow: the next frame's).
    Whole(usize),
    /// Not whole yet; the frame is at least this many bytes long, so its wait is bounded by the
    /// time they take on the wire. Silence before they are in fails it.
    AtLeast(usize),
    /// Not whole yet, and the bytes cannot tell how long it is: silence decides.
    Open(Silence),
    /// These bytes cannot be a frame.
    Invalid,
}

/// What silence on the line means for a frame the bytes cannot tell the end of.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Silence {
    /// The frame is what came before it (RTU: t3.5).
    EndsFrame,
    /// The frame is cut short (ASCII: the inter-character timeout before CR LF).
    FailsFrame,
}

impl Framing {
    /// The longest frame on the wire, in characters.
    pub(crate) fn max_frame_len(self) -> usize {
        match self {
            Framing::Rtu => rtu::MAX_FRAME_LEN,
            Framing::Ascii => ascii::MAX_FRAME_LEN,
            Framing::Tcp => mbap::MAX_FRAME_LEN,
        }
    }

    /// Build the frame for `pdu` to `address` into `out` (cleared first); `transaction` is the
    /// MBAP transaction id (the serial framings have none).
    pub(crate) fn encode_into(self, out: &mut Vec<u8>, transaction: u16, address: u8, pdu: &[u8]) {
        match self {
            Framing::Rtu => rtu::encode_into(out, address, pdu),
            Framing::Ascii => ascii::encode_into(out, address, pdu),
            Framing::Tcp => {
                out.clear();
                let header = Header {
                    transaction,
                    unit: address,
                };
                mbap::encode(header, pdu, out);
            }
        }
    }

    /// The transaction id of a whole frame, in a framing that has one.
    pub(crate) fn transaction(self, whole: &[u8]) -> Option<u16> {
        match self {
            Framing::Rtu | Framing::Ascii => None,
            Framing::Tcp => mbap::transaction(whole),
        }
    }

    /// Whether address 0 is every slave's (a broadcast) rather than one unit's.
    pub fn broadcasts(self) -> bool {
        self != Framing::Tcp
    }

    /// The highest address a request may go to: 247 on a serial line, 255 on a Modbus TCP
    /// device (whose unit 255 is common).
    pub fn highest_address(self) -> u8 {
        match self {
            Framing::Rtu | Framing::Ascii => crate::line::MAX_SERIAL_ADDRESS,
            Framing::Tcp => u8::MAX,
        }
    }

    /// How far `received` makes a reply frame, when `request` (a PDU) went to `slave`, whose
    /// replies take `form`.
    pub(crate) fn reply_completion(
        self,
        received: &[u8],
        slave: u8,
        request: &[u8],
        form: ReplyForm,
    ) -> Completion {
        match self {
            Framing::Rtu => match rtu::reply_len_as(received, slave, request, form) {
                FrameLen::Exact(n) if received.len() >= n => Completion::Whole(n),
                FrameLen::Need(n) | FrameLen::Exact(n) => Completion::AtLeast(n),
                FrameLen::BySilence => Completion::Open(Silence::EndsFrame),
                FrameLen::Invalid => Completion::Invalid,
            },
            // CR LF ends a frame whatever it holds, so no length rule is needed.
            Framing::Ascii => Self::ascii_completion(received),
            Framing::Tcp => Self::mbap_completion(received),
        }
    }

    /// How far `received` makes a request frame, as a slave sees it.
    pub(crate) fn request_completion(self, received: &[u8]) -> Completion {
        match self {
            Framing::Rtu => match rtu::request_len(received) {
                FrameLen::Exact(n) if received.len() >= n => Completion::Whole(n),
                FrameLen::Need(n) | FrameLen::Exact(n) => Completion::AtLeast(n),
                FrameLen::BySilence => Completion::Open(Silence::EndsFrame),
                FrameLen::Invalid => Completion::Invalid,
            },
            Framing::Ascii => Self::ascii_completion(received),
            Framing::Tcp => Self::mbap_completion(received),
        }
    }

    /// How far `received` makes an MBAP frame (either way): whole at the header's length,
    /// invalid with a protocol id other than Modbus's or a length no frame has.
    pub(crate) fn mbap_completion(received: &[u8]) -> Completion {
        match mbap::frame_len(received) {
            Err(_) => Completion::Invalid,
            Ok(None) => Completion::AtLeast(mbap::HEADER_LEN + 1),
            Ok(Some(whole)) if received.len() >= whole => Completion::Whole(whole),
            Ok(Some(whole)) => Completion::AtLeast(whole),
        }
    }

    fn ascii_completion(received: &[u8]) -> Completion {
        match ascii::frame_end(received) {
            Some(end) => Completion::Whole(end),
            None => Completion::Open(Silence::FailsFrame),
        }
    }

    /// The address of a whole frame, with its PDU decoded into `pdu`; `None` when its check
    /// (CRC, LRC) fails or it is no frame.
    pub(crate) fn decode_into(self, whole: &[u8], pdu: &mut Vec<u8>) -> Option<u8> {
        match self {
            Framing::Rtu => rtu::crc_ok(whole).then(|| {
                pdu.clear();
                pdu.extend_from_slice(rtu::pdu_of(whole));
                whole[0]
            }),
            Framing::Ascii => ascii::decode_into(whole, pdu),
            Framing::Tcp => {
                let (header, data) = mbap::split(whole)?;
                pdu.clear();
                pdu.extend_from_slice(data);
                Some(header.unit)
            }
        }
    }

    /// The address and function code a frame's first bytes claim, as far as they go, whether or
    /// not the frame passes its check: for showing a frame that is no reply as it came.
    pub fn header(self, frame: &[u8]) -> (Option<u8>, Option<u8>) {
        match self {
            Framing::Rtu => (frame.first().copied(), frame.get(1).copied()),
            Framing::Ascii => {
                let pair = |at: usize| {
                    let digits = std::str::from_utf8(frame.get(at..at + 2)?).ok()?;
                    u8::from_str_radix(digits, 16).ok()
                };
                (pair(1), pair(3))
            }
            Framing::Tcp => (
                mbap::unit(frame),
                mbap::pdu(frame).and_then(|pdu| pdu.first().copied()),
            ),
        }
    }

    /// Characters on the wire of a frame carrying a PDU of `pdu_len` bytes: RTU adds the
    /// address and the CRC; ASCII writes address, PDU and LRC as hex pairs between `:` and CR LF.
    pub(crate) fn frame_len(self, pdu_len: usize) -> usize {
        match self {
            Framing::Rtu => pdu_len + 3,
            Framing::Ascii => 2 * (pdu_len + 2) + 3,
            Framing::Tcp => pdu_len + mbap::HEADER_LEN,
        }
    }

    /// The physical minimum of one transaction of these PDUs (docs/performance.md, the yardstick),
    /// for a slave that answers as soon as it may: RTU, request and reply on the wire, the
    /// slave's t3.5 before it answers and the master's before the next request; ASCII, the
    /// characters alone, since a frame ends at its LF and the spec owes no silence (the
    /// gateway's own quiet before a frame counts against it).
    pub fn transaction_minimum(
        self,
        timing: &LineTiming,
        request_pdu: usize,
        reply_pdu: usize,
    ) -> Duration {
        let (request, reply) = (self.frame_len(request_pdu), self.frame_len(reply_pdu));
        match self {
            Framing::Rtu => timing.transaction_minimum(request, reply, timing.t35),
            Framing::Ascii => timing.frame_time(request + reply),
            // No wire of the gateway's: the device's own time is all there is.
            Framing::Tcp => Duration::ZERO,
        }
    }

    /// The name `[[bus]] framing` and the metrics use.
    pub fn name(self) -> &'static str {
        match self {
            Framing::Rtu => "rtu",
            Framing::Ascii => "ascii",
            Framing::Tcp => "tcp",
        }
    }
}

/// What carries a line's bytes, as far as its framing cares: the kinds of
/// [`Transport`](super::Transport) a line may have.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TransportKind {
    /// A serial port of the gateway's own.
    Serial,
    /// The built-in simulated line.
    Sim,
    /// A serial device server's socket in raw (transparent) mode.
    Tcp,
    /// A serial device server's socket speaking Telnet COM-PORT-OPTION (RFC 2217).
    Rfc2217,
    /// A TLS connection to a Modbus TCP device (Modbus/TCP Security).
    Tls,
}

impl TransportKind {
    /// As a message names it.
    pub fn name(self) -> &'static str {
        match self {
            TransportKind::Serial => "a serial port",
            TransportKind::Sim => "the simulated line",
            TransportKind::Tcp => "a serial device server's raw TCP socket",
            TransportKind::Rfc2217 => "a serial device server's RFC 2217 socket",
            TransportKind::Tls => "a Modbus/TCP Security (TLS) connection",
        }
    }

    /// The `transport` label of `modbus_gateway_bus_info`.
    pub fn label(self) -> &'static str {
        match self {
            TransportKind::Serial => "serial",
            TransportKind::Sim => "sim",
            TransportKind::Tcp => "tcp",
            TransportKind::Rfc2217 => "rfc2217",
            TransportKind::Tls => "tls",
        }
    }

    /// Whether the line's bytes cross a network to a serial device server: its timing then
    /// budgets the link (docs/device-servers.md).
    pub fn is_network(self) -> bool {
        matches!(
            self,
            TransportKind::Tcp | TransportKind::Rfc2217 | TransportKind::Tls
        )
    }
}

/// Which framing may run over which transport: the one place that decides, for every line. Both
/// serial framings need a byte stream onto a line that keeps the timing; a device server's socket
/// is one (its UART keeps the wire's timing, the link's delay is budgeted). MBAP needs a device
/// that speaks Modbus TCP: on a plain socket, or inside TLS. A framing or
/// transport that comes adds its rows here, and nowhere else.
const LINES: &[(TransportKind, Framing)] = &[
    (TransportKind::Serial, Framing::Rtu),
    (TransportKind::Serial, Framing::Ascii),
    (TransportKind::Sim, Framing::Rtu),
    (TransportKind::Sim, Framing::Ascii),
    (TransportKind::Tcp, Framing::Rtu),
    (TransportKind::Tcp, Framing::Ascii),
    (TransportKind::Rfc2217, Framing::Rtu),
    (TransportKind::Rfc2217, Framing::Ascii),
    // A Modbus TCP device: MBAP on a plain socket, or inside TLS.
    (TransportKind::Tcp, Framing::Tcp),
    (TransportKind::Tls, Framing::Tcp),
];

impl Framing {
    /// Whether a line may frame its bytes this way over `transport` (the table `LINES`).
    pub(crate) fn runs_over(self, transport: TransportKind) -> bool {
        LINES.contains(&(transport, self))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_serial_framing_runs_over_every_transport_and_mbap_only_over_a_plain_socket() {
        for transport in [
            TransportKind::Serial,
            TransportKind::Sim,
            TransportKind::Tcp,
            TransportKind::Rfc2217,
            TransportKind::Tls,
        ] {
            for framing in [Framing::Rtu, Framing::Ascii] {
                assert_eq!(
                    framing.runs_over(transport),
                    transport != TransportKind::Tls,
                    "{framing:?} over {transport:?}"
                );
            }
            assert_eq!(
                Framing::Tcp.runs_over(transport),
                matches!(transport, TransportKind::Tcp | TransportKind::Tls)
            );
        }
    }

    #[test]
    fn a_frame_is_whole_at_its_length_and_a_foreign_protocol_or_length_is_no_frame() {
        let completion = Framing::mbap_completion;
        let mut frame = Vec::new();
        Framing::Tcp.encode_into(&mut frame, 0x1234, 0xFF, &[0x03, 0x00, 0x00, 0x00, 0x02]);
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
        assert_eq!(Framing::Tcp.decode_into(&frame, &mut pdu), Some(0xFF));
        assert_eq!(pdu, [0x03, 0x00, 0x00, 0x00, 0x02]);
        let mut other_protocol = frame.clone();
        other_protocol[3] = 1;
        assert_eq!(completion(&other_protocol), Completion::Invalid);
        let mut too_short = frame;
        too_short[5] = 1;
        assert_eq!(completion(&too_short), Completion::Invalid);
    }

    /// Goodrive300 manual 10.4.1: slave 01H's reply with 0004H = 1388H, 0005H = 0000H.
    const READ_REPLY: [u8; 9] = [
        0x01, // slave address
        0x03, // read holding registers
        0x04, // four data bytes
        0x13, 0x88, 0x00, 0x00, // 0004H, 0005H
        0x7E, 0x9D, // CRC
    ];
    const READ: [u8; 5] = [0x03, 0x00, 0x04, 0x00, 0x02];

    #[test]
    fn an_rtu_reply_is_whole_at_its_length_and_bounded_by_it_before() {
        let rtu = Framing::Rtu;
        let form = ReplyForm::Standard;
        assert_eq!(
            rtu.reply_completion(&READ_REPLY[..2], 1, &READ, form),
            Completion::AtLeast(3)
        );
        assert_eq!(
            rtu.reply_completion(&READ_REPLY[..5], 1, &READ, form),
            Completion::AtLeast(9)
        );
        assert_eq!(
            rtu.reply_completion(&READ_REPLY, 1, &READ, form),
            Completion::Whole(9)
        );
        let stream = [&READ_REPLY[..], &[0x02, 0x03]].concat();
        assert_eq!(
            rtu.reply_completion(&stream, 1, &READ, form),
            Completion::Whole(9)
        );
    }

    #[test]
    fn an_rtu_reply_the_bytes_cannot_measure_ends_by_silence() {
        assert_eq!(
            Framing::Rtu.reply_completion(&[1, 0x41, 9], 1, &[0x41], ReplyForm::Standard),
            Completion::Open(Silence::EndsFrame)
        );
        assert_eq!(
            Framing::Rtu.reply_completion(&[1, 0x03, 0xFF], 1, &READ, ReplyForm::Standard),
            Completion::Invalid
        );
    }

    #[test]
    fn an_rtu_frame_decodes_to_its_address_and_pdu_only_with_a_good_crc() {
        let mut out = vec![0xAA];
        Framing::Rtu.encode_into(&mut out, 0, 1, &READ_REPLY[1..7]);
        assert_eq!(out, READ_REPLY);
        let mut pdu = Vec::new();
        assert_eq!(Framing::Rtu.decode_into(&READ_REPLY, &mut pdu), Some(1));
        assert_eq!(pdu, &READ_REPLY[1..7]);
        let mut bad = READ_REPLY;
        bad[3] ^= 0x01;
        assert_eq!(Framing::Rtu.decode_into(&bad, &mut pdu), None);
        assert_eq!(Framing::Rtu.max_frame_len(), 256);
    }

    #[test]
    fn an_ascii_reply_is_whole_at_its_cr_lf_and_fails_if_silence_comes_first() {
        let ascii = Framing::Ascii;
        let form = ReplyForm::Standard;
        let reply = b":010304138800005D\r\n:02";
        assert_eq!(
            ascii.reply_completion(&reply[..10], 1, &READ, form),
            Completion::Open(Silence::FailsFrame)
        );
        assert_eq!(
            ascii.reply_completion(reply, 1, &READ, form),
            Completion::Whole(19)
        );
        // A user-defined function code needs no length rule either.
        assert_eq!(
            ascii.reply_completion(b":014109B5\r\n", 1, &[0x41], form),
            Completion::Whole(11)
        );
        let mut pdu = Vec::new();
        assert_eq!(ascii.decode_into(&reply[..19], &mut pdu), Some(1));
        assert_eq!(pdu, &READ_REPLY[1..7]);
        let mut out = Vec::new();
        ascii.encode_into(&mut out, 0, 1, &READ);
        assert_eq!(out, b":010300040002F6\r\n");
        assert_eq!(ascii.max_frame_len(), 513);
    }

    #[test]
    fn an_ascii_transaction_costs_its_characters_and_an_rtu_one_its_bytes_and_two_t35() {
        let timing = LineTiming::new(&crate::line::SerialFormat {
            baud: 9600,
            data_bits: 7,
            parity: crate::line::Parity::Even,
            stop_bits: 1,
        });
        // Read 10 registers: a 5-byte request PDU, a 22-byte reply PDU.
        assert_eq!(Framing::Ascii.frame_len(5), 17);
        assert_eq!(Framing::Ascii.frame_len(22), 51);
        assert_eq!(
            Framing::Ascii.transaction_minimum(&timing, 5, 22),
            timing.frame_time(68)
        );
        assert_eq!(
            Framing::Rtu.transaction_minimum(&timing, 5, 22),
            timing.frame_time(8 + 25) + timing.t35 * 2
        );
    }
}
