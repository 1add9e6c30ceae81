//! The transactions with `tests/peers/pymodbus_slave.py`'s slave that several tests make through
//! the gateway, each a (request PDU, the slave's reply PDU) pair: its holding registers hold
//! 1000 + n until written. Written once here, so every line that reaches the script (a pty, ser2net
//! in front of it, RTU or ASCII) is held to the same bytes.

/// A request PDU and the reply PDU the slave answers it with.
pub type Case = (&'static [u8], &'static [u8]);

/// 03 read holding registers 0-2: 1000, 1001, 1002.
pub const READ_HOLDING_0_2: Case = (
    &[0x03, 0x00, 0x00, 0x00, 0x03],
    &[0x03, 0x06, 0x03, 0xE8, 0x03, 0xE9, 0x03, 0xEA],
);

/// Two writes, the read that shows them, and a read the slave refuses, in this order.
pub const WRITES_READ_BACK: [Case; 4] = [
    // 06 write register 1 = 0x1234: echo.
    (
        &[0x06, 0x00, 0x01, 0x12, 0x34],
        &[0x06, 0x00, 0x01, 0x12, 0x34],
    ),
    // 10 write registers 2-3 = 7, 8: start and count.
    (
        &[0x10, 0x00, 0x02, 0x00, 0x02, 0x04, 0x00, 0x07, 0x00, 0x08],
        &[0x10, 0x00, 0x02, 0x00, 0x02],
    ),
    // 03 read registers 0-3 back: 1000 and both writes.
    (
        &[0x03, 0x00, 0x00, 0x00, 0x04],
        &[0x03, 0x08, 0x03, 0xE8, 0x12, 0x34, 0x00, 0x07, 0x00, 0x08],
    ),
    // 03 read register 0x20, which the slave does not have: exception 02, illegal address.
    (&[0x03, 0x00, 0x20, 0x00, 0x01], &[0x83, 0x02]),
];

/// The five transactions: a read, then [`WRITES_READ_BACK`].
pub const FIVE_TRANSACTIONS: [Case; 5] = [
    READ_HOLDING_0_2,
    WRITES_READ_BACK[0],
    WRITES_READ_BACK[1],
    WRITES_READ_BACK[2],
    WRITES_READ_BACK[3],
];
