//! A bus's port events, each logged and counted here: opened (or connected), lost, failing to
//! open, and the end of an outage. Which of them begins or ends an outage the bus decides
//! (`bus::outage`); here each becomes one log line at the level that says so, so that an outage
//! is one warn line when it begins and one info line when it ends, whatever happens in between.

use super::{BusMetrics, LinkDrop, BUS_EVENTS};
use std::fmt::Display;
use std::io;
use std::time::Duration;
use tracing::{debug, error, info, warn};

/// What the loss of a bus's port is to its outages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum PortLoss {
    /// The port had served: an outage begins.
    Served,
    /// The first port of the bus, lost before it served: an outage begins with it.
    Unserved,
    /// Lost before it served, in an outage under way: `unserved` such ports in it so far.
    AgainUnserved { unserved: u32 },
}

impl BusMetrics {
    /// The port is open: the bus's first (`again` false), or one opened in an outage, which is
    /// logged at debug: the outage ends once the port has served ([`BusMetrics::port_back`]).
    pub(crate) fn port_opened(&self, device: &str, again: bool) {
        let bus = &*self.name;
        let network = self.is_network();
        match (again, network) {
            (false, true) => info!(target: BUS_EVENTS, bus, device, "device server connected"),
            (false, false) => info!(target: BUS_EVENTS, bus, device, "serial port open"),
            (true, true) => {
                debug!(target: BUS_EVENTS, bus, device, "device server connected again; the outage ends once it serves");
            }
            (true, false) => {
                debug!(target: BUS_EVENTS, bus, device, "serial port open again; the outage ends once it serves");
            }
        }
        if again {
            self.port_reopens.inc();
        }
        self.port_up.set(1);
    }

    /// An outage is over: a port opened in it has served. It lasted `down_for` (until that port
    /// opened), `failed_opens` opens failed in it and `unserved` ports were lost before serving.
    pub(crate) fn port_back(
        &self,
        device: &str,
        down_for: Duration,
        failed_opens: u32,
        unserved: u32,
    ) {
        let bus = &*self.name;
        let down_s = down_for.as_secs_f64();
        if self.is_network() {
            info!(target: BUS_EVENTS, bus, device, failed_opens, lost_before_serving = unserved, down_s, "device server reconnected");
        } else {
            info!(target: BUS_EVENTS, bus, device, failed_opens, lost_before_serving = unserved, down_s, "serial port reopened");
        }
    }

    /// The port is lost with `error`, as `loss` is to its outages; `dropped` if the gateway
    /// closed the connection itself, and why.
    pub(crate) fn port_lost(
        &self,
        device: &str,
        error: &dyn Display,
        loss: PortLoss,
        dropped: Option<LinkDrop>,
    ) {
        self.port_up.set(0);
        self.link(None);
        let bus = &*self.name;
        if let Some(reason) = dropped {
            self.link_dropped
                .with_label_values(&[bus, reason.label()])
                .inc();
        }
        match (loss, self.is_network()) {
            (PortLoss::Served, true) => {
                warn!(target: BUS_EVENTS, bus, device, %error, "device server connection lost; answering 0x0A and reconnecting");
            }
            (PortLoss::Served, false) => {
                warn!(target: BUS_EVENTS, bus, device, %error, "serial port lost; answering 0x0A and reopening");
            }
            (PortLoss::Unserved, true) => {
                warn!(target: BUS_EVENTS, bus, device, %error, "device server connection lost before it served a request; answering 0x0A and reconnecting with back-off");
            }
            (PortLoss::Unserved, false) => {
                warn!(target: BUS_EVENTS, bus, device, %error, "serial port lost before it served a request; answering 0x0A and reopening with back-off");
            }
            (PortLoss::AgainUnserved { unserved }, true) => {
                debug!(target: BUS_EVENTS, bus, device, %error, lost_before_serving = unserved, "device server connection lost again before it served a request");
            }
            (PortLoss::AgainUnserved { unserved }, false) => {
                debug!(target: BUS_EVENTS, bus, device, %error, lost_before_serving = unserved, "serial port lost again before it served a request");
            }
        }
    }

    /// An open failed; only the first failure of an outage is logged above debug level, at
    /// error if the device refuses what the configuration asks of it (retrying will not cure
    /// that), else at warn.
    pub(crate) fn open_failed(&self, device: &str, error: &io::Error, first: bool) {
        self.port_open_errors.inc();
        let bus = &*self.name;
        let network = self.is_network();
        let refused = error.kind() == io::ErrorKind::Unsupported;
        if first && refused && network {
            error!(target: BUS_EVENTS, bus, device, %error, "the device server refuses the line's settings; answering 0x0A and retrying");
        } else if first && refused {
            error!(target: BUS_EVENTS, bus, device, %error, "cannot open serial port; answering 0x0A and retrying");
        } else if first && network {
            warn!(target: BUS_EVENTS, bus, device, %error, "cannot connect to the device server; answering 0x0A and retrying");
        } else if first {
            warn!(target: BUS_EVENTS, bus, device, %error, "cannot open serial port; answering 0x0A and retrying");
        } else if network {
            debug!(target: BUS_EVENTS, bus, device, %error, "device server still cannot be reached");
        } else {
            debug!(target: BUS_EVENTS, bus, device, %error, "serial port still cannot be opened");
        }
    }
}
