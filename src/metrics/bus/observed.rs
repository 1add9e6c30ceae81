//! What a listen-only line hears, counted: the other master's requests and the time between two
//! asks of one read (its poll interval), the slaves' replies and exceptions and how long they
//! took, the requests nobody answered, and what was discarded (CRC errors, bytes that made no
//! frame, good frames that answered nothing). The families are every bus's; only a listen line
//! makes series in them. Labels are bounded as the requests' are: a slave's address once it is
//! configured or has answered, else `other`; a function the table knows, else `other`.

use super::BusMetrics;
use crate::metrics::labels::{decimal, function, hex};
use crate::metrics::Definer;
use prometheus::{GaugeVec, HistogramVec, IntCounterVec};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Why a listen line discarded what it heard: the `reason` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Discarded {
    /// A frame whose CRC (LRC) failed.
    CrcError,
    /// Bytes that made no frame.
    Broken,
    /// A good frame that answered no request.
    Unpaired,
}

impl Discarded {
    pub(crate) const ALL: [Discarded; 3] =
        [Discarded::CrcError, Discarded::Broken, Discarded::Unpaired];

    pub(crate) fn label(self) -> &'static str {
        match self {
            Discarded::CrcError => "crc_error",
            Discarded::Broken => "broken",
            Discarded::Unpaired => "unpaired",
        }
    }
}

/// The families of the listen lines' series.
#[derive(Clone)]
pub(in crate::metrics) struct ObservedFamilies {
    requests: IntCounterVec,
    replies: IntCounterVec,
    exceptions: IntCounterVec,
    timeouts: IntCounterVec,
    crc_errors: IntCounterVec,
    discarded: IntCounterVec,
    response: HistogramVec,
    poll_interval: GaugeVec,
    last_reply: GaugeVec,
}

impl ObservedFamilies {
    pub(in crate::metrics) fn new(define: &Definer) -> Self {
        let slave = &["bus", "slave"];
        ObservedFamilies {
            requests: define.int_counter(
                "modbus_gateway_observed_requests_total",
                "Listen-only lines: the other master's requests heard, by slave and function.",
                &["bus", "slave", "function"],
            ),
            replies: define.int_counter(
                "modbus_gateway_observed_replies_total",
                "Listen-only lines: replies heard that answered a request, by slave, function \
                 and outcome (ok, exception).",
                &["bus", "slave", "function", "outcome"],
            ),
            exceptions: define.int_counter(
                "modbus_gateway_observed_exceptions_total",
                "Listen-only lines: exception replies heard, by slave and exception code.",
                &["bus", "slave", "code"],
            ),
            timeouts: define.int_counter(
                "modbus_gateway_observed_timeouts_total",
                "Listen-only lines: requests heard that no reply answered within the slave's \
                 response_timeout (or before the master's next request).",
                slave,
            ),
            crc_errors: define.int_counter(
                "modbus_gateway_observed_crc_errors_total",
                "Listen-only lines: frames heard whose CRC (ASCII: LRC) failed.",
                &["bus"],
            ),
            discarded: define.int_counter(
                "modbus_gateway_observed_discarded_total",
                "Listen-only lines: what was heard and discarded, by reason (crc_error, broken: \
                 bytes that made no frame, unpaired: a good frame that answered no request).",
                &["bus", "reason"],
            ),
            response: define.histogram(
                "modbus_gateway_observed_response_seconds",
                "Listen-only lines: from the end of a request heard to the start of its reply.",
                slave,
            ),
            poll_interval: define.gauge(
                "modbus_gateway_observed_poll_interval_seconds",
                "Listen-only lines: the time between the other master's last two asks of the \
                 same read of this slave.",
                slave,
            ),
            last_reply: define.gauge(
                "modbus_gateway_observed_last_reply_timestamp_seconds",
                "Listen-only lines: when this slave's last reply was heard (Unix time).",
                slave,
            ),
        }
    }

    /// A listen line's series at zero from its start: the discarded reasons.
    pub(in crate::metrics) fn start(&self, bus: &str) {
        self.crc_errors.with_label_values(&[bus]);
        for reason in Discarded::ALL {
            self.discarded.with_label_values(&[bus, reason.label()]);
        }
    }

    /// Remove the gauges of `bus`'s `slaves`, gone; the counts of past traffic stay.
    pub(in crate::metrics) fn forget(&self, bus: &str, slaves: impl Iterator<Item = u8>) {
        for address in slaves {
            let labels = &[bus, decimal(address)];
            let _ = self.poll_interval.remove_label_values(labels);
            let _ = self.last_reply.remove_label_values(labels);
        }
    }
}

impl BusMetrics {
    /// `n` bytes heard on a listen line: received, and the line busy their time.
    pub(crate) fn observed_bytes(&self, n: usize) {
        let n = u64::try_from(n).unwrap_or(u64::MAX);
        self.received.inc_by(n);
        #[allow(clippy::cast_precision_loss)] // bytes in one read: far below 2^52
        self.busy.inc_by(n as f64 * self.char_time);
    }

    /// The other master asked `slave` for `function`; `interval` since it last asked the same.
    pub(crate) fn observed_request(&self, slave: u8, code: u8, interval: Option<Duration>) {
        let label = self.slave_label(slave);
        let observed = &self.observed;
        observed
            .requests
            .with_label_values(&[&self.name, label, function(code)])
            .inc();
        if let Some(interval) = interval.filter(|_| label != crate::metrics::labels::OTHER) {
            observed
                .poll_interval
                .with_label_values(&[&self.name, label])
                .set(interval.as_secs_f64());
        }
    }

    /// `slave` answered a `code` request, with `exception` if it was one, `response` after it.
    pub(crate) fn observed_reply(
        &self,
        slave: u8,
        code: u8,
        exception: Option<u8>,
        response: Duration,
    ) {
        self.slave(slave);
        let (name, label, observed) = (&*self.name, decimal(slave), &self.observed);
        let outcome = if exception.is_some() {
            "exception"
        } else {
            "ok"
        };
        observed
            .replies
            .with_label_values(&[name, label, function(code), outcome])
            .inc();
        if let Some(exception) = exception {
            observed
                .exceptions
                .with_label_values(&[name, label, hex(exception)])
                .inc();
        }
        observed
            .response
            .with_label_values(&[name, label])
            .observe(response.as_secs_f64());
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap_or_default();
        observed
            .last_reply
            .with_label_values(&[name, label])
            .set(now.as_secs_f64());
    }

    /// A request to `slave` heard and not answered.
    pub(crate) fn observed_timeout(&self, slave: u8) {
        let label = self.slave_label(slave);
        self.observed
            .timeouts
            .with_label_values(&[&self.name, label])
            .inc();
    }

    /// Something heard and discarded, for `reason`.
    pub(crate) fn observed_discarded(&self, reason: Discarded) {
        let observed = &self.observed;
        if reason == Discarded::CrcError {
            observed.crc_errors.with_label_values(&[&self.name]).inc();
        }
        observed
            .discarded
            .with_label_values(&[&self.name, reason.label()])
            .inc();
    }
}
