//! Waiting in tests: a bound on every wait, and panics counted on the test's thread.

use std::cell::Cell;
use std::sync::Once;
use std::time::Duration;

/// Upper bound for anything a test waits for; a test that hits it has failed, not passed.
pub const PATIENCE: Duration = Duration::from_secs(20);
thread_local! {
    static PANICS: Cell<usize> = const { Cell::new(0) };
}
static COUNT_PANICS: Once = Once::new();

/// Panics raised so far on this thread. A `#[tokio::test]` runtime runs the gateway's tasks on
/// the test's own thread, and tokio turns a panicking session into a merely closed connection, so
/// tests of hostile input compare this before and after.
pub fn panics_on_this_thread() -> usize {
    COUNT_PANICS.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            PANICS.with(|p| p.set(p.get() + 1));
            previous(info);
        }));
    });
    PANICS.with(Cell::get)
}

pub async fn within<F: std::future::Future>(what: &str, future: F) -> F::Output {
    tokio::time::timeout(PATIENCE, future)
        .await
        .unwrap_or_else(|_| panic!("{what}: no result within {PATIENCE:?}"))
}
