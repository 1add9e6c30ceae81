//! The `health` subcommand: ask a running gateway's metrics endpoint whether it is alive
//! (`/healthz`) or ready (`/readyz`), for a container's health check or a script. Exit 0 when it
//! answers 200, 1 (saying why) when it answers otherwise, cannot be reached, or takes too long.

use hyper::{StatusCode, Uri};
use std::net::SocketAddr;
use std::process::ExitCode;
use std::time::Duration;

/// How long the whole check may take: a gateway that does not answer /healthz in this time is
/// not healthy (a container runtime's own timeout is usually 30 s).
const TIMEOUT: Duration = Duration::from_secs(5);

/// The check's URL on the endpoint listening on `listen`: `/readyz` if `ready`, else `/healthz`.
pub fn url_of(listen: SocketAddr, ready: bool) -> String {
    super::http::url_of(listen, if ready { "/readyz" } else { "/healthz" })
}

/// GET `url`; print its answer and exit 0 if it is 200, else say why on stderr and exit 1.
pub fn health(url: &str) -> ExitCode {
    match super::http::uri_of(url).and_then(|uri| check(&uri)) {
        Ok(text) => {
            // A health check's output is kept by the container runtime: the one line it said.
            // A reader gone (`| true`) changes nothing: the answer was had.
            let _ = super::print_out(&format!("{text}\n"));
            ExitCode::SUCCESS
        }
        Err(why) => {
            eprintln!("modbus-gateway: health: {url}: {why}");
            ExitCode::FAILURE
        }
    }
}

/// The body of a 200 answer to `uri`, or why there is none.
fn check(uri: &Uri) -> Result<String, String> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| format!("cannot start the runtime: {e}"))?;
    let answer = async {
        let response = super::http::get(uri).await?;
        let status = response.status();
        // One line, for a health check's log: the lines of a body joined.
        let text = super::http::text_of(response)
            .await
            .lines()
            .collect::<Vec<_>>()
            .join("; ");
        if status == StatusCode::OK {
            Ok(text)
        } else {
            Err(format!("{status}: {text}"))
        }
    };
    runtime.block_on(async {
        tokio::time::timeout(TIMEOUT, answer)
            .await
            .map_err(|_| format!("no answer within {}", humantime::format_duration(TIMEOUT)))?
    })
}
