//! A listen-only line behind a raw device server, on a real loopback socket: what the converter
//! hands over is heard and served from the shadow, and the gateway writes nothing to the socket,
//! before or after the connection is lost and made again.

use super::super::{BusTask, Device};
use crate::config::{Config, DeviceName};
use crate::error::{Answer, RequestError};
use crate::line::rtu;
use crate::metrics::Metrics;
use crate::shutdown;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::{timeout, Instant};

const BOUND: Duration = Duration::from_secs(10);

async fn accept(listener: &TcpListener) -> TcpStream {
    let (socket, _) = timeout(BOUND, listener.accept())
        .await
        .expect("the bus connects")
        .expect("accept");
    socket
}

/// Nothing arrives on `socket` within a moment: the gateway wrote nothing.
async fn nothing_written(socket: &mut TcpStream) {
    let mut buf = [0u8; 64];
    match timeout(Duration::from_millis(200), socket.read(&mut buf)).await {
        Err(_) => {}
        Ok(Ok(0)) => panic!("the gateway closed the connection"),
        Ok(result) => panic!("the gateway wrote to a listen line: {result:?} {buf:02x?}"),
    }
}

#[tokio::test]
async fn a_listen_line_behind_a_device_server_serves_what_it_heard_and_writes_nothing() {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let text = format!(
        "[[bus]]\nname = \"heard\"\ndevice = \"tcp://{addr}\"\nbaud = 115200\nparity = \"none\"\n\
         mode = \"listen\"\nmax_age = \"5s\"\nresponse_timeout = \"100ms\"\n\
         reopen_delay = \"10ms\"\n"
    );
    let config = Config::from_toml_str(&text).unwrap();
    config.check(None).expect("a valid listen line");
    let settings = config.bus[0].clone();
    let DeviceName::Server(server) = settings.device_name() else {
        panic!("a device server")
    };
    let device = Device::Server {
        addr: server,
        format: settings.format(),
        tls: None,
    };
    let task = BusTask::new(settings, device, &Metrics::new());
    let bus = task.handle();
    let (stop, stopping) = shutdown::channel();
    let running = tokio::spawn(task.run(stopping));
    let mut socket = accept(&listener).await;
    // The other master reads two registers from 0004H of slave 1; the manual's answer.
    let request = rtu::encode(1, &[0x03, 0x00, 0x04, 0x00, 0x02]);
    let reply = rtu::encode(1, &[0x03, 0x04, 0x13, 0x88, 0x00, 0x00]);
    socket.write_all(&request).await.unwrap();
    socket.write_all(&reply).await.unwrap();
    let read = [0x03, 0x00, 0x05, 0x00, 0x01];
    let deadline = Instant::now() + BOUND;
    let answer = loop {
        match bus.submit(1, 1, read.to_vec()).await.unwrap() {
            Err(RequestError::Unseen) if Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            other => break other,
        }
    };
    assert_eq!(answer, Ok(Answer::Reply(vec![0x03, 0x02, 0x00, 0x00])));
    let write = [0x06, 0x00, 0x04, 0x00, 0x01];
    assert_eq!(
        bus.submit(1, 1, write.to_vec()).await.unwrap(),
        Err(RequestError::ListenOnly(0x06))
    );
    let unseen = [0x03, 0x00, 0x06, 0x00, 0x01];
    assert_eq!(
        bus.submit(1, 1, unseen.to_vec()).await.unwrap(),
        Err(RequestError::Unseen)
    );
    nothing_written(&mut socket).await;
    // The converter drops the connection: the bus connects again, and still writes nothing.
    drop(socket);
    let mut socket = accept(&listener).await;
    nothing_written(&mut socket).await;
    assert_eq!(
        bus.submit(1, 1, read.to_vec()).await.unwrap(),
        Ok(Answer::Reply(vec![0x03, 0x02, 0x00, 0x00])),
        "what was heard outlives the connection, within max_age"
    );
    stop.stop(Instant::now());
    timeout(BOUND, running).await.unwrap().unwrap();
    let mut rest = Vec::new();
    timeout(BOUND, socket.read_to_end(&mut rest))
        .await
        .expect("the stopped bus closes its connection")
        .unwrap();
    assert_eq!(rest, [0u8; 0], "not a byte, to the end");
}
