//! A gateway started in the test's process from TOML text, on loopback ports.

use crate::wait::within;
use modbus_gateway::gateway::config_from_toml;
use modbus_gateway::Gateway;
use std::net::SocketAddr;
use std::time::Duration;

/// Start a gateway on `toml`, which should listen on 127.0.0.1:0. Its metrics endpoint goes on a
/// free loopback port too, so tests never contend for the default one.
pub async fn start(toml: &str) -> Gateway {
    let mut config = config_from_toml(toml).unwrap_or_else(|e| panic!("test config: {e}"));
    config.metrics.listen = SocketAddr::from(([127, 0, 0, 1], 0));
    Gateway::start(&config).await.expect("gateway starts")
}

pub fn addr(gateway: &Gateway) -> SocketAddr {
    gateway.tcp_addrs()[0]
}

/// Wait until bus `name` has (`up`) or has lost (`!up`) its port.
pub async fn wait_for_bus(gateway: &Gateway, name: &str, up: bool) {
    let what = format!(
        "bus {name} {}",
        if up {
            "opens its port"
        } else {
            "loses its port"
        }
    );
    within(&what, async {
        while gateway.bus_up(name) != Some(up) {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
}
