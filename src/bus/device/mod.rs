//! What a bus opens: its line's transport. A [`Device`] says what to open (a serial device in its
//! format with its driver settings, a peer on the network: a serial device server or a Modbus TCP
//! device, or the simulated line); opened, it is a [`Port`], which the line's master drives
//! through [`Transport`]. This file only dispatches: each transport lives in its own file
//! ([`serial`]: tokio-serial, RS-485 direction control, a USB adapter's latency timer; `net`: a
//! peer's socket, its link budget and, for `rfc2217://`, Telnet (`rfc2217`); [`tls`]: a `tls://`
//! device's client side; `sim`: the simulated line's glue). Which framing may run over which
//! transport is not decided here but in one table of the line's, [`Framing::runs_over`], which
//! [`Device::open_for`] consults. Knows nothing of queues, transactions or what the bytes mean.
//!
//! To add a transport: a variant in [`Device`] and in [`Port`] with its own file here (what it
//! opens, and the [`Transport`] of the opened thing), a [`TransportKind`] with its rows in the
//! framing table; the compiler then names every `match` below that needs an arm for it.

pub(crate) mod net;
mod rfc2217;
pub(crate) mod serial;
mod sim;
pub(crate) mod tls;

pub use serial::SerialDriver;
pub(crate) use tls::TlsDevice;

pub(crate) use serial::SerialFd;

use crate::config::{ServerAddr, ServerMode};
use crate::line::framing::TransportKind;
use crate::line::{Framing, SerialFormat, Transport};
use crate::sim::{SimLine, SimPort};
use std::io;
use std::time::Duration;
use tokio::time::Instant;

/// What a bus opens.
#[derive(Clone)]
pub enum Device {
    /// A serial device: its path, the line's format, and what its driver must do.
    Serial {
        path: String,
        format: SerialFormat,
        driver: SerialDriver,
    },
    /// A serial device server: its address, and the line's format (which `rfc2217://` sets on
    /// the far port at every connect).
    Server {
        addr: ServerAddr,
        format: SerialFormat,
        /// A `tls://` device's client side.
        tls: Option<TlsDevice>,
    },
    Sim(SimLine),
}

/// An opened [`Device`].
pub enum Port {
    Serial(SerialFd),
    Net(net::NetPort),
    /// Boxed: a TLS session is large, and one port per bus is made per connect.
    Tls(Box<net::NetPort<tokio_rustls::client::TlsStream<tokio::net::TcpStream>>>),
    Sim(SimPort),
}

impl Device {
    /// Whether `other` opens the same line the same way: the same serial device in the same
    /// format with the same RS-485 settings and latency timer, or the same simulated line.
    pub(crate) fn same_as(&self, other: &Device) -> bool {
        match (self, other) {
            (
                Device::Serial {
                    path,
                    format,
                    driver,
                },
                Device::Serial {
                    path: p,
                    format: f,
                    driver: d,
                },
            ) => path == p && format == f && driver.same_as(d),
            (
                Device::Server { addr, format, tls },
                Device::Server {
                    addr: a,
                    format: f,
                    tls: t,
                },
            ) => {
                let same_tls = match (tls, t) {
                    (Some(tls), Some(t)) => tls.same_as(t),
                    (None, None) => true,
                    _ => false,
                };
                addr == a && format == f && same_tls
            }
            (Device::Sim(line), Device::Sim(other)) => sim::same_as(line, other),
            // Two kinds of transport are never one line.
            _ => false,
        }
    }

    /// Which kind of transport this is, for the framing table.
    pub fn kind(&self) -> TransportKind {
        match self {
            Device::Serial { .. } => TransportKind::Serial,
            Device::Server { addr, .. } => match addr.mode {
                ServerMode::Raw => TransportKind::Tcp,
                ServerMode::Rfc2217 => TransportKind::Rfc2217,
                ServerMode::Tls => TransportKind::Tls,
            },
            Device::Sim(_) => TransportKind::Sim,
        }
    }

    /// Open the transport. Serial ports are opened exclusively, so two gateways cannot share
    /// one; a device that refuses the RS-485 mode asked for fails the open, naming the key. A
    /// device server is connected to (within [`net::CONNECT_TIMEOUT`]).
    pub async fn open(&self) -> io::Result<Port> {
        match self {
            Device::Serial {
                path,
                format,
                driver,
            } => serial::open(path, format, driver).map(Port::Serial),
            Device::Server { addr, format, tls } => net::open(addr, format, tls.as_ref()).await,
            Device::Sim(line) => sim::open(line),
        }
    }

    /// Open the transport for a line framed by `framing`: refused (`Unsupported`, which
    /// retrying does not cure) if the framing table does not let `framing` run over it.
    pub(crate) async fn open_for(&self, framing: Framing) -> io::Result<Port> {
        self.carries(framing)?;
        self.open().await
    }

    /// Open the transport of a listen-only line framed by `framing`, as [`Device::open_for`]
    /// does: the simulated line opens a listening port, which hears every frame on the wire
    /// (its other master's too) and refuses to send; every other device opens as for a master,
    /// and the bus never writes to it.
    pub(crate) async fn open_to_listen(&self, framing: Framing) -> io::Result<Port> {
        match self {
            Device::Sim(line) => {
                self.carries(framing)?;
                sim::open_listening(line)
            }
            Device::Serial { .. } | Device::Server { .. } => self.open_for(framing).await,
        }
    }

    /// Refused (`Unsupported`) unless the framing table lets `framing` run over this device.
    fn carries(&self, framing: Framing) -> io::Result<()> {
        let kind = self.kind();
        if framing.runs_over(kind) {
            return Ok(());
        }
        Err(io::Error::new(
            io::ErrorKind::Unsupported,
            format!(
                "framing = \"{}\" cannot run over {}",
                framing.name(),
                kind.name()
            ),
        ))
    }

    /// The path of a serial device.
    pub fn path(&self) -> Option<&str> {
        match self {
            Device::Serial { path, .. } => Some(path),
            Device::Server { .. } | Device::Sim(_) => None,
        }
    }

    /// What the bus asks of its serial driver; `None` on other lines.
    pub fn driver(&self) -> Option<&SerialDriver> {
        match self {
            Device::Serial { driver, .. } => Some(driver),
            Device::Server { .. } | Device::Sim(_) => None,
        }
    }
}

impl Port {
    /// A serial port (or pty) opened in non-blocking mode.
    pub fn serial(stream: mio_serial::SerialStream) -> io::Result<Port> {
        SerialFd::new(stream).map(Port::Serial)
    }

    /// A device server's connection: the peer's address, what the link adds to each frame's
    /// time now and the least round trip it is from. `None` on other lines.
    pub(crate) fn link(&self) -> Option<(&str, Duration, Option<Duration>)> {
        match self {
            Port::Net(port) => Some(port.link()),
            Port::Tls(port) => Some(port.link()),
            Port::Serial(_) | Port::Sim(_) => None,
        }
    }
}

/// A transport as the bus task reports it: with the link it crosses, if any. The port of every
/// line; the serving loops are generic over it so that tests can run them on in-memory links.
pub(crate) trait Linked: Transport {
    /// As [`Port::link`].
    fn link(&self) -> Option<(&str, Duration, Option<Duration>)>;
}

impl Linked for Port {
    fn link(&self) -> Option<(&str, Duration, Option<Duration>)> {
        Port::link(self)
    }
}

impl<S: net::Link> Linked for net::NetPort<S> {
    fn link(&self) -> Option<(&str, Duration, Option<Duration>)> {
        Some(net::NetPort::link(self))
    }
}

impl Transport for Port {
    async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        match self {
            Port::Serial(port) => port.send(frame).await,
            Port::Net(port) => port.send(frame).await,
            Port::Tls(port) => port.send(frame).await,
            Port::Sim(port) => port.send(frame).await,
        }
    }

    fn end_of_transmission(&self, returned: Instant, frame_time: Duration) -> Instant {
        match self {
            Port::Serial(port) => port.end_of_transmission(returned, frame_time),
            Port::Net(port) => port.end_of_transmission(returned, frame_time),
            Port::Tls(port) => port.end_of_transmission(returned, frame_time),
            Port::Sim(port) => port.end_of_transmission(returned, frame_time),
        }
    }

    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        match self {
            Port::Serial(port) => port.recv(buf).await,
            Port::Net(port) => port.recv(buf).await,
            Port::Tls(port) => port.recv(buf).await,
            Port::Sim(port) => port.recv(buf).await,
        }
    }

    fn clear_input(&mut self, stale: &mut Vec<u8>) -> io::Result<()> {
        match self {
            Port::Serial(port) => port.clear_input(stale),
            Port::Net(port) => port.clear_input(stale),
            Port::Tls(port) => port.clear_input(stale),
            Port::Sim(port) => port.clear_input(stale),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::{LineTiming, Parity};

    fn sim() -> Device {
        let format = SerialFormat {
            baud: 19_200,
            data_bits: 8,
            parity: Parity::Even,
            stop_bits: 1,
        };
        Device::Sim(SimLine::new(LineTiming::new(&format)))
    }

    #[tokio::test]
    async fn the_simulated_line_opens_for_every_framing_the_table_lets_run_over_it() {
        let device = sim();
        for framing in [Framing::Rtu, Framing::Ascii] {
            assert_eq!(
                framing.runs_over(device.kind()),
                device.open_for(framing).await.is_ok()
            );
        }
    }

    /// `/dev/ttyS1` at 19200 8E1 with `driver`.
    pub(super) fn ttys1(driver: SerialDriver) -> Device {
        Device::Serial {
            path: "/dev/ttyS1".into(),
            format: SerialFormat {
                baud: 19_200,
                data_bits: 8,
                parity: Parity::Even,
                stop_bits: 1,
            },
            driver,
        }
    }

    #[tokio::test]
    async fn the_simulated_line_opens_to_listen_as_a_port_that_refuses_to_send() {
        let Device::Sim(line) = sim() else {
            unreachable!("sim() is the simulated line")
        };
        let device = Device::Sim(line.clone());
        let mut port = device.open_to_listen(Framing::Rtu).await.unwrap();
        assert!(port
            .send(&[0x01, 0x03, 0x00, 0x00, 0x00, 0x01])
            .await
            .is_err());
        assert_eq!(line.stats().listener_frames, 1);
        assert_eq!(line.stats().master_frames, 0);
        assert!(device.open_to_listen(Framing::Tcp).await.is_err());
    }

    #[test]
    fn a_serial_device_and_the_simulated_line_are_never_the_same_line() {
        let serial = ttys1(SerialDriver::default());
        let line = sim();
        assert!(line.same_as(&line.clone()));
        assert!(!line.same_as(&sim()));
        assert!(!serial.same_as(&line));
        assert!(!line.same_as(&serial));
    }
}
