//! The `simulate` subcommand: the simulated slaves of one bus, served as RTU (or ASCII) slaves on
//! a real serial device or on a fresh pty, at the bus's baud and format, until stopped. Picks the
//! bus, powers the slaves on and reopens a lost device; the serving itself is
//! [`crate::sim::responder`].
//! With `--listen`, the simulated line on a TCP socket instead ([`listen`]).

mod listen;

use super::{start_runtime, stop_signal, EXIT_CONFIG};
use crate::bus::{Device, Port, SerialDriver};
use crate::config::{Bus, Config};
use crate::line::{Framing, Parity};
use crate::sim::{self, responder::Responder};
use std::io;
use std::process::ExitCode;
use tokio::time::sleep;
use tokio_serial::SerialPort;
use tracing::{error, info, warn};

/// Where `simulate` serves the slaves.
pub enum Serve {
    /// As RTU (or ASCII) slaves on a serial device, or on a new pty ([`PTY`]).
    Device(String),
    /// The simulated line on a TCP socket at this `HOST:PORT`, as a serial device server in
    /// transparent mode.
    Listen(String),
}

/// Serve the slaves of `bus` (or the only bus with any) on `on` until stopped.
pub fn simulate(config: Config, bus: Option<&str>, on: &Serve) -> ExitCode {
    let bus = match choose_bus(&config, bus) {
        Ok(bus) => bus,
        Err(e) => {
            eprintln!("modbus-gateway: simulate: {e}");
            return ExitCode::from(EXIT_CONFIG);
        }
    };
    let (runtime, _level) = match start_runtime(&config.log) {
        Ok(started) => started,
        Err(code) => return code,
    };
    runtime.block_on(async {
        let announce = |path: &str| {
            let framing = match bus.framing {
                Framing::Rtu => "",
                Framing::Ascii => " (Modbus ASCII)",
                Framing::Tcp => " (Modbus TCP)",
            };
            super::print_out(&format!(
                "serving bus {} on {path} at {}{framing}\n",
                bus.name,
                bus.format()
            ))
        };
        let error = tokio::select! {
            error = serve(bus, on, announce) => error,
            () = stop_signal() => return ExitCode::SUCCESS,
        };
        if super::reader_gone(&error) {
            return ExitCode::SUCCESS;
        }
        match on {
            Serve::Device(device) => error!(device, %error, "cannot serve the simulated slaves"),
            Serve::Listen(listen) => error!(listen, %error, "cannot serve the simulated line"),
        }
        ExitCode::FAILURE
    })
}

/// Serve on the device or the socket `on` says; returns why it stopped.
async fn serve(bus: &Bus, on: &Serve, ready: impl FnOnce(&str) -> io::Result<()>) -> io::Error {
    match on {
        Serve::Device(device) => serve_device(bus, device, ready).await,
        Serve::Listen(listen) => listen::serve(bus, listen, ready).await,
    }
}

/// `--device pty`: open a new pty pair and serve on it.
pub(crate) const PTY: &str = "pty";

/// The bus whose `[[bus.sim_slave]]` entries to serve: the one named, or the only one with any.
pub(crate) fn choose_bus<'a>(config: &'a Config, name: Option<&str>) -> Result<&'a Bus, String> {
    if let Some(name) = name {
        let bus = config
            .bus
            .iter()
            .find(|b| b.name == name)
            .ok_or_else(|| format!("there is no bus named `{name}`"))?;
        if bus.sim_slave.is_empty() {
            return Err(format!("bus `{name}` has no [[bus.sim_slave]] to serve"));
        }
        return Ok(bus);
    }
    let mut simulated = config.bus.iter().filter(|b| !b.sim_slave.is_empty());
    match (simulated.next(), simulated.next()) {
        (Some(bus), None) => Ok(bus),
        (None, _) => Err("no bus has [[bus.sim_slave]] entries to serve".into()),
        (Some(_), Some(_)) => {
            Err("several buses have simulated slaves: choose one with --bus".into())
        }
    }
}

/// The bus's slaves, powered on, behind one responder.
pub fn responder(bus: &Bus) -> Result<Responder, String> {
    let mut responder =
        Responder::framed(bus.line_timing(), bus.framing, bus.master_timing().silence);
    for slaves in &bus.sim_slave {
        for address in slaves.address.iter() {
            let slave = sim::build(slaves, address, bus.format(), bus.framing)
                .map_err(|e| format!("simulated slave {address}: {e}"))?;
            responder.add_slave(address, slave);
        }
    }
    Ok(responder)
}

/// Open `path` at the bus's format. A pty refuses even parity and drops odd, so if the format is
/// refused with parity, the device is opened without it (and the user told).
async fn open(bus: &Bus, path: &str) -> io::Result<Port> {
    let format = bus.format();
    let device = |format| Device::Serial {
        path: path.to_owned(),
        format,
        driver: SerialDriver::default(),
    };
    match device(format).open().await {
        Err(e) if format.parity != Parity::None && e.kind() == io::ErrorKind::InvalidInput => {
            let port = device(crate::line::SerialFormat {
                parity: Parity::None,
                ..format
            })
            .open()
            .await?;
            warn!(device = path, error = %e, "the device refuses parity (a pty?); serving without it");
            Ok(port)
        }
        result => result,
    }
}

/// Serve `bus`'s slaves on `device` (a path, or `PTY`) forever, reopening a lost device.
/// `ready` gets the path masters should open, once the device is open. Returns only on an error
/// that reopening cannot cure.
pub async fn serve_device(
    bus: &Bus,
    device: &str,
    ready: impl FnOnce(&str) -> io::Result<()>,
) -> io::Error {
    let mut responder = match responder(bus) {
        Ok(responder) => responder,
        Err(e) => return io::Error::new(io::ErrorKind::InvalidInput, e),
    };
    let slaves = bus
        .sim_slave
        .iter()
        .map(|s| s.address.iter().count())
        .sum::<usize>();
    if device == PTY {
        let (master, tty) = match mio_serial::SerialStream::pair() {
            Ok(pair) => pair,
            Err(e) => return e.into(),
        };
        let path = tty.name().unwrap_or_default();
        info!(
            device = path,
            slaves,
            bus = bus.name,
            "serving simulated slaves on a new pty"
        );
        if let Err(e) = ready(&path) {
            return e;
        }
        // The far end stays open here too, so the pty lives while masters come and go.
        let mut port = match Port::serial(master) {
            Ok(port) => port,
            Err(e) => return e,
        };
        let error = responder.serve(&mut port).await;
        drop(tty);
        return error;
    }
    let mut ready = Some(ready);
    loop {
        match open(bus, device).await {
            Ok(mut port) => {
                info!(device, slaves, bus = bus.name, "serving simulated slaves");
                if let Some(Err(e)) = ready.take().map(|ready| ready(device)) {
                    return e;
                }
                let error = responder.serve(&mut port).await;
                let stats = responder.stats();
                warn!(device, %error, requests = stats.requests, replies = stats.replies, "serial port lost; reopening");
            }
            Err(e) if ready.is_some() => return e,
            Err(e) => warn!(device, error = %e, "cannot reopen serial port"),
        }
        sleep(bus.reopen_delay).await;
    }
}
