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

/// `count` from `text`'s series `name{labels}`, 0 if absent.
fn count(text: &str, series: &str) -> f64 {
    crate::metrics::sample(text, series).unwrap_or(0.0)
}

#[tokio::test(start_paused = true)]
async fn every_transaction_of_a_saturated_sim_line_is_paired_and_nothing_is_sent() {
    use crate::sim::{RegisterBank, SimLine};
    let text = "[[bus]]\nname = \"heard\"\ndevice = \"sim\"\nbaud = 115200\nparity = \"none\"\n\
         mode = \"listen\"\nresponse_timeout = \"20ms\"\n\
         [bus.sim_master]\nresponse_timeout = \"20ms\"\n\
         [[bus.sim_master.read]]\nslave = 1\nregister = 0\ncount = 4\n\
         [[bus.sim_master.read]]\nslave = 2\ntable = \"input\"\nregister = 0\ncount = 2\n\
         [[bus.sim_master.read]]\nslave = 9\nregister = 0\ncount = 1\n";
    let config = Config::from_toml_str(text).unwrap();
    config.check(None).expect("a valid listen line");
    let settings = config.bus[0].clone();
    let line = SimLine::new(settings.line_timing());
    line.add_slave(1, RegisterBank::new(Duration::ZERO));
    line.add_slave(2, RegisterBank::new(Duration::ZERO));
    line.set_master(settings.sim_master.as_ref().unwrap());
    let metrics = Metrics::new();
    let task = BusTask::new(settings, Device::Sim(line.clone()), &metrics);
    let bus = task.handle();
    tokio::spawn(task.run(shutdown::Stopping::never()));
    tokio::time::sleep(Duration::from_secs(2)).await;
    // Slave 1's holding registers were heard; its input registers and slave 9 never were.
    let outcome = |slave: u8, pdu: &[u8]| bus.submit(1, slave, pdu.to_vec());
    assert!(matches!(
        outcome(1, &[0x03, 0x00, 0x01, 0x00, 0x02]).await.unwrap(),
        Ok(Answer::Reply(pdu)) if pdu.len() == 6
    ));
    assert!(matches!(
        outcome(2, &[0x04, 0x00, 0x00, 0x00, 0x02]).await.unwrap(),
        Ok(Answer::Reply(_))
    ));
    for (slave, pdu) in [
        (1, [0x04, 0, 0, 0, 1]),
        (2, [0x03, 0, 0, 0, 1]),
        (9, [0x03, 0, 0, 0, 1]),
    ] {
        assert_eq!(
            outcome(slave, &pdu).await.unwrap(),
            Err(RequestError::Unseen),
            "slave {slave}, {pdu:02x?}"
        );
    }
    let stats = line.stats();
    assert_eq!(stats.listener_frames, 0, "the listen line sent nothing");
    assert!(stats.other_replies > 100, "{stats:?}");
    let text = metrics.render().unwrap();
    let replies: f64 = [("1", "0x03"), ("2", "0x04")]
        .iter()
        .map(|(slave, function)| {
            let labels =
                format!("bus=\"heard\",function=\"{function}\",outcome=\"ok\",slave=\"{slave}\"");
            count(
                &text,
                &format!("modbus_gateway_observed_replies_total{{{labels}}}"),
            )
        })
        .sum();
    let timeouts = count(
        &text,
        "modbus_gateway_observed_timeouts_total{bus=\"heard\",slave=\"other\"}",
    );
    // Heard up to now; the transaction under way when the clock stopped may not be over yet.
    #[allow(clippy::cast_precision_loss)]
    let (made_replies, made_timeouts) = (stats.other_replies as f64, stats.other_timeouts as f64);
    assert!(
        (made_replies - replies).abs() <= 1.0,
        "{replies} of {made_replies}"
    );
    assert!(
        (made_timeouts - timeouts).abs() <= 1.0,
        "{timeouts} of {made_timeouts}"
    );
    assert_eq!(
        count(
            &text,
            "modbus_gateway_observed_crc_errors_total{bus=\"heard\"}"
        ),
        0.0
    );
}
