//! Modbus RTU framing: CRC-16, frames as bytes, and how long a frame is from its first bytes
//! ([`frame`]). Pure functions over bytes; the master that runs transactions with these frames is
//! [`crate::line`]. Knows nothing of ports, time, TCP, masters, queues or routing.

pub mod frame;
