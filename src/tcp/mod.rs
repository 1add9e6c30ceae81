//! The Modbus TCP side: listeners and connection limits ([`server`]), one task per master
//! ([`session`]), MBAP framing ([`mbap`]). Knows nothing of serial timing or ports.

pub mod mbap;
pub mod server;
pub mod session;

pub use server::{bind, serve, Listener};
pub use session::SessionLimits;
