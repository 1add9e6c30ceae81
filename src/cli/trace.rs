//! The `trace` subcommand: read `GET /trace` from a running gateway's metrics endpoint and print
//! each frame decoded for a terminal, one line per frame, until Ctrl-C. What a frame means comes
//! from the function-code table in [`crate::pdu`]; the wire format from [`crate::line`]. Knows
//! nothing of how the gateway makes the stream.

use super::stop_signal;
use crate::line::{ascii, rtu};
use crate::master::{PORT_PEER_PREFIX, VIRTUAL_TRACE_PREFIX};
use crate::mbap;
use crate::pdu::{self, code};
use http_body_util::BodyExt;
use hyper::{StatusCode, Uri};
use serde::Deserialize;
use std::fmt::Write as _;
use std::io::Write as _;
use std::net::SocketAddr;
use std::process::ExitCode;

/// The trace URL of the metrics endpoint listening on `listen`.
pub fn url_of(listen: SocketAddr) -> String {
    super::http::url_of(listen, "/trace")
}

/// `url` (`/trace` when it names no path) with the filters in its query.
fn with_filters(url: &str, bus: Option<&str>, slave: Option<u8>) -> Result<Uri, String> {
    let uri = super::http::uri_of(url).map_err(|e| format!("`{url}`: {e}"))?;
    let path = match uri.path() {
        "" | "/" => "/trace",
        path => path,
    };
    let mut query: Vec<String> = uri.query().map(str::to_owned).into_iter().collect();
    query.extend(bus.map(|bus| format!("bus={bus}")));
    query.extend(slave.map(|slave| format!("slave={slave}")));
    let query = if query.is_empty() {
        String::new()
    } else {
        format!("?{}", query.join("&"))
    };
    let authority = uri.authority().map(ToString::to_string).unwrap_or_default();
    format!("http://{authority}{path}{query}")
        .parse()
        .map_err(|e| format!("`{url}`: {e}"))
}

/// Print the frames of the trace at `url`, filtered, until Ctrl-C (exit 0) or until the stream
/// cannot be had or ends (exit 1, saying why).
pub fn trace(url: &str, bus: Option<&str>, slave: Option<u8>) -> ExitCode {
    let uri = match with_filters(url, bus, slave) {
        Ok(uri) => uri,
        Err(e) => {
            eprintln!("modbus-gateway: trace: {e}");
            return ExitCode::FAILURE;
        }
    };
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime,
        Err(e) => {
            eprintln!("modbus-gateway: trace: cannot start the runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    runtime.block_on(async {
        tokio::select! {
            error = follow(&uri) => {
                let Some(error) = error else {
                    return ExitCode::SUCCESS;
                };
                eprintln!("modbus-gateway: trace: {uri}: {error}");
                ExitCode::FAILURE
            }
            () = stop_signal() => ExitCode::SUCCESS,
        }
    })
}

/// Read the stream at `uri` and print it; returns why it ended, or `None` if
/// the reader of stdout went away.
async fn follow(uri: &Uri) -> Option<String> {
    let mut response = match super::http::get(uri).await {
        Ok(response) => response,
        Err(e) => return Some(e),
    };
    let status = response.status();
    if status != StatusCode::OK {
        let text = super::http::text_of(response).await;
        return Some(format!("refused ({status}): {text}"));
    }
    let mut events = Events::default();
    let mut out = std::io::stdout().lock();
    while let Some(frame) = response.body_mut().frame().await {
        let Ok(frame) = frame else {
            return Some("the stream broke off".into());
        };
        let Some(data) = frame.data_ref() else {
            continue;
        };
        for line in events.feed(&String::from_utf8_lossy(data)) {
            if let Err(e) = writeln!(out, "{line}").and_then(|()| out.flush()) {
                return (!super::reader_gone(&e)).then(|| format!("cannot write to stdout: {e}"));
            }
        }
    }
    Some("the gateway ended the trace".into())
}

/// Server-Sent Events, cut into events as their text comes, each turned into a line to print.
#[derive(Default)]
struct Events {
    pending: String,
}

impl Events {
    /// The lines to print for the events completed by `text`.
    fn feed(&mut self, text: &str) -> Vec<String> {
        self.pending.push_str(text);
        let mut lines = Vec::new();
        while let Some(end) = self.pending.find("\n\n") {
            let event: String = self.pending.drain(..end + 2).collect();
            let (mut kind, mut data) = ("message", String::new());
            for line in event.lines() {
                if let Some(value) = line.strip_prefix("event:") {
                    kind = if value.trim() == "frame" {
                        "frame"
                    } else if value.trim() == "lost" {
                        "lost"
                    } else {
                        "other"
                    };
                } else if let Some(value) = line.strip_prefix("data:") {
                    data.push_str(value.trim_start());
                }
            }
            match kind {
                "frame" => lines.push(match serde_json::from_str::<Frame>(&data) {
                    Ok(frame) => frame.describe(),
                    Err(e) => format!("(an event this version cannot read: {e}: {data})"),
                }),
                "lost" => {
                    let lost = serde_json::from_str::<Lost>(&data).map_or(0, |l| l.lost);
                    lines.push(format!("lost {}", of(lost, "event")));
                }
                _ => {}
            }
        }
        lines
    }
}

#[derive(Deserialize)]
struct Lost {
    lost: u64,
}

/// A `frame` event's data.
#[derive(Deserialize)]
struct Frame {
    time: String,
    bus: String,
    direction: String,
    slave: u8,
    function: u8,
    hex: String,
    /// Absent from a gateway older than the field: RTU or ASCII, told by the bytes.
    #[serde(default)]
    framing: String,
    outcome: String,
}

fn word(pdu: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]))
}

/// `addr 0xA (A) count N`, `addr 0xA (A) value 0xV`: the two words after the function code. The
/// address in hex as drive manuals write it, and in decimal as SCADA tools do.
fn address_and(pdu: &[u8], second: &str) -> String {
    match (word(pdu, 1), word(pdu, 3)) {
        (Some(address), Some(n)) if second == "count" => {
            format!("addr 0x{address:04x} ({address}) count {n}")
        }
        (Some(address), Some(value)) => {
            format!("addr 0x{address:04x} ({address}) {second} 0x{value:04x}")
        }
        _ => String::new(),
    }
}

/// What a request says beyond its function.
fn request_fields(pdu: &[u8]) -> String {
    match pdu[0] {
        code::READ_COILS
        | code::READ_DISCRETE_INPUTS
        | code::READ_HOLDING_REGISTERS
        | code::READ_INPUT_REGISTERS
        | code::WRITE_MULTIPLE_COILS => address_and(pdu, "count"),
        code::WRITE_SINGLE_COIL | code::WRITE_SINGLE_REGISTER => address_and(pdu, "value"),
        code::WRITE_MULTIPLE_REGISTERS => {
            let values = registers(pdu.get(6..).unwrap_or_default());
            format!("{}: {values}", address_and(pdu, "count"))
        }
        _ => String::new(),
    }
}

/// What a normal reply says beyond its function.
fn reply_fields(pdu: &[u8]) -> String {
    let counted = pdu.get(2..).unwrap_or_default();
    match pdu[0] {
        code::READ_HOLDING_REGISTERS
        | code::READ_INPUT_REGISTERS
        | code::READ_WRITE_MULTIPLE_REGISTERS => {
            let count = counted.len() / 2;
            format!("{}: {}", of(count, "register"), registers(counted))
        }
        code::READ_COILS | code::READ_DISCRETE_INPUTS => {
            let bytes = of(counted.len(), "byte");
            format!("{bytes} of bits: {}", crate::trace::hex(counted))
        }
        code::WRITE_SINGLE_COIL | code::WRITE_SINGLE_REGISTER => address_and(pdu, "value"),
        code::WRITE_MULTIPLE_COILS | code::WRITE_MULTIPLE_REGISTERS => address_and(pdu, "count"),
        _ => String::new(),
    }
}

/// `1 register`, `2 registers`: a count and its noun, singular or plural.
fn of(count: impl std::fmt::Display, noun: &str) -> String {
    let count = count.to_string();
    let plural = if count == "1" { "" } else { "s" };
    format!("{count} {noun}{plural}")
}

/// `0x0000 0x0001`: big-endian registers.
fn registers(bytes: &[u8]) -> String {
    let words: Vec<String> = bytes
        .chunks_exact(2)
        .map(|w| format!("0x{:02x}{:02x}", w[0], w[1]))
        .collect();
    words.join(" ")
}

/// The PDU a wire frame of `framing` carries: an MBAP frame's after its header; an ASCII frame's
/// if it is one, else an RTU frame's (whether or not its check passes: the outcome says that).
fn pdu_of(framing: &str, frame: &[u8]) -> Option<Vec<u8>> {
    if framing == "tcp" {
        return mbap::pdu(frame).map(<[u8]>::to_vec);
    }
    let mut pdu = Vec::new();
    if frame.first() == Some(&b':') && ascii::decode_into(frame, &mut pdu).is_some() {
        return Some(pdu);
    }
    (frame.len() >= 4).then(|| rtu::pdu_of(frame).to_vec())
}

impl Frame {
    /// One line for a terminal: `14:00:00.123456 line1 tx  slave 1    read holding registers
    /// 0x03  addr 0x0000 (0) count 2   01 03 00 00 00 02 c4 0b`.
    fn describe(&self) -> String {
        // The time of day (UTC) of the RFC 3339 time: between the `T` and the `Z`.
        let time = self
            .time
            .split_once('T')
            .map_or(self.time.as_str(), |(_, t)| t.trim_end_matches('Z'));
        let bytes: Vec<u8> = self
            .hex
            .split_whitespace()
            .filter_map(|b| u8::from_str_radix(b, 16).ok())
            .collect();
        let pdu = pdu_of(&self.framing, &bytes).filter(|pdu| !pdu.is_empty());
        let mut line = format!(
            "{time} {} {:<3} slave {:<3}  ",
            self.bus, self.direction, self.slave
        );
        let function = self.function;
        // On a serial master port (bus `serial:NAME`; a bus's name has no colon) and a virtual
        // unit (`virtual:NAME`) the gateway is the slave: there `rx` is the master's request
        // and `tx` the reply.
        let answering = [PORT_PEER_PREFIX, VIRTUAL_TRACE_PREFIX]
            .iter()
            .any(|prefix| self.bus.starts_with(prefix));
        // On a listen-only line both are heard, and the direction says which is which.
        let request = self.direction == "request"
            || (self.direction != "reply" && (self.direction == "tx") != answering);
        if request {
            let name = pdu::function(function).map_or("function", |f| f.name);
            let _ = write!(line, "{} 0x{function:02x}", name.to_lowercase());
            if let Some(pdu) = &pdu {
                push_fields(&mut line, &request_fields(pdu));
            }
            // An answer's outcome is on its own line; a try that got none says so here.
            if !matches!(self.outcome.as_str(), "ok" | "exception" | "answered") {
                let _ = write!(line, "  ({})", self.outcome);
            }
        } else {
            let _ = write!(line, "0x{function:02x} ");
            let readable = matches!(
                self.outcome.as_str(),
                "ok" | "foreign" | "malformed_reply" | "answered" | "unpaired"
            );
            match &pdu {
                Some(pdu) if function & pdu::EXCEPTION_BIT != 0 && pdu.len() > 1 => {
                    let code = pdu[1];
                    let _ = write!(line, "exception 0x{code:02x}");
                    if let Some(name) = pdu::exception_name(code) {
                        let _ = write!(line, " {name}");
                    }
                    if self.outcome != "exception" {
                        let _ = write!(line, " ({})", self.outcome);
                    }
                }
                Some(pdu) if readable => {
                    line.push_str(&self.outcome);
                    push_fields(&mut line, &reply_fields(pdu));
                }
                _ => line.push_str(&self.outcome),
            }
        }
        let _ = write!(line, "   {}", self.hex);
        line
    }
}

fn push_fields(line: &mut String, fields: &str) {
    if !fields.is_empty() {
        line.push_str("  ");
        line.push_str(fields);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(direction: &str, hex: &str, outcome: &str) -> Frame {
        let bytes: Vec<u8> = hex
            .split(' ')
            .map(|b| u8::from_str_radix(b, 16).unwrap())
            .collect();
        Frame {
            time: "2026-11-23T14:00:00.123456Z".into(),
            bus: "line1".into(),
            direction: direction.into(),
            slave: bytes[0],
            function: bytes[1],
            hex: hex.into(),
            framing: String::new(),
            outcome: outcome.into(),
        }
    }

    #[test]
    fn a_reply_of_one_register_or_one_byte_of_bits_says_so_in_the_singular() {
        // Slave 1, function 03, 2 bytes: one register 0x002A; CRC 39 9b.
        let rx = frame("rx", "01 03 02 00 2a 39 9b", "ok");
        assert!(
            rx.describe().contains("0x03 ok  1 register: 0x002a   "),
            "{}",
            rx.describe()
        );
        // Slave 1, function 01, 1 byte of coils: 0x05; CRC 91 8b.
        let rx = frame("rx", "01 01 01 05 91 8b", "ok");
        assert!(
            rx.describe().contains("0x01 ok  1 byte of bits: 05"),
            "{}",
            rx.describe()
        );
        let mut events = Events::default();
        assert_eq!(
            events.feed("event: lost\ndata: {\"lost\":1}\n\n"),
            ["lost 1 event"]
        );
    }

    #[test]
    fn on_a_serial_master_port_the_masters_rx_is_the_request_and_the_gateways_tx_the_reply() {
        let mut rx = frame("rx", "01 03 21 03 00 01 7e 36", "answered");
        rx.bus = "serial:scada".into();
        assert_eq!(
            rx.describe(),
            "14:00:00.123456 serial:scada rx  slave 1    read holding registers 0x03  addr 0x2103 \
             (8451) count 1   01 03 21 03 00 01 7e 36"
        );
        let mut tx = frame("tx", "01 03 02 01 06 39 d6", "answered");
        tx.bus = "serial:scada".into();
        assert_eq!(
            tx.describe(),
            "14:00:00.123456 serial:scada tx  slave 1    0x03 answered  1 register: 0x0106   \
             01 03 02 01 06 39 d6"
        );
        // A request to a unit the port does not answer: the master's frame alone, and why.
        let mut rx = frame("rx", "09 03 00 00 00 01 85 42", "not_addressed");
        rx.bus = "serial:scada".into();
        assert!(
            rx.describe().contains("count 1  (not_addressed)   09 03"),
            "{}",
            rx.describe()
        );
    }

    #[test]
    fn on_a_virtual_unit_too_the_masters_rx_is_the_request() {
        let mut rx = frame("rx", "01 03 21 03 00 01 7e 36", "answered");
        rx.bus = "virtual:copy".into();
        assert!(
            rx.describe()
                .contains("virtual:copy rx  slave 1    read holding registers 0x03"),
            "{}",
            rx.describe()
        );
    }

    #[test]
    fn a_read_and_its_reply_are_decoded_with_their_registers() {
        // Slave 1, read 2 holding registers from 0000H; its answer 0x0000 0x0001.
        let tx = frame("tx", "01 03 00 00 00 02 c4 0b", "ok");
        assert_eq!(
            tx.describe(),
            "14:00:00.123456 line1 tx  slave 1    read holding registers 0x03  addr 0x0000 (0) count 2   \
             01 03 00 00 00 02 c4 0b"
        );
        let rx = frame("rx", "01 03 04 00 00 00 01 3b f3", "ok");
        assert_eq!(
            rx.describe(),
            "14:00:00.123456 line1 rx  slave 1    0x03 ok  2 registers: 0x0000 0x0001   \
             01 03 04 00 00 00 01 3b f3"
        );
    }

    #[test]
    fn a_listen_lines_heard_request_and_reply_are_decoded_as_such() {
        // Heard on a listen-only line: another master's read of 2 registers, and the answer.
        let request = frame("request", "01 03 00 00 00 02 c4 0b", "ok");
        assert!(
            request
                .describe()
                .contains("line1 request slave 1    read holding registers 0x03  addr 0x0000 (0)"),
            "{}",
            request.describe()
        );
        let reply = frame("reply", "01 03 04 00 00 00 01 3b f3", "ok");
        assert!(
            reply
                .describe()
                .contains("line1 reply slave 1    0x03 ok  2 registers: 0x0000 0x0001"),
            "{}",
            reply.describe()
        );
        let timeout = frame("request", "05 03 00 00 00 02 c5 8f", "timeout");
        assert!(
            timeout.describe().contains("(timeout)"),
            "{}",
            timeout.describe()
        );
    }

    #[test]
    fn a_modbus_tcp_devices_frames_are_decoded_after_their_mbap_header() {
        // Transaction 1, unit 1, read 2 holding registers from 0000H: its RTU reading would
        // take the header for an address and a function.
        let mut tx = frame("tx", "00 01 00 00 00 06 01 03 00 00 00 02", "ok");
        tx.framing = "tcp".into();
        tx.slave = 1;
        tx.function = 3;
        assert!(
            tx.describe()
                .contains("read holding registers 0x03  addr 0x0000 (0) count 2"),
            "{}",
            tx.describe()
        );
    }

    #[test]
    fn an_exception_is_named_and_a_vendor_code_is_shown_by_number() {
        let rx = frame("rx", "01 83 02 c0 f1", "exception");
        assert!(
            rx.describe()
                .contains("slave 1    0x83 exception 0x02 illegal data address   01 83 02 c0 f1"),
            "{}",
            rx.describe()
        );
        let vendor = frame("rx", "01 86 07 03 a2", "exception");
        assert!(
            vendor.describe().contains("0x86 exception 0x07   "),
            "{}",
            vendor.describe()
        );
    }

    #[test]
    fn a_request_that_got_no_reply_shows_its_outcome_and_writes_show_their_values() {
        let tx = frame("tx", "05 06 00 01 13 88 d4 d8", "timeout");
        assert!(
            tx.describe().contains(
                "tx  slave 5    write single register 0x06  addr 0x0001 (1) value 0x1388  (timeout)   05 06"
            ),
            "{}",
            tx.describe()
        );
    }

    #[test]
    fn an_ascii_frame_is_decoded_from_its_characters() {
        // `:` 01 03 0000 0002 LRC(FA) CR LF
        let hex = crate::trace::hex(b":010300000002FA\r\n");
        let mut tx = frame("tx", "01 03", "ok");
        tx.hex = hex;
        assert!(
            tx.describe()
                .contains("read holding registers 0x03  addr 0x0000 (0) count 2   3a 30 31"),
            "{}",
            tx.describe()
        );
    }

    #[test]
    fn events_are_cut_from_the_stream_wherever_its_chunks_end() {
        let stream =
            ": modbus-gateway trace\n\n: keepalive\n\nevent: lost\ndata: {\"lost\":17}\n\n\
            event: frame\ndata: {\"time\":\"2026-11-23T14:00:00.123456Z\",\"bus\":\"line1\",\
            \"direction\":\"tx\",\"slave\":1,\"function\":3,\"hex\":\"01 03 00 00 00 02 c4 0b\",\
            \"outcome\":\"ok\"}\n\n";
        let mut events = Events::default();
        let mut lines = Vec::new();
        for chunk in stream.as_bytes().chunks(7) {
            lines.extend(events.feed(std::str::from_utf8(chunk).unwrap()));
        }
        assert_eq!(lines.len(), 2, "{lines:?}");
        assert_eq!(lines[0], "lost 17 events");
        assert!(
            lines[1].starts_with("14:00:00.123456 line1 tx"),
            "{lines:?}"
        );
    }

    #[test]
    fn the_url_gets_the_trace_path_and_the_filters() {
        let uri = with_filters("http://127.0.0.1:9502", Some("line1"), Some(3)).unwrap();
        assert_eq!(
            uri.to_string(),
            "http://127.0.0.1:9502/trace?bus=line1&slave=3"
        );
        assert_eq!(
            url_of("0.0.0.0:9502".parse().unwrap()),
            "http://127.0.0.1:9502/trace"
        );
        assert!(with_filters("ftp://x", None, None).is_err());
    }
}
