//! The network side, where masters reach the gateway. A listener is a transport and a framing
//! ([`Protocol`](crate::master::Protocol) says which pairs there are): what every listener
//! shares, binding, the admission policy and the door ([`listener`]), who may connect and write
//! ([`access`]); streams (TCP, and TLS with Modbus/TCP Security's roles, [`tls`]): the accept
//! loop and connection limits ([`server`]) and one task per master ([`session`]); datagrams:
//! Modbus UDP ([`udp`]); the framings' codecs ([`framing`]: MBAP ([`crate::mbap`]) or RTU). Knows
//! nothing of serial timing or ports.

pub(crate) mod access;
pub(crate) mod framing;
pub(crate) mod listener;
pub(crate) mod server;
pub mod session;
pub(crate) mod tls;
pub(crate) mod udp;

pub(crate) use listener::{bind_all, serve, ListenAddrs, Policy};
