//! The scenarios: which line, which masters, which load, by name. Data only; `run` acts on them.

use modbus_gateway::testing::line::{Framing, Parity, SerialFormat};
use std::net::Ipv4Addr;
use std::time::Duration;

/// Read 10 holding registers from 0000H: 8 bytes on the wire, 25 back. Each master reads a block
/// of its own of the same size (from 10 x its index) but in the `Same` load.
pub(crate) const READ_10: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x0A];
/// Write holding register 0001H: 8 bytes each way.
pub(crate) const WRITE_1: [u8; 5] = [0x06, 0x00, 0x01, 0x12, 0x34];
/// Slaves on the simulated line; masters spread their requests over them.
pub(crate) const SLAVES: u8 = 247;
/// The local address the priority master connects from, and `server.priority`.
pub(crate) const PRIORITY_IP: Ipv4Addr = Ipv4Addr::new(127, 0, 0, 2);

/// One plant value every slave lists in the `values-` scenario: a drive's running values, all
/// in the input registers from 100 x the slave's address (a simulated register slave's input
/// register `a` reads `a`, so each slave's values differ), contiguous, so that each slave is one
/// read of 24 registers. The types, orders, scales and bits mix so that decoding is exercised.
pub(crate) struct PlantValue {
    pub(crate) name: &'static str,
    /// The value's first register from the slave's block.
    pub(crate) offset: u16,
    pub(crate) kind: &'static str,
    /// 1: none.
    pub(crate) scale: f64,
    pub(crate) bit: Option<u8>,
    /// Its registers least significant first (CDAB).
    pub(crate) words_little: bool,
    /// The bytes of each register swapped (BADC).
    pub(crate) bytes_little: bool,
    pub(crate) unit: Option<&'static str>,
}

/// A value of `kind` at `offset`, no scale, bit, order or unit.
const fn value(name: &'static str, offset: u16, kind: &'static str) -> PlantValue {
    PlantValue {
        name,
        offset,
        kind,
        scale: 1.0,
        bit: None,
        words_little: false,
        bytes_little: false,
        unit: None,
    }
}

impl PlantValue {
    const fn scale(self, scale: f64) -> PlantValue {
        PlantValue { scale, ..self }
    }

    const fn bit(self, bit: u8) -> PlantValue {
        PlantValue {
            bit: Some(bit),
            ..self
        }
    }

    const fn words_little(self) -> PlantValue {
        PlantValue {
            words_little: true,
            ..self
        }
    }

    const fn bytes_little(self) -> PlantValue {
        PlantValue {
            bytes_little: true,
            ..self
        }
    }

    const fn unit(self, unit: &'static str) -> PlantValue {
        PlantValue {
            unit: Some(unit),
            ..self
        }
    }
}

/// The values of each slave in the `values-` scenario: 20, in 24 registers.
pub(crate) const PLANT_VALUES: [PlantValue; 20] = [
    value("drive_output_frequency_hertz", 0, "u16")
        .scale(0.01)
        .unit("Hz"),
    value("drive_set_frequency_hertz", 1, "u16")
        .scale(0.01)
        .unit("Hz"),
    value("drive_output_voltage_volts", 2, "u16")
        .scale(0.1)
        .unit("V"),
    value("drive_output_current_amperes", 3, "u16")
        .scale(0.1)
        .unit("A"),
    value("drive_output_torque_ratio", 4, "i16").scale(0.001),
    value("drive_motor_speed_rpm", 5, "i16").unit("rpm"),
    value("drive_running", 6, "u16").bit(0),
    value("drive_reverse", 6, "u16").bit(1),
    value("drive_fault", 6, "bool").bit(3),
    value("drive_fault_code", 7, "u16"),
    value("drive_heatsink_temperature_celsius", 8, "i16")
        .scale(0.1)
        .unit("°C"),
    value("drive_dc_bus_voltage_volts", 9, "u16")
        .scale(0.1)
        .unit("V"),
    value("drive_run_time_seconds", 10, "u32")
        .scale(3600.0)
        .unit("s"),
    value("drive_energy_joules", 12, "u32")
        .words_little()
        .scale(3_600_000.0)
        .unit("J"),
    value("drive_output_power_watts", 14, "f32")
        .scale(1000.0)
        .unit("W"),
    value("drive_power_factor_ratio", 16, "f32").words_little(),
    value("drive_input_frequency_hertz", 18, "f32")
        .bytes_little()
        .unit("Hz"),
    value("drive_encoder_position_counts", 20, "i32"),
    value("drive_pid_setpoint_ratio", 22, "u16").scale(0.001),
    value("drive_pid_feedback_ratio", 23, "u16").scale(0.001),
];

/// Where slave `address`'s block of plant values starts.
pub(crate) fn plant_base(address: u8) -> u16 {
    100 * u16::from(address)
}

#[derive(Clone, Copy, PartialEq)]
pub(crate) enum Line {
    /// The built-in simulated line, timed at its baud rate.
    Sim,
    /// A pty pair with an RTU slave in this process that answers at once: no line timing.
    Pty,
    /// The same simulated line, timed at its baud rate, served by `simulate --listen` in a
    /// process of its own; the gateway's bus reaches it as a serial device server (`tcp://`).
    DeviceServer,
    /// A Modbus TCP device in this process that answers at once, or after the scenario's
    /// `device_delay` (`framing = "tcp"` on `tcp://`): no serial line at all.
    TcpDevice,
}

impl Line {
    /// Whether the line keeps the physical timing of its baud rate, so that its efficiency and
    /// the gateway's line metrics mean something.
    pub(crate) fn timed(self) -> bool {
        matches!(self, Line::Sim | Line::DeviceServer)
    }
}

#[derive(Clone, Copy, PartialEq)]
pub(crate) enum Load {
    /// Read 10 holding registers (a block of its own), back to back, from each slave in turn.
    Read,
    /// Every fourth request a write of one register, the rest reads of 10.
    Mix,
    /// Connected, sending nothing.
    Idle,
    /// Every master reads the same 10 holding registers of slave 1, back to back: coalescing.
    Same,
    /// Every master reads its own 10 holding registers of slave 1, back to back: nothing to
    /// coalesce.
    Own,
    /// No master: every slave lists [`PLANT_VALUES`], which the gateway polls; the bench reads
    /// its metrics endpoint (`plant`).
    Values,
    /// Every master reads the whole of a virtual unit, back to back: answered from memory, from
    /// the values the gateway polls of the drives on the line (`virtual_unit`), no line time.
    Virtual,
    /// The `Values` load's slaves, their values published through a local mosquitto
    /// (`[mqtt]`), measured beside the same gateway without it; the masters read at a period
    /// beside the polls (`mqtt`).
    Mqtt,
    /// A listen-only line: its other master (`[bus.sim_master]`) reads a few slaves back to
    /// back; the gateway hears and pairs it, and one master reads the shadow (`listen`).
    Listen,
}

/// The gateway's audit journal (`[audit]`), which takes an entry for every write before it is
/// queued and one for its outcome.
#[derive(Clone, Copy, PartialEq, Debug)]
pub(crate) enum Journal {
    /// No `[audit]`.
    Off,
    /// A journal in a directory the bench makes: each entry handed to the kernel (`write`).
    On,
    /// The same with `fsync = true`: each write's entry synced to the disk before it is queued.
    Fsync,
}

impl Journal {
    /// As the scenarios' names and the reports say it.
    pub(crate) fn label(self) -> &'static str {
        match self {
            Journal::Off => "off",
            Journal::On => "on",
            Journal::Fsync => "fsync",
        }
    }
}

/// How the bench's masters talk to the gateway.
#[derive(Clone, Copy, PartialEq)]
pub(crate) enum Kind {
    /// Modbus TCP.
    Tcp,
    /// RTU frames on a TCP connection.
    RtuOverTcp,
    /// Modbus UDP.
    Udp,
    /// Modbus/TCP Security: Modbus TCP inside TLS, with a client certificate.
    Tls,
    /// The three kinds in turn, master by master.
    Mixed,
}

pub(crate) struct Scenario {
    pub(crate) name: String,
    pub(crate) line: Line,
    pub(crate) kind: Kind,
    pub(crate) framing: Framing,
    pub(crate) format: SerialFormat,
    pub(crate) masters: usize,
    pub(crate) load: Load,
    /// `[[bus]] coalesce_reads` (the gateway's default: on).
    pub(crate) coalesce: bool,
    /// A Modbus TCP device's `max_in_flight` (1: one request at a time).
    pub(crate) in_flight: usize,
    /// How long the Modbus TCP device takes to answer each request (zero: at once).
    pub(crate) device_delay: Duration,
    /// One more master, connecting from 127.0.0.2 (in `server.priority`), reading a block of its
    /// own: back to back (`Some(ZERO)`) or one read per period.
    pub(crate) priority: Option<Duration>,
    /// The priority master is a serial master on a serial master port of the gateway
    /// (`[[server.serial]]`, a `pty:` port with `priority = true`), not a TCP connection.
    pub(crate) priority_on_port: bool,
    pub(crate) journal: Journal,
    /// The MQTT load's `[mqtt] publish_interval`.
    pub(crate) publish_interval: Option<Duration>,
    /// `[[bus]] byte_timeout`: the silence that ends a frame, if longer than t3.5.
    pub(crate) byte_timeout: Option<Duration>,
}

impl Scenario {
    /// Whether the masters' transactions take the line's time, so that they are paced by it and
    /// its efficiency means something: a timed line, and not answered from memory.
    pub(crate) fn on_the_line(&self) -> bool {
        self.line.timed() && self.load != Load::Virtual
    }

    /// Modbus TCP masters on the simulated RTU line, reads coalescing, no priority master.
    fn sim(name: String, format: SerialFormat, masters: usize, load: Load) -> Scenario {
        Scenario {
            name,
            line: Line::Sim,
            kind: Kind::Tcp,
            framing: Framing::Rtu,
            format,
            masters,
            load,
            coalesce: true,
            in_flight: 1,
            device_delay: Duration::ZERO,
            priority: None,
            priority_on_port: false,
            journal: Journal::Off,
            publish_interval: None,
            byte_timeout: None,
        }
    }
}

/// 8 data bits, one stop bit.
fn format(baud: u32, parity: Parity) -> SerialFormat {
    SerialFormat {
        baud,
        data_bits: 8,
        parity,
        stop_bits: 1,
    }
}

/// The two simulated lines most scenarios run on, with their labels.
const LINES: [(u32, Parity, &str); 2] =
    [(9600, Parity::Even, "8E1"), (115_200, Parity::None, "8N1")];

/// Every scenario, in the order `--list` shows and a full run measures them.
pub(crate) fn scenarios() -> Vec<Scenario> {
    let mut all = Vec::new();
    line_scenarios(&mut all);
    kind_scenarios(&mut all);
    journal_scenarios(&mut all);
    many_scenarios(&mut all);
    for masters in [1, 100] {
        all.push(Scenario {
            line: Line::TcpDevice,
            framing: Framing::Tcp,
            ..Scenario::sim(
                format!("tcp-device-read-{masters}"),
                format(115_200, Parity::None),
                masters,
                Load::Read,
            )
        });
    }
    // The same 100 masters with 16 requests outstanding on the device's connection.
    all.push(Scenario {
        line: Line::TcpDevice,
        framing: Framing::Tcp,
        in_flight: 16,
        ..Scenario::sim(
            "tcp-device-pipelined-read-100".to_owned(),
            format(115_200, Parity::None),
            100,
            Load::Read,
        )
    });
    // 8 masters on a device that answers every request after 5 ms, one request at a time and 4.
    for (in_flight, name) in [
        (1, "tcp-device-5ms-read-8"),
        (4, "tcp-device-5ms-pipelined-read-8"),
    ] {
        all.push(Scenario {
            line: Line::TcpDevice,
            framing: Framing::Tcp,
            in_flight,
            device_delay: Duration::from_millis(5),
            ..Scenario::sim(
                name.to_owned(),
                format(115_200, Parity::None),
                8,
                Load::Read,
            )
        });
    }
    for masters in [0, 1000] {
        all.push(Scenario::sim(
            format!("idle-{masters}"),
            format(9600, Parity::Even),
            masters,
            Load::Idle,
        ));
    }
    plant_scenarios(&mut all);
    listen_scenarios(&mut all);
    // 100 masters reading a virtual unit, on the demo's 9600 8E1 line whose drives it shows.
    all.push(Scenario::sim(
        "virtual-unit-100".to_owned(),
        format(9600, Parity::Even),
        100,
        Load::Virtual,
    ));
    all
}

/// A listen-only 115200 line saturated by its other master, heard and paired, one master
/// reading the shadow: frames told apart by t3.5 of silence, as the spec has it, then by their
/// lengths alone, a silence of 10 ms (`byte_timeout`) ending only a frame they cannot measure:
/// what a host whose scheduler may hold the gateway longer than t3.5 needs.
fn listen_scenarios(all: &mut Vec<Scenario>) {
    for (byte_timeout, label) in [(None, ""), (Some(10), "-byte-timeout-10ms")] {
        all.push(Scenario {
            byte_timeout: byte_timeout.map(Duration::from_millis),
            ..Scenario::sim(
                format!("listen-115200{label}"),
                format(115_200, Parity::None),
                1,
                Load::Listen,
            )
        });
    }
}

/// The gateway polling plant values with no master, on the simulated line and behind a device
/// server; and the same values published over MQTT, with masters reading beside.
fn plant_scenarios(all: &mut Vec<Scenario>) {
    // The gateway polling plant values with no master; behind a device server, the simulated
    // slaves' CPU is `simulate`'s, so the gateway's own cost of polling shows.
    let name = format!("values-{SLAVES}x{}", PLANT_VALUES.len());
    let values = Scenario::sim(name, format(115_200, Parity::None), 0, Load::Values);
    let twin = Scenario {
        name: format!("device-server-{}", values.name),
        line: Line::DeviceServer,
        ..Scenario::sim(String::new(), values.format, 0, Load::Values)
    };
    all.extend([values, twin]);
    // The same values published through a local mosquitto, with masters reading beside: every
    // value again each 10 s (the poll interval; the simulated values never change, so that is
    // the steady rate), then each second, the least `publish_interval` takes.
    for (interval, label) in [(10, ""), (1, "-1s")] {
        all.push(Scenario {
            publish_interval: Some(Duration::from_secs(interval)),
            ..Scenario::sim(
                format!("mqtt{label}-{SLAVES}x{}", PLANT_VALUES.len()),
                format(115_200, Parity::None),
                crate::mqtt::MASTERS,
                Load::Mqtt,
            )
        });
    }
}

/// Modbus TCP masters reading (and writing) on the simulated RTU and ASCII lines; for 1 and 100
/// masters reading, right after, the same with the simulated line behind a device server, so
/// that a run of both interleaves them.
fn line_scenarios(all: &mut Vec<Scenario>) {
    for (baud, parity, label) in LINES {
        for masters in [1, 10, 100, 1000] {
            let name = format!("sim-{baud}-{label}-read-{masters}");
            let sim = Scenario::sim(name, format(baud, parity), masters, Load::Read);
            if masters == 1 || masters == 100 {
                let name = format!("device-server-{baud}-{label}-read-{masters}");
                let twin = Scenario {
                    name,
                    line: Line::DeviceServer,
                    ..Scenario::sim(String::new(), sim.format, masters, Load::Read)
                };
                all.extend([sim, twin]);
            } else {
                all.push(sim);
            }
        }
        let name = format!("sim-{baud}-{label}-mix-100");
        all.push(Scenario::sim(name, format(baud, parity), 100, Load::Mix));
    }
    let ascii_7e1 = SerialFormat {
        data_bits: 7,
        ..format(9600, Parity::Even)
    };
    for masters in [1, 100] {
        all.push(Scenario {
            framing: Framing::Ascii,
            ..Scenario::sim(
                format!("ascii-9600-7E1-read-{masters}"),
                ascii_7e1,
                masters,
                Load::Read,
            )
        });
    }
}

/// Masters of the other kinds on the 115200 line, and one master on the untimed pty.
fn kind_scenarios(all: &mut Vec<Scenario>) {
    let sim_115200 = format(115_200, Parity::None);
    for (kind, label) in [
        (Kind::RtuOverTcp, "rtu-over-tcp"),
        (Kind::Udp, "udp"),
        (Kind::Tls, "tls"),
        (Kind::Mixed, "mixed-kinds"),
    ] {
        // A mix of one master is one Modbus TCP master: the mix has 99, 33 of each kind.
        let counts: &[usize] = if kind == Kind::Mixed { &[99] } else { &[1, 99] };
        for &masters in counts {
            let name = format!("sim-115200-8N1-{label}-read-{masters}");
            all.push(Scenario {
                kind,
                ..Scenario::sim(name, sim_115200, masters, Load::Read)
            });
        }
    }
    // Over TLS too: with no line timing to hide it, what a TLS record costs shows.
    for (kind, name) in [(Kind::Tcp, "read"), (Kind::Tls, "tls-read")] {
        let name = format!("pty-115200-untimed-{name}-1");
        all.push(Scenario {
            line: Line::Pty,
            kind,
            ..Scenario::sim(name, sim_115200, 1, Load::Read)
        });
    }
}

/// The mixed load with the audit journal off, on, and on with `fsync`, one right after the other
/// so that a run compares them. 100 masters on the 115200 line, which is the bottleneck; on the
/// untimed pty and on a Modbus TCP device that answers at once, where what is left is the
/// gateway's own time (and on the device, no inter-frame gap either); and one master on each of
/// those two, whose every write waits for its own entry's sync where with 100 masters a write's
/// sync is long done before its turn. Their names end in `-journal-off`, `-journal-on` and
/// `-journal-fsync`; the last two are reported against the first.
fn journal_scenarios(all: &mut Vec<Scenario>) {
    let sim_115200 = format(115_200, Parity::None);
    for (line, prefix, masters) in [
        (Line::Sim, "sim-115200-8N1", 100),
        (Line::Pty, "pty-115200-untimed", 100),
        (Line::Pty, "pty-115200-untimed", 1),
        (Line::TcpDevice, "tcp-device", 100),
        (Line::TcpDevice, "tcp-device", 1),
    ] {
        let framing = if line == Line::TcpDevice {
            Framing::Tcp
        } else {
            Framing::Rtu
        };
        for journal in [Journal::Off, Journal::On, Journal::Fsync] {
            let name = format!("{prefix}-mix-{masters}-journal-{}", journal.label());
            all.push(Scenario {
                line,
                framing,
                journal,
                ..Scenario::sim(name, sim_115200, masters, Load::Mix)
            });
        }
    }
}

/// The `-journal-off` scenario that `name`, a `-journal-on` or `-journal-fsync` one, is
/// measured against.
pub(crate) fn journal_off_twin(name: &str) -> Option<String> {
    let stem = name
        .strip_suffix("-journal-on")
        .or_else(|| name.strip_suffix("-journal-fsync"))?;
    Some(format!("{stem}-journal-off"))
}

/// Many masters, one read: coalescing, what it costs when there is nothing to coalesce, and a
/// priority master among them.
fn many_scenarios(all: &mut Vec<Scenario>) {
    let sim_9600 = format(9600, Parity::Even);
    for (baud, parity, label) in LINES {
        for masters in [1, 10, 100] {
            let name = format!("many-{baud}-{label}-same-{masters}");
            all.push(Scenario::sim(
                name,
                format(baud, parity),
                masters,
                Load::Same,
            ));
        }
    }
    for (coalesce, suffix) in [(true, ""), (false, "-uncoalesced")] {
        let name = format!("many-9600-8E1-own-100{suffix}");
        all.push(Scenario {
            coalesce,
            ..Scenario::sim(name, sim_9600, 100, Load::Own)
        });
    }
    // A priority master among 100 that saturate the line: polling back to back (the share
    // limit decides), then every 200 ms (a fifth of the line).
    for (period, label) in [(Duration::ZERO, ""), (Duration::from_millis(200), "-200ms")] {
        let name = format!("many-9600-8E1-priority{label}-100");
        all.push(Scenario {
            priority: Some(period),
            ..Scenario::sim(name, sim_9600, 100, Load::Own)
        });
    }
    // The split bus: the line's old master on a serial master port of the gateway (a pty,
    // `priority = true`), polling every 100 ms, and 100 Modbus TCP masters saturating the line;
    // then the same master on TCP, for the port's own cost.
    for (on_port, name) in [
        (true, "serial-port-9600-8E1-priority-100ms-100"),
        (false, "many-9600-8E1-priority-100ms-100"),
    ] {
        all.push(Scenario {
            priority: Some(Duration::from_millis(100)),
            priority_on_port: on_port,
            ..Scenario::sim(name.to_owned(), sim_9600, 100, Load::Own)
        });
    }
}

/// The scenarios `chosen` names select: a whole name, or its leading part up to a `-`; all if
/// none.
pub(crate) fn select<'a>(all: &'a [Scenario], chosen: &[String]) -> Vec<&'a Scenario> {
    all.iter()
        .filter(|s| {
            chosen.is_empty()
                || chosen.iter().any(|c| {
                    s.name == *c
                        || s.name
                            .strip_prefix(c.as_str())
                            .is_some_and(|r| r.starts_with('-'))
                })
        })
        .collect()
}
