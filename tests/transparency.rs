//! Byte transparency: the PDU a master sends is the PDU on the wire, and the PDU the slave answers
//! (normal or exception, vendor codes included) is the PDU the master gets, for every function
//! code the issue names and a user-defined one.

use crate::support::{addr, pty_config, start, start_sim, PtySlave, RawMaster};
use modbus_gateway::testing::line::rtu;
use modbus_gateway::testing::sim::Source;

/// (request PDU, the slave's reply PDU), mostly the examples of the Modbus Application Protocol
/// specification V1.1b3 chapter 6.
const CASES: &[(&[u8], &[u8])] = &[
    // 01 read coils 20-38.
    (
        &[0x01, 0x00, 0x13, 0x00, 0x13],
        &[0x01, 0x03, 0xCD, 0x6B, 0x05],
    ),
    // 02 read discrete inputs 197-218.
    (
        &[0x02, 0x00, 0xC4, 0x00, 0x16],
        &[0x02, 0x03, 0xAC, 0xDB, 0x35],
    ),
    // 03 read holding registers 108-110.
    (
        &[0x03, 0x00, 0x6B, 0x00, 0x03],
        &[0x03, 0x06, 0x02, 0x2B, 0x00, 0x00, 0x00, 0x64],
    ),
    // 04 read input register 9.
    (&[0x04, 0x00, 0x08, 0x00, 0x01], &[0x04, 0x02, 0x00, 0x0A]),
    // 05 write coil 173 on: echo.
    (
        &[0x05, 0x00, 0xAC, 0xFF, 0x00],
        &[0x05, 0x00, 0xAC, 0xFF, 0x00],
    ),
    // 06 write register 2 = 3: echo.
    (
        &[0x06, 0x00, 0x01, 0x00, 0x03],
        &[0x06, 0x00, 0x01, 0x00, 0x03],
    ),
    // 08 diagnostics, return query data: echo.
    (
        &[0x08, 0x00, 0x00, 0xA5, 0x37],
        &[0x08, 0x00, 0x00, 0xA5, 0x37],
    ),
    // 0F write 10 coils from 20.
    (
        &[0x0F, 0x00, 0x13, 0x00, 0x0A, 0x02, 0xCD, 0x01],
        &[0x0F, 0x00, 0x13, 0x00, 0x0A],
    ),
    // 10 write registers 2-3.
    (
        &[0x10, 0x00, 0x01, 0x00, 0x02, 0x04, 0x00, 0x0A, 0x01, 0x02],
        &[0x10, 0x00, 0x01, 0x00, 0x02],
    ),
    // 11 report server id: id 7, running, "GW!".
    (&[0x11], &[0x11, 0x05, 0x07, 0xFF, b'G', b'W', b'!']),
    // 16 mask write register 4.
    (
        &[0x16, 0x00, 0x04, 0x00, 0xF2, 0x00, 0x25],
        &[0x16, 0x00, 0x04, 0x00, 0xF2, 0x00, 0x25],
    ),
    // 17 read 6 registers from 4, write 3 from 15.
    (
        &[
            0x17, 0x00, 0x03, 0x00, 0x06, 0x00, 0x0E, 0x00, 0x03, 0x06, 0x00, 0xFF, 0x00, 0xFF,
            0x00, 0xFF,
        ],
        &[
            0x17, 0x0C, 0x00, 0xFE, 0x0A, 0xCD, 0x00, 0x01, 0x00, 0x03, 0x00, 0x0D, 0x00, 0xFF,
        ],
    ),
    // 2B/0E read device identification, basic stream: "ACM", "X1".
    (
        &[0x2B, 0x0E, 0x01, 0x00],
        &[
            0x2B, 0x0E, 0x01, 0x01, 0x00, 0x00, 0x02, 0x00, 0x03, b'A', b'C', b'M', 0x01, 0x02,
            b'X', b'1',
        ],
    ),
    // 41, user-defined: whatever the device says.
    (
        &[0x41, 0x12, 0x34, 0x56],
        &[0x41, 0x99, 0x88, 0x77, 0x66, 0x55],
    ),
    // Exceptions pass unchanged, the drives' vendor codes 05-09 included.
    (&[0x03, 0x7F, 0x00, 0x00, 0x01], &[0x83, 0x02]),
    (&[0x06, 0x20, 0x00, 0x00, 0x09], &[0x86, 0x07]),
    (
        &[0x10, 0x00, 0x01, 0x00, 0x01, 0x02, 0x00, 0x00],
        &[0x90, 0x09],
    ),
    (&[0x42], &[0xC2, 0x05]),
];

fn canned_reply(request_frame: &[u8]) -> Option<Vec<u8>> {
    let pdu = rtu::pdu_of(request_frame);
    let (_, reply) = CASES.iter().find(|(request, _)| *request == pdu)?;
    Some(rtu::encode(request_frame[0], reply))
}

#[tokio::test]
async fn every_function_code_crosses_a_pty_byte_for_byte_both_ways() {
    let slave = PtySlave::start(canned_reply);
    let gateway = start(&pty_config(&slave.path, "")).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    for (i, (request, reply)) in CASES.iter().enumerate() {
        let unit = 1 + (i % 247) as u8;
        let got = master.call(i as u16, unit, request).await;
        assert_eq!(&got, reply, "reply to {request:02X?}");
        let on_wire = slave.received();
        assert_eq!(
            on_wire.last().unwrap(),
            &rtu::encode(unit, request),
            "request {request:02X?}"
        );
    }
    assert_eq!(
        slave.received().len(),
        CASES.len(),
        "each request went out once"
    );
}

#[tokio::test]
async fn every_function_code_crosses_the_sim_line_byte_for_byte_both_ways() {
    let gateway = start_sim("").await;
    let line = gateway.sim_line("sim").unwrap().clone();
    let mut master = RawMaster::connect(addr(&gateway)).await;
    for (i, (request, _)) in CASES.iter().enumerate() {
        let unit = 1 + (i % 4) as u8;
        let got = master.call(i as u16, unit, request).await;
        let frames = line.frames();
        let sent = frames
            .iter()
            .rev()
            .find(|f| f.from == Source::Master)
            .unwrap();
        assert_eq!(
            sent.bytes,
            rtu::encode(unit, request),
            "request {request:02X?}"
        );
        let answer = frames.last().unwrap();
        assert_eq!(answer.from, Source::Slave(unit));
        assert_eq!(
            rtu::pdu_of(&answer.bytes),
            got.as_slice(),
            "reply to {request:02X?}"
        );
    }
}
