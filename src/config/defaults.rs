//! Every default of the configuration, defined once: the values a key takes when the file and the
//! environment leave it out. Knows nothing of how they are checked or used.

use crate::line::{Framing, LineTiming, Parity};
use std::net::SocketAddr;
use std::time::Duration;

pub(crate) fn listen() -> Vec<SocketAddr> {
    vec![SocketAddr::from(([0, 0, 0, 0], 502))]
}
pub(crate) const MAX_CONNECTIONS: usize = 1024;
/// Slots one address leaves to the others by default (half of them, with fewer than twice as
/// many in all).
pub(crate) const SLOTS_FOR_OTHER_ADDRESSES: usize = 8;
/// All but [`SLOTS_FOR_OTHER_ADDRESSES`]: one host never takes every slot, the PLCs, HMIs and
/// SCADA on other hosts always find room, and a host with many masters still gets nearly all.
pub(crate) fn max_connections_per_address(max_connections: usize) -> usize {
    max_connections - SLOTS_FOR_OTHER_ADDRESSES.min(max_connections / 2)
}
pub(crate) const IDLE_TIMEOUT: Duration = Duration::from_secs(600);
pub(crate) const PIPELINE_DEPTH: usize = 16;
pub(crate) const SHUTDOWN_TIMEOUT: Duration = Duration::from_secs(10);
pub(crate) const FRAME_TIMEOUT: Duration = Duration::from_secs(5);
pub(crate) const KEEPALIVE: Duration = Duration::from_secs(60);
pub(crate) fn tls_handshake_timeout() -> Duration {
    Duration::from_secs(10)
}
pub(crate) fn metrics_listen() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 9502))
}
pub(crate) const LOG_LEVEL: &str = "info";

pub(crate) fn baud() -> u32 {
    19_200
}
/// 8 for RTU, which needs them; 7 for ASCII, whose characters fit (7E1, Modbus over Serial Line
/// V1.02, 2.5.2).
pub(crate) fn data_bits(framing: Framing) -> u8 {
    match framing {
        Framing::Rtu | Framing::Tcp => 8,
        Framing::Ascii => 7,
    }
}
/// 1 with parity, 2 without, so that every character is 11 bits long, as the spec asks.
pub(crate) fn stop_bits(parity: Parity) -> u8 {
    if parity == Parity::None {
        2
    } else {
        1
    }
}
/// RTS is asserted while the gateway sends, as most transceivers' driver enable wants.
pub(crate) fn rts_on_send() -> bool {
    true
}
/// Quiet before an ASCII frame: the spec asks for none, but a master that waits a character and a
/// half after the last one it heard never talks over a slave that is still sending.
pub(crate) fn ascii_gap(line: &LineTiming) -> Duration {
    line.char_time * 3 / 2
}
/// The inter-character timeout of an ASCII line: the spec's figure.
pub(crate) fn ascii_byte_timeout() -> Duration {
    Duration::from_secs(1)
}
/// The silence that ends an RTU reply of unknown length behind a serial device server: t3.5 is
/// below a network's jitter (a segment may come a few milliseconds after the one before it).
pub(crate) const NETWORK_BYTE_TIMEOUT: Duration = Duration::from_millis(20);
pub(crate) fn parity() -> Parity {
    Parity::Even
}
pub(crate) fn response_timeout() -> Duration {
    Duration::from_secs(1)
}
pub(crate) fn turnaround_delay() -> Duration {
    Duration::from_millis(100)
}
pub(crate) fn broadcast_reply() -> bool {
    true
}
pub(crate) fn queue_depth() -> usize {
    256
}
pub(crate) fn queue_timeout() -> Duration {
    Duration::from_secs(1)
}
/// A serial master port answers every address a slave may have.
pub(crate) fn port_units() -> super::UnitSet {
    let mut units = super::UnitSet::default();
    (1..=crate::line::MAX_SERIAL_ADDRESS).for_each(|u| units.insert(u));
    units
}
/// Below the 1 s response timeout most masters default to, with room for the reply's own time
/// on the wire.
pub(crate) fn answer_within() -> Duration {
    Duration::from_millis(800)
}
pub(crate) fn reopen_delay() -> Duration {
    Duration::from_millis(250)
}
pub(crate) fn reopen_delay_max() -> Duration {
    Duration::from_secs(5)
}
pub(crate) fn slave_down_after() -> u32 {
    3
}
pub(crate) fn max_in_flight() -> usize {
    1
}
/// The most requests a device's connection may have outstanding: Modbus TCP devices that
/// pipeline at all take a handful.
pub(crate) const MAX_IN_FLIGHT: usize = 16;
pub(crate) fn match_transaction_id() -> bool {
    true
}
pub(crate) fn coalesce_reads() -> bool {
    true
}
pub(crate) const PRIORITY_SHARE: f64 = 0.9;
pub(crate) fn slave_probe_interval() -> Duration {
    Duration::from_secs(5)
}

/// The most of a line's time polling may take while masters wait.
pub(crate) fn poll_share() -> f64 {
    0.2
}
/// How often a slave's values are read unless it or a value says otherwise.
pub(crate) const POLL_INTERVAL: Duration = Duration::from_secs(10);

/// The journal's size before it rotates.
pub(crate) fn audit_max_size() -> super::audit::ByteSize {
    super::audit::ByteSize(10 << 20)
}
/// Rotated journal files kept.
pub(crate) fn audit_keep() -> u32 {
    5
}
/// What a `true` by default reads.
pub(crate) fn yes() -> bool {
    true
}
/// The first level of every MQTT topic the gateway publishes.
pub(crate) fn mqtt_topic_prefix() -> String {
    "modbus-gateway".to_owned()
}
/// At least once.
pub(crate) fn mqtt_qos() -> i64 {
    1
}
/// An unchanged value is published again this often.
pub(crate) fn mqtt_publish_interval() -> Duration {
    Duration::from_secs(60)
}
/// Home Assistant's own default.
pub(crate) fn mqtt_discovery_prefix() -> String {
    "homeassistant".to_owned()
}

/// A listen line's shadow data older than this is not served: most masters poll more often.
pub(crate) fn listen_max_age() -> Duration {
    Duration::from_secs(10)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_stop_bits_keep_characters_at_11_bits() {
        assert_eq!(stop_bits(Parity::None), 2);
        assert_eq!(stop_bits(Parity::Even), 1);
        assert_eq!(stop_bits(Parity::Odd), 1);
    }
}
