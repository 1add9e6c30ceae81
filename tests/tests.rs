//! The integration tests, in one crate so they build once. Where a new test goes:
//! - `device_link`: a bus behind a serial device server (`tcp://`), against device servers that
//!   misbehave as converters do: stale bytes, a late reply, a restart, a Modbus TCP server where a
//!   raw converter should be (pymodbus).
//! - `device_server`: a bus on `tcp://` or `rfc2217://` to ser2net in front of a pty, with
//!   pymodbus's RTU and ASCII servers behind it: third-party masters as on a local line, the
//!   line's settings over RFC 2217 (at every connect) and 0xFF both ways, ser2net restarted
//!   mid-traffic, a stale reply it forwards on the reconnect.
//! - `docs`: the reference pages (docs/) name every configuration key and every metric, and
//!   every link between them and the README leads somewhere; the package ships every demo;
//!   `docs::readme` runs the README's walkthroughs (writes and the journal, metric greps);
//!   `docs::paths`: every path the code's maps (docs/architecture.md, docs/development.md) name
//!   exists.
//! - `layers`: the crate's modules have no cycle, and `metrics` imports no runtime part.
//! - `clock`: no test sleeps on the real clock and then asserts, or bounds an elapsed time by
//!   the wall clock (read from the sources of tests/ and test-support/).
//! - `cli`: the binary: check-config, config errors, environment, run and stop, logs. (The bench's
//!   test is in `bench/tests/`.)
//! - `audit_cli`: the `audit` subcommand on a journal and its rotated files: writes joined to
//!   their outcomes, filters, `--json`, the configured journal, exit statuses.
//! - `audit_journal`: the journal of writes (`[audit]`): a `kill -9` in a burst of writes, a full
//!   file system under each `on_error`, a journal that cannot be opened, rotation.
//! - `tcp`: the Modbus TCP side and masters that abuse it: pipelining and floods, MBAP errors and
//!   length lies, half-sent requests, the connection limit and its policies, idle timeout,
//!   keepalive, garbage.
//! - `access`: `server.allow` and `server.read_only`.
//! - `hostile`: masters that break the rules on purpose: frames hidden after a request, every
//!   unit and function code to swell the metrics, floods of errors to drown the log, a serial
//!   master port's master sending noise, short frames and forbidden requests; a master reading
//!   and writing every address of a virtual unit.
//! - `answers`: what the gateway answers itself: no route, broadcast, queue full, port down/back.
//! - `ascii`: Modbus ASCII on the line, end to end: the manuals' frames, every function code, the
//!   fault knobs in ASCII, metrics, reload.
//! - `transparency`: function codes and exceptions byte for byte, on the sim line and a pty.
//! - `line`: the serial line discipline on the paused clock: timeouts, t3.5, retries, efficiency.
//! - `fairness`: hundreds of masters at once, and floods of the bus queue.
//! - `drives`: the simulated drives of config/demo.toml: registers, exceptions, ramps, timing.
//! - `faults`: each fault knob of a simulated slave and what the gateway makes of it.
//! - `serial`: the real serial path on pty pairs, with a third-party client.
//! - `serial_port_life`: a serial master port in a running gateway: opened when its UART
//!   appears, on `/status`, its `pty:` link there while the gateway runs.
//! - `rs485`: `[bus.rs485]` on ptys: a refused direction control (0x0A, the error naming the
//!   key), a line that echoes.
//! - `peers`: third-party peers on the serial path: pymodbus's RTU and ASCII servers behind the
//!   gateway, its ASCII client on `simulate`, its RTU-over-TCP and UDP clients on the gateway;
//!   `peers::tls_walkthrough` runs the TLS walkthrough of docs/security.md (openssl) and its TLS
//!   client; `peers::serial_port`: pymodbus's serial client (RTU, ASCII) and libmodbus's RTU
//!   master as the master of a serial master port, in front of the sim line and pymodbus's server.
//! - `values_peers`: plant values of every type and layout polled from pymodbus's RTU server on a
//!   pty, exact on `/values` and `/metrics`, in the plan's reads.
//! - `reads`: many masters, one read: coalescing and its freshness, `coalesce_reads = false`,
//!   the cache, priority masters and their share of the line.
//! - `rtu_over_tcp`: masters sending plain RTU frames on TCP: framing, bad CRCs, exceptions as RTU.
//! - `tcp_device`: a Modbus TCP device behind the gateway (`framing = "tcp"`): one connection for
//!   many masters, replies matched by transaction id, unit 0, `connect_delay`, a restart.
//! - `tls`: Modbus/TCP Security: roles, refused certificates, handshake timeout, many TLS masters.
//! - `udp`: Modbus UDP masters: replies to their source, access lists, what is dropped.
//! - `simulate`: the `simulate` subcommand answering RTU masters on a pty.
//! - `service`: the gateway under a service manager: graceful stop.
//! - `metrics`: `/metrics`, `/healthz`, `/readyz` after known traffic; promtool; shipped rules.
//! - `listen`: listen-only lines (`mode = "listen"`) on a shared line of ptys (the tap): a
//!   pymodbus master and slave heard, values and shadow reads, not a byte written; a hostile line.
//! - `mqtt`: `[mqtt]` against Debian's mosquitto and mosquitto_sub: values on change, deadband
//!   and publish_interval, retained flags, the last will, availability, Home Assistant discovery
//!   across restarts, sets under the rules and the journal, the broker down, mqtts, a wrong
//!   password, a publisher sending what its rules forbid.
//! - `status`: the status page `/` and its data `/status` after known traffic.
//! - `virtual_units`: `[[virtual]]` in a running gateway: the demo's drives, every encoding, a meter
//!   through its own template, staleness, the exceptions, writes through, ruled and journaled,
//!   a hundred masters at once.
//! - `trace`: `GET /trace` and the `trace` subcommand: frames, filters, slow readers, limits.
//! - `templates`: the shipped device templates against the simulated devices they were made
//!   for, each in a known state.
//! - `values`: plant values for Prometheus: a drive's values in their units, a slave that stops
//!   answering, `GET /values`, bad values and templates refused naming their keys.
//! - `writes`: `[[rule]]` through every protocol (each match key and action, what reaches the
//!   line) and the journal of writes: masters, rules and outcomes, reload, start errors.
//!
//! `support` has the shared pieces: the workspace's `test-support` crate (gateway start-up, typed
//! configurations, a bus on the simulated line, a raw master, a pty slave, the test PKI).
//!
//! `tests/soak.rs` is a crate of its own (it counts the whole process's heap with its own
//! allocator), ignored by plain `cargo test`; `.ci/run` runs it in release.

// Test code may be long and cast freely; the workspace lint table is for the product.
#![allow(
    unreachable_pub,
    clippy::too_many_lines,
    clippy::cast_possible_truncation,
    // Deadlines on daemons run as processes, which no paused clock reaches, and tokio's own
    // sleeps: src/timer.rs's choice of precision is the product's.
    clippy::disallowed_types,
    clippy::disallowed_methods
)]

mod support;

mod access;
mod answers;
mod ascii;
mod audit_cli;
mod audit_journal;
mod cli;
mod clock;
mod device_link;
mod device_server;
mod docs;
mod drives;
mod fairness;
mod faults;
mod hostile;
mod layers;
mod line;
mod listen;
mod metrics;
mod mqtt;
mod peers;
mod reads;
mod rs485;
mod rtu_over_tcp;
mod serial;
mod serial_port_life;
mod service;
mod simulate;
mod status;
mod tcp;
mod tcp_device;
mod templates;
mod tls;
mod trace;
mod transparency;
mod udp;
mod values;
mod values_peers;
mod virtual_units;
mod writes;
