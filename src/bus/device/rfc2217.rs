//! The client side of RFC 2217 (the Telnet COM-PORT-OPTION), for a line behind a serial device
//! server: the bytes that ask the server for BINARY, SUPPRESS-GO-AHEAD and COM-PORT-OPTION and set
//! the line's format; a Telnet decoder that separates the line's data from the server's commands
//! however the input is split across reads, answers what the protocol owes and records the settings
//! the server reports back; and [`negotiate`], which drives that exchange on a fresh connection
//! until the server has acknowledged the format or a deadline passes.
//!
//! Knows nothing of sockets, addresses or reconnection (the caller opens the stream and brings the
//! deadline), nor of framing or what the data bytes mean. Modem and line state, flow control
//! suspension and the server's signature are consumed and not acted on.

use crate::line::{Parity, SerialFormat};
use std::io;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;

/// Interpret As Command: starts every Telnet command; doubled, it is one data byte 0xFF.
const IAC: u8 = 255;
const DONT: u8 = 254;
const DO: u8 = 253;
const WONT: u8 = 252;
const WILL: u8 = 251;
/// Subnegotiation Begin: `IAC SB option ... IAC SE`.
const SB: u8 = 250;
/// Subnegotiation End.
const SE: u8 = 240;

const TRANSMIT_BINARY: u8 = 0;
const SUPPRESS_GO_AHEAD: u8 = 3;
const COM_PORT_OPTION: u8 = 44;

/// The options the client enables on its own side and agrees to on the server's, and whether it
/// asks the server to enable it too. RFC 2217 has the client offer COM-PORT-OPTION (WILL) and the
/// server agree (DO); a server offering it as well is agreed to rather than refused, because
/// refusing would draw a WONT 44 that reads like a refusal of ours.
const WANTED: [(u8, bool); 3] = [
    (TRANSMIT_BINARY, true),
    (SUPPRESS_GO_AHEAD, true),
    (COM_PORT_OPTION, false),
];

/// COM-PORT-OPTION commands, client to server; the server's reply to each is the same code + 100.
const SET_BAUDRATE: u8 = 1;
const SET_DATASIZE: u8 = 2;
const SET_PARITY: u8 = 3;
const SET_STOPSIZE: u8 = 4;
const SET_CONTROL: u8 = 5;
const SERVER_OFFSET: u8 = 100;
const REPLY_BAUDRATE: u8 = SET_BAUDRATE + SERVER_OFFSET;
const REPLY_DATASIZE: u8 = SET_DATASIZE + SERVER_OFFSET;
const REPLY_PARITY: u8 = SET_PARITY + SERVER_OFFSET;
const REPLY_STOPSIZE: u8 = SET_STOPSIZE + SERVER_OFFSET;

/// SET-CONTROL's value for "no flow control".
const CONTROL_NO_FLOW_CONTROL: u8 = 1;

/// Each parity and its SET-PARITY value (RFC 2217 also has 4 mark and 5 space, which a Modbus line
/// never uses and which are not recorded when reported).
const PARITY_CODES: [(Parity, u8); 3] = [(Parity::None, 1), (Parity::Odd, 2), (Parity::Even, 3)];

/// SET-STOPSIZE's value for one and a half stop bits (1 and 2 are themselves).
const STOPSIZE_ONE_AND_A_HALF: u8 = 3;

/// Longest subnegotiation kept; a longer one (none of RFC 2217's settings comes near it, only a
/// signature text might) is dropped whole, so a misbehaving server cannot grow the buffer.
const MAX_SUBNEGOTIATION: usize = 256;

/// The error when the server refused COM-PORT-OPTION.
const NOT_RFC2217: &str = "the device server is not an RFC 2217 server (it refused the \
    COM-PORT-OPTION); use tcp:// for a raw one";

/// Where the decoder is in the Telnet grammar between two bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum State {
    /// Data bytes.
    Data,
    /// After an IAC among data.
    Command,
    /// After IAC WILL, WONT, DO or DONT (the verb), before the option.
    Option(u8),
    /// Inside `IAC SB ... IAC SE`.
    Sub,
    /// After an IAC inside a subnegotiation.
    SubCommand,
}

/// One side of one wanted option (RFC 1143's states, without the queue the client never needs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Side {
    Off,
    /// Requested by the client's negotiation, not yet answered.
    Asked,
    On,
}

/// Telnet state of one connection to an RFC 2217 server: a decoder that survives any split of
/// the input across reads, and what the server has reported.
#[derive(Clone, Debug)]
pub(crate) struct Telnet {
    state: State,
    /// The subnegotiation being read, its option first; at most [`MAX_SUBNEGOTIATION`] bytes.
    sub: Vec<u8>,
    /// The subnegotiation being read outgrew [`MAX_SUBNEGOTIATION`] and will be dropped.
    sub_overflow: bool,
    /// The client's side of each [`WANTED`] option, in its order.
    ours: [Side; WANTED.len()],
    /// The server's side of each [`WANTED`] option, in its order.
    theirs: [Side; WANTED.len()],
    /// Options of other kinds already refused, by the verb of the refusal: so that a server
    /// repeating its request is not answered again.
    declined: Declined,
    refused: bool,
    reported: Reported,
}

/// A set of (refusal verb, option) pairs: 256 options on each of two sides.
#[derive(Clone, Debug, Default)]
struct Declined([u64; 8]);

impl Declined {
    /// Add the pair; whether it was new.
    fn insert(&mut self, ours: bool, option: u8) -> bool {
        let bit = usize::from(ours) * 256 + usize::from(option);
        let (word, mask) = (bit / 64, 1u64 << (bit % 64));
        let new = self.0[word] & mask == 0;
        self.0[word] |= mask;
        new
    }
}

/// The serial settings the server has reported back (its replies to SET-BAUDRATE, SET-DATASIZE,
/// SET-PARITY and SET-STOPSIZE), each None until reported.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Reported {
    pub(crate) baud: Option<u32>,
    pub(crate) data_bits: Option<u8>,
    pub(crate) parity: Option<Parity>,
    /// 1 or 2; 3 is RFC 2217's code for one and a half.
    pub(crate) stop_bits: Option<u8>,
}

impl Reported {
    /// All four settings have been acknowledged.
    pub(crate) fn complete(&self) -> bool {
        self.baud.is_some()
            && self.data_bits.is_some()
            && self.parity.is_some()
            && self.stop_bits.is_some()
    }

    /// The first setting the server reported differently from `format`, as a message such as
    /// "the device server set 9600 baud, not 19200"; None when all match. Only as good as the
    /// server's report: ser2net 4.3 echoes what was asked once the device accepted the call, even
    /// where the device quietly kept another setting (a pty stays 8N whatever is asked).
    pub(crate) fn mismatch(&self, format: &SerialFormat) -> Option<String> {
        let differs = if let Some(baud) = self.baud.filter(|&b| b != format.baud) {
            format!("{baud} baud, not {}", format.baud)
        } else if let Some(bits) = self.data_bits.filter(|&b| b != format.data_bits) {
            format!("{bits} data bits, not {}", format.data_bits)
        } else if let Some(parity) = self.parity.filter(|&p| p != format.parity) {
            format!("{} parity, not {}", parity.name(), format.parity.name())
        } else if let Some(stop) = self.stop_bits.filter(|&s| s != format.stop_bits) {
            format!("{}, not {}", stop_bits(stop), format.stop_bits)
        } else {
            return None;
        };
        Some(format!("the device server set {differs}"))
    }

    /// Record the server's COM-PORT-OPTION command `code` with its `value`. A reply of 0 (which
    /// would mean "what is it?") and anything not a setting are ignored.
    fn record(&mut self, code: u8, value: &[u8]) {
        match (code, value) {
            (REPLY_BAUDRATE, &[a, b, c, d]) => {
                self.baud = Some(u32::from_be_bytes([a, b, c, d])).filter(|&baud| baud != 0);
            }
            (REPLY_DATASIZE, &[bits]) if bits != 0 => self.data_bits = Some(bits),
            (REPLY_PARITY, &[value]) => {
                let row = PARITY_CODES.iter().find(|&&(_, code)| code == value);
                if let Some(&(parity, _)) = row {
                    self.parity = Some(parity);
                }
            }
            (REPLY_STOPSIZE, &[size]) if size != 0 => self.stop_bits = Some(size),
            _ => {}
        }
    }
}

/// `stop` stop bits as a sentence writes them.
fn stop_bits(stop: u8) -> String {
    match stop {
        1 => "1 stop bit".to_owned(),
        STOPSIZE_ONE_AND_A_HALF => "1.5 stop bits".to_owned(),
        n => format!("{n} stop bits"),
    }
}

/// The SET-PARITY value of `parity`.
fn parity_code(parity: Parity) -> u8 {
    let row = PARITY_CODES.iter().find(|&&(p, _)| p == parity);
    row.map_or(1, |&(_, code)| code)
}

impl Telnet {
    /// A connection whose client has sent (or is about to send) [`Telnet::negotiation`].
    pub(crate) fn new() -> Telnet {
        let ask = |ask_server: bool| if ask_server { Side::Asked } else { Side::Off };
        Telnet {
            state: State::Data,
            sub: Vec::with_capacity(MAX_SUBNEGOTIATION),
            sub_overflow: false,
            ours: [Side::Asked; WANTED.len()],
            theirs: WANTED.map(|(_, ask_server)| ask(ask_server)),
            declined: Declined::default(),
            refused: false,
            reported: Reported::default(),
        }
    }

    /// What a client sends right after connecting: the option negotiation (WILL/DO
    /// TRANSMIT-BINARY, WILL/DO SUPPRESS-GO-AHEAD, WILL COM-PORT-OPTION) and the subnegotiations
    /// SET-BAUDRATE, SET-DATASIZE, SET-PARITY, SET-STOPSIZE and SET-CONTROL (no flow control) for
    /// `format`.
    pub(crate) fn negotiation(format: &SerialFormat) -> Vec<u8> {
        let mut out = Vec::with_capacity(64);
        for (option, ask_server) in WANTED {
            out.extend_from_slice(&[IAC, WILL, option]);
            if ask_server {
                out.extend_from_slice(&[IAC, DO, option]);
            }
        }
        let settings: [(u8, &[u8]); 5] = [
            (SET_BAUDRATE, &format.baud.to_be_bytes()),
            (SET_DATASIZE, &[format.data_bits]),
            (SET_PARITY, &[parity_code(format.parity)]),
            (SET_STOPSIZE, &[format.stop_bits]),
            (SET_CONTROL, &[CONTROL_NO_FLOW_CONTROL]),
        ];
        for (code, value) in settings {
            out.extend_from_slice(&[IAC, SB, COM_PORT_OPTION, code]);
            Telnet::escape_into(value, &mut out);
            out.extend_from_slice(&[IAC, SE]);
        }
        out
    }

    /// Append `data` to `out` with every IAC (0xFF) doubled.
    pub(crate) fn escape_into(data: &[u8], out: &mut Vec<u8>) {
        for chunk in data.split_inclusive(|&byte| byte == IAC) {
            out.extend_from_slice(chunk);
            if chunk.last() == Some(&IAC) {
                out.push(IAC);
            }
        }
    }

    /// Take bytes received from the server: data bytes are appended to `data` (IAC IAC becomes one
    /// 0xFF), Telnet commands are consumed, answers the protocol owes (agreeing to BINARY, SGA and
    /// COM-PORT-OPTION; refusing every other option with DONT/WONT, once, without loops) are
    /// appended to `answer`, and the server's replies to the settings (codes 101-104, and
    /// NOTIFY-LINESTATE/MODEMSTATE etc., which are consumed) are recorded. `answer` holds only
    /// answers owed and not yet sent: one that a later command undoes is withdrawn from it, so it
    /// holds at most one per wanted option and side, and one refusal per other option.
    /// Returns how many data bytes were appended.
    pub(crate) fn receive(
        &mut self,
        input: &[u8],
        data: &mut Vec<u8>,
        answer: &mut Vec<u8>,
    ) -> usize {
        let before = data.len();
        for &byte in input {
            self.state = self.step(byte, data, answer);
        }
        data.len() - before
    }

    /// The settings the server has reported so far.
    pub(crate) fn reported(&self) -> Reported {
        self.reported
    }

    /// The server refused COM-PORT-OPTION (WONT/DONT 44): it is a plain Telnet or raw server.
    pub(crate) fn refused(&self) -> bool {
        self.refused
    }

    /// One byte of input in the current state; the state after it.
    fn step(&mut self, byte: u8, data: &mut Vec<u8>, answer: &mut Vec<u8>) -> State {
        match self.state {
            State::Data if byte == IAC => State::Command,
            State::Data => {
                data.push(byte);
                State::Data
            }
            State::Command => self.command(byte, data),
            State::Option(verb) => {
                self.option(verb, byte, answer);
                State::Data
            }
            State::Sub if byte == IAC => State::SubCommand,
            State::Sub => {
                self.sub_push(byte);
                State::Sub
            }
            State::SubCommand => match byte {
                IAC => {
                    self.sub_push(IAC);
                    State::Sub
                }
                SE => {
                    self.subnegotiation_end();
                    State::Data
                }
                // An unterminated subnegotiation (its SE lost): drop it and take the command as
                // one, which resynchronises on the next.
                _ => {
                    self.sub.clear();
                    self.command(byte, data)
                }
            },
        }
    }

    /// The byte after an IAC outside a subnegotiation. NOP, GA and the other two-byte commands
    /// mean nothing to a client in BINARY mode and are dropped.
    fn command(&mut self, byte: u8, data: &mut Vec<u8>) -> State {
        match byte {
            IAC => {
                data.push(IAC);
                State::Data
            }
            WILL | WONT | DO | DONT => State::Option(byte),
            SB => {
                self.sub.clear();
                self.sub_overflow = false;
                State::Sub
            }
            _ => State::Data,
        }
    }

    /// The server's `verb` about `option`: answer only a change of state, never an
    /// acknowledgement, so that no exchange loops.
    fn option(&mut self, verb: u8, option: u8, answer: &mut Vec<u8>) {
        // DO/DONT are about the client's side, WILL/WONT about the server's.
        let ours = matches!(verb, DO | DONT);
        let enable = matches!(verb, DO | WILL);
        let (yes, no) = if ours { (WILL, WONT) } else { (DO, DONT) };
        let Some(index) = WANTED.iter().position(|&(wanted, _)| wanted == option) else {
            if enable && self.declined.insert(ours, option) {
                answer.extend_from_slice(&[IAC, no, option]);
            }
            return;
        };
        if option == COM_PORT_OPTION && !enable && (ours || self.ours[index] == Side::Asked) {
            // DONT 44 refuses our WILL; a WONT 44 before any DO is a server answering the wrong
            // side of the same refusal.
            self.refused = true;
        }
        let side = if ours {
            &mut self.ours[index]
        } else {
            &mut self.theirs[index]
        };
        let was = std::mem::replace(side, if enable { Side::On } else { Side::Off });
        match (was, enable) {
            (Side::Off, true) => owe(answer, [IAC, yes, option], [IAC, no, option]),
            (Side::On, false) => owe(answer, [IAC, no, option], [IAC, yes, option]),
            _ => {}
        }
    }

    /// Keep one byte of the subnegotiation, up to [`MAX_SUBNEGOTIATION`].
    fn sub_push(&mut self, byte: u8) {
        if self.sub.len() < MAX_SUBNEGOTIATION {
            self.sub.push(byte);
        } else {
            self.sub_overflow = true;
        }
    }

    /// A whole subnegotiation has arrived: record it if it is a setting the server reports.
    fn subnegotiation_end(&mut self) {
        if !std::mem::take(&mut self.sub_overflow) {
            if let [COM_PORT_OPTION, code, ref value @ ..] = self.sub[..] {
                self.reported.record(code, value);
            }
        }
        self.sub.clear();
    }
}

/// Owe the server `reply`, unless `answer` (the answers owed and not yet sent, three bytes each)
/// still holds `undone`, the opposite answer about the same option and side: the server has asked
/// for the state the client was in when it last told it, which is not answered (RFC 854), and
/// the two are dropped. A server toggling an option leaves at most one answer owed for it.
fn owe(answer: &mut Vec<u8>, reply: [u8; 3], undone: [u8; 3]) {
    match answer.chunks_exact(3).rposition(|owed| owed == undone) {
        Some(at) => drop(answer.drain(at * 3..at * 3 + 3)),
        None => answer.extend_from_slice(&reply),
    }
}

/// Negotiate on a freshly connected `stream`: write `Telnet::negotiation(format)`, then read (and
/// write any answers owed) until the server has acknowledged all four settings, or `deadline`.
/// Data bytes received meanwhile are dropped; returns how many. Errors (io::Error with a message a
/// user can act on): the server refused COM-PORT-OPTION ("... is not an RFC 2217 server; use
/// tcp:// for a raw one"), a setting reported back differs (Reported::mismatch), no
/// acknowledgement by the deadline ("... did not acknowledge ...: is it an RFC 2217 server?",
/// ErrorKind::TimedOut), EOF.
pub(crate) async fn negotiate<S>(
    stream: &mut S,
    telnet: &mut Telnet,
    format: &SerialFormat,
    deadline: Instant,
) -> io::Result<usize>
where
    S: AsyncRead + AsyncWrite + Unpin,
{
    match tokio::time::timeout_at(deadline, exchange(stream, telnet, format)).await {
        Ok(outcome) => outcome,
        Err(_) => Err(io::Error::new(
            io::ErrorKind::TimedOut,
            format!(
                "the device server did not acknowledge {format} in time: is it an RFC 2217 server?"
            ),
        )),
    }
}

/// [`negotiate`] without its deadline.
async fn exchange<S>(
    stream: &mut S,
    telnet: &mut Telnet,
    format: &SerialFormat,
) -> io::Result<usize>
where
    S: AsyncRead + AsyncWrite + Unpin,
{
    stream.write_all(&Telnet::negotiation(format)).await?;
    stream.flush().await?;
    let mut input = [0u8; 512];
    let (mut data, mut answer) = (Vec::new(), Vec::new());
    let mut dropped = 0;
    loop {
        if telnet.refused() {
            return Err(io::Error::new(io::ErrorKind::Unsupported, NOT_RFC2217));
        }
        let reported = telnet.reported();
        if let Some(mismatch) = reported.mismatch(format) {
            return Err(io::Error::new(io::ErrorKind::InvalidData, mismatch));
        }
        if reported.complete() {
            return Ok(dropped);
        }
        let read = stream.read(&mut input).await?;
        if read == 0 {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "the device server closed the connection during the RFC 2217 negotiation",
            ));
        }
        dropped += telnet.receive(&input[..read], &mut data, &mut answer);
        data.clear();
        if !answer.is_empty() {
            stream.write_all(&answer).await?;
            stream.flush().await?;
            answer.clear();
        }
    }
}

#[cfg(test)]
mod tests;
