//! One plain HTTP/1.1 GET to the gateway's metrics endpoint, for the subcommands that read it
//! (`trace`, `health`): the connection, the request and its response, or why there is none.

use bytes::Bytes;
use http_body_util::{BodyExt, Empty};
use hyper::body::Incoming;
use hyper::header::HOST;
use hyper::{Request, Response, Uri};
use hyper_util::rt::TokioIo;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use tokio::net::TcpStream;

/// The URL of `path` on the metrics endpoint listening on `listen` (a wildcard address is
/// reached on loopback).
pub(super) fn url_of(listen: SocketAddr, path: &str) -> String {
    let ip = match listen.ip() {
        IpAddr::V4(ip) if ip.is_unspecified() => IpAddr::V4(Ipv4Addr::LOCALHOST),
        IpAddr::V6(ip) if ip.is_unspecified() => IpAddr::V6(Ipv6Addr::LOCALHOST),
        ip => ip,
    };
    format!("http://{}{path}", SocketAddr::new(ip, listen.port()))
}

/// `url` if it is an `http://HOST:PORT...` URL, else what it lacks.
pub(super) fn uri_of(url: &str) -> Result<Uri, String> {
    let uri: Uri = url.parse().map_err(|e| format!("no URL: {e}"))?;
    if uri.scheme_str() != Some("http") || uri.authority().is_none() {
        return Err("an http:// URL with host and port is needed".into());
    }
    Ok(uri)
}

/// `GET` the path and query of `uri` (an `http://HOST:PORT/...` URL) on a connection of its own;
/// the response, or what went wrong in words for the user.
pub(super) async fn get(uri: &Uri) -> Result<Response<Incoming>, String> {
    let authority = uri.authority().map(ToString::to_string).unwrap_or_default();
    let stream = TcpStream::connect(&authority)
        .await
        .map_err(|e| format!("cannot reach the gateway's metrics endpoint: {e}"))?;
    let (mut sender, connection) =
        hyper::client::conn::http1::handshake::<_, Empty<Bytes>>(TokioIo::new(stream))
            .await
            .map_err(|e| format!("cannot talk HTTP to it: {e}"))?;
    tokio::spawn(connection);
    let path = uri.path_and_query().map_or("/", |p| p.as_str());
    let request = Request::get(path)
        .header(HOST, &authority)
        .body(Empty::new())
        .map_err(|e| e.to_string())?;
    sender
        .send_request(request)
        .await
        .map_err(|e| format!("no answer: {e}"))
}

/// The body of `response` as trimmed text (empty if it cannot be read).
pub(super) async fn text_of(response: Response<Incoming>) -> String {
    let body = response.into_body().collect().await.ok();
    body.map(|b| String::from_utf8_lossy(&b.to_bytes()).trim().to_owned())
        .unwrap_or_default()
}
