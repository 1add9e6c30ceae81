//! The HTTP endpoint on `metrics.listen`: `/metrics` (Prometheus text format), `/healthz` (the
//! process answers) and `/readyz` (every bus has its port open, else 503 naming those that have
//! not), `/trace` (the live trace of the lines, `metrics::sse`). HTTP/1.1 by hyper; a few
//! scrapers at a time, each bounded in time, so a stuck client cannot hold the endpoint; a trace
//! stream is bounded in number instead, and lasts as long as its reader.

use super::sse;
use super::Metrics;
use bytes::Bytes;
use http_body_util::{Either, Full};
use hyper::body::Incoming;
use hyper::header::{HeaderValue, ALLOW, CONTENT_TYPE};
use hyper::service::service_fn;
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::{TokioIo, TokioTimer};
use std::convert::Infallible;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tracing::{debug, warn};

/// HTTP connections served at once; more are closed at accept.
const MAX_CONNECTIONS: usize = 16;
/// A client must send its request headers within this.
const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// A kept-alive connection is closed after this; Prometheus simply opens another.
const CONNECTION_LIFETIME: Duration = Duration::from_secs(120);
/// Pause after an accept error such as running out of file descriptors.
const ACCEPT_ERROR_PAUSE: Duration = Duration::from_millis(100);
const TEXT: &str = "text/plain; charset=utf-8";

/// The buses whose port is not open; empty when the gateway is ready.
pub type Readiness = Arc<dyn Fn() -> Vec<String> + Send + Sync>;

struct State {
    metrics: Arc<Metrics>,
    not_ready: Readiness,
}

/// Serve the endpoint on `listener` forever.
pub async fn serve(listener: TcpListener, metrics: Arc<Metrics>, not_ready: Readiness) {
    let state = Arc::new(State { metrics, not_ready });
    let slots = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(error) => {
                warn!(%error, "metrics endpoint: accept failed");
                tokio::time::sleep(ACCEPT_ERROR_PAUSE).await;
                continue;
            }
        };
        let Ok(slot) = slots.clone().try_acquire_owned() else {
            debug!(%peer, "metrics endpoint: too many connections, closing");
            continue;
        };
        let state = state.clone();
        tokio::spawn(async move {
            // Whether the connection carries a trace stream, which lasts as long as its reader.
            let streaming = Arc::new(AtomicBool::new(false));
            let streams = streaming.clone();
            let service = service_fn(move |request: Request<Incoming>| {
                let response =
                    if request.uri().path() == "/trace" && request.method() == Method::GET {
                        let response = sse::respond(&state.metrics.trace, request.uri().query());
                        streams.fetch_or(response.status() == StatusCode::OK, Ordering::Relaxed);
                        response
                    } else {
                        respond(&state, &request).map(Either::Left)
                    };
                async move { Ok::<_, Infallible>(response) }
            });
            let connection = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT)
                .serve_connection(TokioIo::new(stream), service);
            let mut connection = std::pin::pin!(connection);
            // A connection past its lifetime is simply dropped, unless it streams the trace.
            let ended = match tokio::time::timeout(CONNECTION_LIFETIME, connection.as_mut()).await {
                Ok(ended) => Some(ended),
                Err(_) if streaming.load(Ordering::Relaxed) => Some(connection.await),
                Err(_) => None,
            };
            if let Some(Err(error)) = ended {
                debug!(%peer, %error, "metrics endpoint: connection failed");
            }
            drop(slot);
        });
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
            let down = (state.not_ready)();
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
            "not found; try /metrics, /healthz or /readyz\n".into(),
        ),
    }
}
