//! What a bus opens: a serial device through tokio-serial, or the simulated line. Both become a
//! [`Port`] the RTU master drives through [`Transport`].

use crate::line::{Parity, SerialFormat, Transport};
use crate::sim::{SimLine, SimPort};
use mio_serial::SerialStream;
use std::future::Future;
use std::io::{self, Read, Write};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::pin::pin;
use std::task::{Context, Waker};
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;
use tokio_serial::{ClearBuffer, DataBits, FlowControl, SerialPort, StopBits};

/// Largest read from a serial port in one call.
const READ_CHUNK: usize = 256;

/// How to open a bus's line.
#[derive(Clone)]
pub enum Device {
    Serial { path: String, format: SerialFormat },
    Sim(SimLine),
}

pub enum Port {
    Serial(SerialFd),
    Sim(SimPort),
}

/// A serial port in the runtime's reactor for reading only. Registered for writing too (as
/// tokio-serial does), the port would wake the runtime once more per frame, when the driver's
/// output buffer drains while the master already waits for the reply. A write that would block
/// (the driver's buffer full) waits on a registration of its own.
pub struct SerialFd(AsyncFd<SerialStream>);

impl Port {
    /// A serial port (or pty) opened in non-blocking mode.
    pub fn serial(stream: SerialStream) -> io::Result<Port> {
        // SAFETY: the AsyncFd owns the stream, so its descriptor stays open and the same.
        let fd = unsafe { AsyncFd::register_with_interest(stream, Interest::READABLE) }?;
        Ok(Port::Serial(SerialFd(fd)))
    }
}

/// Wait until `fd` can take more bytes.
async fn writable(fd: &impl AsRawFd) -> io::Result<()> {
    // SAFETY: dup takes a descriptor and returns a new one or -1.
    let raw = unsafe { libc::dup(fd.as_raw_fd()) };
    if raw < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: `raw` was just opened and is owned by nobody else.
    let dup = unsafe { OwnedFd::from_raw_fd(raw) };
    // SAFETY: the AsyncFd owns `dup`, so it stays open and the same.
    let registered = unsafe { AsyncFd::register_with_interest(dup, Interest::WRITABLE) }?;
    let _ = registered.writable().await?;
    Ok(())
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
                let builder = tokio_serial::new(path, format.baud)
                    .data_bits(data_bits)
                    .parity(parity)
                    .stop_bits(stop_bits)
                    .flow_control(FlowControl::None);
                Port::serial(SerialStream::open(&builder)?)
            }
            Device::Sim(line) => line.open().map(Port::Sim),
        }
    }
}

/// Whether input may have arrived since the port was last read dry: the reactor has seen it
/// readable since, or has not looked yet. Asks tokio, not the kernel: `tcflush` is the most
/// expensive syscall of a transaction (on a pty it also wakes the other side), and between
/// transactions the bus task reads the port dry while it waits. Bytes that reach the kernel after
/// the reactor last looked are not flushed; on the wire they overlap the gap before the frame.
fn may_hold_input(fd: &AsyncFd<SerialStream>) -> bool {
    // Unconstrained: a task out of its cooperative budget would see "not ready" and skip a flush
    // it needs.
    let readable = pin!(tokio::task::unconstrained(fd.readable()));
    readable
        .poll(&mut Context::from_waker(Waker::noop()))
        .is_ready()
}

impl Transport for Port {
    async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        match self {
            // write_all returns once the kernel holds the bytes. Never flush: on a serial port
            // that is a blocking tcdrain on the runtime thread.
            Port::Serial(SerialFd(fd)) => {
                let mut rest = frame;
                while !rest.is_empty() {
                    match fd.get_ref().write(rest) {
                        Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
                        Ok(n) => rest = &rest[n..],
                        Err(e) if e.kind() == io::ErrorKind::WouldBlock => writable(fd).await?,
                        Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                        Err(e) => return Err(e),
                    }
                }
                Ok(())
            }
            Port::Sim(port) => port.send(frame).await,
        }
    }

    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        match self {
            Port::Serial(SerialFd(fd)) => {
                let mut chunk = [0u8; READ_CHUNK];
                let n = loop {
                    let mut ready = fd.readable().await?;
                    match ready.try_io(|fd| fd.get_ref().read(&mut chunk)) {
                        Ok(read) => {
                            let n = read?;
                            // A short read emptied the driver's buffer (as tokio assumes for
                            // sockets): the next read waits for the reactor instead of
                            // spending a syscall to hear "would block".
                            if n > 0 && n < chunk.len() {
                                ready.clear_ready();
                            }
                            break n;
                        }
                        Err(_would_block) => continue,
                    }
                };
                buf.extend_from_slice(&chunk[..n]);
                Ok(n)
            }
            Port::Sim(port) => port.recv(buf).await,
        }
    }

    fn clear_input(&mut self) -> io::Result<()> {
        match self {
            Port::Serial(SerialFd(fd)) => {
                if !may_hold_input(fd) {
                    return Ok(());
                }
                fd.get_ref()
                    .clear(ClearBuffer::Input)
                    .map_err(io::Error::from)
            }
            Port::Sim(port) => port.clear_input(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;
    use tokio::time::timeout;

    /// Both ends of a pty, each as a port.
    fn pty() -> (Port, Port) {
        let (far, near) = SerialStream::pair().unwrap();
        (Port::serial(far).unwrap(), Port::serial(near).unwrap())
    }

    async fn recv_exactly(port: &mut Port, len: usize) -> Vec<u8> {
        let mut buf = Vec::new();
        while buf.len() < len {
            let n = timeout(Duration::from_secs(5), port.recv(&mut buf))
                .await
                .expect("bytes arrive")
                .unwrap();
            assert!(n > 0);
        }
        buf
    }

    #[tokio::test]
    async fn a_frame_sent_on_a_serial_port_arrives_whole_at_the_far_end() {
        let (mut far, mut near) = pty();
        let frame: Vec<u8> = (0..=255).collect();
        near.send(&frame).await.unwrap();
        assert_eq!(recv_exactly(&mut far, frame.len()).await, frame);
    }

    #[tokio::test]
    async fn a_write_larger_than_the_drivers_buffer_waits_for_room_and_arrives_whole() {
        let (mut far, mut near) = pty();
        let bytes: Vec<u8> = (0..65_536u32).map(|i| (i % 251) as u8).collect();
        let (sent, received) = tokio::join!(
            timeout(Duration::from_secs(5), near.send(&bytes)),
            recv_exactly(&mut far, bytes.len()),
        );
        sent.expect("the driver takes every byte").unwrap();
        assert_eq!(received, bytes);
    }

    #[tokio::test]
    async fn bytes_waiting_in_a_serial_port_before_a_frame_are_flushed() {
        let (mut far, mut near) = pty();
        far.send(&[0xAA, 0xBB]).await.unwrap();
        // Long enough for the runtime's reactor to see them arrive.
        tokio::time::sleep(Duration::from_millis(50)).await;
        near.clear_input().unwrap();
        far.send(&[0x01]).await.unwrap();
        assert_eq!(recv_exactly(&mut near, 1).await, [0x01]);
    }
}
