//! The writes' metrics and the journal's events: writes by protocol, rule action and outcome;
//! the journal's errors, the writes it could not record, whether it is writable now and how
//! big its file is. Labels come as plain words from the journal's side (bounded sets: four
//! protocols, three actions, eight outcomes, four operations).

use super::Definer;
use prometheus::{IntCounterVec, IntGaugeVec};
use std::path::Path;
use tracing::{debug, error, info};

/// The label values of a family without labels.
const NONE: &[&str] = &[];

/// What the journal was doing when it failed: the `operation` label.
const OPERATIONS: [&str; 4] = ["open", "write", "rotate", "sync"];

pub struct AuditMetrics {
    writes: IntCounterVec,
    errors: IntCounterVec,
    unrecorded: IntCounterVec,
    refused: IntCounterVec,
    writable: IntGaugeVec,
    bytes: IntGaugeVec,
}

/// The log target of the journal's events.
const AUDIT_EVENTS: &str = "modbus_gateway::audit";

impl AuditMetrics {
    pub(super) fn new(define: &Definer) -> Self {
        let errors = define.int_counter(
            "modbus_gateway_audit_errors_total",
            "Audit journal operations that failed (open, write, rotate, sync).",
            &["operation"],
        );
        for operation in OPERATIONS {
            errors.with_label_values(&[operation]);
        }
        let unrecorded = define.int_counter(
            "modbus_gateway_audit_unrecorded_writes_total",
            "Writes sent without a journal entry because the journal could not be written \
             (audit.on_error = \"allow\").",
            &[],
        );
        unrecorded.with_label_values(NONE);
        let refused = define.int_counter(
            "modbus_gateway_audit_refused_writes_total",
            "Writes refused with exception 0x0A because the journal could not be written \
             (audit.on_error = \"deny_writes\").",
            &[],
        );
        refused.with_label_values(NONE);
        AuditMetrics {
            writes: define.int_counter(
                "modbus_gateway_writes_total",
                "Write-class requests (every function that may change a slave, broadcasts \
                 included) by the master's protocol, the deciding rule's action and the \
                 outcome.",
                &["protocol", "action", "outcome"],
            ),
            errors,
            unrecorded,
            refused,
            writable: define.int_gauge(
                "modbus_gateway_audit_journal_writable",
                "1 while the audit journal takes entries, 0 while it cannot be written; absent \
                 without [audit].",
                &[],
            ),
            bytes: define.int_gauge(
                "modbus_gateway_audit_journal_bytes",
                "Size of the live audit journal file (before it is rotated at audit.max_size).",
                &[],
            ),
        }
    }

    /// A write-class request ended.
    pub fn write_ended(&self, protocol: &str, action: &str, outcome: &str) {
        self.writes
            .with_label_values(&[protocol, action, outcome])
            .inc();
    }

    /// The journal at `path` is open and `bytes` long, or (`None`) there is none.
    pub fn journal(&self, open: Option<u64>) {
        match open {
            Some(bytes) => {
                self.writable.with_label_values(NONE).set(1);
                self.bytes.with_label_values(NONE).set(gauge(bytes));
            }
            None => {
                let _ = self.writable.remove_label_values(NONE);
                let _ = self.bytes.remove_label_values(NONE);
            }
        }
    }

    /// The journal's live file is `bytes` long now.
    pub fn journal_bytes(&self, bytes: u64) {
        self.bytes.with_label_values(NONE).set(gauge(bytes));
    }

    /// `operation` on the journal at `path` failed. The first failure of a streak is logged
    /// as an error; the rest at debug (they are counted, and the recovery says how many).
    pub fn journal_failed(
        &self,
        path: &Path,
        operation: &'static str,
        reason: &dyn std::fmt::Display,
        first: bool,
        writes: &'static str,
    ) {
        self.errors.with_label_values(&[operation]).inc();
        self.writable.with_label_values(NONE).set(0);
        let path = path.display();
        if first {
            error!(target: AUDIT_EVENTS, %path, operation, error = %reason, "cannot write the audit journal: {writes}");
        } else {
            debug!(target: AUDIT_EVENTS, %path, operation, error = %reason, "the audit journal still cannot be written");
        }
    }

    /// A write went on unrecorded, or was refused, for the journal.
    pub fn unrecorded(&self, refused: bool) {
        if refused {
            self.refused.with_label_values(NONE).inc();
        } else {
            self.unrecorded.with_label_values(NONE).inc();
        }
    }

    /// The journal at `path` takes entries again, after `unrecorded` writes went on without
    /// one and `refused` were refused.
    pub fn journal_recovered(&self, path: &Path, unrecorded: u64, refused: u64) {
        self.writable.with_label_values(NONE).set(1);
        let path = path.display();
        info!(target: AUDIT_EVENTS, %path, unrecorded, refused, "the audit journal is writable again");
    }
}

fn gauge(bytes: u64) -> i64 {
    i64::try_from(bytes).unwrap_or(i64::MAX)
}
