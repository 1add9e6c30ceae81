//! The real serial path: the gateway opens a pty like a serial device, and a third-party Modbus
//! TCP client (tokio-modbus) reads and writes the slave behind it; a reply with a bad CRC or from
//! another address is never forwarded, and a port that vanishes gives 0x0A until it is back.

use crate::support::{
    addr, pty_config, start, start_sim, wait_for_bus, PtySlave, RawMaster, TempDir,
};
use modbus_gateway::testing::line::rtu;
use tokio_modbus::client::{tcp, Reader, Writer};
use tokio_modbus::Slave;

const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];

async fn read_and_write_with_tokio_modbus(gateway: &modbus_gateway::Gateway, unit: u8) {
    let mut ctx = tcp::connect_slave(addr(gateway), Slave(unit))
        .await
        .unwrap();
    ctx.write_single_register(0x0004, 5000)
        .await
        .unwrap()
        .unwrap();
    ctx.write_multiple_registers(0x0005, &[50, 60])
        .await
        .unwrap()
        .unwrap();
    let words = ctx
        .read_holding_registers(0x0004, 3)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(words, [5000, 50, 60]);
    ctx.write_multiple_coils(0x0010, &[true, false, true])
        .await
        .unwrap()
        .unwrap();
    let coils = ctx.read_coils(0x0010, 3).await.unwrap().unwrap();
    assert_eq!(coils, [true, false, true]);
    let inputs = ctx.read_input_registers(0x0100, 2).await.unwrap().unwrap();
    assert_eq!(inputs, [0x0100, 0x0101]);
    let exception = ctx.read_holding_registers(0x0000, 200).await.unwrap();
    assert!(
        exception.is_err(),
        "a read of 200 registers is refused by the slave"
    );
}

#[tokio::test]
async fn a_third_party_client_reads_and_writes_through_the_gateway_to_a_pty_slave() {
    let slave = PtySlave::registers();
    let gateway = start(&pty_config(&slave.path, "")).await;
    read_and_write_with_tokio_modbus(&gateway, 3).await;
    assert!(slave.received().iter().all(|f| f[0] == 3 && rtu::crc_ok(f)));
}

#[tokio::test]
async fn a_third_party_client_reads_and_writes_through_the_gateway_to_the_sim_line() {
    let gateway = start_sim("").await;
    read_and_write_with_tokio_modbus(&gateway, 2).await;
}

#[tokio::test]
async fn a_reply_with_a_bad_crc_is_not_forwarded() {
    let slave = PtySlave::start(|request| {
        let mut reply = rtu::encode(request[0], &[0x03, 0x02, 0x12, 0x34]);
        *reply.last_mut().unwrap() ^= 0xFF;
        Some(reply)
    });
    let gateway = start(&pty_config(&slave.path, "response_timeout = \"100ms\"")).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ).await, [0x83, 0x0B]);
}

#[tokio::test]
async fn a_reply_from_another_address_is_discarded() {
    let slave =
        PtySlave::start(|request| Some(rtu::encode(request[0] + 1, &[0x03, 0x02, 0x12, 0x34])));
    let gateway = start(&pty_config(&slave.path, "response_timeout = \"100ms\"")).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ).await, [0x83, 0x0B]);
}

#[tokio::test]
async fn reads_are_retried_on_a_bad_reply_and_succeed() {
    let mut calls = 0;
    let slave = PtySlave::start(move |request| {
        calls += 1;
        let mut reply = rtu::encode(request[0], &[0x03, 0x02, 0x12, 0x34]);
        if calls == 1 {
            *reply.last_mut().unwrap() ^= 0xFF;
        }
        Some(reply)
    });
    let gateway = start(&pty_config(&slave.path, "retries = 1")).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ).await, [0x03, 0x02, 0x12, 0x34]);
    assert_eq!(slave.received().len(), 2);
}

#[tokio::test]
async fn a_serial_port_that_vanishes_gives_0x0a_at_once_and_is_reopened_when_back() {
    let dir = TempDir::new("vanish");
    let device = dir.join("ttyRS485");
    let first = PtySlave::registers();
    std::os::unix::fs::symlink(&first.path, &device).unwrap();
    let keys = "response_timeout = \"1h\"\nreopen_delay = \"10ms\"\nreopen_delay_max = \"50ms\"";
    let gateway = start(&pty_config(device.to_str().unwrap(), keys)).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 1, &[0x06, 0x00, 0x01, 0x00, 0x07]).await[0],
        0x06
    );

    first.unplug();
    wait_for_bus(&gateway, "pty", false).await;
    // With a one-hour timeout, an answer at all is an answer at once.
    assert_eq!(master.call(2, 1, &READ).await, [0x83, 0x0A]);

    let second = PtySlave::registers();
    std::fs::remove_file(&device).unwrap();
    std::os::unix::fs::symlink(&second.path, &device).unwrap();
    wait_for_bus(&gateway, "pty", true).await;
    assert_eq!(
        master.call(3, 1, &READ).await,
        [0x03, 0x02, 0x00, 0x00],
        "same connection"
    );
    assert_eq!(second.received().len(), 1);
}
