//! mosquitto (Debian bookworm's 2.0.11) as the tests' MQTT broker, and its clients as the far
//! side the tests read and write through: `mosquitto_sub` as a [`Subscriber`] that collects what
//! is published, `mosquitto_pub` as [`publish`].
//!
//! A [`Broker`] listens on a free loopback port with a config of its own in a temp dir:
//! anonymous ([`Broker::start`]), with a password file ([`Broker::with_password`]), or on TLS with
//! a server certificate of the test's [`Pki`] and a password file ([`Broker::with_tls`]). It is up
//! when its log says `mosquitto version … running` (said once every listener is bound); a port
//! taken between choosing and binding it is `Error: Address already in use` and an exit, and
//! another port is tried. The clients get the broker's port, credentials and CA from the `Broker`.
//!
//! A [`Subscriber`] is ready once subscribed: mosquitto_sub says nothing when its SUBACK comes,
//! so it also subscribes to a probe topic of its own (under `$mbgw-probe/`, which no `#` matches)
//! and publishes probes there until one comes back; the probes are not among its messages.
//!
//! What mosquitto 2.0 does that a test must know:
//! - a config with a `listener` admits no anonymous client unless it says `allow_anonymous true`;
//! - `log_type` takes one type a line: `log_type error warning` on one line silently logs nothing;
//! - started as root it becomes the `mosquitto` user before it reads the password file (and
//!   exits if it cannot), which under a umask of 077, or in a temp dir only root may enter, it
//!   cannot: the config says `user root` (ignored when not started as root), and its log then
//!   says `Warning: Mosquitto should not be run as root/administrator.`, harmlessly;
//! - its listening socket has SO_REUSEADDR: killed, its port can be bound again at once;
//! - with MQTT 3.1.1 (the clients' default) a message has the retain flag only when it comes from
//!   the retained store, at a new subscription: one published retained while a client is
//!   subscribed reaches that client with the flag clear;
//! - mosquitto_sub reconnects to a broker killed and started again about a second after it is
//!   back, and subscribes again (a clean session): what was published before that is lost to it
//!   ([`Subscriber::until_subscribed`] waits for it).

use crate::process::tool;
use crate::tls::Pki;
use crate::wait::PATIENCE;
use std::ffi::OsString;
use std::io::{BufRead, BufReader, Read};
use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::time::Instant;

/// Ports tried before a start gives up, each chosen free a moment before mosquitto binds it.
const PORT_ATTEMPTS: usize = 10;
/// How often a wait looks again.
const POLL: Duration = Duration::from_millis(10);
/// How long a subscriber waits for one probe before it publishes another.
const PROBE_EVERY: Duration = Duration::from_millis(200);
/// mosquitto's line for a listener it could not bind (then it exits).
const BIND_FAILED: &str = "Error: Address already in use";
/// Where the subscribers' probes go: a topic starting with `$` matches no `#` or `+` filter.
const PROBE_PREFIX: &str = "$mbgw-probe/";
/// mosquitto_sub's output format: retained flag (0/1), topic, payload as hex (so that a payload
/// with a newline or a tab is still one line), tab separated.
const FORMAT: &str = "%r\t%t\t%x";

/// Temp directories, client ids and probe topics of this process's fixtures, told apart.
static STARTED: AtomicUsize = AtomicUsize::new(0);

/// The programs a broker and its clients run.
#[derive(Clone)]
struct Programs {
    mosquitto: PathBuf,
    sub: PathBuf,
    publish: PathBuf,
}

impl Programs {
    /// mosquitto and its clients; `None` (see [`tool`]) if one is missing.
    fn find() -> Option<Programs> {
        Some(Programs {
            mosquitto: mosquitto_program()?,
            sub: tool("mosquitto_sub")?,
            publish: tool("mosquitto_pub")?,
        })
    }
}

/// How a client reaches the broker: mosquitto_pub with the broker's address, credentials and CA.
#[derive(Clone)]
struct Client {
    publish: PathBuf,
    /// `-h`, `-p`, and `-u`/`-P`, `--cafile` when the broker wants them.
    args: Vec<OsString>,
}

impl Client {
    /// Run mosquitto_pub (QoS 1: it exits once the broker has the message) and wait for its exit,
    /// bounded; its status and what it printed.
    fn publish(
        &self,
        topic: &str,
        payload: &str,
        retain: bool,
    ) -> (std::process::ExitStatus, String) {
        let mut command = Command::new(&self.publish);
        command.args(&self.args).args(["-q", "1", "-t", topic]);
        if payload.is_empty() {
            command.arg("-n");
        } else {
            command.args(["-m", payload]);
        }
        if retain {
            command.arg("-r");
        }
        let mut child = command
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("mosquitto_pub starts");
        // Blocking, on the real clock (a test's paused tokio clock would not move): PATIENCE in
        // sleeps of POLL.
        let mut polls = 0..PATIENCE.as_millis() / POLL.as_millis();
        let status = loop {
            if let Some(status) = child.try_wait().expect("wait for mosquitto_pub") {
                break status;
            }
            if polls.next().is_none() {
                let _ = child.kill();
                let _ = child.wait();
                panic!("mosquitto_pub to {topic:?}: no exit within {PATIENCE:?}");
            }
            std::thread::sleep(POLL);
        };
        let mut errors = String::new();
        if let Some(mut stderr) = child.stderr.take() {
            let _ = stderr.read_to_string(&mut errors);
        }
        (status, errors)
    }
}

/// The broker's listener and who may connect.
struct Setup {
    /// `(CA, certificate, key)` in the broker's dir: a TLS listener.
    tls: Option<(PathBuf, PathBuf, PathBuf)>,
    /// `(user, password)`, also in the broker's password file: no anonymous clients.
    credentials: Option<(String, String)>,
}

/// A running mosquitto on a loopback port, with its own config in a temp dir; killed when
/// dropped.
pub struct Broker {
    programs: Programs,
    setup: Setup,
    addr: SocketAddr,
    dir: PathBuf,
    config: PathBuf,
    child: Option<Child>,
    /// What mosquitto logged, over all its starts.
    log: Arc<Mutex<String>>,
}

/// What came of one start of mosquitto.
enum Started {
    Running,
    PortTaken,
}

impl Broker {
    /// A broker that admits anonymous clients, once it accepts connections; `None` without
    /// mosquitto and its clients (what [`tool`] does for a missing tool).
    pub async fn start() -> Option<Broker> {
        let programs = Programs::find()?;
        let broker = Broker::new(programs, |_| Setup {
            tls: None,
            credentials: None,
        });
        Some(broker.listen().await)
    }

    /// A broker that admits only `user` with `password` (its password file made by
    /// `mosquitto_passwd`), once it accepts connections; `None` without mosquitto and its
    /// clients.
    pub async fn with_password(user: &str, password: &str) -> Option<Broker> {
        let programs = Programs::find()?;
        let passwd = tool("mosquitto_passwd")?;
        let broker = Broker::new(programs, |dir| {
            write_password_file(&passwd, dir, user, password);
            Setup {
                tls: None,
                credentials: Some((user.to_owned(), password.to_owned())),
            }
        });
        Some(broker.listen().await)
    }

    /// A broker on TLS only (a server certificate for localhost and 127.0.0.1 issued by `pki`)
    /// that admits only `user` with `password`, once it accepts connections; `None` without
    /// mosquitto and its clients. The CA and the certificate are copied into the broker's own
    /// dir: `pki` may be dropped before the broker.
    pub async fn with_tls(pki: &Pki, user: &str, password: &str) -> Option<Broker> {
        let programs = Programs::find()?;
        let passwd = tool("mosquitto_passwd")?;
        let broker = Broker::new(programs, |dir| {
            write_password_file(&passwd, dir, user, password);
            let file = format!("mosquitto-{}", STARTED.fetch_add(1, Ordering::Relaxed));
            let server = pki.server(&file, "localhost", 365);
            let copy = |from: &Path, name: &str| {
                let to = dir.join(name);
                std::fs::copy(from, &to).expect("copy a TLS file into the broker's dir");
                to
            };
            Setup {
                tls: Some((
                    copy(&pki.ca_path, "ca.crt"),
                    copy(&server.cert_path, "server.crt"),
                    copy(&server.key_path, "server.key"),
                )),
                credentials: Some((user.to_owned(), password.to_owned())),
            }
        });
        Some(broker.listen().await)
    }

    /// A broker not started yet, its dir made and set up by `setup`.
    fn new(programs: Programs, setup: impl FnOnce(&Path) -> Setup) -> Broker {
        let dir = std::env::temp_dir().join(format!(
            "mbgw-mosquitto-{}-{}",
            std::process::id(),
            STARTED.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("a temp dir for mosquitto's config");
        Broker {
            programs,
            setup: setup(&dir),
            addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            config: dir.join("mosquitto.conf"),
            dir,
            child: None,
            log: Arc::default(),
        }
    }

    /// Start on a free port (another if mosquitto finds it taken), once it accepts connections.
    async fn listen(mut self) -> Broker {
        for _ in 0..PORT_ATTEMPTS {
            let port = TcpListener::bind("127.0.0.1:0")
                .and_then(|listener| listener.local_addr())
                .expect("a free loopback port")
                .port();
            self.addr.set_port(port);
            let password_file = self
                .setup
                .credentials
                .is_some()
                .then(|| self.dir.join("passwd"));
            let tls = self
                .setup
                .tls
                .as_ref()
                .map(|(ca, cert, key)| (ca.as_path(), cert.as_path(), key.as_path()));
            std::fs::write(&self.config, config(port, password_file.as_deref(), tls))
                .expect("write mosquitto's config");
            match self.run().await {
                Started::Running => return self,
                Started::PortTaken => self.kill(),
            }
        }
        panic!("mosquitto found no free port in {PORT_ATTEMPTS} attempts");
    }

    /// Where the broker listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The broker as a gateway's `[mqtt]` `broker` names it: `mqtt://127.0.0.1:PORT`, or
    /// `mqtts://127.0.0.1:PORT` on TLS.
    pub fn url(&self) -> String {
        let scheme = if self.setup.tls.is_some() {
            "mqtts"
        } else {
            "mqtt"
        };
        format!("{scheme}://{}", self.addr)
    }

    /// On TLS, the CA that signed the broker's certificate (a copy in the broker's dir).
    pub fn ca_file(&self) -> Option<&Path> {
        self.setup.tls.as_ref().map(|(ca, _, _)| ca.as_path())
    }

    /// What mosquitto logged so far, over all its starts: connections, subscriptions, errors.
    pub fn log(&self) -> String {
        self.log.lock().expect("the broker's log").clone()
    }

    /// Kill the broker (SIGKILL, as a crash would): its clients' connections drop, its port stops
    /// listening, and what it held (retained messages, sessions) is gone.
    pub fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Start the broker again with the same config, on the same port, once it accepts
    /// connections (killing it first if it runs). Its clients find it again by themselves.
    pub async fn start_again(&mut self) {
        self.kill();
        let deadline = Instant::now() + PATIENCE;
        // The port was this broker's a moment ago: a bind failure now is someone's passing use of
        // it, so try again, bounded.
        while let Started::PortTaken = self.run().await {
            assert!(
                Instant::now() < deadline,
                "mosquitto could not bind {} again within {PATIENCE:?}:\n{}",
                self.addr,
                self.log()
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Spawn mosquitto on the config and wait until it runs or says its port is taken.
    async fn run(&mut self) -> Started {
        let since = self.log().len();
        let mut child = Command::new(&self.programs.mosquitto)
            .arg("-c")
            .arg(&self.config)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("mosquitto starts");
        if let Some(stdout) = child.stdout.take() {
            collect_lines(stdout, Arc::clone(&self.log));
        }
        if let Some(stderr) = child.stderr.take() {
            collect_lines(stderr, Arc::clone(&self.log));
        }
        self.child = Some(child);
        let deadline = Instant::now() + PATIENCE;
        loop {
            let log = self.log();
            let this_start = log.get(since..).unwrap_or_default();
            if this_start.lines().any(is_running_line) {
                return Started::Running;
            }
            let child = self.child.as_mut().expect("just spawned");
            if let Ok(Some(status)) = child.try_wait() {
                // Its last lines may still be in the pipe: the readers end at its exit.
                tokio::time::sleep(Duration::from_millis(50)).await;
                let log = self.log();
                if log.get(since..).unwrap_or_default().contains(BIND_FAILED) {
                    self.child = None;
                    return Started::PortTaken;
                }
                panic!("mosquitto exited ({status}):\n{log}");
            }
            assert!(
                Instant::now() < deadline,
                "mosquitto on {}: not running within {PATIENCE:?}:\n{log}",
                self.addr
            );
            tokio::time::sleep(POLL).await;
        }
    }

    /// How mosquitto_pub reaches this broker.
    fn client(&self) -> Client {
        Client {
            publish: self.programs.publish.clone(),
            args: self.client_args(),
        }
    }

    /// The options that take a mosquitto client to this broker.
    fn client_args(&self) -> Vec<OsString> {
        let mut args: Vec<OsString> = vec![
            "-h".into(),
            self.addr.ip().to_string().into(),
            "-p".into(),
            self.addr.port().to_string().into(),
        ];
        if let Some((user, password)) = &self.setup.credentials {
            args.extend(["-u".into(), user.into(), "-P".into(), password.into()]);
        }
        if let Some(ca) = self.ca_file() {
            args.extend(["--cafile".into(), ca.as_os_str().to_owned()]);
        }
        args
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.kill();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Publish `payload` (empty: a zero-length message, which `retain` makes the clearing of a
/// retained message) to `topic` with mosquitto_pub, at QoS 1 and as the broker's user if it has
/// one; returns once the broker has it, and panics if mosquitto_pub fails.
pub fn publish(broker: &Broker, topic: &str, payload: &str, retain: bool) {
    let (status, errors) = broker.client().publish(topic, payload, retain);
    assert!(
        status.success(),
        "mosquitto_pub to {topic:?} failed ({status}): {errors}\nthe broker's log:\n{}",
        broker.log()
    );
}

/// One message as a subscriber received it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Message {
    /// The topic it was published to (not the filter that matched it).
    pub topic: String,
    /// The payload as text (bytes that are not UTF-8 replaced).
    pub payload: String,
    /// The retain flag as delivered: set only for a message from the retained store (see the
    /// module's notes).
    pub retained: bool,
}

/// A `mosquitto_sub` subscribed to topic filters on a broker, collecting what it receives;
/// killed when dropped. It does not borrow the broker, which may be killed and started again
/// under it.
pub struct Subscriber {
    child: Mutex<Child>,
    client: Client,
    probe_topic: String,
    messages: Arc<Mutex<Vec<Message>>>,
    probes: Arc<AtomicUsize>,
    /// What mosquitto_sub printed on its standard error, and lines of its output not understood.
    errors: Arc<Mutex<String>>,
}

impl Subscriber {
    /// mosquitto_sub subscribed (QoS 1) to `filters` on `broker`, as the broker's user if it has
    /// one, once the subscriptions hold (retained messages they match are then already in, or on
    /// their way in before anything published later).
    pub async fn start(broker: &Broker, filters: &[&str]) -> Subscriber {
        let n = STARTED.fetch_add(1, Ordering::Relaxed);
        let id = format!("mbgw-sub-{}-{n}", std::process::id());
        let probe_topic = format!("{PROBE_PREFIX}{id}");
        let mut command = Command::new(&broker.programs.sub);
        command
            .args(broker.client_args())
            .args(["-q", "1", "-i", &id, "-F", FORMAT]);
        // The probe's filter last: mosquitto_sub sends all filters in one SUBSCRIBE, so a probe
        // that comes back means every filter before it holds.
        for filter in filters.iter().copied().chain([probe_topic.as_str()]) {
            command.args(["-t", filter]);
        }
        let mut child = command
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("mosquitto_sub starts");
        let messages = Arc::<Mutex<Vec<Message>>>::default();
        let probes = Arc::new(AtomicUsize::new(0));
        let errors = Arc::<Mutex<String>>::default();
        if let Some(stderr) = child.stderr.take() {
            collect_lines(stderr, Arc::clone(&errors));
        }
        if let Some(stdout) = child.stdout.take() {
            let (messages, probes, errors) = (
                Arc::clone(&messages),
                Arc::clone(&probes),
                Arc::clone(&errors),
            );
            std::thread::spawn(move || {
                for line in BufReader::new(stdout).lines() {
                    let Ok(line) = line else { return };
                    match parse_line(&line) {
                        Some(message) if message.topic.starts_with(PROBE_PREFIX) => {
                            probes.fetch_add(1, Ordering::Relaxed);
                        }
                        Some(message) => messages.lock().expect("messages").push(message),
                        None => {
                            let mut errors = errors.lock().expect("errors");
                            errors.push_str("not understood: ");
                            errors.push_str(&line);
                            errors.push('\n');
                        }
                    }
                }
            });
        }
        let subscriber = Subscriber {
            child: Mutex::new(child),
            client: broker.client(),
            probe_topic,
            messages,
            probes,
            errors,
        };
        subscriber.until_subscribed().await;
        subscriber
    }

    /// Wait (bounded) until the subscriptions hold: a probe published now comes back. After the
    /// broker is started again, this is when mosquitto_sub is back on it.
    pub async fn until_subscribed(&self) {
        let seen = self.probes.load(Ordering::Relaxed);
        let deadline = Instant::now() + PATIENCE;
        loop {
            // A broker not back yet refuses the probe: the next one is tried.
            let _ = self.client.publish(&self.probe_topic, "probe", false);
            let sent = Instant::now();
            while sent.elapsed() < PROBE_EVERY {
                if self.probes.load(Ordering::Relaxed) > seen {
                    return;
                }
                self.assert_running();
                tokio::time::sleep(POLL).await;
            }
            assert!(
                Instant::now() < deadline,
                "mosquitto_sub: not subscribed within {PATIENCE:?}: {}",
                self.errors()
            );
        }
    }

    /// The messages received so far (the probes left out), oldest first.
    pub fn messages(&self) -> Vec<Message> {
        self.messages.lock().expect("messages").clone()
    }

    /// Forget the messages received so far.
    pub fn clear(&self) {
        self.messages.lock().expect("messages").clear();
    }

    /// Wait (bounded) until the messages received so far satisfy `pred`; those messages. `what`
    /// names the wait in the panic of one that never ends.
    pub async fn until(&self, what: &str, pred: impl Fn(&[Message]) -> bool) -> Vec<Message> {
        let deadline = Instant::now() + PATIENCE;
        loop {
            let messages = self.messages();
            if pred(&messages) {
                return messages;
            }
            assert!(
                Instant::now() < deadline,
                "{what}: not within {PATIENCE:?}; received: {messages:#?}\n{}",
                self.errors()
            );
            self.assert_running();
            tokio::time::sleep(POLL).await;
        }
    }

    /// Wait (bounded) for a message on `topic` (exactly: not a filter); the first one received.
    pub async fn first_on(&self, topic: &str) -> Message {
        let messages = self
            .until(&format!("a message on {topic:?}"), |messages| {
                messages.iter().any(|message| message.topic == topic)
            })
            .await;
        messages
            .into_iter()
            .find(|message| message.topic == topic)
            .expect("until found it")
    }

    /// What mosquitto_sub printed on its standard error, and output lines not understood.
    pub fn errors(&self) -> String {
        self.errors.lock().expect("errors").clone()
    }

    /// Panic if mosquitto_sub has exited (refused, or a TLS handshake failed).
    fn assert_running(&self) {
        let mut child = self.child.lock().expect("the child");
        if let Ok(Some(status)) = child.try_wait() {
            // Its last words may still be in the pipe.
            std::thread::sleep(Duration::from_millis(50));
            panic!("mosquitto_sub exited ({status}): {}", self.errors());
        }
    }
}

impl Drop for Subscriber {
    fn drop(&mut self) {
        if let Ok(child) = self.child.get_mut() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Append each line of `stream` to `into`, on a thread of its own, until the stream ends.
fn collect_lines(stream: impl Read + Send + 'static, into: Arc<Mutex<String>>) {
    std::thread::spawn(move || {
        for line in BufReader::new(stream).lines() {
            let Ok(line) = line else { return };
            let mut into = into.lock().expect("collected lines");
            into.push_str(&line);
            into.push('\n');
        }
    });
}

/// Whether a log line is mosquitto's `TIME: mosquitto version 2.0.11 running`, its last at a
/// start, said once every listener is bound.
fn is_running_line(line: &str) -> bool {
    line.contains(": mosquitto version ") && line.ends_with(" running")
}

/// A line of mosquitto_sub's [`FORMAT`] as a message; `None` if it is not one.
fn parse_line(line: &str) -> Option<Message> {
    let mut fields = line.splitn(3, '\t');
    let retained = match fields.next()? {
        "0" => false,
        "1" => true,
        _ => return None,
    };
    let topic = fields.next()?.to_owned();
    let hex = fields.next()?;
    let bytes = (0..hex.len())
        .step_by(2)
        .map(|at| u8::from_str_radix(hex.get(at..at + 2)?, 16).ok())
        .collect::<Option<Vec<u8>>>()?;
    Some(Message {
        topic,
        payload: String::from_utf8_lossy(&bytes).into_owned(),
        retained,
    })
}

/// mosquitto's config: one listener on 127.0.0.1:`port`, anonymous clients unless there is a
/// `password_file`, TLS with `tls` (CA, certificate, key), nothing kept on disk, every log line
/// of interest on standard error.
fn config(port: u16, password_file: Option<&Path>, tls: Option<(&Path, &Path, &Path)>) -> String {
    // Started as root, mosquitto would become the `mosquitto` user before reading the password
    // file, which root's umask or temp dir may keep from that user.
    let mut config = format!("user root\npersistence false\nlistener {port} 127.0.0.1\n");
    if let Some((ca, cert, key)) = tls {
        config.push_str(&format!(
            "cafile {}\ncertfile {}\nkeyfile {}\n",
            ca.display(),
            cert.display(),
            key.display()
        ));
    }
    match password_file {
        Some(file) => config.push_str(&format!(
            "allow_anonymous false\npassword_file {}\n",
            file.display()
        )),
        None => config.push_str("allow_anonymous true\n"),
    }
    config.push_str("log_dest stderr\n");
    // One type a line: several on one line log nothing at all.
    for kind in [
        "error",
        "warning",
        "notice",
        "information",
        "subscribe",
        "unsubscribe",
    ] {
        config.push_str(&format!("log_type {kind}\n"));
    }
    config
}

/// `user`'s password file for mosquitto, `passwd` in `dir`, by `mosquitto_passwd -b -c`.
fn write_password_file(passwd: &Path, dir: &Path, user: &str, password: &str) {
    let output = Command::new(passwd)
        .args(["-b", "-c"])
        .arg(dir.join("passwd"))
        .args([user, password])
        .stdin(Stdio::null())
        .output()
        .expect("mosquitto_passwd runs");
    assert!(
        output.status.success(),
        "mosquitto_passwd failed ({}): {}",
        output.status,
        String::from_utf8_lossy(&output.stderr)
    );
}

/// Debian's /usr/sbin/mosquitto (a user's PATH may not have /usr/sbin), else one on the PATH; if
/// neither, what [`tool`] does for a missing tool.
fn mosquitto_program() -> Option<PathBuf> {
    let sbin = PathBuf::from("/usr/sbin/mosquitto");
    if sbin.is_file() {
        return Some(sbin);
    }
    tool("mosquitto")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_of_the_format_is_a_message_with_its_payload_decoded() {
        assert_eq!(
            parse_line("1\tplant/bus1/3/power\t31322e35"),
            Some(Message {
                topic: "plant/bus1/3/power".into(),
                payload: "12.5".into(),
                retained: true,
            })
        );
        let multiline = parse_line("0\ta b\t780a79").expect("a message");
        assert_eq!(
            (multiline.payload.as_str(), multiline.retained),
            ("x\ny", false)
        );
        assert_eq!(
            parse_line("0\tempty\t").map(|m| m.payload),
            Some(String::new())
        );
        assert_eq!(parse_line("0\tt\t7"), None, "an odd number of hex digits");
        assert_eq!(parse_line("Connection error"), None);
    }

    #[test]
    fn the_config_names_the_listener_the_password_file_and_the_tls_files() {
        let plain = config(18830, None, None);
        assert!(plain.contains("listener 18830 127.0.0.1\n"), "{plain}");
        assert!(plain.contains("allow_anonymous true\n"), "{plain}");
        assert!(!plain.contains("cafile"), "{plain}");
        let tls = config(
            18831,
            Some(Path::new("/d/passwd")),
            Some((
                Path::new("/d/ca.crt"),
                Path::new("/d/s.crt"),
                Path::new("/d/s.key"),
            )),
        );
        for line in [
            "allow_anonymous false\n",
            "password_file /d/passwd\n",
            "cafile /d/ca.crt\n",
            "certfile /d/s.crt\n",
            "keyfile /d/s.key\n",
        ] {
            assert!(tls.contains(line), "{line:?} in {tls}");
        }
    }

    #[tokio::test]
    async fn a_retained_message_arrives_retained_and_a_live_one_not() {
        let Some(broker) = Broker::start().await else {
            return;
        };
        assert_eq!(broker.url(), format!("mqtt://{}", broker.addr()));
        assert_eq!(broker.ca_file(), None);
        publish(&broker, "plant/old", "before", true);
        let subscriber = Subscriber::start(&broker, &["plant/#"]).await;
        let old = subscriber.first_on("plant/old").await;
        assert_eq!((old.payload.as_str(), old.retained), ("before", true));
        publish(&broker, "plant/new", "live", false);
        publish(&broker, "plant/kept", "live and kept", true);
        let messages = subscriber
            .until("both live messages", |messages| messages.len() == 3)
            .await;
        assert_eq!(
            messages[1..],
            [
                Message {
                    topic: "plant/new".into(),
                    payload: "live".into(),
                    retained: false
                },
                Message {
                    topic: "plant/kept".into(),
                    payload: "live and kept".into(),
                    retained: false
                },
            ],
            "a message to a subscription that holds has no retain flag"
        );
        assert!(
            broker.log().contains(" 1 plant/#"),
            "the subscription is in the log:\n{}",
            broker.log()
        );
    }

    #[tokio::test]
    async fn with_a_password_file_the_user_gets_the_messages() {
        let Some(broker) = Broker::with_password("gateway", "s3cret words").await else {
            return;
        };
        let subscriber = Subscriber::start(&broker, &["a/b", "c/+"]).await;
        publish(&broker, "c/d", "{\"v\": 1}", false);
        publish(&broker, "a/b", "", false);
        let messages = subscriber
            .until("two messages", |messages| messages.len() == 2)
            .await;
        assert_eq!(messages[0].payload, "{\"v\": 1}");
        assert_eq!(
            (messages[1].topic.as_str(), messages[1].payload.as_str()),
            ("a/b", "")
        );
        assert!(broker.log().contains("as mbgw-sub-"), "{}", broker.log());
    }

    #[tokio::test]
    async fn anonymous_clients_are_refused_by_a_broker_with_a_password_file() {
        let Some(broker) = Broker::with_password("gateway", "secret").await else {
            return;
        };
        let mut anonymous = broker.client();
        anonymous.args.truncate(4);
        let (status, errors) = anonymous.publish("a/b", "x", false);
        assert!(!status.success(), "refused: {errors}");
    }

    #[tokio::test]
    #[should_panic(expected = "not authorised")]
    async fn a_subscriber_with_a_wrong_password_fails_with_mosquitto_subs_words() {
        let Some(mut broker) = Broker::with_password("gateway", "secret").await else {
            // Nothing to check without mosquitto: the panic the test expects.
            panic!("not authorised (no mosquitto here)");
        };
        broker.setup.credentials = Some(("gateway".into(), "wrong".into()));
        Subscriber::start(&broker, &["a/b"]).await;
    }

    #[tokio::test]
    async fn over_tls_the_user_gets_the_messages() {
        let pki = Pki::new("mqtt-ca");
        let Some(broker) = Broker::with_tls(&pki, "gateway", "secret").await else {
            return;
        };
        drop(pki);
        assert_eq!(broker.url(), format!("mqtts://{}", broker.addr()));
        let ca = broker.ca_file().expect("a CA on TLS");
        assert!(ca.is_file());
        publish(&broker, "tls/kept", "1", true);
        let subscriber = Subscriber::start(&broker, &["tls/#"]).await;
        publish(&broker, "tls/live", "2", false);
        let messages = subscriber
            .until("both messages", |messages| messages.len() == 2)
            .await;
        assert_eq!(
            messages
                .iter()
                .map(|m| (m.topic.as_str(), m.payload.as_str(), m.retained))
                .collect::<Vec<_>>(),
            [("tls/kept", "1", true), ("tls/live", "2", false)]
        );
    }

    #[tokio::test]
    async fn a_subscriber_is_back_on_a_broker_started_again() {
        let Some(mut broker) = Broker::start().await else {
            return;
        };
        let addr = broker.addr();
        let subscriber = Subscriber::start(&broker, &["x"]).await;
        broker.kill();
        assert!(
            std::net::TcpStream::connect(addr).is_err(),
            "killed: no listener"
        );
        broker.start_again().await;
        assert_eq!(broker.addr(), addr);
        subscriber.until_subscribed().await;
        publish(&broker, "x", "after", false);
        assert_eq!(subscriber.first_on("x").await.payload, "after");
    }
}
