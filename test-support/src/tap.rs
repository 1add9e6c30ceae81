//! A shared RS-485 line made of ptys, for listen-only lines: the pty of a third-party master (M)
//! and the line of a third-party slave (S) joined by a relay that copies every byte both ways,
//! and copies both directions to the gateway's pty (G) as a tap on the wire would. The relay reads
//! G too, and keeps every byte the gateway wrote: on a listen line there must be none.
//!
//! The gateway opens G by a link in a folder of the test's, so that G can be lost (its pty
//! closed, as a USB adapter pulled out) and come back as a new pty behind the same path. Knobs
//! for a hostile line act on G alone, so the master and the slave go on undisturbed: bytes
//! injected, the next reply of the slave corrupted on its way to G.

use crate::wait::within;
use std::fs::File;
use std::io;
use std::os::fd::{AsRawFd, BorrowedFd};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::io::unix::AsyncFd;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};

/// Chunks the relay may be ahead of the gateway's pty before it drops what it copies there (and
/// counts it): the line between master and slave never waits for the gateway.
const TO_GATEWAY_BACKLOG: usize = 1024;
/// The slave's baud rate as the relay opens its line; a pty passes bytes instantly whatever it is.
const BAUD: u32 = 115_200;

/// The master side of a pty pair, as the relay holds it, and its tty kept open (so that the
/// master side never reads EIO while nobody else has the tty open).
///
/// `SerialStream::pair()` opens both without close-on-exec: every process spawned while they are
/// open (the gateway under test, the Python peers, another test's) would hold them too, and a
/// pty some child holds cannot be lost. So the relay keeps close-on-exec copies and closes the
/// originals at once.
struct Pty {
    master: Arc<AsyncFd<File>>,
    path: String,
    _tty: File,
}

impl Pty {
    // Two unsafe calls, each with its SAFETY comment: a borrow of a descriptor to copy it, and
    // the copy handed to tokio's reactor.
    #[allow(unsafe_code)]
    fn pair() -> Pty {
        let (master, tty) = SerialStream::pair().expect("a pty pair");
        let path = tty.name().expect("a pty has a path");
        // SAFETY: `master` owns this descriptor and outlives the borrow, which only duplicates it.
        let borrowed = unsafe { BorrowedFd::borrow_raw(master.as_raw_fd()) };
        // F_DUPFD_CLOEXEC; the copy shares the original's file description, O_NONBLOCK with it.
        let copy = borrowed
            .try_clone_to_owned()
            .expect("a copy of the pty's master");
        drop(master);
        // Opened again by its path, as std opens every file: close-on-exec.
        let tty_copy = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&path)
            .expect("the pty's tty opens");
        drop(tty);
        // SAFETY: the File owns its descriptor, and the AsyncFd owns the File until it drops it.
        let polled = unsafe { AsyncFd::register(File::from(copy)) };
        Pty {
            master: Arc::new(polled.expect("the pty's master polled")),
            path,
            _tty: tty_copy,
        }
    }
}

/// Reads and writes of a pty's master side, on the runtime.
#[derive(Clone)]
struct PtyMaster(Arc<AsyncFd<File>>);

impl PtyMaster {
    async fn read(&self, buf: &mut [u8]) -> io::Result<usize> {
        loop {
            let mut ready = self.0.readable().await?;
            if let Ok(result) = ready.try_io(|fd| io::Read::read(&mut fd.get_ref(), buf)) {
                return result;
            }
        }
    }

    async fn write_all(&self, mut buf: &[u8]) -> io::Result<()> {
        while !buf.is_empty() {
            let mut ready = self.0.writable().await?;
            if let Ok(result) = ready.try_io(|fd| io::Write::write(&mut fd.get_ref(), buf)) {
                let n = result?;
                if n == 0 {
                    return Err(io::ErrorKind::WriteZero.into());
                }
                buf = &buf[n..];
            }
        }
        Ok(())
    }
}

/// What crossed the line between the master and the slave so far, each way.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LineLog {
    pub to_slave: Vec<u8>,
    pub to_master: Vec<u8>,
}

/// What the relay's tasks share with the test.
#[derive(Default)]
struct Shared {
    line: Mutex<LineLog>,
    written_by_gateway: Mutex<Vec<u8>>,
    /// The gateway's pty as it is now: where copies and injections go (`None` while it is lost).
    to_gateway: Mutex<Option<mpsc::Sender<Vec<u8>>>>,
    corrupt_next_reply: AtomicBool,
    corrupted: AtomicUsize,
    /// Addresses whose replies reach nobody.
    muted: Mutex<Vec<u8>>,
    delivered_to_gateway: AtomicUsize,
    dropped_to_gateway: AtomicUsize,
}

impl Shared {
    fn sender(&self) -> Option<mpsc::Sender<Vec<u8>>> {
        self.to_gateway
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Hand a copy to G without waiting: dropped (and counted) if G is lost or far behind.
    fn copy_to_gateway(&self, bytes: &[u8]) {
        let sent = self
            .sender()
            .is_some_and(|to| to.try_send(bytes.to_vec()).is_ok());
        if !sent {
            self.dropped_to_gateway
                .fetch_add(bytes.len(), Ordering::Relaxed);
        }
    }
}

/// The gateway's pty of the moment and the two tasks on its master side.
struct GatewayPort {
    writer: JoinHandle<()>,
    reader: JoinHandle<()>,
    _pty: Pty,
}

impl Drop for GatewayPort {
    fn drop(&mut self) {
        self.writer.abort();
        self.reader.abort();
    }
}

/// The shared line: start it on the slave's line, give the master [`Tap::master_path`] and the
/// gateway [`Tap::gateway_path`].
pub struct Tap {
    master_path: String,
    link: PathBuf,
    shared: Arc<Shared>,
    relay: JoinHandle<()>,
    gateway: Option<GatewayPort>,
    _master: Pty,
}

impl Tap {
    /// The line between the slave on `slave_path` (a serial port by path: a pty's end) and a new
    /// pty for the master, with G linked as `gateway` in `dir`.
    pub fn start(slave_path: &str, dir: &Path) -> Tap {
        let master = Pty::pair();
        let slave = tokio_serial::new(slave_path, BAUD)
            .open_native_async()
            .unwrap_or_else(|e| panic!("the slave's line {slave_path}: {e}"));
        let shared = Arc::new(Shared::default());
        let relay = tokio::spawn(relay(
            PtyMaster(Arc::clone(&master.master)),
            slave,
            Arc::clone(&shared),
        ));
        let mut tap = Tap {
            master_path: master.path.clone(),
            link: dir.join("gateway"),
            shared,
            relay,
            gateway: None,
            _master: master,
        };
        tap.reopen_gateway_port();
        tap
    }

    /// The master's end of the line, a pty path to open as a serial port.
    pub fn master_path(&self) -> &str {
        &self.master_path
    }

    /// The gateway's `device`: a link to G, the same path across a loss and a reopen.
    pub fn gateway_path(&self) -> &Path {
        &self.link
    }

    /// Every byte the gateway wrote on its port so far, in order, across every G it had.
    pub fn written_by_gateway(&self) -> Vec<u8> {
        self.shared
            .written_by_gateway
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// What the master and the slave said to each other so far.
    pub fn line(&self) -> LineLog {
        self.shared
            .line
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Bytes written to G so far: the line's copies and injections.
    pub fn delivered_to_gateway(&self) -> usize {
        self.shared.delivered_to_gateway.load(Ordering::Relaxed)
    }

    /// Bytes of the line's that never reached G: it was lost, or the gateway far behind.
    pub fn dropped_to_gateway(&self) -> usize {
        self.shared.dropped_to_gateway.load(Ordering::Relaxed)
    }

    /// Put `bytes` on G alone, in one write, after what the relay copied before (the master and
    /// the slave never see them). Waits while G's backlog is full, so a loop of injections runs
    /// as fast as the gateway reads. False if G is lost.
    pub async fn inject(&self, bytes: &[u8]) -> bool {
        let Some(to) = self.shared.sender() else {
            return false;
        };
        within("G takes the injected bytes", to.send(bytes.to_vec()))
            .await
            .is_ok()
    }

    /// [`Tap::inject`], then wait (bounded) until the bytes are written to G.
    pub async fn inject_written(&self, bytes: &[u8]) {
        let before = self.delivered_to_gateway();
        assert!(
            self.inject(bytes).await,
            "G is lost: nothing to inject into"
        );
        self.until_delivered(before + bytes.len()).await;
    }

    /// Wait (bounded) until `total` bytes were written to G.
    pub async fn until_delivered(&self, total: usize) {
        within(&format!("{total} bytes written to G"), async {
            while self.delivered_to_gateway() < total {
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        })
        .await;
    }

    /// The slave's next reply reaches G with its last byte changed: the master gets it intact,
    /// the gateway sees a CRC error.
    pub fn corrupt_next_reply(&self) {
        self.shared.corrupt_next_reply.store(true, Ordering::SeqCst);
    }

    /// From now on, what the slave answers as `address` reaches neither the master nor G: a
    /// slave that is not on the line. (pymodbus 3.16's server answers every address, those it
    /// does not serve with exception 04: its simulator's lookup fails with a KeyError.)
    pub fn mute_replies_from(&self, address: u8) {
        self.shared
            .muted
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(address);
    }

    /// Replies corrupted so far.
    pub fn corrupted(&self) -> usize {
        self.shared.corrupted.load(Ordering::SeqCst)
    }

    /// Wait (bounded) until `n` replies have been corrupted on their way to G.
    pub async fn until_corrupted(&self, n: usize) {
        within(&format!("{n} replies corrupted"), async {
            while self.corrupted() < n {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await;
    }

    /// Pull G out: its pty closes (the gateway's reads fail) and the link leads nowhere.
    pub fn lose_gateway_port(&mut self) {
        *self
            .shared
            .to_gateway
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = None;
        self.gateway = None;
        let _ = std::fs::remove_file(&self.link);
    }

    /// Plug G in: a new pty, the link re-pointed at it in one step (a rename).
    pub fn reopen_gateway_port(&mut self) {
        self.lose_gateway_port();
        let pty = Pty::pair();
        let (to, from) = mpsc::channel(TO_GATEWAY_BACKLOG);
        let side = PtyMaster(Arc::clone(&pty.master));
        let shared = Arc::clone(&self.shared);
        let writer = tokio::spawn(write_to_gateway(side.clone(), from, shared));
        let shared = Arc::clone(&self.shared);
        let reader = tokio::spawn(async move {
            let mut chunk = [0u8; 1024];
            while let Ok(n @ 1..) = side.read(&mut chunk).await {
                shared
                    .written_by_gateway
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .extend_from_slice(&chunk[..n]);
            }
        });
        let fresh = self.link.with_extension("new");
        let _ = std::fs::remove_file(&fresh);
        std::os::unix::fs::symlink(&pty.path, &fresh).expect("a link to G");
        std::fs::rename(&fresh, &self.link).expect("the link re-pointed");
        self.gateway = Some(GatewayPort {
            writer,
            reader,
            _pty: pty,
        });
        *self
            .shared
            .to_gateway
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(to);
    }
}

impl Drop for Tap {
    fn drop(&mut self) {
        self.relay.abort();
        let _ = std::fs::remove_file(&self.link);
    }
}

async fn write_to_gateway(port: PtyMaster, mut from: mpsc::Receiver<Vec<u8>>, shared: Arc<Shared>) {
    while let Some(bytes) = from.recv().await {
        if port.write_all(&bytes).await.is_err() {
            return;
        }
        shared
            .delivered_to_gateway
            .fetch_add(bytes.len(), Ordering::Relaxed);
    }
}

/// M to S and S to M, each chunk copied to G after it is passed on; ends when either side does.
async fn relay(master: PtyMaster, mut slave: SerialStream, shared: Arc<Shared>) {
    let mut from_master = [0u8; 1024];
    let mut from_slave = [0u8; 1024];
    loop {
        tokio::select! {
            n = master.read(&mut from_master) => {
                let Ok(n @ 1..) = n else { return };
                let bytes = &from_master[..n];
                shared.line.lock().unwrap_or_else(PoisonError::into_inner)
                    .to_slave.extend_from_slice(bytes);
                if slave.write_all(bytes).await.is_err() {
                    return;
                }
                shared.copy_to_gateway(bytes);
            }
            n = slave.read(&mut from_slave) => {
                let Ok(n @ 1..) = n else { return };
                let bytes = &from_slave[..n];
                let muted = shared.muted.lock().unwrap_or_else(PoisonError::into_inner)
                    .contains(&bytes[0]);
                if muted {
                    continue;
                }
                shared.line.lock().unwrap_or_else(PoisonError::into_inner)
                    .to_master.extend_from_slice(bytes);
                if master.write_all(bytes).await.is_err() {
                    return;
                }
                // A whole reply comes in one chunk from pymodbus; one too short to be a reply
                // (5 bytes at least) is passed on as it is, and the next one is corrupted.
                if n >= 5 && shared.corrupt_next_reply.swap(false, Ordering::SeqCst) {
                    let mut bad = bytes.to_vec();
                    bad[n - 1] ^= 0x5A;
                    shared.copy_to_gateway(&bad);
                    shared.corrupted.fetch_add(1, Ordering::SeqCst);
                } else {
                    shared.copy_to_gateway(bytes);
                }
            }
        }
    }
}
