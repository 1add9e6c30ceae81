//! What a bus reports of the link behind its line: whether it is a device server's connection,
//! that connection's round trip and budget, and a USB serial adapter's latency timer. The port's
//! own events (opened, lost, failing to open) are `metrics::port`'s.

use super::BusMetrics;
use crate::metrics::BUS_EVENTS;
use std::io;
use std::sync::atomic::Ordering;
use std::sync::PoisonError;
use std::time::Duration;
use tracing::{info, warn};

/// A device server's connection, as the status page shows it.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkSnapshot {
    /// The address connected to.
    pub peer: String,
    /// What the gateway adds to each frame's time for the link.
    pub budget: Duration,
    /// The least round trip the kernel has measured, if it did.
    pub round_trip: Option<Duration>,
}

impl BusMetrics {
    pub(in crate::metrics) fn is_network(&self) -> bool {
        self.network.load(Ordering::Relaxed)
    }

    /// The device server's connection now (`None`: not connected): its series and the status
    /// page's figures. Cheap when nothing changed, as after most transactions.
    pub(crate) fn link(&self, now: Option<(&str, Duration, Option<Duration>)>) {
        let mut link = self.link.lock().unwrap_or_else(PoisonError::into_inner);
        let was = link
            .as_ref()
            .map(|l| (l.peer.as_str(), l.budget, l.round_trip));
        if was == now {
            return;
        }
        let now = now.map(|(peer, budget, round_trip)| LinkSnapshot {
            peer: peer.to_owned(),
            budget,
            round_trip,
        });
        let labels = &[&*self.name];
        match &now {
            Some(snapshot) => {
                self.link_budget
                    .with_label_values(labels)
                    .set(snapshot.budget.as_secs_f64());
                match snapshot.round_trip {
                    Some(rtt) => self
                        .link_round_trip
                        .with_label_values(labels)
                        .set(rtt.as_secs_f64()),
                    None => {
                        let _ = self.link_round_trip.remove_label_values(labels);
                    }
                }
            }
            None => {
                let _ = self.link_budget.remove_label_values(labels);
                let _ = self.link_round_trip.remove_label_values(labels);
            }
        }
        *link = now;
    }

    /// The device server's connection as last reported, if connected.
    pub fn link_snapshot(&self) -> Option<LinkSnapshot> {
        self.link
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// The USB adapter's latency timer as the port's open found (and maybe set) it, with the
    /// sysfs file it is read from, or `None` if the device has none; `refused` is why setting
    /// the configured value failed. `key` is the bus's (`bus[0]`).
    pub fn latency_timer(
        &self,
        device: &str,
        key: &str,
        timer: Option<(Duration, &std::path::Path)>,
        refused: Option<&io::Error>,
    ) {
        let bus = &*self.name;
        let Some((value, file)) = timer else {
            let _ = self.latency_timer.remove_label_values(&[bus]);
            return;
        };
        let latency_timer_ms = value.as_millis();
        let file = file.display().to_string();
        match refused {
            None => {
                info!(target: BUS_EVENTS, bus, device, latency_timer_ms, file, "USB adapter latency timer");
            }
            Some(error) => {
                warn!(target: BUS_EVENTS, bus, device, latency_timer_ms, file, %error, "cannot set {key}.latency_timer; the adapter keeps its timer (see docs/rs485.md for a udev rule)");
            }
        }
        self.latency_timer
            .with_label_values(&[bus])
            .set(value.as_secs_f64());
    }
}

#[cfg(test)]
mod latency_tests {
    use crate::metrics::Metrics;
    use std::path::Path;
    use std::time::Duration;

    const SERIES: &str = "modbus_gateway_serial_latency_timer_seconds{bus=\"line1\"}";

    fn sample(metrics: &Metrics) -> Option<f64> {
        crate::metrics::sample(&metrics.render().unwrap(), SERIES)
    }

    #[test]
    fn the_latency_timer_found_at_open_is_exported_in_seconds_and_dropped_when_there_is_none() {
        let metrics = Metrics::new();
        let settings =
            crate::Config::from_toml_str("[[bus]]\nname = \"line1\"\ndevice = \"/dev/ttyUSB0\"\n")
                .unwrap()
                .bus
                .remove(0);
        let bus = metrics.bus(&settings);
        assert_eq!(sample(&metrics), None, "unknown until the port opens");
        let file = Path::new("/sys/bus/usb-serial/devices/ttyUSB0/latency_timer");
        let timer = (Duration::from_millis(16), file);
        bus.latency_timer("/dev/ttyUSB0", "bus[0]", Some(timer), None);
        assert_eq!(sample(&metrics), Some(0.016));
        bus.latency_timer("/dev/ttyUSB0", "bus[0]", None, None);
        assert_eq!(sample(&metrics), None);
    }
}
