//! The network side: listeners and connection limits ([`server`]), who may connect and write
//! ([`access`]), one task per master ([`session`]), how a master frames its requests
//! ([`upstream`]: MBAP ([`mbap`]) or RTU over TCP), Modbus/TCP Security's TLS and roles
//! ([`tls`]), and Modbus UDP ([`udp`]). Knows nothing of
//! serial timing or ports.

pub(crate) mod access;
pub(crate) mod mbap;
pub(crate) mod server;
pub mod session;
pub(crate) mod tls;
pub(crate) mod udp;
pub(crate) mod upstream;

pub(crate) use server::{bind, serve, Policy};
pub use session::SessionLimits;
pub(crate) use upstream::Upstream;
