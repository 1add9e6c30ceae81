//! What a bus opens: a serial device through tokio-serial, or the simulated line. Both become a
//! [`Port`] the RTU master drives through [`Transport`].

use crate::rtu::{Parity, SerialFormat, Transport};
use crate::sim::{SimLine, SimPort};
use std::io;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_serial::{
    ClearBuffer, DataBits, FlowControl, SerialPort, SerialPortBuilderExt, SerialStream, StopBits,
};

/// Largest read from a serial port in one call.
const READ_CHUNK: usize = 256;

/// How to open a bus's line.
#[derive(Clone)]
pub enum Device {
    Serial { path: String, format: SerialFormat },
    Sim(SimLine),
}

pub enum Port {
    Serial(SerialStream),
    Sim(SimPort),
}

impl Device {
    /// Whether `other` opens the same line the same way: the same serial device in the same
    /// format, or the same simulated line.
    pub fn same_as(&self, other: &Device) -> bool {
        match (self, other) {
            (Device::Serial { path, format }, Device::Serial { path: p, format: f }) => {
                path == p && format == f
            }
            (Device::Sim(line), Device::Sim(other)) => line.same_line(other),
            _ => false,
        }
    }

    /// Open the line. Serial ports are opened exclusively, so two gateways cannot share one.
    pub fn open(&self) -> io::Result<Port> {
        match self {
            Device::Serial { path, format } => {
                let data_bits = match format.data_bits {
                    7 => DataBits::Seven,
                    _ => DataBits::Eight,
                };
                let parity = match format.parity {
                    Parity::None => tokio_serial::Parity::None,
                    Parity::Even => tokio_serial::Parity::Even,
                    Parity::Odd => tokio_serial::Parity::Odd,
                };
                let stop_bits = match format.stop_bits {
                    2 => StopBits::Two,
                    _ => StopBits::One,
                };
                let stream = tokio_serial::new(path, format.baud)
                    .data_bits(data_bits)
                    .parity(parity)
                    .stop_bits(stop_bits)
                    .flow_control(FlowControl::None)
                    .open_native_async()
                    .map_err(io::Error::from)?;
                Ok(Port::Serial(stream))
            }
            Device::Sim(line) => line.open().map(Port::Sim),
        }
    }
}

impl Transport for Port {
    async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        match self {
            // write_all returns once the kernel holds the bytes. Never flush: on a serial port
            // that is a blocking tcdrain on the runtime thread.
            Port::Serial(stream) => stream.write_all(frame).await,
            Port::Sim(port) => port.send(frame).await,
        }
    }

    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        match self {
            Port::Serial(stream) => {
                let mut chunk = [0u8; READ_CHUNK];
                let n = stream.read(&mut chunk).await?;
                buf.extend_from_slice(&chunk[..n]);
                Ok(n)
            }
            Port::Sim(port) => port.recv(buf).await,
        }
    }

    fn clear_input(&mut self) -> io::Result<()> {
        match self {
            Port::Serial(stream) => stream.clear(ClearBuffer::Input).map_err(io::Error::from),
            Port::Sim(port) => port.clear_input(),
        }
    }
}
