//! What the gateway answers itself, seen by a master over TCP: no route (0x0A), broadcast,
//! reads refused at the broadcast address (0x01), a full queue (0x06), a port that is down (0x0A
//! at once) and back.

use crate::support::{addr, start_sim, wait_for_bus, Bus, GatewayConfig, RawMaster};

const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x01];

#[tokio::test]
async fn a_unit_with_no_route_gets_0x0a() {
    let gateway = start_sim("").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    // One bus: units 0-247 are slave addresses; 248-255 go nowhere.
    assert_eq!(master.call(1, 250, &READ).await, [0x83, 0x0A]);
    assert_eq!(master.call(2, 255, &[0x41, 0x01]).await, [0xC1, 0x0A]);
    assert_eq!(gateway.sim_line("sim").unwrap().stats().master_frames, 0);
}

#[tokio::test]
async fn with_two_buses_units_go_where_their_routes_say() {
    let gateway = GatewayConfig::new()
        .bus(Bus::sim("a").baud(115_200).sim_slaves("1"))
        .bus(Bus::sim("b").baud(115_200).sim_slaves("1"))
        .route("1", "a", None)
        .route_offset("101", "b", -100)
        .route("255", "b", 1)
        .start()
        .await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(
        master.call(1, 1, &[0x06, 0x00, 0x00, 0x00, 0x0A]).await[0],
        0x06
    );
    assert_eq!(
        master.call(2, 101, &[0x06, 0x00, 0x00, 0x00, 0x0B]).await[0],
        0x06
    );
    assert_eq!(master.call(3, 1, &READ).await, [0x03, 0x02, 0x00, 0x0A]);
    assert_eq!(
        master.call(4, 255, &READ).await,
        [0x03, 0x02, 0x00, 0x0B],
        "unit 255 is slave 1 on b"
    );
    assert_eq!(
        master.call(5, 2, &READ).await,
        [0x83, 0x0A],
        "unit 2 has no route"
    );
}

#[tokio::test]
async fn a_broadcast_write_reaches_every_slave_and_is_answered_with_the_normal_response() {
    let gateway = start_sim("turnaround_delay = \"20ms\"").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let write = [0x06, 0x00, 0x07, 0x0B, 0xB8];
    assert_eq!(master.call(1, 0, &write).await, write);
    for slave in 1..=4 {
        let read = [0x03, 0x00, 0x07, 0x00, 0x01];
        assert_eq!(
            master.call(10 + u16::from(slave), slave, &read).await,
            [0x03, 0x02, 0x0B, 0xB8]
        );
    }
}

#[tokio::test]
async fn without_broadcast_reply_a_broadcast_gets_no_answer() {
    let gateway = start_sim("broadcast_reply = false\nturnaround_delay = \"20ms\"").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    master.send(1, 0, &[0x06, 0x00, 0x07, 0x00, 0x01]).await;
    master.send(2, 1, &[0x03, 0x00, 0x07, 0x00, 0x01]).await;
    let reply = master.recv().await;
    assert_eq!(reply.transaction, 2, "the broadcast was not answered");
    assert_eq!(
        reply.pdu,
        [0x03, 0x02, 0x00, 0x01],
        "but it was carried out"
    );
}

#[tokio::test]
async fn a_read_to_the_broadcast_address_is_refused_with_0x01_and_never_sent() {
    let gateway = start_sim("").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 0, &READ).await, [0x83, 0x01]);
    assert_eq!(
        master.call(2, 0, &[0x08, 0x00, 0x00, 0x12, 0x34]).await,
        [0x88, 0x01]
    );
    assert_eq!(master.call(3, 0, &[0x41, 0x00]).await, [0xC1, 0x01]);
    assert_eq!(gateway.sim_line("sim").unwrap().stats().master_frames, 0);
}

#[tokio::test]
async fn function_codes_no_master_may_send_get_0x01() {
    let gateway = start_sim("").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &[0x00, 0x01]).await, [0x80, 0x01]);
    assert_eq!(master.call(2, 1, &[0x83, 0x01]).await, [0x83, 0x01]);
    assert_eq!(gateway.sim_line("sim").unwrap().stats().master_frames, 0);
}

#[tokio::test]
async fn a_full_queue_answers_0x06_and_serves_what_it_holds() {
    // The test runtime has one thread: all six requests are queued before the bus takes one.
    let gateway = start_sim("queue_depth = 2").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    let mut burst = Vec::new();
    for tid in 1..=6 {
        burst.extend(RawMaster::adu(tid, 1, &[0x04, 0x00, tid as u8, 0x00, 0x01]));
    }
    master.send_raw(&burst).await;
    let mut pdus = Vec::new();
    for tid in 1..=6 {
        let reply = master.recv().await;
        assert_eq!(reply.transaction, tid);
        pdus.push(reply.pdu);
    }
    assert_eq!(pdus[0], [0x04, 0x02, 0x00, 0x01]);
    assert_eq!(pdus[1], [0x04, 0x02, 0x00, 0x02]);
    for pdu in &pdus[2..] {
        assert_eq!(pdu, &[0x84, 0x06]);
    }
}

#[tokio::test]
async fn a_silent_slave_gets_0x0b() {
    let gateway = start_sim("response_timeout = \"50ms\"").await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 9, &READ).await, [0x83, 0x0B]);
    assert_eq!(
        master.call(2, 1, &READ).await,
        [0x03, 0x02, 0x00, 0x00],
        "the bus goes on"
    );
}

#[tokio::test]
async fn an_unplugged_adapter_gets_0x0a_at_once_and_is_served_again_when_back() {
    // With a one-hour timeout, a 0x0A that arrives at all arrived without waiting for a timer.
    let gateway = start_sim(
        "response_timeout = \"1h\"\nreopen_delay = \"10ms\"\nreopen_delay_max = \"50ms\"",
    )
    .await;
    let line = gateway.sim_line("sim").unwrap().clone();
    let mut master = RawMaster::connect(addr(&gateway)).await;
    assert_eq!(master.call(1, 1, &READ).await, [0x03, 0x02, 0x00, 0x00]);
    line.unplug();
    wait_for_bus(&gateway, "sim", false).await;
    assert_eq!(master.call(2, 1, &READ).await, [0x83, 0x0A]);
    line.plug();
    wait_for_bus(&gateway, "sim", true).await;
    assert_eq!(
        master.call(3, 1, &READ).await,
        [0x03, 0x02, 0x00, 0x00],
        "same connection"
    );
}

#[tokio::test]
async fn a_lost_port_leaves_the_other_buses_serving() {
    let gateway = GatewayConfig::new()
        .bus(
            Bus::sim("a")
                .baud(115_200)
                .response_timeout("1h")
                .sim_slaves("1"),
        )
        .bus(Bus::sim("b").baud(115_200).sim_slaves("1"))
        .route("1", "a", None)
        .route("2", "b", 1)
        .start()
        .await;
    gateway.sim_line("a").unwrap().unplug();
    wait_for_bus(&gateway, "a", false).await;
    let mut master = RawMaster::connect(addr(&gateway)).await;
    for tid in 0..5 {
        assert_eq!(
            master.call(tid, 1, &READ).await,
            [0x83, 0x0A],
            "bus a is down"
        );
        assert_eq!(
            master.call(tid, 2, &READ).await,
            [0x03, 0x02, 0x00, 0x00],
            "bus b serves"
        );
    }
}
