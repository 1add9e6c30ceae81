//! The Telnet decoder, the negotiation's bytes and [`negotiate`] against fake servers.

use super::*;
use std::time::Duration;
use tokio::io::{duplex, DuplexStream};

/// 19200 baud 8E1, the line most tests negotiate.
const E1_19200: SerialFormat = SerialFormat {
    baud: 19_200,
    data_bits: 8,
    parity: Parity::Even,
    stop_bits: 1,
};

/// How long the tests' fake servers are given.
const PATIENCE: Duration = Duration::from_secs(5);

/// A server's replies to the four settings: `IAC SB 44 code+100 value IAC SE` each.
fn replies(baud: u32, data_bits: u8, parity: u8, stop_bits: u8) -> Vec<u8> {
    let mut out = Vec::new();
    let settings: [(u8, &[u8]); 4] = [
        (101, &baud.to_be_bytes()),
        (102, &[data_bits]),
        (103, &[parity]),
        (104, &[stop_bits]),
    ];
    for (code, value) in settings {
        out.extend_from_slice(&[IAC, SB, 44, code]);
        Telnet::escape_into(value, &mut out);
        out.extend_from_slice(&[IAC, SE]);
    }
    out
}

/// A server agreeing to everything the client asked for, then acknowledging 19200 8E1.
fn agreeing_server() -> Vec<u8> {
    let mut out = vec![
        IAC, DO, 0, // DO TRANSMIT-BINARY: agrees to our WILL
        IAC, WILL, 0, // WILL TRANSMIT-BINARY: agrees to our DO
        IAC, DO, 3, // DO SUPPRESS-GO-AHEAD
        IAC, WILL, 3, // WILL SUPPRESS-GO-AHEAD
        IAC, DO, 44, // DO COM-PORT-OPTION
    ];
    out.extend(replies(19_200, 8, 3, 1));
    out
}

fn decode(telnet: &mut Telnet, input: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let (mut data, mut answer) = (Vec::new(), Vec::new());
    let count = telnet.receive(input, &mut data, &mut answer);
    assert_eq!(count, data.len());
    (data, answer)
}

#[test]
fn negotiation_for_19200_8e1_asks_for_binary_sga_and_the_com_port_option_then_sets_the_format() {
    #[rustfmt::skip]
    let expected = [
        IAC, WILL, 0, IAC, DO, 0, // TRANSMIT-BINARY both ways
        IAC, WILL, 3, IAC, DO, 3, // SUPPRESS-GO-AHEAD both ways
        IAC, WILL, 44, // COM-PORT-OPTION, as its client
        IAC, SB, 44, 1, 0x00, 0x00, 0x4B, 0x00, IAC, SE, // SET-BAUDRATE 19200, big-endian
        IAC, SB, 44, 2, 8, IAC, SE, // SET-DATASIZE 8
        IAC, SB, 44, 3, 3, IAC, SE, // SET-PARITY 3: even
        IAC, SB, 44, 4, 1, IAC, SE, // SET-STOPSIZE 1
        IAC, SB, 44, 5, 1, IAC, SE, // SET-CONTROL 1: no flow control
    ];
    assert_eq!(Telnet::negotiation(&E1_19200), expected);
}

#[test]
fn a_baud_rate_containing_0xff_is_doubled_inside_its_subnegotiation() {
    let format = SerialFormat {
        baud: 0x0001_FF00,
        ..E1_19200
    };
    let bytes = Telnet::negotiation(&format);
    let baud = [IAC, SB, 44, 1, 0x00, 0x01, IAC, IAC, 0x00, IAC, SE];
    assert!(bytes.windows(baud.len()).any(|w| w == baud));
}

#[test]
fn data_with_0xff_escaped_and_decoded_comes_back_unchanged() {
    let sent = [0x01, IAC, 0x03, IAC, IAC, 0x00, 0x0D, 0x00, IAC];
    let mut wire = Vec::new();
    Telnet::escape_into(&sent, &mut wire);
    assert_eq!(wire.len(), sent.len() + 4, "each 0xFF doubled");
    let (data, answer) = decode(&mut Telnet::new(), &wire);
    assert_eq!(data, sent, "CR NUL is data too, in BINARY mode");
    assert!(answer.is_empty());
}

/// A server's stream mixing every kind of thing a client meets, and what it must make of it.
fn mixed_stream() -> (Vec<u8>, Vec<u8>, Vec<u8>) {
    let mut input = agreeing_server();
    input.extend_from_slice(&[b'A', IAC, IAC, b'B']); // data "A", 0xFF, "B"
    input.extend_from_slice(&[IAC, 241]); // NOP
    input.extend_from_slice(&[IAC, SB, 44, 107, IAC, IAC, IAC, SE]); // NOTIFY-MODEMSTATE 0xFF
    input.extend_from_slice(&[IAC, SB, 44, 106, 0x60, IAC, SE]); // NOTIFY-LINESTATE
    input.extend_from_slice(&[IAC, WILL, 1]); // WILL ECHO: refused
    input.extend_from_slice(&[0x0D, 0x00, IAC, 249, b'C']); // CR NUL, GA, "C"
    let data = vec![b'A', 0xFF, b'B', 0x0D, 0x00, b'C'];
    (input, data, vec![IAC, DONT, 1])
}

#[test]
fn decoding_gives_the_same_result_wherever_the_input_is_split() {
    let (input, data, answer) = mixed_stream();
    let reported = Reported {
        baud: Some(19_200),
        data_bits: Some(8),
        parity: Some(Parity::Even),
        stop_bits: Some(1),
    };
    for split in 0..=input.len() {
        let mut telnet = Telnet::new();
        let (mut got, mut owed) = decode(&mut telnet, &input[..split]);
        let (rest, more) = decode(&mut telnet, &input[split..]);
        got.extend(rest);
        owed.extend(more);
        assert_eq!(got, data, "data, split at {split}");
        assert_eq!(owed, answer, "answers, split at {split}");
        assert_eq!(telnet.reported(), reported, "settings, split at {split}");
        assert!(!telnet.refused());
    }
}

#[test]
fn decoding_byte_by_byte_gives_the_same_result_as_all_at_once() {
    let (input, data, answer) = mixed_stream();
    let mut telnet = Telnet::new();
    let (mut got, mut owed) = (Vec::new(), Vec::new());
    for byte in &input {
        telnet.receive(std::slice::from_ref(byte), &mut got, &mut owed);
    }
    assert_eq!((got, owed), (data, answer));
    assert!(telnet.reported().complete());
}

#[test]
fn an_unknown_option_is_refused_once_however_often_the_server_asks() {
    let mut telnet = Telnet::new();
    let ask = [
        IAC, WILL, 1, // WILL ECHO
        IAC, DO, 24, // DO TERMINAL-TYPE
        IAC, WILL, 1, IAC, DO, 24, // both again
    ];
    let (_, answer) = decode(&mut telnet, &ask);
    assert_eq!(answer, [IAC, DONT, 1, IAC, WONT, 24]);
    let (_, answer) = decode(&mut telnet, &ask);
    assert!(answer.is_empty(), "asked again: {answer:?}");
}

#[test]
fn the_servers_agreement_to_what_the_client_asked_is_not_answered() {
    let mut telnet = Telnet::new();
    let (_, answer) = decode(&mut telnet, &agreeing_server());
    assert!(
        answer.is_empty(),
        "acknowledged an acknowledgement: {answer:?}"
    );
    let (_, answer) = decode(&mut telnet, &agreeing_server());
    assert!(answer.is_empty(), "repeated agreement answered: {answer:?}");
}

#[test]
fn ser2net_4_3_acknowledging_19200_8n2_as_captured_is_decoded_with_only_echo_refused() {
    #[rustfmt::skip]
    let captured = [
        IAC, WILL, 3, IAC, DO, 3, // SUPPRESS-GO-AHEAD, offered unprompted
        IAC, WILL, 1, IAC, DONT, 1, // WILL ECHO, and DONT ECHO for the client's side
        IAC, DO, 0, IAC, WILL, 0, // TRANSMIT-BINARY both ways
        IAC, DO, 44, // COM-PORT-OPTION, also sent to a client that asked nothing
        IAC, DO, 3, // SUPPRESS-GO-AHEAD again
        IAC, SB, 44, 107, 0, IAC, SE, // NOTIFY-MODEMSTATE: no modem lines
        IAC, SB, 44, 101, 0x00, 0x00, 0x4B, 0x00, IAC, SE, // baud 19200
        IAC, SB, 44, 102, 8, IAC, SE, // 8 data bits
        IAC, SB, 44, 103, 1, IAC, SE, // parity none
        IAC, SB, 44, 104, 2, IAC, SE, // 2 stop bits
        IAC, SB, 44, 105, 1, IAC, SE, // no flow control
    ];
    let format = SerialFormat {
        parity: Parity::None,
        stop_bits: 2,
        ..E1_19200
    };
    let mut telnet = Telnet::new();
    let (data, answer) = decode(&mut telnet, &captured);
    assert!(data.is_empty());
    assert_eq!(answer, [IAC, DONT, 1]);
    assert!(telnet.reported().complete());
    assert_eq!(telnet.reported().mismatch(&format), None);
}

#[test]
fn a_server_offering_the_com_port_option_itself_is_agreed_to() {
    let (_, answer) = decode(&mut Telnet::new(), &[IAC, WILL, 44]);
    assert_eq!(answer, [IAC, DO, 44]);
}

#[test]
fn a_server_turning_binary_off_is_acknowledged_once() {
    let mut telnet = Telnet::new();
    decode(&mut telnet, &agreeing_server());
    let (_, answer) = decode(&mut telnet, &[IAC, WONT, 0, IAC, WONT, 0]);
    assert_eq!(answer, [IAC, DONT, 0]);
}

#[test]
fn dont_or_wont_com_port_option_means_the_server_refused_it() {
    for verb in [DONT, WONT] {
        let mut telnet = Telnet::new();
        decode(&mut telnet, &[IAC, verb, 44]);
        assert!(telnet.refused(), "verb {verb}");
    }
    let mut telnet = Telnet::new();
    decode(&mut telnet, &[IAC, DO, 44, IAC, WONT, 44]);
    assert!(
        !telnet.refused(),
        "WONT after DO is about the server's own side"
    );
}

#[test]
fn an_over_long_subnegotiation_is_dropped_and_decoding_carries_on() {
    let mut input = vec![IAC, SB, 44, 101, 0, 0, 0x25, 0x80]; // SET-BAUDRATE 9600 reply...
    input.extend(std::iter::repeat_n(0, MAX_SUBNEGOTIATION)); // ...with far too much after it
    input.extend_from_slice(&[IAC, SE, b'x']);
    input.extend(replies(19_200, 8, 3, 1));
    let mut telnet = Telnet::new();
    let (data, _) = decode(&mut telnet, &input);
    assert_eq!(data, b"x");
    assert_eq!(telnet.reported().baud, Some(19_200));
    assert!(telnet.sub.capacity() <= MAX_SUBNEGOTIATION);
}

#[test]
fn a_subnegotiation_missing_its_se_gives_way_to_the_next_command() {
    let mut input = vec![IAC, SB, 44, 107, 0x30]; // NOTIFY-MODEMSTATE, SE lost
    input.extend(replies(19_200, 8, 3, 1));
    let mut telnet = Telnet::new();
    decode(&mut telnet, &input);
    assert!(telnet.reported().complete());
}

#[test]
fn mismatch_names_the_first_setting_the_server_set_differently() {
    let agreed = Reported {
        baud: Some(19_200),
        data_bits: Some(8),
        parity: Some(Parity::Even),
        stop_bits: Some(1),
    };
    assert_eq!(agreed.mismatch(&E1_19200), None);
    assert_eq!(Reported::default().mismatch(&E1_19200), None);
    let cases = [
        (
            Reported {
                baud: Some(9_600),
                parity: Some(Parity::None),
                ..agreed
            },
            "the device server set 9600 baud, not 19200",
        ),
        (
            Reported {
                data_bits: Some(7),
                ..agreed
            },
            "the device server set 7 data bits, not 8",
        ),
        (
            Reported {
                parity: Some(Parity::None),
                ..agreed
            },
            "the device server set none parity, not even",
        ),
        (
            Reported {
                stop_bits: Some(2),
                ..agreed
            },
            "the device server set 2 stop bits, not 1",
        ),
        (
            Reported {
                stop_bits: Some(3),
                ..agreed
            },
            "the device server set 1.5 stop bits, not 1",
        ),
    ];
    for (reported, message) in cases {
        assert_eq!(reported.mismatch(&E1_19200).as_deref(), Some(message));
    }
}

#[test]
fn only_all_four_settings_make_a_complete_report() {
    let mut telnet = Telnet::new();
    let all = replies(19_200, 8, 3, 1);
    let (three, _) = all.split_at(all.len() - 7); // without the SET-STOPSIZE reply
    decode(&mut telnet, three);
    assert!(!telnet.reported().complete());
    decode(&mut telnet, &all[three.len()..]);
    assert!(telnet.reported().complete());
}

/// Negotiate 19200 8E1 against a fake server that reads the client's negotiation, then writes
/// `reply` and keeps the connection open; the outcome and what the client wrote after.
async fn negotiate_against(reply: Vec<u8>) -> (io::Result<usize>, Vec<u8>) {
    let (mut client, mut server) = duplex(4096);
    let expected = Telnet::negotiation(&E1_19200);
    let server_side = tokio::spawn(async move {
        let mut asked = vec![0; expected.len()];
        server.read_exact(&mut asked).await.expect("negotiation");
        assert_eq!(asked, expected);
        server.write_all(&reply).await.expect("reply");
        server
    });
    let deadline = Instant::now() + PATIENCE;
    let outcome = negotiate(&mut client, &mut Telnet::new(), &E1_19200, deadline).await;
    drop(client);
    let mut server: DuplexStream = server_side.await.expect("server");
    let mut after = Vec::new();
    server.read_to_end(&mut after).await.expect("after");
    (outcome, after)
}

#[tokio::test]
async fn negotiate_succeeds_once_the_server_acknowledges_all_four_settings() {
    let mut reply = vec![b'x', IAC, IAC]; // data ahead of the acknowledgements: dropped
    reply.extend_from_slice(&[IAC, WILL, 1]); // WILL ECHO, refused
    reply.extend(agreeing_server());
    let (outcome, after) = negotiate_against(reply).await;
    assert_eq!(outcome.expect("negotiated"), 2);
    assert_eq!(after, [IAC, DONT, 1]);
}

#[tokio::test]
async fn negotiate_with_a_server_refusing_the_com_port_option_says_to_use_tcp() {
    let (outcome, _) = negotiate_against(vec![IAC, WONT, 44]).await;
    let error = outcome.expect_err("refused");
    assert_eq!(error.kind(), io::ErrorKind::Unsupported);
    assert!(error.to_string().contains("use tcp://"), "{error}");
}

#[tokio::test]
async fn negotiate_with_a_server_setting_another_baud_rate_names_it() {
    let mut reply = vec![IAC, DO, 44];
    reply.extend(replies(9_600, 8, 3, 1));
    let (outcome, _) = negotiate_against(reply).await;
    let error = outcome.expect_err("mismatch");
    assert_eq!(error.kind(), io::ErrorKind::InvalidData);
    assert_eq!(
        error.to_string(),
        "the device server set 9600 baud, not 19200"
    );
}

#[tokio::test(start_paused = true)]
async fn negotiate_with_a_silent_server_times_out_at_the_deadline() {
    let (mut client, _server) = duplex(4096);
    let start = Instant::now();
    let deadline = start + PATIENCE;
    let outcome = negotiate(&mut client, &mut Telnet::new(), &E1_19200, deadline).await;
    let error = outcome.expect_err("silent");
    assert_eq!(error.kind(), io::ErrorKind::TimedOut);
    assert!(error.to_string().contains("is it an RFC 2217 server?"));
    assert_eq!(Instant::now(), deadline);
}

#[tokio::test]
async fn negotiate_with_a_server_that_hangs_up_reports_the_end_of_the_connection() {
    let (mut client, mut server) = duplex(4096);
    let server_side = tokio::spawn(async move {
        let mut asked = vec![0; Telnet::negotiation(&E1_19200).len()];
        server.read_exact(&mut asked).await.expect("negotiation");
        server.write_all(&[IAC, DO, 44]).await.expect("reply");
    });
    let deadline = Instant::now() + PATIENCE;
    let outcome = negotiate(&mut client, &mut Telnet::new(), &E1_19200, deadline).await;
    server_side.await.expect("server");
    let error = outcome.expect_err("hung up");
    assert_eq!(error.kind(), io::ErrorKind::UnexpectedEof);
    assert!(
        error.to_string().contains("closed the connection"),
        "{error}"
    );
}
