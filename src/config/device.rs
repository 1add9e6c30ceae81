//! What a bus's `device` names, read once: the simulated line (`"sim"`), a serial device of the
//! gateway's own (a path), or a peer on the network: a serial device server (`tcp://HOST:PORT` in
//! raw, transparent mode; `rfc2217://HOST:PORT` with the line's settings negotiated over Telnet)
//! or a Modbus TCP device (`tcp://` with `framing = "tcp"`, or `tls://HOST:PORT`, Modbus/TCP
//! Security). Pure parsing; knows nothing of sockets, name resolution or ports.

use super::bus::SIM_DEVICE;
use crate::line::framing::TransportKind;
use std::fmt;

/// How the gateway talks to a serial device server.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ServerMode {
    /// `tcp://`: the socket carries the line's bytes as they are.
    Raw,
    /// `rfc2217://`: Telnet with COM-PORT-OPTION; the gateway sets the far port's format.
    Rfc2217,
    /// `tls://`: a Modbus TCP device behind TLS (Modbus/TCP Security), `[bus.tls]`.
    Tls,
}

impl ServerMode {
    /// The scheme `device` writes it with, and the `transport` label of the metrics.
    pub fn scheme(self) -> &'static str {
        match self {
            ServerMode::Raw => "tcp",
            ServerMode::Rfc2217 => "rfc2217",
            ServerMode::Tls => "tls",
        }
    }
}

/// A serial device server's address as `device` writes it: a host name or an IPv4 address, or an
/// IPv6 address in brackets, and a port.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ServerAddr {
    pub mode: ServerMode,
    /// Without brackets: `::1`, not `[::1]`.
    pub host: String,
    pub port: u16,
}

impl fmt::Display for ServerAddr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let scheme = self.mode.scheme();
        if self.host.contains(':') {
            write!(f, "{scheme}://[{}]:{}", self.host, self.port)
        } else {
            write!(f, "{scheme}://{}:{}", self.host, self.port)
        }
    }
}

/// What `device` names.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DeviceName {
    Sim,
    /// A serial device's path.
    Serial(String),
    Server(ServerAddr),
}

impl DeviceName {
    /// Read `device`; the error says what is wrong and what the key takes.
    pub fn parse(device: &str) -> Result<DeviceName, String> {
        if device.is_empty() {
            return Err(format!(
                "needs a serial device path, \"{SIM_DEVICE}\", {TAKES}"
            ));
        }
        if device == SIM_DEVICE {
            return Ok(DeviceName::Sim);
        }
        let Some((scheme, rest)) = device.split_once("://") else {
            return Ok(DeviceName::Serial(device.to_owned()));
        };
        let mode = match scheme {
            "tcp" => ServerMode::Raw,
            "rfc2217" => ServerMode::Rfc2217,
            "tls" => ServerMode::Tls,
            _ => {
                return Err(format!(
                    "`{scheme}://` is not a kind of device: a serial device path, \
                     \"{SIM_DEVICE}\", {TAKES}"
                ))
            }
        };
        let (host, port) = host_and_port(rest).map_err(|why| format!("`{device}`: {why}"))?;
        Ok(DeviceName::Server(ServerAddr { mode, host, port }))
    }

    /// The kind of transport it is, for the framing table.
    pub fn kind(&self) -> TransportKind {
        match self {
            DeviceName::Sim => TransportKind::Sim,
            DeviceName::Serial(_) => TransportKind::Serial,
            DeviceName::Server(addr) => match addr.mode {
                ServerMode::Raw => TransportKind::Tcp,
                ServerMode::Rfc2217 => TransportKind::Rfc2217,
                ServerMode::Tls => TransportKind::Tls,
            },
        }
    }
}

/// The network forms `device` takes, for messages.
const TAKES: &str =
    "tcp://HOST:PORT (a serial device server in raw mode, or a Modbus TCP device), \
                     rfc2217://HOST:PORT or tls://HOST:PORT (a Modbus/TCP Security device)";

/// `HOST:PORT` or `[IPV6]:PORT`, and nothing after it.
fn host_and_port(text: &str) -> Result<(String, u16), String> {
    let (host, port) = if let Some(bracketed) = text.strip_prefix('[') {
        let (host, rest) = bracketed
            .split_once(']')
            .ok_or("an IPv6 address's `[` has no `]`")?;
        let port = rest
            .strip_prefix(':')
            .ok_or("needs `:PORT` after the address")?;
        if host.parse::<std::net::Ipv6Addr>().is_err() {
            return Err(format!("`{host}` is not an IPv6 address"));
        }
        (host, port)
    } else {
        let (host, port) = text.rsplit_once(':').ok_or("needs HOST:PORT")?;
        if host.contains(':') {
            return Err(format!("an IPv6 address goes in brackets: [{host}]:{port}"));
        }
        (host, port)
    };
    if host.is_empty() {
        return Err("needs a host before `:PORT`".into());
    }
    if host.contains(['/', '@', '?', '#', ' ']) {
        return Err(format!("`{host}` is not a host name or address"));
    }
    match port.parse::<u16>() {
        Ok(port) if port > 0 => Ok((host.to_owned(), port)),
        _ => Err(format!("`{port}` is not a port 1-65535")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn server(mode: ServerMode, host: &str, port: u16) -> DeviceName {
        DeviceName::Server(ServerAddr {
            mode,
            host: host.into(),
            port,
        })
    }

    #[test]
    fn a_device_is_the_simulated_line_a_serial_path_or_a_device_server_by_name_v4_or_v6() {
        use ServerMode::{Raw, Rfc2217};
        assert_eq!(DeviceName::parse("sim"), Ok(DeviceName::Sim));
        assert_eq!(
            DeviceName::parse("/dev/ttyUSB0"),
            Ok(DeviceName::Serial("/dev/ttyUSB0".into()))
        );
        for (text, parsed) in [
            ("tcp://10.0.0.20:4001", server(Raw, "10.0.0.20", 4001)),
            ("tcp://nport-3.plant:950", server(Raw, "nport-3.plant", 950)),
            ("rfc2217://[::1]:2217", server(Rfc2217, "::1", 2217)),
            ("rfc2217://[fe80::1]:7000", server(Rfc2217, "fe80::1", 7000)),
        ] {
            assert_eq!(DeviceName::parse(text), Ok(parsed.clone()), "{text}");
            let DeviceName::Server(addr) = parsed else {
                unreachable!()
            };
            assert_eq!(addr.to_string(), text, "written back as given");
        }
    }

    #[test]
    fn a_device_server_address_that_is_not_host_and_port_is_refused_saying_why() {
        for (text, why) in [
            ("", "needs a serial device path"),
            ("ftp://host:21", "`ftp://` is not a kind of device"),
            ("tcp://host", "needs HOST:PORT"),
            ("tcp://:502", "needs a host"),
            ("tcp://host:0", "`0` is not a port"),
            ("tcp://host:70000", "`70000` is not a port"),
            ("tcp://host:502/x", "`502/x` is not a port"),
            (
                "tcp://::1:502",
                "an IPv6 address goes in brackets: [::1]:502",
            ),
            ("tcp://[::1]502", "needs `:PORT`"),
            ("tcp://[::1:502", "has no `]`"),
            ("tcp://[nope]:502", "`nope` is not an IPv6 address"),
            ("tcp://user@host:502", "is not a host name"),
        ] {
            let error = DeviceName::parse(text).expect_err(text);
            assert!(error.contains(why), "{text}: {error}");
        }
    }
}
