//! What a device server can make its port hold, bounded: one drain of the socket before a frame,
//! and on an `rfc2217://` line the Telnet answers owed to the converter between two frames (a
//! converter toggling options back and forth owes little; one past [`MAX_OWED`] is dropped).

use super::tests::Measured;
use super::*;
use crate::metrics::LinkDrop;
use tokio::io::DuplexStream;

const IAC: u8 = 255;
const DONT: u8 = 254;
const DO: u8 = 253;
const WONT: u8 = 252;
const WILL: u8 = 251;

/// One round of a converter toggling options, as found in issue 38.
#[rustfmt::skip]
const TOGGLING: [u8; 15] = [
    IAC, DO, 0, IAC, DONT, 0, // TRANSMIT-BINARY on the client's side, on and off
    IAC, WILL, 3, IAC, WONT, 3, // SUPPRESS-GO-AHEAD on the server's side, on and off
    IAC, DO, 99, // an option nobody knows
];

/// An `rfc2217://` port past its negotiation on an in-memory link of `capacity` bytes, and the
/// link's far end.
fn telnet_port(capacity: usize) -> (NetPort<Measured>, DuplexStream) {
    let (near, far) = tokio::io::duplex(capacity);
    let link = Measured {
        stream: near,
        round_trip: None,
    };
    let mut port = NetPort::new(link, "192.0.2.7:4001".into());
    port.telnet = Some(Box::new(Telnet::new()));
    (port, far)
}

#[test]
fn options_toggled_back_and_forth_leave_at_most_one_answer_owed_for_each() {
    let mut telnet = Telnet::new();
    let (mut data, mut owed) = (Vec::new(), Vec::new());
    telnet.receive(&TOGGLING, &mut data, &mut owed);
    let first = owed.clone();
    assert_eq!(first, [IAC, WONT, 0, IAC, DONT, 3, IAC, WONT, 99]);
    for _ in 0..10_000 {
        telnet.receive(&TOGGLING, &mut data, &mut owed);
    }
    // Each round turns both options on (which withdraws the answers owed for turning them off)
    // and off again; option 99 was refused once.
    assert_eq!(owed, [IAC, WONT, 99, IAC, WONT, 0, IAC, DONT, 3]);
    assert!(data.is_empty());
}

#[tokio::test]
async fn a_converter_toggling_options_while_the_line_is_idle_is_owed_a_few_bytes() {
    let (mut port, mut far) = telnet_port(4096);
    let converter = tokio::spawn(async move {
        for _ in 0..2_000 {
            far.write_all(&TOGGLING).await.unwrap();
        }
        far.write_all(&[0x42]).await.unwrap(); // a data byte at last
        far
    });
    let mut got = Vec::new();
    while got.is_empty() {
        port.recv(&mut got).await.unwrap();
    }
    assert_eq!(got, [0x42]);
    assert!(port.owed.len() <= 9, "{} bytes owed", port.owed.len());
    // They go with the next frame, before it.
    let mut far = converter.await.unwrap();
    port.send(&[0x01, 0x03]).await.unwrap();
    let mut sent = vec![0u8; port.out.len()];
    far.read_exact(&mut sent).await.unwrap();
    assert_eq!(sent[sent.len() - 2..], [0x01, 0x03]);
    assert!(port.owed.is_empty());
}

/// Every option but the three an RFC 2217 client wants, asked for on both sides: each refused
/// once, 1.5 KiB of answers.
fn every_option() -> Vec<u8> {
    (0..=u8::MAX)
        .filter(|option| ![0, 3, 44].contains(option))
        .flat_map(|option| [IAC, DO, option, IAC, WILL, option])
        .collect()
}

#[tokio::test]
async fn a_converter_that_would_be_owed_more_than_the_cap_is_dropped_and_says_why() {
    let (mut port, mut far) = telnet_port(4096);
    // Each three-byte request owes a three-byte refusal.
    let mut asked = every_option();
    assert!(asked.len() > MAX_OWED);
    asked.push(0x42);
    let converter = tokio::spawn(async move {
        far.write_all(&asked).await.unwrap();
        far
    });
    let mut got = Vec::new();
    let error = loop {
        match port.recv(&mut got).await {
            Ok(_) => assert!(got.is_empty(), "the data came through: {got:02X?}"),
            Err(error) => break error,
        }
    };
    assert_eq!(
        Dropped::of(&error),
        Some(LinkDrop::TelnetAnswers),
        "{error}"
    );
    // Checked after each read: one read's answers at most past the cap.
    assert!(port.owed.len() <= MAX_OWED + READ_CHUNK);
    // The same in the drain before a frame.
    let (mut port, mut far) = telnet_port(64 * 1024);
    far.write_all(&every_option()).await.unwrap();
    let error = port.clear_input(&mut Vec::new()).unwrap_err();
    assert_eq!(
        Dropped::of(&error),
        Some(LinkDrop::TelnetAnswers),
        "{error}"
    );
    drop(converter.await.unwrap());
}

#[tokio::test]
async fn one_drain_reads_at_most_its_cap_and_leaves_the_rest_in_the_socket() {
    let (near, mut far) = tokio::io::duplex(64 * 1024);
    let link = Measured {
        stream: near,
        round_trip: None,
    };
    let mut port = NetPort::new(link, "192.0.2.7:4001".into());
    let flood = vec![0x55; 5 * MAX_DRAIN / 2];
    far.write_all(&flood).await.unwrap();
    let mut stale = Vec::new();
    for expected in [MAX_DRAIN, MAX_DRAIN, MAX_DRAIN / 2] {
        stale.clear();
        port.clear_input(&mut stale).unwrap();
        assert_eq!(stale.len(), expected);
    }
}
