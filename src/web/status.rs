//! What the status page shows, as data: the buses, their slaves, the masters connected now and
//! the last writes, served as JSON at `/status` and rendered by the page at `/` (`status.html`,
//! `status.css` and `status.js`, compiled in). The values are read from where they are kept
//! (the bus's metrics and handle, the listener's sessions, the writes' record); this module only
//! holds their shape and the line's recent utilisation, which needs the busy time of a moment
//! ago.

use serde::Serialize;
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, SystemTime};
use tokio::time::Instant;

/// The page itself: one self-contained HTML file, its style and script inline, put together when
/// compiled from `status.css`, `status.html` (the body's markup) and `status.js`.
pub(crate) const PAGE: &str = concat!(
    "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n",
    "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n",
    "<title>modbus-gateway status</title>\n<style>\n",
    include_str!("status.css"),
    "</style>\n</head>\n<body>\n",
    include_str!("status.html"),
    "<script>\n",
    include_str!("status.js"),
    "</script>\n</body>\n</html>\n",
);

/// The utilisation shown is the line's busy time over about this much of the recent past.
const UTILISATION_WINDOW: Duration = Duration::from_secs(60);
/// Samples of a line's busy time closer together than this are not kept.
const SAMPLE_SPACING: Duration = Duration::from_secs(1);

/// The whole page's data; its default, a gateway with nothing to show.
#[derive(Clone, Debug, Default, Serialize)]
pub(crate) struct Status {
    pub(crate) version: &'static str,
    /// When the answer was made (RFC 3339, UTC).
    pub(crate) time: String,
    pub(crate) uptime_seconds: f64,
    pub(crate) buses: Vec<BusStatus>,
    /// The masters connected now over TCP (Modbus TCP, RTU over TCP, TLS), and those of the
    /// serial master ports whose device is open (`serial:NAME`); UDP masters have no connection
    /// and are not listed.
    pub(crate) masters: Vec<MasterStatus>,
    /// The serial master ports (`[[server.serial]]`) and their masters' traffic.
    pub(crate) serial_ports: Vec<SerialPortStatus>,
    /// The virtual units (`[[virtual]]`): each register's source, value and age.
    pub(crate) virtual_units: Vec<crate::virtuals::ShownUnit>,
    /// The last writes (every function that may change a slave), newest last, each with its
    /// outcome once it has one: the journal's lines (docs/writes.md).
    pub(crate) writes: Vec<crate::audit::Recent>,
}

#[derive(Clone, Debug, Serialize)]
pub(crate) struct BusStatus {
    pub(crate) name: String,
    /// The serial device's path, or `"simulated"`.
    pub(crate) device: String,
    /// `rtu` or `ascii`.
    pub(crate) framing: &'static str,
    /// The serial format, e.g. `9600 8E1`.
    pub(crate) format: String,
    /// What carries the line: `serial`, `sim`, `tcp` or `rfc2217`.
    pub(crate) transport: &'static str,
    /// `master`, or `listen`: another master drives the line, and its transactions are the
    /// ones heard.
    pub(crate) mode: &'static str,
    /// The serial port is open, or the device server connected.
    pub(crate) port_up: bool,
    /// A line behind a device server, while connected: its link.
    pub(crate) link: Option<LinkStatus>,
    /// Share of the recent past (about a minute) the line carried characters, 0 to 1.
    pub(crate) utilisation: f64,
    pub(crate) queue_depth: usize,
    pub(crate) queue_capacity: usize,
    /// Transactions on the line since the bus started, retries included in each.
    pub(crate) transactions: u64,
    pub(crate) slaves: Vec<SlaveStatus>,
}

/// A device server's connection (docs/device-servers.md).
#[derive(Clone, Debug, Serialize)]
pub(crate) struct LinkStatus {
    /// The address connected to.
    pub(crate) peer: String,
    /// The least round trip the kernel has measured, if it did.
    pub(crate) round_trip_seconds: Option<f64>,
    /// What the gateway adds to each frame's time for the link.
    pub(crate) budget_seconds: f64,
}

#[derive(Clone, Debug, Serialize)]
pub(crate) struct SlaveStatus {
    pub(crate) address: u8,
    /// The simulated drive's model, for a slave of a simulated line.
    pub(crate) model: Option<&'static str>,
    /// Whether its last transaction that tells got a valid answer (`modbus_gateway_slave_up`).
    pub(crate) up: bool,
    /// Its last answer, normal or exception (RFC 3339, UTC), or `null` if none yet.
    pub(crate) last_answer: Option<String>,
    pub(crate) last_answer_seconds_ago: Option<f64>,
    /// The median of its recent round trips (the last 32 transactions), or `null` if none.
    pub(crate) round_trip_p50_seconds: Option<f64>,
    /// Its requests by outcome (the `outcome` label of `modbus_gateway_requests_total`).
    pub(crate) requests: BTreeMap<String, u64>,
    /// Its requests that did not end `ok`.
    pub(crate) errors: u64,
    /// The gateway's own polls of its plant values (`modbus_gateway_polls_total`).
    pub(crate) polls: u64,
}

/// A serial master port.
#[derive(Clone, Debug, Serialize)]
pub(crate) struct SerialPortStatus {
    pub(crate) name: String,
    pub(crate) device: String,
    /// `19200 8E1`.
    pub(crate) format: String,
    /// `rtu` or `ascii`.
    pub(crate) framing: &'static str,
    /// Whether its device is open.
    pub(crate) up: bool,
    /// Its master's frames by how they ended, as `modbus_gateway_serial_requests_total`'s
    /// `outcome` label says.
    pub(crate) requests: BTreeMap<&'static str, u64>,
}

#[derive(Clone, Debug, Serialize)]
pub(crate) struct MasterStatus {
    /// The peer's `ip:port`, or `serial:NAME` for a serial master port's master.
    pub(crate) address: String,
    /// `tcp`, `rtu_over_tcp`, `tls` or `serial`.
    pub(crate) protocol: &'static str,
    /// `read_write`, `read_only` or `none`.
    pub(crate) rights: &'static str,
    /// The role of its certificate, on a TLS connection that has one.
    pub(crate) role: Option<String>,
    pub(crate) priority: bool,
    /// RFC 3339, UTC.
    pub(crate) connected_since: String,
    pub(crate) connected_seconds: f64,
    /// Requests it has sent on this connection.
    pub(crate) requests: u64,
}

/// `time` as RFC 3339 in UTC, to the millisecond.
pub(crate) fn rfc3339(time: SystemTime) -> String {
    humantime::format_rfc3339_millis(time).to_string()
}

/// Seconds from `then` to `now`, 0 if `then` is later.
pub(crate) fn seconds_between(then: SystemTime, now: SystemTime) -> f64 {
    now.duration_since(then).unwrap_or_default().as_secs_f64()
}

/// The recent utilisation of each line, from samples of its busy time taken as the status is
/// asked for: busy seconds over the elapsed time since the oldest sample of the window, or since
/// the line's first sample if the window holds nothing older than a second yet.
#[derive(Default)]
pub(crate) struct Utilisation {
    samples: Mutex<HashMap<String, VecDeque<(Instant, f64)>>>,
}

impl Utilisation {
    /// The utilisation of bus `name`, whose busy time is `busy` seconds at `now`; `since` is when
    /// it started counting (for an answer before any earlier sample).
    pub(crate) fn of(&self, name: &str, busy: f64, now: Instant, since: Instant) -> f64 {
        let mut all = self.samples.lock().unwrap_or_else(PoisonError::into_inner);
        let samples = all.entry(name.to_owned()).or_default();
        while samples.len() > 1 && samples[1].0 + UTILISATION_WINDOW <= now {
            samples.pop_front();
        }
        let (base_at, base_busy) = samples
            .front()
            .copied()
            .filter(|(at, _)| *at + SAMPLE_SPACING <= now)
            .unwrap_or((since, 0.0));
        if samples
            .back()
            .is_none_or(|(at, _)| *at + SAMPLE_SPACING <= now)
        {
            samples.push_back((now, busy));
        }
        let elapsed = now.saturating_duration_since(base_at).as_secs_f64();
        if elapsed <= 0.0 {
            return 0.0;
        }
        ((busy - base_busy) / elapsed).clamp(0.0, 1.0)
    }

    /// Forget the buses not in `names` (removed by a reload).
    pub(crate) fn keep_only(&self, names: &[&str]) {
        self.samples
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .retain(|name, _| names.contains(&name.as_str()));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utilisation_is_the_busy_share_of_the_recent_window_not_of_all_time() {
        let utilisation = Utilisation::default();
        let start = Instant::now();
        let at = |s: u64| start + Duration::from_secs(s);
        // Before any sample: since the start.
        assert!((utilisation.of("line1", 5.0, at(10), start) - 0.5).abs() < 1e-9);
        // Busy all of the next 10 s.
        assert!((utilisation.of("line1", 15.0, at(20), start) - 1.0).abs() < 1e-9);
        // Then idle for two minutes: the busy past has left the window.
        utilisation.of("line1", 15.0, at(100), start);
        let idle = utilisation.of("line1", 15.0, at(140), start);
        assert!(idle.abs() < 1e-9, "{idle}");
        // Another line has its own samples.
        assert!((utilisation.of("line2", 1.0, at(140), at(130)) - 0.1).abs() < 1e-9);
    }
}
