//! The configurations many tests start from, made with [`crate::config`]. The `*_config`
//! functions take extra bus keys as TOML text, as the tests that use them have always written
//! them; a test that composes more builds on the [`Bus`] values here.

use crate::config::{Bus, GatewayConfig};
use crate::gateway::start;
use modbus_gateway::Gateway;

/// The simulated 9600 8E1 line named "sim" that most tests use, with no slaves yet.
pub fn sim_line() -> Bus {
    Bus::sim("sim").baud(9600).parity("even")
}

/// A gateway on one simulated 9600 8E1 line named "sim" with register-bank slaves 1-4, plus `extra`
/// bus keys.
pub async fn start_sim(extra: &str) -> Gateway {
    start(&sim_config(extra)).await
}

/// [`start_sim`]'s configuration.
pub fn sim_config(extra: &str) -> String {
    GatewayConfig::new()
        .bus(sim_line().text(extra).sim_slaves("1-4"))
        .to_toml()
}

/// [`sim_config`] with `[server]` keys added (as text).
pub fn sim_config_with_server(server: &str, bus: &str) -> String {
    GatewayConfig::new()
        .server_table(server)
        .bus(sim_line().text(bus).sim_slaves("1-4"))
        .to_toml()
}

/// The serial bus named "pty" on `path`, 115200 8N2 (ptys refuse parity; two stop bits are the
/// default without it).
pub fn pty_line(path: &str) -> Bus {
    Bus::on("pty", path).baud(115_200).parity("none")
}

/// A gateway configuration with one serial bus named "pty" on `path` ([`pty_line`]), plus `extra`
/// bus keys.
pub fn pty_config(path: &str, extra: &str) -> String {
    GatewayConfig::new()
        .bus(pty_line(path).text(extra))
        .to_toml()
}

/// A gateway configuration with one simulated line at 115200 baud, fast enough that a trace
/// reader that does not read is soon blocked.
pub fn fast_sim_config() -> String {
    GatewayConfig::new()
        .bus(
            Bus::sim("sim")
                .baud(115_200)
                .parity("even")
                .sim_slaves("1-4"),
        )
        .to_toml()
}

/// The line two hundred masters share at once: simulated, 115200 8N1, register slaves 1-4, with
/// room in its queue for every master's pipeline and a queue timeout no request reaches.
pub fn crowded_line() -> Bus {
    Bus::sim("fast")
        .baud(115_200)
        .parity("none")
        .queue_depth(2048)
        .queue_timeout("60s")
        .sim_slaves("1-4")
}

/// A gateway configuration for floods: Modbus TCP and UDP listeners, one simulated line at `baud`
/// with register slaves 1 and 2, `queue_depth` places and a queue timeout no read reaches.
pub fn flood_target(baud: u32, queue_depth: usize) -> String {
    GatewayConfig::new()
        .listen_udp("127.0.0.1:0")
        .bus(
            Bus::sim("sim")
                .baud(baud)
                .parity("none")
                .key("queue_depth", queue_depth)
                .key("queue_timeout", "60s")
                .sim_slaves("1-2"),
        )
        .to_toml()
}
