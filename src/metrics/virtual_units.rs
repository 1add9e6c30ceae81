//! The virtual units' metrics: each unit's requests by how they ended (`[[virtual]]`).

use super::Definer;
use crate::error::{Answer, Outcome, RequestError};
use crate::pdu::{ExceptionCode, EXCEPTION_BIT};
use prometheus::IntCounterVec;

/// How a request to a virtual unit ended: the `outcome` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum VirtualOutcome {
    /// A read answered from memory.
    Answered,
    /// A write carried out on its source slave (or acknowledged by a rule).
    Written,
    /// 0x0B: a register it touches is older than its `max_age`, never read, failed its last
    /// poll, or out of its type's range.
    Stale,
    /// 0x02: it touches an address the unit does not lay out.
    NotMapped,
    /// Another exception the unit made itself: 0x01 (a function it does not answer, a register
    /// that is not writable), 0x03 (a quantity or a value it cannot take), 0x06 (a reload).
    Exception,
    /// Refused by a rule, a read-only or role setting, or the journal.
    Denied,
    /// A write its source slave did not carry out: its exception, or no answer.
    Failed,
}

impl VirtualOutcome {
    pub(crate) const ALL: [VirtualOutcome; 7] = [
        VirtualOutcome::Answered,
        VirtualOutcome::Written,
        VirtualOutcome::Stale,
        VirtualOutcome::NotMapped,
        VirtualOutcome::Exception,
        VirtualOutcome::Denied,
        VirtualOutcome::Failed,
    ];

    pub(crate) fn label(self) -> &'static str {
        match self {
            VirtualOutcome::Answered => "answered",
            VirtualOutcome::Written => "written",
            VirtualOutcome::Stale => "stale",
            VirtualOutcome::NotMapped => "not_mapped",
            VirtualOutcome::Exception => "exception",
            VirtualOutcome::Denied => "denied",
            VirtualOutcome::Failed => "failed",
        }
    }

    /// What `outcome` of a request with `function` to a virtual unit was.
    pub(crate) fn of(function: u8, outcome: &Outcome) -> VirtualOutcome {
        match outcome {
            Err(RequestError::Emulated(code)) => match code {
                ExceptionCode::GatewayTargetFailedToRespond => VirtualOutcome::Stale,
                ExceptionCode::IllegalDataAddress => VirtualOutcome::NotMapped,
                _ => VirtualOutcome::Exception,
            },
            // A write's source slave answered with an exception.
            Ok(Answer::Reply(pdu)) if pdu.first().is_some_and(|f| f & EXCEPTION_BIT != 0) => {
                VirtualOutcome::Failed
            }
            Ok(_) if (0x01..=0x04).contains(&function) => VirtualOutcome::Answered,
            Ok(_) => VirtualOutcome::Written,
            Err(
                RequestError::Denied { .. }
                | RequestError::ReadOnly(_)
                | RequestError::NoAccess(_)
                | RequestError::UnitNotPermitted(_)
                | RequestError::Unverifiable(_)
                | RequestError::Unrecorded(_),
            ) => VirtualOutcome::Denied,
            Err(RequestError::InvalidFunction(_) | RequestError::BadLength { .. }) => {
                VirtualOutcome::Exception
            }
            Err(_) => VirtualOutcome::Failed,
        }
    }
}

/// `modbus_gateway_virtual_requests_total`.
pub(crate) struct VirtualMetrics {
    requests: IntCounterVec,
}

impl VirtualMetrics {
    pub(super) fn new(define: &Definer) -> Self {
        VirtualMetrics {
            requests: define.int_counter(
                "modbus_gateway_virtual_requests_total",
                "Requests to a virtual unit ([[virtual]]), answered from memory, by how they \
                 ended.",
                &["unit", "name", "outcome"],
            ),
        }
    }

    /// Every outcome's series of the virtual unit `unit` called `name`, at 0 until counted.
    pub(crate) fn declare(&self, unit: u8, name: &str) {
        let unit = unit.to_string();
        for outcome in VirtualOutcome::ALL {
            self.requests
                .with_label_values(&[unit.as_str(), name, outcome.label()]);
        }
    }

    /// A request with `function` to unit `unit` (`name`) ended in `outcome`.
    pub(crate) fn request(&self, unit: u8, name: &str, function: u8, outcome: &Outcome) {
        let label = VirtualOutcome::of(function, outcome).label();
        self.requests
            .with_label_values(&[unit.to_string().as_str(), name, label])
            .inc();
    }
}
