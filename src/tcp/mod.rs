//! The Modbus TCP side: listeners and connection limits ([`server`]), who may connect and write
//! ([`access`]), one task per master ([`session`]), MBAP framing ([`mbap`]). Knows nothing of
//! serial timing or ports.

pub mod access;
pub mod mbap;
pub mod server;
pub mod session;

pub use server::{bind, serve, Listener, Policy};
pub use session::SessionLimits;
