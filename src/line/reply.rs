//! Whether a received PDU answers the request waiting for it, and how long such a reply is, from
//! the function-code table in [`crate::pdu`] and the slave's [`ReplyForm`]. Works on addresses
//! and PDUs, after the framing has checked and unwrapped the frame: knows nothing of CRC, LRC,
//! frame lengths, ports or time.

use crate::mbap;
use crate::pdu::{self, PduLen, Shape, EXCEPTION_BIT, EXCEPTION_PDU_LEN};

/// How a slave shapes its replies where it departs from the standard.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ReplyForm {
    #[default]
    Standard,
    /// Read Holding Registers (03) replies may carry their byte count as two bytes, big-endian
    /// (the "non-standard Modbus" mode of some inverters). Standard replies are accepted too.
    WideReadCount,
}

/// What a received frame is to the request that is waiting for its answer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Verdict {
    /// It answers the request (normally or with an exception).
    Answer,
    /// Intact, from the slave asked, with the request's function code, but not the shape the
    /// request asks for (byte count, echo, sub-function). Either the slave's own odd answer, or a
    /// late answer to an earlier request to it: only the caller knows whether one may be pending.
    Malformed,
    /// Intact, but not from this exchange: another slave's frame, or another function's reply.
    /// Never delivered to anyone.
    Foreign,
    /// The frame's check (CRC, LRC) fails: noise, a collision, or a frame cut short. Only the
    /// tests' whole-frame check (`rtu::check_reply`) says it: the framing drops such a frame
    /// before anything is judged, and `judge` never says it.
    #[cfg(test)]
    Corrupt,
}

/// Length of the reply PDU whose first bytes are `pdu`, as far as they tell. `request` is the
/// request PDU when the reply claims to answer it (the slave asked, its function code), `None`
/// otherwise: only then do the lengths that only the request knows, and `form`, apply.
pub(crate) fn reply_len(pdu: &[u8], request: Option<&[u8]>, form: ReplyForm) -> PduLen {
    let Some(&function) = pdu.first() else {
        return PduLen::Need(1);
    };
    if function & EXCEPTION_BIT != 0 {
        return PduLen::Exact(EXCEPTION_PDU_LEN);
    }
    if form == ReplyForm::WideReadCount
        && function == pdu::code::READ_HOLDING_REGISTERS
        && request.is_some()
    {
        // A standard count is never 0, so a 0 where it belongs is the high byte of a wide one.
        let wide = pdu.get(1) == Some(&0);
        return pdu::Len::Counted { at: 1, wide }.of(pdu, request);
    }
    pdu::function(function).map_or(PduLen::Unknown, |row| row.reply.of(pdu, request))
}

fn quantity(request: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([
        *request.get(at)?,
        *request.get(at + 1)?,
    ]))
}

fn fits_request(reply: &[u8], request: &[u8]) -> bool {
    let shape = request
        .first()
        .and_then(|&code| pdu::function(code))
        .map_or(Shape::Any, |row| row.reply_shape);
    match shape {
        Shape::ByteCount { quantity_at, unit } => {
            let byte_count = reply.get(1).map(|&b| usize::from(b));
            quantity(request, quantity_at).is_none_or(|q| byte_count == Some(unit.bytes(q)))
        }
        Shape::Echo { from, to } => reply.get(from..to) == request.get(from..to),
        Shape::Any => true,
    }
}

/// Judge the intact frame from `address` carrying `pdu`, received after sending `request` (a PDU)
/// to `slave`.
pub(crate) fn judge(
    address: u8,
    pdu: &[u8],
    slave: u8,
    request: &[u8],
    form: ReplyForm,
) -> Verdict {
    // A function code with the exception bit is no request: nothing answers it.
    let Some(&request_function) = request.first().filter(|&&f| f & EXCEPTION_BIT == 0) else {
        return Verdict::Foreign;
    };
    if address != slave {
        return Verdict::Foreign;
    }
    let Some(&function) = pdu.first() else {
        return Verdict::Foreign;
    };
    if function == request_function | EXCEPTION_BIT && pdu.len() == EXCEPTION_PDU_LEN {
        return Verdict::Answer;
    }
    if function != request_function {
        Verdict::Foreign
    } else if fits_request(&answer_pdu(pdu, form), request) {
        Verdict::Answer
    } else {
        Verdict::Malformed
    }
}

/// A reply PDU that [`judge`] found to be the answer, in standard form: a wide read count loses
/// its high byte, so the master on TCP gets what the standard says.
pub(crate) fn answer_pdu(pdu: &[u8], form: ReplyForm) -> Vec<u8> {
    match pdu {
        [pdu::code::READ_HOLDING_REGISTERS, 0x00, count, data @ ..]
            if form == ReplyForm::WideReadCount =>
        {
            let mut standard = Vec::with_capacity(pdu.len() - 1);
            standard.extend_from_slice(&[0x03, *count]);
            standard.extend_from_slice(data);
            standard
        }
        _ => pdu.to_vec(),
    }
}

/// Whether `received` is a Modbus TCP (MBAP) answer to the serial `frame` sent: a server that read
/// the frame's first bytes as an MBAP header answers with its transaction id (the frame's address
/// and function code), its protocol id (0, or the frame's next two bytes echoed), and a length
/// the bytes after it fill.
pub(crate) fn is_mbap_reply(received: &[u8], frame: &[u8]) -> bool {
    if received.len() < mbap::HEADER_LEN + 1 || frame.len() < 4 {
        return false;
    }
    let field = |bytes: &[u8]| mbap::transaction(bytes).zip(mbap::protocol(bytes));
    let (Some((transaction, protocol)), Some((address_function, next))) =
        (field(received), field(frame))
    else {
        return false;
    };
    let length = mbap::length(received).map_or(0, usize::from);
    transaction == address_function
        && (protocol == 0 || protocol == next)
        && length >= 2
        && received.len() == mbap::HEADER_LEN - 1 + length
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Read two holding registers from 0004H (Goodrive300 manual 10.4.1), and its answer.
    const READ: [u8; 5] = [0x03, 0x00, 0x04, 0x00, 0x02];
    const READ_ANSWER: [u8; 6] = [0x03, 0x04, 0x13, 0x88, 0x00, 0x00];

    #[test]
    fn a_reply_is_judged_by_its_address_function_and_shape_without_any_framing() {
        let standard = ReplyForm::Standard;
        assert_eq!(judge(1, &READ_ANSWER, 1, &READ, standard), Verdict::Answer);
        assert_eq!(judge(2, &READ_ANSWER, 1, &READ, standard), Verdict::Foreign);
        assert_eq!(judge(1, &[0x83, 0x02], 1, &READ, standard), Verdict::Answer);
        assert_eq!(
            judge(1, &[0x84, 0x02], 1, &READ, standard),
            Verdict::Foreign
        );
        let short = [0x03, 0x02, 0x13, 0x88];
        assert_eq!(judge(1, &short, 1, &READ, standard), Verdict::Malformed);
        assert_eq!(judge(1, &[], 1, &READ, standard), Verdict::Foreign);
    }

    /// The count is measured only for such a reply too.
    #[test]
    fn a_wide_read_count_is_answered_only_for_a_reply_that_claims_the_request() {
        let wide = [0x03, 0x00, 0x04, 0x13, 0x88, 0x00, 0x00];
        let form = ReplyForm::WideReadCount;
        assert_eq!(reply_len(&wide, Some(&READ), form), PduLen::Exact(7));
        assert_eq!(reply_len(&wide, None, form), PduLen::Exact(2));
        assert_eq!(reply_len(&wide[..1], Some(&READ), form), PduLen::Need(2));
        assert_eq!(judge(1, &wide, 1, &READ, form), Verdict::Answer);
        assert_eq!(answer_pdu(&wide, form), READ_ANSWER);
        assert_eq!(answer_pdu(&wide, ReplyForm::Standard), wide);
    }

    #[test]
    fn a_modbus_tcp_servers_answer_to_an_rtu_frame_is_told_from_a_slaves_reply() {
        // Read 2 holding registers from 0000H of slave 1, as RTU; pymodbus 3.16's Modbus TCP
        // server reads it as MBAP (transaction 0103H, unit C4H, function 0BH) and answers so.
        let frame = [0x01, 0x03, 0x00, 0x00, 0x00, 0x02, 0xC4, 0x0B];
        let answer = [
            0x01, 0x03, 0x00, 0x00, 0x00, 0x06, 0xC4, 0x0B, 0x00, 0x00, 0x00, 0x00,
        ];
        assert!(is_mbap_reply(&answer, &frame));
        // Cut short, or with more after it, it is not one frame.
        assert!(!is_mbap_reply(&answer[..11], &frame));
        assert!(!is_mbap_reply(&[&answer[..], &[0]].concat(), &frame));
        // The slave's own RTU reply, even one that starts alike, is not.
        let reply = [0x01, 0x03, 0x04, 0x00, 0x07, 0x00, 0x07, 0x3A, 0x30];
        assert!(!is_mbap_reply(&reply, &frame));
        // A write's echo whose value happens to match the length is no MBAP answer either:
        // protocol id 0001H is neither 0 nor echoed.
        let write = [0x01, 0x06, 0x00, 0x01, 0x00, 0x02, 0x59, 0xCB];
        assert!(!is_mbap_reply(
            &write,
            &[0x01, 0x06, 0x00, 0x00, 0x00, 0x02, 0x08, 0x0B]
        ));
    }
}
