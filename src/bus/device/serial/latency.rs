//! A USB serial adapter's latency timer (FTDI and kin): how long the adapter holds received
//! bytes before it hands them over, 16 ms by default. Read, and set when configured, through the
//! `latency_timer` attribute sysfs gives the adapter's tty on the usb-serial bus; the root of
//! sysfs is a parameter so tests can stand a directory in for it. Knows nothing of ports or
//! metrics.

use std::io;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Where sysfs is mounted.
pub(crate) const SYSFS: &str = "/sys";

/// The adapter's latency timer as found at open.
#[derive(Debug)]
pub(crate) struct LatencyTimer {
    pub file: PathBuf,
    /// The timer after the open (set, or as it was).
    pub value: Duration,
    /// Writing the configured value failed (typically: the file is root's).
    pub refused: Option<io::Error>,
}

/// The latency timer file of `device` under `sysfs`, if the device is a USB serial adapter that
/// has one. Symlinks (the `by-id` names udev makes) are followed to the tty they name.
fn timer_file(sysfs: &Path, device: &Path) -> Option<PathBuf> {
    let tty = std::fs::canonicalize(device).ok()?;
    let file = sysfs
        .join("bus/usb-serial/devices")
        .join(tty.file_name()?)
        .join("latency_timer");
    file.is_file().then_some(file)
}

fn read_ms(file: &Path) -> Option<Duration> {
    let text = std::fs::read_to_string(file).ok()?;
    text.trim().parse().ok().map(Duration::from_millis)
}

/// Read `device`'s latency timer and, if `wanted` differs, set it. `None` if the device has no
/// latency timer (not a USB serial adapter, a pty, the simulated line).
pub(crate) fn adjust(
    sysfs: &Path,
    device: &Path,
    wanted: Option<Duration>,
) -> Option<LatencyTimer> {
    let file = timer_file(sysfs, device)?;
    let mut value = read_ms(&file)?;
    let mut refused = None;
    if let Some(wanted) = wanted.filter(|&wanted| wanted != value) {
        match std::fs::write(&file, wanted.as_millis().to_string()) {
            Ok(()) => value = read_ms(&file).unwrap_or(wanted),
            Err(error) => refused = Some(error),
        }
    }
    Some(LatencyTimer {
        file,
        value,
        refused,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::symlink;

    /// A directory standing in for sysfs and /dev, with a USB adapter `ttyUSB3` whose latency
    /// timer reads `ms`, and a by-id link to it.
    struct FakeSys {
        root: PathBuf,
    }

    impl FakeSys {
        fn new(name: &str, ms: &str) -> FakeSys {
            let root =
                std::env::temp_dir().join(format!("mbgw-latency-{name}-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&root);
            let tty = root.join("sys/bus/usb-serial/devices/ttyUSB3");
            std::fs::create_dir_all(&tty).unwrap();
            std::fs::write(tty.join("latency_timer"), ms).unwrap();
            std::fs::create_dir_all(root.join("dev/serial/by-id")).unwrap();
            std::fs::write(root.join("dev/ttyUSB3"), "").unwrap();
            std::fs::write(root.join("dev/ttyS0"), "").unwrap();
            symlink(
                root.join("dev/ttyUSB3"),
                root.join("dev/serial/by-id/usb-FTDI_FT232R-if00-port0"),
            )
            .unwrap();
            FakeSys { root }
        }

        fn sys(&self) -> PathBuf {
            self.root.join("sys")
        }

        fn file(&self) -> PathBuf {
            self.sys()
                .join("bus/usb-serial/devices/ttyUSB3/latency_timer")
        }
    }

    impl Drop for FakeSys {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.root);
        }
    }

    #[test]
    fn the_latency_timer_of_an_adapter_named_by_id_is_read_and_left_alone_by_default() {
        let fake = FakeSys::new("read", "16\n");
        let by_id = fake
            .root
            .join("dev/serial/by-id/usb-FTDI_FT232R-if00-port0");
        let timer = adjust(&fake.sys(), &by_id, None).expect("a USB adapter");
        assert_eq!(timer.value, Duration::from_millis(16));
        assert_eq!(timer.file, fake.file());
        assert!(timer.refused.is_none());
        assert_eq!(std::fs::read_to_string(fake.file()).unwrap(), "16\n");
    }

    #[test]
    fn a_configured_latency_timer_is_written_in_milliseconds() {
        let fake = FakeSys::new("write", "16\n");
        let device = fake.root.join("dev/ttyUSB3");
        let timer = adjust(&fake.sys(), &device, Some(Duration::from_millis(1))).unwrap();
        assert_eq!(timer.value, Duration::from_millis(1));
        assert_eq!(std::fs::read_to_string(fake.file()).unwrap(), "1");
    }

    #[test]
    fn a_device_that_is_no_usb_adapter_has_no_latency_timer() {
        let fake = FakeSys::new("none", "16\n");
        let device = fake.root.join("dev/ttyS0");
        assert!(adjust(&fake.sys(), &device, Some(Duration::from_millis(1))).is_none());
        assert!(adjust(&fake.sys(), Path::new("/nonexistent/tty"), None).is_none());
    }
}
