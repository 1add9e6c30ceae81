//! ser2net (Debian's 4.3) as a serial device server in front of a pty: the far side of a bus
//! whose `device` is `tcp://` (a raw accepter) or `rfc2217://` (a `telnet(rfc2217)` one). It
//! knows nothing of Modbus; the slave on the pty is the test's.
//!
//! The pty it serves is a path the test gives it. The tests give it the gateway's end of
//! `tests/peers/pymodbus_slave.py`'s cable (two pty pairs whose master sides the script bridges)
//! rather than a socat pair: the script holds both slave ends open for its whole life, so ser2net
//! opening the pty at each connection, closing it when the connection ends and vanishing when it
//! is killed is never a hangup that the slave's side sees, and the script logs every byte either
//! way, which the tests read as the wire.
//!
//! ser2net gives no sign on standard output that its accepter is up, and a probe connection would
//! open the pty (and, on an RFC 2217 accepter, set it) as a session of its own. So it counts as up
//! when the kernel's table of TCP sockets (`/proc/net/tcp`) has a listening socket on its port that
//! is one of its own file descriptors. A port taken between choosing and binding it is a line
//! "Unable to startup network port" on its output: another port is tried.
//!
//! What ser2net 4.3 does that a test must know:
//! - it opens the serial device when a connection arrives and sets the connector's settings
//!   (`9600n81` here) on it then, and it puts back the termios it found when the connection ends:
//!   a pty's settings show what a client negotiated only while that client is connected;
//! - on a pty it never acknowledges RFC 2217 SET-CONTROL (DTR, RTS: a pty has no modem lines), so a
//!   client that waits for that acknowledgement (pyserial's `rfc2217://`) gives up;
//! - `Unable to start mdns: Out of memory` on its output at every start is harmless.

use crate::process::tool;
use crate::wait::within;
use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpListener};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// How the accepter speaks to its clients.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accepter {
    /// Transparent: the socket's bytes are the line's (a bus's `tcp://`).
    Raw,
    /// Telnet with the COM-PORT-OPTION of RFC 2217 (a bus's `rfc2217://`).
    Rfc2217,
}

/// Ports tried before a start gives up, each chosen free a moment before ser2net binds it.
const PORT_ATTEMPTS: usize = 10;
/// How often the start looks for its listening socket.
const POLL: Duration = Duration::from_millis(10);
/// ser2net's line for an accepter it could not bind.
const BIND_FAILED: &str = "Unable to startup network port";

/// Temp directories of this process's fixtures, told apart.
static STARTED: AtomicUsize = AtomicUsize::new(0);

/// A running ser2net with one connection from a loopback port to a pty; killed when dropped.
pub struct Ser2net {
    program: PathBuf,
    accepter: Accepter,
    addr: SocketAddr,
    dir: PathBuf,
    config: PathBuf,
    child: Option<Child>,
    /// What the running ser2net printed so far.
    output: Arc<Mutex<String>>,
}

/// What came of one start of ser2net.
enum Started {
    Listening,
    PortTaken,
}

impl Ser2net {
    /// ser2net serving `device` with the connector settings `settings` (ser2net's form,
    /// `9600n81`) on a free loopback port, once it accepts connections; `None` without ser2net
    /// (see [`ser2net_program`]).
    pub async fn start(device: &str, settings: &str, accepter: Accepter) -> Option<Ser2net> {
        let program = ser2net_program()?;
        let dir = std::env::temp_dir().join(format!(
            "mbgw-ser2net-{}-{}",
            std::process::id(),
            STARTED.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).expect("a temp dir for ser2net's config");
        let mut server = Ser2net {
            program,
            accepter,
            addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            config: dir.join("ser2net.yaml"),
            dir,
            child: None,
            output: Arc::default(),
        };
        for _ in 0..PORT_ATTEMPTS {
            let port = TcpListener::bind("127.0.0.1:0")
                .and_then(|listener| listener.local_addr())
                .expect("a free loopback port")
                .port();
            server.addr.set_port(port);
            std::fs::write(&server.config, config(device, settings, accepter, port))
                .expect("write ser2net's config");
            match server.run().await {
                Started::Listening => return Some(server),
                Started::PortTaken => server.kill(),
            }
        }
        panic!("ser2net found no free port in {PORT_ATTEMPTS} attempts");
    }

    /// Where the accepter listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The bus `device` that reaches this server: `tcp://127.0.0.1:PORT` for a raw accepter,
    /// `rfc2217://127.0.0.1:PORT` for an RFC 2217 one.
    pub fn device(&self) -> String {
        let scheme = match self.accepter {
            Accepter::Raw => "tcp",
            Accepter::Rfc2217 => "rfc2217",
        };
        format!("{scheme}://{}", self.addr)
    }

    /// What ser2net printed since it was last started.
    pub fn output(&self) -> String {
        self.output.lock().unwrap().clone()
    }

    /// Kill ser2net (SIGKILL, as a crash or a power cut would): its connections drop and its port
    /// stops listening.
    pub fn stop(&mut self) {
        self.kill();
    }

    /// Start ser2net again with the same config, on the same port, once it accepts connections.
    pub async fn restart(&mut self) {
        self.kill();
        // The port was this fixture's a moment ago: a bind failure now is transient (ser2net
        // retries the accepter every second, as its config says), so wait for the listen.
        if let Started::PortTaken = self.run().await {
            within("ser2net binds its port again", self.listening()).await;
        }
    }

    /// Spawn ser2net on the config and wait until it listens or says its port is taken.
    async fn run(&mut self) -> Started {
        let mut child = Command::new(&self.program)
            // -d: in the foreground, its log on standard output.
            .args(["-d", "-c"])
            .arg(&self.config)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("ser2net starts");
        let output = Arc::new(Mutex::new(String::new()));
        for stream in [
            child
                .stdout
                .take()
                .map(|s| Box::new(s) as Box<dyn std::io::Read + Send>),
            child
                .stderr
                .take()
                .map(|s| Box::new(s) as Box<dyn std::io::Read + Send>),
        ]
        .into_iter()
        .flatten()
        {
            let output = Arc::clone(&output);
            std::thread::spawn(move || {
                for line in BufReader::new(stream).lines() {
                    let Ok(line) = line else { return };
                    let mut output = output.lock().unwrap();
                    output.push_str(&line);
                    output.push('\n');
                }
            });
        }
        self.output = output;
        self.child = Some(child);
        let what = format!("ser2net listens on {}", self.addr);
        within(&what, async {
            loop {
                if self.owns_listener() {
                    return Started::Listening;
                }
                if self.output().contains(BIND_FAILED) {
                    return Started::PortTaken;
                }
                let child = self.child.as_mut().expect("just spawned");
                if let Ok(Some(status)) = child.try_wait() {
                    panic!("ser2net exited ({status}):\n{}", self.output());
                }
                tokio::time::sleep(POLL).await;
            }
        })
        .await
    }

    /// Until the running ser2net listens on the port.
    async fn listening(&self) {
        while !self.owns_listener() {
            tokio::time::sleep(POLL).await;
        }
    }

    /// Whether a socket listening on the port is one of the running ser2net's descriptors.
    fn owns_listener(&self) -> bool {
        let Some(child) = &self.child else {
            return false;
        };
        let Some(inode) = listening_inode(self.addr) else {
            return false;
        };
        let socket = format!("socket:[{inode}]");
        let Ok(fds) = std::fs::read_dir(format!("/proc/{}/fd", child.id())) else {
            return false;
        };
        fds.flatten().any(|fd| {
            std::fs::read_link(fd.path()).is_ok_and(|target| target.as_os_str() == &*socket)
        })
    }

    fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

impl Drop for Ser2net {
    fn drop(&mut self) {
        self.kill();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Debian's /usr/sbin/ser2net (a user's PATH may not have /usr/sbin), else one on the PATH; if
/// neither, what [`tool`] does for a missing tool.
fn ser2net_program() -> Option<PathBuf> {
    let sbin = PathBuf::from("/usr/sbin/ser2net");
    if sbin.is_file() {
        return Some(sbin);
    }
    tool("ser2net")
}

/// ser2net's YAML: one connection from a loopback TCP port to `device`. `local`: ignore the modem
/// lines (a pty has none); the accepter is retried every second should its bind fail.
fn config(device: &str, settings: &str, accepter: Accepter, port: u16) -> String {
    let stack = match accepter {
        Accepter::Raw => "",
        Accepter::Rfc2217 => "telnet(rfc2217),",
    };
    format!(
        "%YAML 1.1\n---\nconnection: &line\n  accepter: {stack}tcp,127.0.0.1,{port}\n  \
         connector: serialdev,{device},{settings},local\n  options:\n    \
         accepter-retry-time: 1\n"
    )
}

/// The inode of the socket listening on `addr` (IPv4), from `/proc/net/tcp`.
fn listening_inode(addr: SocketAddr) -> Option<String> {
    // Fields: sl, local address (hex IP in host order : hex port), remote address, state (0A is
    // LISTEN), queues, timer, retransmits, uid, timeout, inode.
    let SocketAddr::V4(v4) = addr else {
        return None;
    };
    let local = format!(
        "{:08X}:{:04X}",
        u32::from_ne_bytes(v4.ip().octets()),
        v4.port()
    );
    let table = std::fs::read_to_string("/proc/net/tcp").ok()?;
    table.lines().skip(1).find_map(|line| {
        let fields: Vec<&str> = line.split_whitespace().collect();
        (fields.get(1) == Some(&local.as_str()) && fields.get(3) == Some(&"0A"))
            .then(|| fields.get(9).map(|inode| (*inode).to_owned()))
            .flatten()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_config_names_the_accepter_stack_the_port_and_the_device() {
        assert_eq!(
            config("/dev/pts/7", "9600n81", Accepter::Rfc2217, 4001),
            "%YAML 1.1\n---\nconnection: &line\n  accepter: telnet(rfc2217),tcp,127.0.0.1,4001\n  \
             connector: serialdev,/dev/pts/7,9600n81,local\n  options:\n    \
             accepter-retry-time: 1\n"
        );
        assert!(config("/dev/pts/7", "9600n81", Accepter::Raw, 4001)
            .contains("  accepter: tcp,127.0.0.1,4001\n"));
    }

    #[test]
    fn a_listener_of_this_process_is_found_in_the_kernels_table() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let inode = listening_inode(addr).expect("the listener is in /proc/net/tcp");
        let socket = format!("socket:[{inode}]");
        let ours = std::fs::read_dir("/proc/self/fd")
            .unwrap()
            .flatten()
            .any(|fd| std::fs::read_link(fd.path()).is_ok_and(|t| t.as_os_str() == &*socket));
        assert!(ours, "{socket} is one of this process's descriptors");
        drop(listener);
        assert_eq!(listening_inode(addr), None, "closed: no longer listening");
    }
}
