//! `GET /trace`: the live trace of the lines as Server-Sent Events, one `frame` event per frame,
//! filtered here by `bus` and `slave`. Each reader has a task of its own that takes events from
//! the [`TraceHub`] and writes them into its response body; a reader that does not keep up loses
//! events (told to it by a `lost` event) and never holds up anyone else. A reader whose stream
//! takes nothing for [`STALLED_AFTER`] (its socket full: it stopped reading) is dropped, so that
//! it does not keep one of the [`MAX_READERS`] places.

use crate::trace::{lost_sse, TraceHub, TraceReader, Traced, MAX_READERS};
use bytes::Bytes;
use http_body_util::channel::{Channel, Sender};
use http_body_util::{Either, Full};
use hyper::header::{HeaderValue, CACHE_CONTROL, CONTENT_TYPE};
use hyper::{Response, StatusCode};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::Notify;
use tracing::info;

/// A response of the metrics endpoint: whole, or the trace's stream.
pub(super) type Body = Either<Full<Bytes>, Channel<Bytes>>;

/// A comment line this often, so that a reader sees the stream is alive and a reader that has
/// gone is noticed by the failed write.
const KEEPALIVE: Duration = Duration::from_secs(5);
/// A stream that takes no chunk for this long, two keepalives, has a reader that stopped
/// reading: its socket's buffers, the connection's and [`BUFFERED`] chunks are full.
const STALLED_AFTER: Duration = Duration::from_secs(2 * KEEPALIVE.as_secs());
/// Chunks waiting between a reader's task and its connection; past these the task waits, and
/// the events it does not take meanwhile are lost to that reader.
const BUFFERED: usize = 16;
const OPENED: &str = ": modbus-gateway trace\n\n";
const STILL_HERE: &str = ": keepalive\n\n";

/// Which frames a reader wants.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
struct Wanted {
    bus: Option<String>,
    slave: Option<u8>,
}

/// The filter a query string asks for, or the status and message that refuse it.
fn filter(query: Option<&str>, buses: &[String]) -> Result<Wanted, (StatusCode, String)> {
    let mut filter = Wanted::default();
    for (key, value) in super::query_pairs(query)? {
        let value = value.as_ref();
        match key.as_ref() {
            "bus" => filter.bus = Some(super::bus_named(value, buses)?),
            // Every address byte a frame can carry: a Modbus TCP device's units are 0-255, and
            // anything on a serial line may answer at 248-255 too.
            "slave" => match value.parse::<u8>() {
                Ok(slave) => filter.slave = Some(slave),
                Err(_) => {
                    return Err((
                        StatusCode::BAD_REQUEST,
                        format!("slave must be an address from 0 to 255, not `{value}`\n"),
                    ))
                }
            },
            _ => {
                return Err((
                    StatusCode::BAD_REQUEST,
                    format!("unknown parameter `{key}`; /trace takes bus and slave\n"),
                ))
            }
        }
    }
    Ok(filter)
}

impl Wanted {
    fn admits(&self, event: &crate::trace::TraceEvent) -> bool {
        self.bus.as_deref().is_none_or(|bus| *event.bus == *bus)
            && self.slave.is_none_or(|slave| event.slave == slave)
    }
}

fn text(status: StatusCode, body: String) -> Response<Body> {
    let mut response = Response::new(Either::Left(Full::new(Bytes::from(body))));
    *response.status_mut() = status;
    response.headers_mut().insert(
        CONTENT_TYPE,
        HeaderValue::from_static("text/plain; charset=utf-8"),
    );
    response
}

/// Answer `GET /trace?query` from `peer`: the stream, or why not. `hang_up` is told to close
/// the connection when its reader has stalled.
pub(super) fn respond(
    hub: &Arc<TraceHub>,
    query: Option<&str>,
    peer: SocketAddr,
    hang_up: Arc<Notify>,
) -> Response<Body> {
    let filter = match filter(query, &hub.buses()) {
        Ok(filter) => filter,
        Err((status, message)) => return text(status, message),
    };
    let Some(reader) = hub.subscribe() else {
        return text(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{MAX_READERS} trace readers already; try again later\n"),
        );
    };
    let (sender, body) = Channel::new(BUFFERED);
    tokio::spawn(async move {
        if pump(reader, filter, sender).await == Ended::Stalled {
            info!(%peer, "trace reader dropped: its stream took nothing for {STALLED_AFTER:?}");
            hang_up.notify_one();
        }
    });
    let mut response = Response::new(Either::Right(body));
    let headers = response.headers_mut();
    headers.insert(CONTENT_TYPE, HeaderValue::from_static("text/event-stream"));
    headers.insert(CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response
}

/// Why a stream ended.
#[derive(Debug, PartialEq, Eq)]
enum Ended {
    /// Its body is gone: the reader left.
    Gone,
    /// Its body took nothing for [`STALLED_AFTER`].
    Stalled,
}

/// Hand `chunk` to `body`, unless the reader left or stalled.
async fn send(body: &mut Sender<Bytes>, chunk: Bytes) -> Result<(), Ended> {
    match tokio::time::timeout(STALLED_AFTER, body.send_data(chunk)).await {
        Ok(Ok(())) => Ok(()),
        Ok(Err(_)) => Err(Ended::Gone),
        Err(_) => Err(Ended::Stalled),
    }
}

/// Write what `reader` gets and `filter` admits into `body` until the reader leaves or stalls.
async fn pump(mut reader: TraceReader, filter: Wanted, mut body: Sender<Bytes>) -> Ended {
    if let Err(ended) = send(&mut body, Bytes::from_static(OPENED.as_bytes())).await {
        return ended;
    }
    let start = tokio::time::Instant::now() + KEEPALIVE;
    let mut keepalive = tokio::time::interval_at(start, KEEPALIVE);
    let mut lost = 0;
    loop {
        let chunk = tokio::select! {
            traced = reader.next() => match traced {
                Traced::Lost(n) => {
                    lost += n;
                    continue;
                }
                Traced::Frame(event) if filter.admits(&event) => {
                    let mut chunk = String::new();
                    if lost > 0 {
                        chunk = lost_sse(lost);
                        lost = 0;
                    }
                    chunk.push_str(&event.to_sse());
                    Bytes::from(chunk)
                }
                Traced::Frame(_) => continue,
            },
            _ = keepalive.tick() => Bytes::from_static(STILL_HERE.as_bytes()),
        };
        if let Err(ended) = send(&mut body, chunk).await {
            return ended;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trace::{Direction, TraceEvent};
    use http_body_util::BodyExt;
    use std::time::SystemTime;

    fn buses() -> Vec<String> {
        vec!["line0".into(), "line1".into()]
    }

    #[test]
    fn the_query_filters_by_bus_and_slave() {
        assert_eq!(filter(None, &buses()), Ok(Wanted::default()));
        assert_eq!(
            filter(Some("bus=line1&slave=247"), &buses()),
            Ok(Wanted {
                bus: Some("line1".into()),
                slave: Some(247)
            })
        );
        for slave in [0, 248, 255] {
            assert_eq!(
                filter(Some(&format!("slave={slave}")), &buses()),
                Ok(Wanted {
                    bus: None,
                    slave: Some(slave)
                })
            );
        }
    }

    #[test]
    fn an_unknown_bus_is_not_found_and_the_known_ones_are_named() {
        let (status, message) = filter(Some("bus=line9"), &buses()).unwrap_err();
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert!(message.contains("line0, line1"), "{message}");
    }

    #[test]
    fn a_slave_outside_0_to_255_is_a_bad_request() {
        for query in ["slave=256", "slave=-1", "slave=x", "slave=", "colour=red"] {
            let refused = filter(Some(query), &buses());
            assert_eq!(refused.unwrap_err().0, StatusCode::BAD_REQUEST, "{query}");
        }
    }

    fn event(slave: u8) -> TraceEvent {
        TraceEvent {
            time: SystemTime::UNIX_EPOCH,
            bus: "line1".into(),
            direction: Direction::Tx,
            slave,
            function: 3,
            bytes: vec![slave, 3],
            framing: "rtu",
            outcome: "ok",
        }
    }

    /// The body's chunks until it has none ready.
    async fn ready_chunks(body: &mut Channel<Bytes>) -> String {
        let mut text = String::new();
        while let Ok(Some(Ok(frame))) =
            tokio::time::timeout(Duration::from_millis(1), body.frame()).await
        {
            text.push_str(std::str::from_utf8(&frame.into_data().unwrap()).unwrap());
        }
        text
    }

    #[tokio::test(start_paused = true)]
    async fn the_stream_opens_with_a_comment_filters_frames_and_keeps_alive() {
        let hub = Arc::new(TraceHub::new());
        let (sender, mut body) = Channel::new(BUFFERED);
        let filter = Wanted {
            bus: None,
            slave: Some(2),
        };
        tokio::spawn(pump(hub.subscribe().unwrap(), filter, sender));
        tokio::task::yield_now().await;
        hub.publish(event(1));
        hub.publish(event(2));
        let text = ready_chunks(&mut body).await;
        assert_eq!(text, format!("{OPENED}{}", event(2).to_sse()));
        tokio::time::sleep(KEEPALIVE).await;
        assert_eq!(ready_chunks(&mut body).await, STILL_HERE);
    }

    /// A stream that takes nothing for two keepalives.
    #[tokio::test(start_paused = true)]
    async fn a_stream_unread_for_two_keepalives_ends_stalled_and_a_dropped_one_gone() {
        let hub = Arc::new(TraceHub::new());
        let (sender, body) = Channel::new(BUFFERED);
        let stalled = tokio::spawn(pump(hub.subscribe().unwrap(), Wanted::default(), sender));
        tokio::task::yield_now().await;
        // Nobody reads the body: the opening comment and the events fill it.
        for _ in 0..BUFFERED {
            hub.publish(event(1));
            tokio::task::yield_now().await;
        }
        tokio::time::sleep(STALLED_AFTER - KEEPALIVE).await;
        assert!(!stalled.is_finished(), "not stalled for long enough yet");
        tokio::time::sleep(KEEPALIVE * 2).await;
        assert!(stalled.is_finished(), "stalled by now");
        assert_eq!(stalled.await.unwrap(), Ended::Stalled);
        assert!(!hub.active(), "its place in the hub is free");
        drop(body);

        let (sender, body) = Channel::new(BUFFERED);
        let gone = tokio::spawn(pump(hub.subscribe().unwrap(), Wanted::default(), sender));
        drop(body);
        tokio::time::sleep(KEEPALIVE).await;
        assert!(gone.is_finished(), "gone at the next keepalive");
        assert_eq!(gone.await.unwrap(), Ended::Gone);
    }

    #[tokio::test(start_paused = true)]
    async fn a_reader_that_stops_reading_is_told_how_many_events_it_lost() {
        let hub = Arc::new(TraceHub::new());
        let (sender, mut body) = Channel::new(BUFFERED);
        tokio::spawn(pump(hub.subscribe().unwrap(), Wanted::default(), sender));
        tokio::task::yield_now().await;
        // Nobody reads the body: the pump fills it and stops taking events.
        for _ in 0..5000 {
            hub.publish(event(1));
            tokio::task::yield_now().await;
        }
        let text = ready_chunks(&mut body).await;
        let lost: u64 = text
            .split("event: lost\ndata: {\"lost\":")
            .skip(1)
            .map(|rest| rest.split('}').next().unwrap().parse::<u64>().unwrap())
            .sum();
        assert!(lost > 0, "{text}");
        let frames = text.matches("event: frame").count() as u64;
        assert_eq!(frames + lost, 5000, "every event is either read or lost");
    }
}
