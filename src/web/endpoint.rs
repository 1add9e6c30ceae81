//! The HTTP endpoint on `metrics.listen`: `/` (the status page), `/status` (its data, JSON),
//! `/values` (the plant values, JSON), `/metrics` (Prometheus text format), `/healthz` (the
//! process answers), `/readyz` (every bus has its port open, else 503 naming those that have not)
//! and `/trace` (the live trace of the lines, `sse`). HTTP/1.1 by hyper.
//!
//! The endpoint keeps room for Prometheus whatever the other clients do. It holds
//! [`MAX_CONNECTIONS`] connections; at most [`MAX_READERS`] of them stream the trace (a stream
//! whose reader stops reading is dropped, `sse`), so the others are only for requests
//! that are answered at once. A connection that has not sent a whole request yet (a silent one
//! is closed after [`FIRST_BYTE_TIMEOUT`], an unfinished request head after [`HEADER_TIMEOUT`]),
//! or whose answer has been going out for over [`ANSWER_GRACE`], holds its place only until a
//! newcomer needs it: when the endpoint is full the newcomer takes the place of the one that has
//! waited longest, silent ones first ([`Connections::admit`]). A scrape, which sends its request
//! as soon as it connects, is therefore never kept out by silent sockets or stalled trace
//! readers. One request per connection (no keep-alive), so an answered connection holds no
//! place. Every socket gets TCP keepalive probes, so a peer that vanished is noticed, and a
//! fixed send buffer ([`SEND_BUFFER`]), so a client that stops reading is soon blocked.

use super::{sse, status, Inspect, StatusSource};
use crate::metrics::Metrics;
use crate::trace::MAX_READERS;
use base64::prelude::{Engine, BASE64_STANDARD};
use bytes::Bytes;
use http_body_util::{Either, Full};
use hyper::body::Incoming;
use hyper::header::{
    HeaderValue, ALLOW, CACHE_CONTROL, CONTENT_SECURITY_POLICY, CONTENT_TYPE,
    X_CONTENT_TYPE_OPTIONS,
};
use hyper::service::service_fn;
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::{TokioIo, TokioTimer};
use std::collections::BTreeMap;
use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::time::Duration;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Notify;
use tokio::time::Instant;
use tracing::{debug, warn};

/// HTTP connections open at once, trace streams included.
const MAX_CONNECTIONS: usize = 16;
/// The trace's streams leave half the places to requests answered at once.
const _: () = assert!(MAX_READERS * 2 <= MAX_CONNECTIONS);
/// A client must send its first byte within this: Prometheus, curl and browsers send their
/// request as soon as they have connected.
const FIRST_BYTE_TIMEOUT: Duration = Duration::from_secs(2);
/// A client must send its request headers within this, from its first byte.
const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// An answer still going out after this (its client reads slowly or not at all) no longer
/// protects its connection from being closed to make room; rendering `/metrics` takes
/// milliseconds.
const ANSWER_GRACE: Duration = Duration::from_secs(2);
/// A connection is closed after this, unless it streams the trace (one that is still being
/// answered has a client that does not read).
const CONNECTION_LIFETIME: Duration = Duration::from_secs(120);
/// Silence before the first TCP keepalive probe of a client.
const TCP_KEEPALIVE: Duration = Duration::from_secs(60);
/// Each connection's socket send buffer (SO_SNDBUF; Linux doubles it, and no longer grows it up
/// to 4 MiB): a client that stops reading pins at most that much kernel memory, and its trace
/// stream blocks within seconds on a busy line, so that it is noticed. Plenty for answers on a
/// LAN.
const SEND_BUFFER: usize = 32 * 1024;
/// Pause after an accept error such as running out of file descriptors.
const ACCEPT_ERROR_PAUSE: Duration = Duration::from_millis(100);
const TEXT: &str = "text/plain; charset=utf-8";
const HTML: &str = "text/html; charset=utf-8";
const JSON: &str = "application/json";

struct State {
    metrics: Arc<Metrics>,
    gateway: Arc<dyn Inspect>,
    status: StatusSource,
    connections: Mutex<Connections>,
}

/// What a connection is doing, in the order in which it gives up its place to a newcomer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Phase {
    /// Connected, not a byte sent yet.
    Silent,
    /// Sending its request head.
    Asking,
    /// Its request is being answered (then it is closed: one request per connection).
    Answering,
    /// Streams the trace: never closed to make room (bounded in number instead).
    Streaming,
}

/// What to do with a newly accepted connection.
#[derive(Debug, PartialEq, Eq)]
enum Arrival {
    Admit,
    /// Admit it in the place of this connection, which is closed.
    Replace(u64),
    Refuse,
}

struct Open {
    phase: Phase,
    since: Instant,
    /// Told when the connection is to be closed: to make room, or its trace reader stalled.
    close: Arc<Notify>,
}

/// The endpoint's open connections by id (ids grow with each accept).
#[derive(Default)]
struct Connections {
    next: u64,
    open: BTreeMap<u64, Open>,
}

impl Connections {
    /// Whether a newcomer gets a place at `now`: a free one; else the place of the connection
    /// that has waited longest among the silent ones, then among those still sending their
    /// request, then among those whose answer has been going out for over [`ANSWER_GRACE`].
    /// Trace streams and fresh answers keep theirs.
    fn admit(&self, now: Instant) -> Arrival {
        if self.open.len() < MAX_CONNECTIONS {
            return Arrival::Admit;
        }
        self.open
            .iter()
            .filter(|(_, open)| match open.phase {
                Phase::Silent | Phase::Asking => true,
                Phase::Answering => now.saturating_duration_since(open.since) > ANSWER_GRACE,
                Phase::Streaming => false,
            })
            .min_by_key(|(id, open)| (open.phase, open.since, **id))
            .map_or(Arrival::Refuse, |(id, _)| Arrival::Replace(*id))
    }

    fn add(&mut self, phase: Phase, now: Instant) -> (u64, Arc<Notify>) {
        let id = self.next;
        self.next += 1;
        let close = Arc::new(Notify::new());
        let open = Open {
            phase,
            since: now,
            close: close.clone(),
        };
        self.open.insert(id, open);
        (id, close)
    }

    fn set(&mut self, id: u64, phase: Phase, now: Instant) {
        if let Some(open) = self.open.get_mut(&id) {
            open.phase = phase;
            open.since = now;
        }
    }

    fn phase(&self, id: u64) -> Option<Phase> {
        self.open.get(&id).map(|open| open.phase)
    }

    /// Forget connection `id`; its close handle, to tell it to close.
    fn remove(&mut self, id: u64) -> Option<Arc<Notify>> {
        self.open.remove(&id).map(|open| open.close)
    }
}

impl State {
    fn connections(&self) -> std::sync::MutexGuard<'_, Connections> {
        self.connections
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    fn set(&self, id: u64, phase: Phase) {
        self.connections().set(id, phase, Instant::now());
    }
}

/// Serve the endpoint on `listener` forever.
pub(crate) async fn serve(listener: TcpListener, metrics: Arc<Metrics>, gateway: Arc<dyn Inspect>) {
    let state = Arc::new(State {
        metrics,
        gateway,
        status: StatusSource::new(),
        connections: Mutex::new(Connections::default()),
    });
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(error) => {
                warn!(%error, "metrics endpoint: accept failed");
                tokio::time::sleep(ACCEPT_ERROR_PAUSE).await;
                continue;
            }
        };
        let phase = first_phase(&stream);
        let (id, close) = {
            let mut connections = state.connections();
            let now = Instant::now();
            match connections.admit(now) {
                Arrival::Admit => {}
                Arrival::Replace(old) => {
                    debug!(%peer, "metrics endpoint: full, closing the connection waiting longest");
                    if let Some(close) = connections.remove(old) {
                        close.notify_one();
                    }
                }
                Arrival::Refuse => {
                    debug!(%peer, "metrics endpoint: too many connections, closing");
                    continue;
                }
            }
            connections.add(phase, now)
        };
        let state = state.clone();
        tokio::spawn(async move {
            tokio::select! {
                () = connection(&state, id, stream, peer, close.clone()) => {}
                () = close.notified() => {
                    debug!(%peer, "metrics endpoint: connection closed to make room or stalled");
                }
            }
            state.connections().remove(id);
        });
    }
}

/// [`Phase::Asking`] if the client's first bytes are already here (a scrape's usually are by
/// the time it is accepted), else [`Phase::Silent`].
fn first_phase(stream: &TcpStream) -> Phase {
    let mut byte = [std::mem::MaybeUninit::<u8>::uninit()];
    match socket2::SockRef::from(stream).peek(&mut byte) {
        Ok(n) if n > 0 => Phase::Asking,
        _ => Phase::Silent,
    }
}

/// Serve one connection until it ends, its first byte or request head comes too late, or its
/// lifetime is over (unless it streams the trace).
async fn connection(
    state: &Arc<State>,
    id: u64,
    stream: TcpStream,
    peer: SocketAddr,
    close: Arc<Notify>,
) {
    if let Err(error) = crate::socket::set_keepalive(&stream, TCP_KEEPALIVE) {
        debug!(%peer, %error, "metrics endpoint: cannot set TCP keepalive");
    }
    if let Err(error) = socket2::SockRef::from(&stream).set_send_buffer_size(SEND_BUFFER) {
        debug!(%peer, %error, "metrics endpoint: cannot set the send buffer");
    }
    match tokio::time::timeout(FIRST_BYTE_TIMEOUT, stream.peek(&mut [0u8; 1])).await {
        Ok(Ok(n)) if n > 0 => state.set(id, Phase::Asking),
        Ok(_) => return,
        Err(_) => {
            debug!(%peer, "metrics endpoint: nothing sent within {FIRST_BYTE_TIMEOUT:?}, closing");
            return;
        }
    }
    let served = state.clone();
    let service = service_fn(move |request: Request<Incoming>| {
        let response = if request.uri().path() == "/trace" && request.method() == Method::GET {
            let response = sse::respond(
                &served.metrics.trace,
                request.uri().query(),
                peer,
                close.clone(),
            );
            let streams = response.status() == StatusCode::OK;
            served.set(
                id,
                if streams {
                    Phase::Streaming
                } else {
                    Phase::Answering
                },
            );
            response
        } else {
            served.set(id, Phase::Answering);
            respond(&served, &request).map(Either::Left)
        };
        async move { Ok::<_, Infallible>(response) }
    });
    // One request per connection: an answered connection does not linger holding a place.
    let connection = hyper::server::conn::http1::Builder::new()
        .keep_alive(false)
        .timer(TokioTimer::new())
        .header_read_timeout(HEADER_TIMEOUT)
        .serve_connection(TokioIo::new(stream), service);
    let mut connection = std::pin::pin!(connection);
    // A connection past its lifetime is simply dropped, unless it streams the trace.
    let ended = match tokio::time::timeout(CONNECTION_LIFETIME, connection.as_mut()).await {
        Ok(ended) => Some(ended),
        Err(_) if state.connections().phase(id) == Some(Phase::Streaming) => Some(connection.await),
        Err(_) => None,
    };
    if let Some(Err(error)) = ended {
        debug!(%peer, %error, "metrics endpoint: connection failed");
    }
}

fn response(status: StatusCode, content_type: &'static str, body: String) -> Response<Full<Bytes>> {
    let mut response = Response::new(Full::new(Bytes::from(body)));
    *response.status_mut() = status;
    response
        .headers_mut()
        .insert(CONTENT_TYPE, HeaderValue::from_static(content_type));
    response
}

/// The page's Content-Security-Policy: it loads nothing from elsewhere, talks only to this
/// endpoint, and runs only its own inline script and style, allowed by their SHA-256.
fn page_policy() -> &'static HeaderValue {
    static POLICY: OnceLock<HeaderValue> = OnceLock::new();
    POLICY.get_or_init(|| {
        let script = inline_hash(status::PAGE, "script");
        let style = inline_hash(status::PAGE, "style");
        let policy = format!(
            "default-src 'none'; connect-src 'self'; base-uri 'none'; form-action 'none'; \
             frame-ancestors 'none'; script-src {script}; style-src {style}"
        );
        HeaderValue::from_str(&policy).expect("a policy is printable ASCII")
    })
}

/// The content of the first `<tag>` element of `page` ("" if it has none).
fn inline<'a>(page: &'a str, tag: &str) -> &'a str {
    page.split_once(&format!("<{tag}>"))
        .and_then(|(_, rest)| rest.split_once(&format!("</{tag}>")))
        .map_or("", |(content, _)| content)
}

/// The CSP source (`'sha256-...'`) of the content of the first `<tag>` element of `page`.
fn inline_hash(page: &str, tag: &str) -> String {
    let content = inline(page, tag);
    let digest = ring::digest::digest(&ring::digest::SHA256, content.as_bytes());
    format!("'sha256-{}'", BASE64_STANDARD.encode(digest))
}

/// The status page, with a policy that lets it do nothing but run its own script.
fn status_page() -> Response<Full<Bytes>> {
    let mut page = response(StatusCode::OK, HTML, status::PAGE.to_owned());
    let headers = page.headers_mut();
    headers.insert(CONTENT_SECURITY_POLICY, page_policy().clone());
    headers.insert(X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    headers.insert(CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    page
}

/// `what` as JSON, or a 500 saying why it cannot be.
fn json(what: &str, value: &impl serde::Serialize) -> Response<Full<Bytes>> {
    match serde_json::to_string(value) {
        Ok(json) => response(StatusCode::OK, JSON, json),
        Err(error) => {
            warn!(%error, "cannot render the {what}");
            response(
                StatusCode::INTERNAL_SERVER_ERROR,
                TEXT,
                format!("cannot render the {what}: {error}\n"),
            )
        }
    }
}

/// `GET /values` with `query`.
fn values(state: &State, query: Option<&str>) -> Response<Full<Bytes>> {
    let buses: Vec<String> = state
        .gateway
        .buses()
        .iter()
        .map(|b| b.name().to_owned())
        .collect();
    match super::values::filter(query, &buses) {
        Ok(filter) => match state.gateway.values().listing(&filter) {
            Ok(json) => response(StatusCode::OK, JSON, json),
            Err(error) => response(
                StatusCode::INTERNAL_SERVER_ERROR,
                TEXT,
                format!("cannot render the values: {error}\n"),
            ),
        },
        Err((status, message)) => response(status, TEXT, message),
    }
}

fn respond(state: &State, request: &Request<Incoming>) -> Response<Full<Bytes>> {
    if !matches!(*request.method(), Method::GET | Method::HEAD) {
        let mut refused = response(
            StatusCode::METHOD_NOT_ALLOWED,
            TEXT,
            "only GET and HEAD\n".into(),
        );
        refused
            .headers_mut()
            .insert(ALLOW, HeaderValue::from_static("GET, HEAD"));
        return refused;
    }
    match request.uri().path() {
        "/" => status_page(),
        "/status" => json("status", &state.status.read(state.gateway.as_ref())),
        "/values" => values(state, request.uri().query()),
        "/metrics" => match state.metrics.render() {
            Ok(text) => response(StatusCode::OK, prometheus::TEXT_FORMAT, text),
            Err(error) => {
                warn!(%error, "cannot render the metrics");
                response(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    TEXT,
                    format!("cannot render the metrics: {error}\n"),
                )
            }
        },
        "/healthz" => response(StatusCode::OK, TEXT, "ok\n".into()),
        "/readyz" => {
            let down = super::not_ready(state.gateway.as_ref());
            if down.is_empty() {
                response(StatusCode::OK, TEXT, "ready\n".into())
            } else {
                let buses: String = down
                    .iter()
                    .map(|b| format!("bus {b}: port down\n"))
                    .collect();
                response(
                    StatusCode::SERVICE_UNAVAILABLE,
                    TEXT,
                    format!("not ready\n{buses}"),
                )
            }
        }
        _ => response(
            StatusCode::NOT_FOUND,
            TEXT,
            "not found; try / (the status page), /status, /values, /trace, /metrics, /healthz or \
             /readyz\n"
                .into(),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A full endpoint: 8 trace streams, and the other places in `phases`, the first opened
    /// first, each `since` one second after the previous from `start`.
    fn full(start: Instant, phases: &[Phase]) -> Connections {
        let mut connections = Connections::default();
        for _ in 0..MAX_READERS {
            connections.add(Phase::Streaming, start);
        }
        for (n, phase) in (0u32..).zip(phases) {
            connections.add(*phase, start + Duration::from_secs(n.into()));
        }
        assert_eq!(connections.open.len(), MAX_CONNECTIONS);
        connections
    }

    /// The place of the silent connection waiting longest.
    #[test]
    fn a_newcomer_gets_a_free_place_or_that_of_the_longest_silent_connection() {
        let start = Instant::now();
        let mut connections = Connections::default();
        connections.add(Phase::Silent, start);
        assert_eq!(connections.admit(start), Arrival::Admit);
        // Ids 8-15: an answer going out for long, an unfinished head, then silent ones.
        let mut phases = vec![Phase::Answering, Phase::Asking];
        phases.extend([Phase::Silent; 6]);
        let now = start + Duration::from_secs(60);
        assert_eq!(full(start, &phases).admit(now), Arrival::Replace(10));
        // No silent one: the unfinished head, then the answer that takes too long.
        phases.truncate(2);
        phases.extend([Phase::Streaming; 6]);
        assert_eq!(full(start, &phases).admit(now), Arrival::Replace(9));
        phases[1] = Phase::Streaming;
        assert_eq!(full(start, &phases).admit(now), Arrival::Replace(8));
    }

    #[test]
    fn trace_streams_and_answers_within_their_grace_keep_their_places() {
        let start = Instant::now();
        let connections = full(start, &[Phase::Answering; 8]);
        // The last answer began 7 s after `start`.
        let within_grace = start + Duration::from_secs(7) + ANSWER_GRACE;
        assert_eq!(connections.admit(within_grace), Arrival::Replace(8));
        let connections = full(start + Duration::from_secs(60), &[Phase::Answering; 8]);
        assert_eq!(connections.admit(start), Arrival::Refuse);
        let connections = full(start, &[Phase::Streaming; 8]);
        assert_eq!(
            connections.admit(start + Duration::from_secs(3600)),
            Arrival::Refuse
        );
    }

    #[test]
    fn the_page_policy_allows_exactly_its_own_inline_script_and_style() {
        let policy = page_policy().to_str().unwrap();
        // `echo -n 'x' | openssl dgst -sha256 -binary | base64`
        assert_eq!(
            inline_hash("<p><script>x</script>", "script"),
            "'sha256-LXEWQrcmsEQBYnyp+6wy9chTD7GQPMTbAiWHF5IaSIE='"
        );
        for tag in ["script", "style"] {
            assert!(
                status::PAGE.matches(&format!("<{tag}>")).count() == 1,
                "{tag}"
            );
            let hash = inline_hash(status::PAGE, tag);
            assert!(policy.contains(&format!("{tag}-src {hash}")), "{policy}");
        }
        assert!(policy.starts_with("default-src 'none'; connect-src 'self';"));
        assert!(!policy.contains("unsafe"));
    }

    #[test]
    fn the_page_puts_what_it_is_given_in_as_text_and_styles_only_by_class() {
        // Bus names, value names, labels and units come from the configuration and the trace
        // from the line: none of it may become markup. And the policy refuses style attributes,
        // so a plot or a row styled by one would silently lose its style.
        let script = inline(status::PAGE, "script");
        assert!(script.contains("textContent"), "the script is found");
        for markup in [
            "innerHTML",
            "outerHTML",
            "insertAdjacentHTML",
            "document.write",
            "createContextualFragment",
            "DOMParser",
            "setAttribute(\"style\"",
        ] {
            assert!(!script.contains(markup), "the page's script uses {markup}");
        }
        assert!(!status::PAGE.contains(" style="), "a style attribute");
    }
}
