//! Serial master ports (`[[server.serial]]`): a master on a serial line talks to the gateway as
//! its slave. One task per port opens its device (a UART with its transceiver as `[bus.rs485]`
//! drives one, a pty the gateway makes and links for local software, or a serial device
//! server's port), serves its master ([`serve`]) and opens it again when it is lost or missing,
//! as a bus does. The master enters through the dispatcher like every other (routes, rules,
//! journal, queue), as protocol `serial`, master `serial:NAME`. Knows nothing of how a bus serves
//! it.

mod serve;

use crate::bus::device::{Device, Port, SerialDriver};
use crate::config::{PortDevice, ServerSerial};
use crate::dispatch::Client;
use crate::line::{LineTiming, SerialFormat};
use crate::master::{MasterId, Peer, Protocol, Rights};
use crate::metrics::{Metrics, PortMetrics};
use crate::net::server::{Connected, Shared};
use crate::trace::BusTap;
use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime};
use tracing::warn;

pub(crate) use serve::Settings;

/// A port as the status page sees it.
pub(crate) struct PortView {
    pub(crate) name: Arc<str>,
    pub(crate) device: String,
    pub(crate) format: String,
    pub(crate) framing: &'static str,
    pub(crate) metrics: PortMetrics,
    rights: Rights,
    priority: bool,
    since: SystemTime,
    requests: AtomicU64,
}

impl PortView {
    /// Its master, as the status page lists masters: there while the device is open.
    pub(crate) fn master(&self) -> Option<Connected> {
        self.metrics.is_up().then(|| Connected {
            peer: Peer::Port(self.name.clone()),
            protocol: Protocol::Serial,
            rights: self.rights,
            role: None,
            priority: self.priority,
            since: self.since,
            requests: self.requests.load(Ordering::Relaxed),
        })
    }

    pub(crate) fn requested(&self) {
        self.requests.fetch_add(1, Ordering::Relaxed);
    }
}

/// `[[server.serial]]` at `index`, ready to run: what to open and how to serve.
struct Planned {
    settings: Settings,
    device: PortDevice,
    /// `server.serial[i]`, for the keys errors name.
    key: String,
    reopen_delay: Duration,
    view: Arc<PortView>,
}

fn plan(index: usize, port: &ServerSerial, master: MasterId, metrics: &Metrics) -> Planned {
    let format = port.format();
    let format_label = format!("{} {}", format.baud, format_name(&format));
    let framing = port.framing;
    let name: Arc<str> = Arc::from(port.name.as_str());
    let key = format!("server.serial[{index}]");
    let device = PortDevice::parse(&port.device).unwrap_or(PortDevice::Uart(port.device.clone()));
    let timing = LineTiming::new(&format);
    let rights = if port.read_only {
        Rights::ReadOnly
    } else {
        Rights::ReadWrite
    };
    let mut client = Client::at(master, Peer::Port(name.clone()), rights)
        .speaking(Protocol::Serial)
        .prioritised(port.priority);
    client.limited_by = port
        .read_only
        .then(|| Arc::from(format!("{key}.read_only").as_str()));
    let silence = port.silence(matches!(device, PortDevice::Server(_)));
    let view = Arc::new(PortView {
        name,
        device: port.device.clone(),
        format: format_label.clone(),
        framing: framing.name(),
        metrics: metrics
            .serial
            .port(&port.name, &port.device, &format_label, framing.name()),
        rights,
        priority: port.priority,
        since: SystemTime::now(),
        requests: AtomicU64::new(0),
    });
    Planned {
        settings: Settings {
            framing,
            timing,
            silence,
            units: port.units,
            answer_within: port.answer_within,
            echo: port.rs485.echo,
            client,
        },
        device,
        key,
        reopen_delay: port.reopen_delay,
        view,
    }
}

/// `8E1`.
fn format_name(format: &SerialFormat) -> String {
    format!(
        "{}{}{}",
        format.data_bits,
        format.parity.letter(),
        format.stop_bits
    )
}

/// The ports of `ports`, each on its own task in `tasks`, serving through `dispatcher`; what
/// the status page reads of them.
pub(crate) fn start(
    ports: &[ServerSerial],
    shared: &Arc<Shared>,
    tasks: &mut tokio::task::JoinSet<()>,
) -> Vec<Arc<PortView>> {
    let metrics = &shared.metrics;
    let mut views = Vec::new();
    for (index, port) in ports.iter().enumerate() {
        let planned = plan(index, port, shared.new_master(), metrics);
        views.push(planned.view.clone());
        let trace = metrics
            .trace
            .register(Arc::from(Peer::Port(planned.view.name.clone()).to_string()));
        let format = port.format();
        let driver = SerialDriver {
            rs485: port.rs485.clone(),
            latency_timer: port.latency_timer,
            key: planned.key.clone(),
        };
        tasks.spawn(run(planned, format, driver, shared.clone(), trace));
    }
    views
}

/// Serve the port forever: open, serve until the device is lost, wait, open again.
async fn run(
    mut planned: Planned,
    format: SerialFormat,
    driver: SerialDriver,
    shared: Arc<Shared>,
    trace: BusTap,
) {
    let dispatcher = &shared.dispatcher;
    let view = planned.view.clone();
    let text = view.device.clone();
    let mut pty: Option<pty::Pty> = None;
    loop {
        let opened = match &planned.device {
            PortDevice::Uart(path) => {
                Device::Serial {
                    path: path.clone(),
                    format,
                    driver: driver.clone(),
                }
                .open()
                .await
            }
            PortDevice::Server(addr) => {
                Device::Server {
                    addr: addr.clone(),
                    format,
                    tls: None,
                }
                .open()
                .await
            }
            PortDevice::Pty(link) => pty::open(link, &mut pty),
        };
        let error = match opened {
            Ok(mut port) => {
                view.metrics.opened(&text);
                serve::serve(&mut port, &mut planned.settings, dispatcher, &view, &trace).await
            }
            Err(error) => error,
        };
        view.metrics.lost(&text, &error, planned.reopen_delay);
        dispatcher.forget(planned.settings.client.master);
        if error.kind() == io::ErrorKind::Unsupported {
            warn!(port = %view.name, %error, "serial master port cannot be served");
        }
        tokio::time::sleep(planned.reopen_delay).await;
    }
}

mod pty {
    //! `pty:PATH`: a pty the gateway makes, its far end linked at `PATH` for local software to
    //! open. The gateway keeps the far end open too, so the pty lives while the software comes
    //! and goes; the link is replaced at start and removed when the port's task ends.

    use super::Port;
    use mio_serial::SerialPort as _;
    use std::io;
    use std::path::{Path, PathBuf};

    pub(super) struct Pty {
        link: PathBuf,
        /// The far end, kept open.
        _tty: mio_serial::SerialStream,
    }

    impl Drop for Pty {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.link);
        }
    }

    /// A new pty with `link` to its far end (a pty lost is made again), and its near end as
    /// the port.
    pub(super) fn open(link: &str, held: &mut Option<Pty>) -> io::Result<Port> {
        *held = None;
        let (near, tty) = mio_serial::SerialStream::pair()?;
        let far = tty
            .name()
            .ok_or_else(|| io::Error::other("the new pty has no path"))?;
        let link = Path::new(link);
        if let Some(dir) = link.parent() {
            std::fs::create_dir_all(dir)?;
        }
        match std::fs::remove_file(link) {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(e),
        }
        std::os::unix::fs::symlink(&far, link).map_err(|e| {
            io::Error::new(
                e.kind(),
                format!("cannot link {} to {far}: {e}", link.display()),
            )
        })?;
        *held = Some(Pty {
            link: link.to_path_buf(),
            _tty: tty,
        });
        Port::serial(near)
    }
}

#[cfg(test)]
mod tests;
