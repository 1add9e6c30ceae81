//! Driving an RS-485 transceiver's driver enable on a serial port: the kernel's RS-485 mode
//! (`struct serial_rs485` through `TIOCSRS485`), or RTS switched by the gateway around each frame
//! (`TIOCMBIS`/`TIOCMBIC`, which never block). What the settings mean is the configuration's;
//! when a frame has left the wire is the serial port's ([`super::SerialFd`]). Knows nothing of
//! frames or time.

// Unsafe blocks, each with its SAFETY comment: the RS-485 and modem-line ioctls.
#![allow(unsafe_code)]

use crate::config::{Rs485, Rs485Mode};
use std::io;
use std::os::fd::{AsRawFd, BorrowedFd};
use std::time::Duration;

/// The kernel's RS-485 flags (Linux's serial RS-485 interface): RS-485 mode on.
pub(crate) const SER_RS485_ENABLED: u32 = 1 << 0;
/// RTS level while sending.
pub(crate) const SER_RS485_RTS_ON_SEND: u32 = 1 << 1;
/// RTS level after sending.
pub(crate) const SER_RS485_RTS_AFTER_SEND: u32 = 1 << 2;
/// The receiver stays on while sending.
pub(crate) const SER_RS485_RX_DURING_TX: u32 = 1 << 4;

/// The kernel's `struct serial_rs485`, 32 bytes: the flags, the delays in milliseconds, and five
/// words the kernel reserves (or uses for addressing, which the gateway leaves off). libc has the
/// ioctl numbers but not this struct.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct SerialRs485 {
    pub(crate) flags: u32,
    pub(crate) delay_rts_before_send: u32,
    pub(crate) delay_rts_after_send: u32,
    pub(crate) padding: [u32; 5],
}

impl SerialRs485 {
    /// What `TIOCSRS485` is given for `settings` (in `kernel` mode).
    pub(crate) fn of(settings: &Rs485) -> SerialRs485 {
        let mut flags = SER_RS485_ENABLED;
        for (set, flag) in [
            (settings.rts_on_send, SER_RS485_RTS_ON_SEND),
            (settings.rts_after_send, SER_RS485_RTS_AFTER_SEND),
            (settings.rx_during_tx, SER_RS485_RX_DURING_TX),
        ] {
            if set {
                flags |= flag;
            }
        }
        SerialRs485 {
            flags,
            delay_rts_before_send: millis(settings.delay_before_send),
            delay_rts_after_send: millis(settings.delay_after_send),
            padding: [0; 5],
        }
    }
}

fn millis(delay: Duration) -> u32 {
    u32::try_from(delay.as_millis()).unwrap_or(u32::MAX)
}

/// The error a port's open fails with when its device refuses what `key` asks for: of kind
/// `Unsupported`, whatever the device answered, which the message carries.
pub(crate) fn refused(key: &str, mode: Rs485Mode, what: &str, error: &io::Error) -> io::Error {
    io::Error::new(
        io::ErrorKind::Unsupported,
        format!(
            "{key} = \"{}\": the device refuses {what}: {error}",
            mode.as_str()
        ),
    )
}

/// Put the port in the kernel's RS-485 mode; returns the settings as the driver took them (it
/// clears what it does not support).
pub(crate) fn enable_kernel_mode(
    fd: BorrowedFd<'_>,
    wanted: &SerialRs485,
) -> io::Result<SerialRs485> {
    let fd = fd.as_raw_fd();
    let mut set = *wanted;
    // SAFETY: `fd` is open (borrowed); TIOCSRS485 reads and writes one `struct serial_rs485`,
    // which `set` is.
    if unsafe { libc::ioctl(fd, libc::TIOCSRS485, &raw mut set) } < 0 {
        return Err(io::Error::last_os_error());
    }
    let mut got = SerialRs485::default();
    // SAFETY: `fd` is open (borrowed); TIOCGRS485 writes one `struct serial_rs485`, which `got`
    // is.
    if unsafe { libc::ioctl(fd, libc::TIOCGRS485, &raw mut got) } < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(got)
}

/// Raise (`true`) or drop RTS. Does not wait for the line.
pub(crate) fn set_rts(fd: BorrowedFd<'_>, level: bool) -> io::Result<()> {
    let request = if level {
        libc::TIOCMBIS
    } else {
        libc::TIOCMBIC
    };
    let bits: libc::c_int = libc::TIOCM_RTS;
    // SAFETY: `fd` is open (borrowed); TIOCMBIS and TIOCMBIC read one int, which `bits` is.
    if unsafe { libc::ioctl(fd.as_raw_fd(), request, &raw const bits) } < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(text: &str) -> Rs485 {
        let text = format!(
            "[[bus]]\nname = \"a\"\ndevice = \"/dev/ttyS1\"\n[bus.rs485]\nmode = \"kernel\"\n{text}"
        );
        crate::Config::from_toml_str(&text)
            .unwrap_or_else(|e| panic!("{e}"))
            .bus
            .remove(0)
            .rs485
    }

    #[test]
    fn the_kernel_struct_is_the_32_bytes_linux_serial_h_declares() {
        assert_eq!(std::mem::size_of::<SerialRs485>(), 32);
        assert_eq!(std::mem::offset_of!(SerialRs485, delay_rts_before_send), 4);
        assert_eq!(std::mem::offset_of!(SerialRs485, delay_rts_after_send), 8);
    }

    #[test]
    fn kernel_mode_by_default_raises_rts_to_send_and_drops_it_after() {
        assert_eq!(
            SerialRs485::of(&settings("")),
            SerialRs485 {
                flags: SER_RS485_ENABLED | SER_RS485_RTS_ON_SEND,
                delay_rts_before_send: 0,
                delay_rts_after_send: 0,
                padding: [0; 5],
            }
        );
        assert_eq!(SER_RS485_ENABLED | SER_RS485_RTS_ON_SEND, 0b11);
    }

    #[test]
    fn kernel_mode_takes_inverted_rts_the_delays_in_milliseconds_and_rx_during_tx() {
        let built = SerialRs485::of(&settings(
            "rts_on_send = false\nrts_after_send = true\ndelay_before_send = \"2ms\"\n\
             delay_after_send = \"15ms\"\nrx_during_tx = true\n",
        ));
        assert_eq!(
            built,
            SerialRs485 {
                flags: SER_RS485_ENABLED | SER_RS485_RTS_AFTER_SEND | SER_RS485_RX_DURING_TX,
                delay_rts_before_send: 2,
                delay_rts_after_send: 15,
                padding: [0; 5],
            }
        );
        assert_eq!(built.flags, 0b1_0101);
    }
}
