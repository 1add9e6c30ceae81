//! The Modbus TCP side: listeners and connection limits ([`server`]), who may connect and write
//! ([`access`]), one task per master ([`session`]), MBAP framing ([`mbap`]). Knows nothing of
//! serial timing or ports.

pub(crate) mod access;
pub(crate) mod mbap;
pub(crate) mod server;
pub mod session;

pub(crate) use server::{bind, serve, Policy};
pub use session::SessionLimits;
