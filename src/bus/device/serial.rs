//! A serial port as a bus's transport: opening the device exclusively in its format through
//! tokio-serial, the RS-485 transceiver's direction control ([`rs485`]: the kernel's mode, or RTS
//! raised before a frame and dropped once its last character has left the wire, by the clock,
//! never by tcdrain), and a USB adapter's latency timer ([`latency`]). Knows nothing of framing,
//! transactions or the other transports.

// Unsafe blocks, each with its SAFETY comment: registering the port's fd with the runtime.
#![allow(unsafe_code)]

pub(crate) mod latency;
pub(crate) mod rs485;

use crate::config::{Rs485, Rs485Mode};
use crate::line::{LineTiming, Parity, SerialFormat, Transport};
use crate::timer::LineTimer;
use mio_serial::SerialStream;
use rs485::SerialRs485;
use std::future::Future;
use std::io::{self, Read, Write};
use std::os::fd::{AsFd, BorrowedFd};
use std::pin::pin;
use std::task::{Context, Waker};
use std::time::Duration;
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;
use tokio::time::Instant;
use tokio_serial::{ClearBuffer, DataBits, FlowControl, SerialPort, StopBits};

/// Largest read from a serial port in one call.
const READ_CHUNK: usize = 256;

/// What a bus asks of a serial port's driver beyond the format.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SerialDriver {
    pub rs485: Rs485,
    /// A USB adapter's latency timer to set at open.
    pub latency_timer: Option<Duration>,
    /// The bus's key (`bus[0]`), for errors that name the key at fault.
    pub key: String,
}

impl SerialDriver {
    /// `bus[index]`'s settings.
    pub fn of(index: usize, settings: &crate::config::Bus) -> SerialDriver {
        SerialDriver {
            rs485: settings.rs485.clone(),
            latency_timer: settings.latency_timer,
            key: format!("bus[{index}]"),
        }
    }

    /// Whether a port opened for `self` serves `other` too (the key it is named by may differ).
    pub(super) fn same_as(&self, other: &SerialDriver) -> bool {
        self.rs485 == other.rs485 && self.latency_timer == other.latency_timer
    }
}

/// Open the device at `path` exclusively, so two gateways cannot share one, in `format`, and
/// drive its transceiver as `driver` says. A device that refuses the RS-485 mode asked for fails
/// the open, naming the key.
pub(super) fn open(
    path: &str,
    format: &SerialFormat,
    driver: &SerialDriver,
) -> io::Result<SerialFd> {
    let port = SerialFd::new(open_serial(path, format)?)?;
    drive_transceiver(port, path, format, driver)
}

/// Put the open `port` in the RS-485 mode `driver` asks for.
fn drive_transceiver(
    mut port: SerialFd,
    path: &str,
    format: &SerialFormat,
    driver: &SerialDriver,
) -> io::Result<SerialFd> {
    let settings = &driver.rs485;
    let key = format!("{}.rs485.mode", driver.key);
    let refused = |what: &str, e: &io::Error| rs485::refused(&key, settings.mode, what, e);
    match settings.mode {
        Rs485Mode::Off => Ok(port),
        Rs485Mode::Kernel => {
            let wanted = SerialRs485::of(settings);
            let got = rs485::enable_kernel_mode(port.fd.as_fd(), &wanted)
                .map_err(|e| refused("the kernel's RS-485 mode (TIOCSRS485)", &e))?;
            tracing::info!(
                device = path,
                flags = format!("{:#x}", got.flags),
                delay_rts_before_send_ms = got.delay_rts_before_send,
                delay_rts_after_send_ms = got.delay_rts_after_send,
                asked_flags = format!("{:#x}", wanted.flags),
                "kernel RS-485 mode on"
            );
            let delays = got.delay_rts_before_send + got.delay_rts_after_send;
            port.kernel_delays = Duration::from_millis(u64::from(delays));
            Ok(port)
        }
        Rs485Mode::Rts => {
            let idle = settings.rts_after_send;
            rs485::set_rts(port.fd.as_fd(), idle)
                .map_err(|e| refused("RTS control (TIOCMBIC/TIOCMBIS)", &e))?;
            let rts = RtsSwitch {
                on_send: settings.rts_on_send,
                after_send: idle,
                before: settings.delay_before_send,
                after: settings.delay_after_send,
                line: LineTiming::new(format),
                timer: LineTimer::new(),
                set_rts: rs485::set_rts,
            };
            Ok(port.with_rts(rts))
        }
    }
}

/// The gateway's [`Parity`] as tokio-serial spells it: the one place the two meet.
fn tokio_parity(parity: Parity) -> tokio_serial::Parity {
    match parity {
        Parity::None => tokio_serial::Parity::None,
        Parity::Even => tokio_serial::Parity::Even,
        Parity::Odd => tokio_serial::Parity::Odd,
    }
}

/// Open `path` in `format`, without flow control.
fn open_serial(path: &str, format: &SerialFormat) -> io::Result<SerialStream> {
    let data_bits = match format.data_bits {
        7 => DataBits::Seven,
        _ => DataBits::Eight,
    };
    let stop_bits = match format.stop_bits {
        2 => StopBits::Two,
        _ => StopBits::One,
    };
    let builder = tokio_serial::new(path, format.baud)
        .data_bits(data_bits)
        .parity(tokio_parity(format.parity))
        .stop_bits(stop_bits)
        .flow_control(FlowControl::None);
    Ok(SerialStream::open(&builder)?)
}

/// A serial port in the runtime's reactor for reading only. Registered for writing too (as
/// tokio-serial does), the port would wake the runtime once more per frame, when the driver's
/// output buffer drains while the master already waits for the reply. A write that would block
/// (the driver's buffer full) waits on a registration of its own.
pub struct SerialFd {
    fd: AsyncFd<SerialStream>,
    /// Set when the gateway switches the transceiver with RTS (`rs485.mode = "rts"`).
    rts: Option<RtsSwitch>,
    /// In the kernel's RS-485 mode: the delays its driver keeps before and after each frame.
    kernel_delays: Duration,
}

/// RTS around each frame: its level while sending and after, the delays before the first byte
/// and after the last, and the line's speed to know when the last byte is out.
struct RtsSwitch {
    on_send: bool,
    after_send: bool,
    before: Duration,
    after: Duration,
    line: LineTiming,
    timer: LineTimer,
    /// Sets RTS: [`rs485::set_rts`] (a test records instead).
    set_rts: fn(BorrowedFd<'_>, bool) -> io::Result<()>,
}

impl SerialFd {
    /// A serial port (or pty) opened in non-blocking mode.
    pub fn new(stream: SerialStream) -> io::Result<SerialFd> {
        // SAFETY: the AsyncFd owns the stream, so its descriptor stays open and the same.
        let fd = unsafe { AsyncFd::register_with_interest(stream, Interest::READABLE) }?;
        Ok(SerialFd {
            fd,
            rts: None,
            kernel_delays: Duration::ZERO,
        })
    }

    /// The port, switching RTS around each frame.
    fn with_rts(mut self, rts: RtsSwitch) -> SerialFd {
        self.rts = Some(rts);
        self
    }
}

/// Wait until `fd` can take more bytes, on a registration of a duplicate of it.
async fn writable(fd: BorrowedFd<'_>) -> io::Result<()> {
    let dup = fd.try_clone_to_owned()?;
    // SAFETY: the AsyncFd owns `dup`, so it stays open and the same.
    let registered = unsafe { AsyncFd::register_with_interest(dup, Interest::WRITABLE) }?;
    let _ = registered.writable().await?;
    Ok(())
}

/// Hand all of `frame` to the driver. Returns once the kernel holds the bytes. Never flush: on a
/// serial port that is a blocking tcdrain on the runtime thread.
async fn write_all(fd: &AsyncFd<SerialStream>, frame: &[u8]) -> io::Result<()> {
    let mut rest = frame;
    while !rest.is_empty() {
        match fd.get_ref().write(rest) {
            Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
            Ok(n) => rest = &rest[n..],
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => writable(fd.as_fd()).await?,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
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

impl Transport for SerialFd {
    /// Send `frame`; with RTS switching, raise RTS first and drop it once the frame's last
    /// character has left the wire (its length at the line's speed from when the write started,
    /// the line being idle then) plus `delay_after_send`, waited for on a timer.
    async fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        let Some(rts) = &mut self.rts else {
            return write_all(&self.fd, frame).await;
        };
        (rts.set_rts)(self.fd.as_fd(), rts.on_send)?;
        if !rts.before.is_zero() {
            rts.timer.sleep_until(Instant::now() + rts.before).await;
        }
        let started = Instant::now();
        let written = write_all(&self.fd, frame).await;
        if written.is_ok() {
            let out = started + rts.line.frame_time(frame.len()) + rts.after;
            rts.timer.sleep_until(out).await;
        }
        // Dropped even after a failed write, so the line is never left driven.
        let dropped = (rts.set_rts)(self.fd.as_fd(), rts.after_send);
        written.and(dropped)
    }

    /// With RTS switching, `send` returns once the frame is out; in the kernel's RS-485 mode the
    /// driver's delays come on top of the frame.
    fn end_of_transmission(&self, returned: Instant, frame_time: Duration) -> Instant {
        match self.rts {
            Some(_) => returned,
            None => returned + self.kernel_delays + frame_time,
        }
    }

    async fn recv(&mut self, buf: &mut Vec<u8>) -> io::Result<usize> {
        let mut chunk = [0u8; READ_CHUNK];
        let n = loop {
            let mut ready = self.fd.readable().await?;
            match ready.try_io(|fd| fd.get_ref().read(&mut chunk)) {
                Ok(read) => {
                    let n = read?;
                    // A short read emptied the driver's buffer (as tokio assumes for sockets):
                    // the next read waits for the reactor instead of spending a syscall to hear
                    // "would block".
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

    fn clear_input(&mut self, _stale: &mut Vec<u8>) -> io::Result<()> {
        if !may_hold_input(&self.fd) {
            return Ok(());
        }
        self.fd
            .get_ref()
            .clear(ClearBuffer::Input)
            .map_err(io::Error::from)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::time::timeout;

    /// Both ends of a pty, each as a port.
    fn pty() -> (SerialFd, SerialFd) {
        let (far, near) = SerialStream::pair().unwrap();
        (SerialFd::new(far).unwrap(), SerialFd::new(near).unwrap())
    }

    async fn recv_exactly(port: &mut SerialFd, len: usize) -> Vec<u8> {
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

    #[test]
    fn a_change_of_rs485_settings_or_latency_timer_reopens_the_port_but_a_new_index_does_not() {
        let device = super::super::tests::ttys1;
        let first = device(SerialDriver::default());
        let moved = device(SerialDriver {
            key: "bus[3]".into(),
            ..SerialDriver::default()
        });
        assert!(first.same_as(&moved));
        let rts = device(SerialDriver {
            rs485: Rs485 {
                mode: Rs485Mode::Rts,
                ..Rs485::default()
            },
            ..SerialDriver::default()
        });
        assert!(!first.same_as(&rts));
        let latency = device(SerialDriver {
            latency_timer: Some(Duration::from_millis(1)),
            ..SerialDriver::default()
        });
        assert!(!first.same_as(&latency));
    }

    /// RTS levels set, and when.
    static RTS: std::sync::Mutex<Vec<(Instant, bool)>> = std::sync::Mutex::new(Vec::new());

    fn record_rts(_: BorrowedFd<'_>, level: bool) -> io::Result<()> {
        RTS.lock().unwrap().push((Instant::now(), level));
        Ok(())
    }

    #[tokio::test(start_paused = true)]
    async fn in_rts_mode_rts_drops_once_the_frames_last_character_has_left_the_wire() {
        let (mut far, near) = SerialStream::pair().unwrap();
        let format = SerialFormat {
            baud: 9600,
            data_bits: 8,
            parity: Parity::None,
            stop_bits: 2,
        };
        let line = LineTiming::new(&format);
        let (before, after) = (Duration::from_millis(1), Duration::from_millis(2));
        let mut port = SerialFd::new(near).unwrap().with_rts(RtsSwitch {
            on_send: true,
            after_send: false,
            before,
            after,
            line,
            timer: LineTimer::new(),
            set_rts: record_rts,
        });
        let now = Instant::now();
        assert_eq!(port.end_of_transmission(now, line.frame_time(8)), now);
        let frame = [0x01, 0x03, 0x00, 0x04, 0x00, 0x02, 0x85, 0xCA];
        let started = Instant::now();
        port.send(&frame).await.unwrap();
        let returned = Instant::now();
        let events = RTS.lock().unwrap().clone();
        // Raised at once; dropped the delay before, the frame's 8 characters and the delay
        // after later (tokio's timer wakes on whole milliseconds), when send returns.
        let earliest = started + before + line.frame_time(frame.len()) + after;
        let resolution = Duration::from_millis(1);
        assert_eq!(events.len(), 2, "{events:?}");
        assert_eq!(events[0], (started, true));
        let (dropped_at, level) = events[1];
        assert!(!level);
        assert!(dropped_at >= earliest, "{:?} early", earliest - dropped_at);
        assert!(
            dropped_at <= earliest + 2 * resolution,
            "{:?} late",
            dropped_at - earliest
        );
        assert_eq!(returned, dropped_at);
        let mut buf = [0u8; 8];
        std::io::Read::read_exact(&mut far, &mut buf).unwrap();
        assert_eq!(buf, frame);
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
        near.clear_input(&mut Vec::new()).unwrap();
        far.send(&[0x01]).await.unwrap();
        assert_eq!(recv_exactly(&mut near, 1).await, [0x01]);
    }
}
