use super::*;
use crate::line::{ascii, rtu};

const CHAR: Duration = Duration::from_micros(100);
const SILENCE: Duration = Duration::from_micros(1750);
const TIMEOUT: Duration = Duration::from_millis(100);

fn ear(framing: Framing) -> Ear {
    let timing = EarTiming {
        silence: SILENCE,
        char_time: CHAR,
    };
    Ear::new(framing, timing, [TIMEOUT; 256])
}

/// Read two registers from 0004H of slave 1, and the manual's reply (shared/reference/001).
fn read() -> (Vec<u8>, Vec<u8>) {
    let request = rtu::encode(0x01, &[0x03, 0x00, 0x04, 0x00, 0x02]);
    let reply = rtu::encode(0x01, &[0x03, 0x04, 0x13, 0x88, 0x00, 0x00]);
    (request, reply)
}

fn heard(ear: &mut Ear, chunks: &[&[u8]], start: Instant) -> Vec<Event> {
    let mut out = Vec::new();
    let mut at = start;
    for chunk in chunks {
        at += CHAR * u32::try_from(chunk.len()).unwrap();
        ear.feed(chunk, at, &mut out);
    }
    out
}

fn answered(out: &[Event]) -> Vec<(u8, Vec<u8>, Vec<u8>)> {
    out.iter()
        .filter_map(|h| match h {
            Event::Answered { request, reply, .. } => {
                Some((request.address, request.pdu.clone(), reply.pdu.clone()))
            }
            _ => None,
        })
        .collect()
}

#[test]
fn a_request_and_its_reply_in_one_read_are_paired() {
    let (request, reply) = read();
    let mut ear = ear(Framing::Rtu);
    let both = [request.clone(), reply.clone()].concat();
    let out = heard(&mut ear, &[&both], Instant::now());
    assert_eq!(
        answered(&out),
        vec![(1, request[1..6].to_vec(), reply[1..7].to_vec())]
    );
    assert_eq!(out.len(), 1);
}

#[test]
fn byte_by_byte_frames_pair_the_same_and_the_response_time_is_the_silence_between() {
    let (request, reply) = read();
    let mut ear = ear(Framing::Rtu);
    let mut out = Vec::new();
    let mut at = Instant::now();
    for byte in &request {
        at += CHAR;
        ear.feed(&[*byte], at, &mut out);
    }
    at += Duration::from_millis(5);
    for byte in &reply {
        at += CHAR;
        ear.feed(&[*byte], at, &mut out);
    }
    match out.as_slice() {
        [Event::Answered { response, .. }] => {
            assert_eq!(*response, Duration::from_millis(5));
        }
        other => panic!("heard {other:?}"),
    }
}

#[test]
fn a_reply_with_a_bad_crc_ends_its_request_as_corrupt() {
    let (request, mut reply) = read();
    reply[4] ^= 0xFF;
    let mut ear = ear(Framing::Rtu);
    let out = heard(&mut ear, &[&request, &reply], Instant::now());
    match out.as_slice() {
        [Event::Corrupt {
            request: Some(r), ..
        }] => assert_eq!(r.address, 1),
        other => panic!("heard {other:?}"),
    }
    assert_eq!(ear.next_deadline(), None, "nothing is left waiting");
}

#[test]
fn a_request_nobody_answers_is_unanswered_at_its_timeout_or_the_next_request() {
    let (request, reply) = read();
    let start = Instant::now();
    let mut ear = ear(Framing::Rtu);
    let mut out = heard(&mut ear, &[&request], start);
    let deadline = ear.next_deadline().expect("a reply is due");
    ear.tick(deadline - Duration::from_millis(1), &mut out);
    assert!(out.is_empty());
    ear.tick(deadline, &mut out);
    assert!(matches!(out.as_slice(), [Event::Unanswered(r)] if r.address == 1));
    // The next request comes before the timeout: the first went unanswered all the same.
    let other = rtu::encode(0x02, &[0x03, 0x00, 0x00, 0x00, 0x01]);
    let mut out = heard(&mut ear, &[&request, &other], deadline);
    assert!(matches!(out.as_slice(), [Event::Unanswered(r)] if r.address == 1));
    out.clear();
    ear.tick(deadline + TIMEOUT * 3, &mut out);
    assert!(matches!(out.as_slice(), [Event::Unanswered(r)] if r.address == 2));
    drop(reply);
}

#[test]
fn another_slaves_reply_is_unpaired_and_the_asked_slaves_still_pairs() {
    let (request, reply) = read();
    let foreign = rtu::encode(0x02, &[0x03, 0x04, 0xDE, 0xAD, 0xBE, 0xEF]);
    let mut ear = ear(Framing::Rtu);
    let out = heard(&mut ear, &[&request, &foreign, &reply], Instant::now());
    assert!(matches!(&out[0], Event::Unpaired(f) if f.address == 2));
    assert_eq!(answered(&out).len(), 1);
    assert_eq!(answered(&out)[0].0, 1);
}

#[test]
fn a_reply_to_nobody_is_unpaired_and_a_wrong_shape_reply_is_no_answer() {
    let (request, _) = read();
    let nobody = rtu::encode(0x05, &[0x03, 0x02, 0x00, 0x07]);
    let mut ear = ear(Framing::Rtu);
    let start = Instant::now();
    let mut out = heard(&mut ear, &[&nobody], start);
    ear.tick(start + SILENCE * 2, &mut out);
    assert!(
        matches!(out.as_slice(), [Event::Unpaired(f)] if f.address == 5),
        "{out:?}"
    );
    // Straight before a request, with no silence between: its bytes alone tell its length.
    let out = heard(
        &mut ear,
        &[&[nobody.clone(), request.clone()].concat()],
        start,
    );
    assert!(
        matches!(&out[..], [Event::Unpaired(f)] if f.address == 5),
        "{out:?}"
    );
    // Slave 1 answers a read of two registers with one: intact, but not the answer.
    let short = rtu::encode(0x01, &[0x03, 0x02, 0x00, 0x07]);
    let out = heard(&mut ear, &[&request, &short], Instant::now());
    assert!(answered(&out).is_empty(), "{out:?}");
}

#[test]
fn an_exception_answers_and_a_broadcast_awaits_no_reply() {
    let (request, _) = read();
    let exception = rtu::encode(0x01, &[0x83, 0x02]);
    let broadcast = rtu::encode(0x00, &[0x06, 0x00, 0x01, 0x00, 0x02]);
    let mut ear = ear(Framing::Rtu);
    let out = heard(
        &mut ear,
        &[&request, &exception, &broadcast],
        Instant::now(),
    );
    assert!(matches!(&out[0], Event::Answered { reply, .. } if reply.is_exception()));
    assert!(matches!(&out[1], Event::Broadcast(f) if f.address == 0));
    assert_eq!(ear.next_deadline(), None);
}

#[test]
fn noise_then_silence_is_broken_and_the_next_frames_pair() {
    let (request, reply) = read();
    let mut ear = ear(Framing::Rtu);
    let start = Instant::now();
    let mut out = heard(&mut ear, &[&[0x01, 0x03, 0x00]], start);
    ear.tick(start + Duration::from_millis(10), &mut out);
    assert!(matches!(out.as_slice(), [Event::Broken { bytes, .. }] if bytes.len() == 3));
    let out = heard(
        &mut ear,
        &[&request, &reply],
        start + Duration::from_millis(20),
    );
    assert_eq!(answered(&out).len(), 1);
}

#[test]
fn random_bytes_never_pair_and_never_pile_up() {
    let mut ear = ear(Framing::Rtu);
    let mut seed = 0x2545_F491_u32;
    let mut out = Vec::new();
    let mut at = Instant::now();
    for _ in 0..20_000 {
        let mut chunk = [0u8; 16];
        for byte in &mut chunk {
            seed ^= seed << 13;
            seed ^= seed >> 17;
            seed ^= seed << 5;
            *byte = seed.to_le_bytes()[0];
        }
        at += CHAR * 16;
        ear.feed(&chunk, at, &mut out);
        assert!(ear.buf.len() <= 2 * rtu::MAX_FRAME_LEN);
        out.retain(|h| matches!(h, Event::Answered { .. }));
    }
    assert!(out.len() <= 2, "{} chance pairings", out.len());
}

#[test]
fn ascii_frames_pair_by_their_characters_and_a_bad_lrc_is_corrupt() {
    let request = ascii::encode(0x01, &[0x03, 0x00, 0x04, 0x00, 0x02]);
    let reply = ascii::encode(0x01, &[0x03, 0x04, 0x13, 0x88, 0x00, 0x00]);
    let mut ear = ear(Framing::Ascii);
    let out = heard(&mut ear, &[&request, &reply], Instant::now());
    assert_eq!(answered(&out).len(), 1);
    let mut bad = reply.clone();
    let at = bad.len() - 4;
    bad[at] = if bad[at] == b'0' { b'1' } else { b'0' };
    let out = heard(&mut ear, &[&request, &bad], Instant::now());
    assert!(
        matches!(
            out.as_slice(),
            [Event::Corrupt {
                request: Some(_),
                ..
            }]
        ),
        "{out:?}"
    );
}
