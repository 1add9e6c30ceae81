//! The gateway's own polls of a slave's plant values, as its bus's metrics count them: every poll,
//! and every failed one by outcome. Their series are made at zero once the slave's values are to
//! be polled, as a known slave's other series are, so that a rate or an alert on failed polls has
//! a series to read before the first failure. Knows nothing of what a poll reads.

use super::bus::BusMetrics;
use super::labels::decimal;
use std::sync::atomic::Ordering;

/// The `outcome` label of a failed poll of plant values.
pub(crate) const POLL_OUTCOMES: [&str; 7] = [
    "timeout",
    "exception",
    "bad_reply",
    "port_down",
    "slave_down",
    "queue_full",
    "expired",
];

impl BusMetrics {
    /// The gateway is to poll `slave`'s plant values: its poll series, at zero until it does.
    pub(crate) fn will_poll(&self, slave: u8) {
        let address = decimal(slave);
        self.polls.with_label_values(&[&*self.name, address]);
        for outcome in POLL_OUTCOMES {
            self.poll_errors
                .with_label_values(&[&*self.name, address, outcome]);
        }
    }

    /// The gateway polled `slave`'s plant values; the poll failed as `failed` (one of
    /// [`POLL_OUTCOMES`]) if it did.
    pub(crate) fn polled(&self, slave: u8, failed: Option<&'static str>) {
        let address = decimal(slave);
        self.polls.with_label_values(&[&*self.name, address]).inc();
        if let Some(known) = self.known(slave) {
            known.polls.fetch_add(1, Ordering::Relaxed);
        }
        if let Some(outcome) = failed {
            let labels = &[&*self.name, address, outcome];
            self.poll_errors.with_label_values(labels).inc();
        }
    }
}
