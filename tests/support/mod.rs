//! The integration tests' shared pieces are the workspace's `test-support` crate
//! (test-support/): a gateway started from TOML or from a typed configuration, a bus on the
//! simulated line, a raw master, a pty slave, the test PKI, scrapes. A helper that only one test
//! file needs lives in that file.

pub use test_support::*;
