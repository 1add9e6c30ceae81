//! The `modbus-gateway` command: `run` (the default) serves the configured gateway until SIGINT or
//! SIGTERM; `check-config` validates the file and prints the resolved configuration; `simulate`
//! serves a bus's simulated slaves on a real serial device or a pty; `trace` prints the frames on
//! the lines of a running gateway; `health` asks a running gateway's /healthz; `audit` prints
//! the journal of writes (`[audit]`), each write with its outcome; `completions` and `man`
//! describe this command line. This file
//! is the command line and the dispatch; each subcommand but those two is in the library's
//! [`modbus_gateway::cli`].

use clap::{ArgAction, CommandFactory, Parser, Subcommand};
use clap_mangen::roff::{bold, italic, roman, Inline, Roff};
use modbus_gateway::cli::{
    self, audit,
    check_config::check_config,
    health,
    run::run,
    simulate::{simulate, Serve},
    trace,
};
use modbus_gateway::config::DEFAULT_PATH;
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    // The command's name, not the crate's (modbus-gatewayd): in --help, --version, the manual
    // pages and the completions.
    name = "modbus-gateway",
    version,
    about = "Modbus TCP to Modbus RTU (RS-485) gateway",
    long_about = "Modbus TCP to Modbus RTU (RS-485) gateway. Masters on Ethernet (Modbus TCP, RTU \
                  over TCP, UDP, Modbus/TCP Security) and on serial master ports share RS-485 \
                  lines of Modbus RTU or ASCII slaves: the gateway is the one master of each line, with the serial line \
                  spec's timing, fair sharing between masters, its own exceptions (0x0A, 0x0B, \
                  0x06) and Prometheus metrics. Without a subcommand it runs the gateway."
)]
struct Cli {
    /// Configuration file (TOML). MBGW__SECTION__KEY environment variables override it.
    #[arg(long, short, global = true, default_value = DEFAULT_PATH)]
    config: PathBuf,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Run the gateway (the default).
    Run,
    /// Validate the configuration and print it resolved, defaults included.
    CheckConfig {
        /// Print nothing when the configuration is valid (errors still go to stderr).
        #[arg(long)]
        quiet: bool,
    },
    /// Serve a bus's simulated slaves as RTU slaves on a serial device, at its baud and format,
    /// or its simulated line on a TCP socket as a serial device server in transparent mode.
    #[command(group(clap::ArgGroup::new("on").required(true).args(["device", "listen"])))]
    Simulate {
        /// The serial device to answer on, or `pty` for a new pty pair (its path is printed).
        #[arg(long)]
        device: Option<String>,
        /// Serve the line on this TCP address instead, one client at a time, in raw
        /// (transparent) mode; port 0 picks a free port (the address is printed).
        #[arg(long, value_name = "HOST:PORT")]
        listen: Option<String>,
        /// The bus whose [[bus.sim_slave]] entries to serve (default: the only one with any).
        #[arg(long)]
        bus: Option<String>,
    },
    /// Print the frames on the lines of a running gateway as they happen, decoded, one line per
    /// frame (from its metrics endpoint's /trace), until Ctrl-C.
    Trace {
        /// Only this bus's frames.
        #[arg(long)]
        bus: Option<String>,
        /// Only the frames to and from this slave address (0-255: a Modbus TCP device's units
        /// go up to 255).
        #[arg(long)]
        slave: Option<u8>,
        /// The trace's URL (default: `metrics.listen` of the configuration, path /trace).
        #[arg(long)]
        url: Option<String>,
    },
    /// Ask a running gateway whether it is alive: GET /healthz on its metrics endpoint (exit
    /// 0 on 200, printing its answer; 1 otherwise, saying why), within 5 s. The container
    /// image's health check.
    Health {
        /// Ask /readyz instead: every bus has its port open.
        #[arg(long)]
        ready: bool,
        /// The URL to ask (default: `metrics.listen` of the configuration, path /healthz, or
        /// /readyz with --ready).
        #[arg(long)]
        url: Option<String>,
    },
    /// Print the journal of writes (`[audit]`), each write with its outcome, oldest first.
    ///
    /// Each write-class request a master sent: when, who sent it, where it went, what it
    /// writes, the rule that decided and how it ended, one line per write (and a line for each
    /// gap in the journal). The filters combine: a write is printed when it matches all of them.
    Audit {
        /// The journal to read, with its rotated files PATH.1, PATH.2...; default: `audit.path`
        /// of the configuration. Given, no configuration file is read.
        #[arg(long, value_name = "PATH")]
        journal: Option<PathBuf>,
        #[command(flatten)]
        filters: AuditFilters,
    },
    /// Print a completion script for a shell (bash: save it as
    /// /usr/share/bash-completion/completions/modbus-gateway).
    Completions {
        /// The shell to complete in.
        shell: clap_complete::Shell,
    },
    /// Print the manual page (roff, as `man -l -` reads it), or write every page to a directory.
    Man {
        /// Write modbus-gateway.1 and a page per subcommand here instead.
        #[arg(long, value_name = "DIR")]
        out_dir: Option<PathBuf>,
    },
}

/// The `audit` subcommand's filters and format, as typed: the library checks them.
#[derive(clap::Args)]
struct AuditFilters {
    /// Only writes at or after TIME: UTC, as 2026-11-28T10:00:00Z, `2026-11-28 10:00:00` or
    /// 2026-11-28 (its midnight); or a duration ago, as 1h, 30m, 2days.
    #[arg(long, value_name = "TIME")]
    since: Option<String>,
    /// Only writes at or before TIME (as for --since).
    #[arg(long, value_name = "TIME")]
    until: Option<String>,
    /// Only writes from this master: an IP address (192.168.20.5), an address and port
    /// (192.168.20.5:50312, [fd00::5]:50312) or a network (192.168.20.0/24).
    #[arg(long, value_name = "ADDR")]
    master: Option<String>,
    /// Only writes to these unit ids: 3, or a list of ids and ranges as 1-4,7.
    #[arg(long, value_name = "UNITS")]
    unit: Option<String>,
    /// Only writes to this data address or any of a range, decimal or hex: 100, 0x2000,
    /// 0x2000-0x2001 (a write matches if the addresses it writes overlap it; a write whose
    /// bytes name no address, such as a user-defined function, never does).
    #[arg(long, value_name = "ADDRS")]
    register: Option<String>,
    /// Only writes that ended so: answered, slave_exception, gateway_exception, denied,
    /// acknowledged, timeout, broadcast, cancelled, or pending (no outcome recorded). Repeat it
    /// or give a comma list for any of several.
    #[arg(long, value_name = "WORD")]
    outcome: Vec<String>,
    /// Only writes routed to this bus.
    #[arg(long, value_name = "NAME")]
    bus: Option<String>,
    /// One JSON object a line instead: the write's journal fields, `kind` "write", and
    /// `outcome` (its outcome line's fields, or null, with `pending` saying why); a gap is
    /// its journal line.
    #[arg(long)]
    json: bool,
}

impl AuditFilters {
    fn options(&self) -> audit::Options {
        audit::Options {
            since: self.since.clone(),
            until: self.until.clone(),
            master: self.master.clone(),
            unit: self.unit.clone(),
            register: self.register.clone(),
            outcome: self.outcome.clone(),
            bus: self.bus.clone(),
            json: self.json,
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // These describe the command line itself: no configuration needed.
    match cli.command {
        Some(Command::Completions { shell }) => return print_completions(shell),
        Some(Command::Man { out_dir }) => return man_pages(out_dir.as_deref()),
        _ => {}
    }
    // Given its URL, the trace needs no configuration: it may run on another machine.
    if let Some(Command::Trace {
        bus,
        slave,
        url: Some(url),
    }) = &cli.command
    {
        return trace::trace(url, bus.as_deref(), *slave);
    }
    if let Some(Command::Health { url: Some(url), .. }) = &cli.command {
        return health::health(url);
    }
    // Given its path, the journal needs no configuration: it may be a copy on another machine.
    if let Some(Command::Audit {
        journal: Some(journal),
        filters,
    }) = &cli.command
    {
        return audit::audit(journal, &filters.options());
    }
    let config = match cli::load(&cli.config) {
        Ok(config) => config,
        Err(code) => return code,
    };
    match cli.command.unwrap_or(Command::Run) {
        Command::CheckConfig { quiet } => check_config(&cli.config, &config, quiet),
        Command::Run => run(&cli.config, config),
        Command::Simulate {
            device,
            listen,
            bus,
        } => {
            let on = match (device, listen) {
                (Some(device), _) => Serve::Device(device),
                (None, Some(listen)) => Serve::Listen(listen),
                (None, None) => unreachable!("clap requires --device or --listen"),
            };
            simulate(config, bus.as_deref(), &on)
        }
        Command::Trace { bus, slave, .. } => {
            let url = trace::url_of(config.metrics.listen);
            trace::trace(&url, bus.as_deref(), slave)
        }
        Command::Health { ready, .. } => {
            health::health(&health::url_of(config.metrics.listen, ready))
        }
        Command::Audit { filters, .. } => match audit::journal_of(&cli.config, &config) {
            Ok(journal) => audit::audit(&journal, &filters.options()),
            Err(code) => code,
        },
        Command::Completions { .. } | Command::Man { .. } => unreachable!("handled before loading"),
    }
}

/// The script is made in memory: clap_complete panics on a failed write (a closed pipe).
fn print_completions(shell: clap_complete::Shell) -> ExitCode {
    let mut command = Cli::command();
    let mut script = Vec::new();
    clap_complete::generate(shell, &mut command, "modbus-gateway", &mut script);
    let mut out = std::io::stdout().lock();
    let written = out.write_all(&script).and_then(|()| out.flush());
    match written {
        Err(error) if !cli::reader_gone(&error) => {
            eprintln!("modbus-gateway: cannot write to stdout: {error}");
            ExitCode::FAILURE
        }
        _ => ExitCode::SUCCESS,
    }
}

/// What the manual page says beyond the options: files, environment, exit status, where to read on.
const MAN_SECTIONS: &str = r#".SH FILES
.TP
/etc/modbus\-gateway/gateway.toml
The configuration (a conffile of the Debian package). Every key is described in
/usr/share/doc/modbus\-gateway/docs/configuration.md.
.TP
/usr/share/doc/modbus\-gateway/
The README, the reference pages (docs/), the demo configurations and the Prometheus files.
.SH ENVIRONMENT
.TP
MBGW__SECTION__KEY
Overrides a configuration key: MBGW__SERVER__LISTEN, MBGW__BUS__0__BAUD (array entries by index).
.TP
RUST_LOG
Overrides log.level (tracing's filter syntax).
.SH EXIT STATUS
0 on a clean stop (SIGTERM, SIGINT), a valid configuration, or when the reader of the output
goes away (a closed pipe); 2 when the configuration cannot be
used (each problem is written to stderr, naming its key); 1 on any other failure.
.SH SIGNALS
SIGHUP reloads the configuration; a configuration that cannot be used is refused and the one in
force stays. SIGTERM and SIGINT stop the gateway after the transactions in flight.
.SH SEE ALSO
systemctl(1), journalctl(1), promtool(1)
"#;

/// The command line as the manual describes it: without clap's `help` subcommand, which would be
/// listed as a page of its own that `--help` makes needless. Built, so that each subcommand has
/// its name on the command line (`modbus-gateway trace`) and its page's (`modbus-gateway-trace`).
fn man_command() -> clap::Command {
    let mut command = Cli::command().disable_help_subcommand(true);
    command.build();
    command
}

/// One argument as the synopsis writes it: an option with its value (`-c|--config <CONFIG>`), a
/// flag, or a positional's value (`SHELL`).
fn synopsis_arg(arg: &clap::Arg) -> Vec<Inline> {
    let takes_values = arg.get_num_args().is_some_and(|n| n.takes_values());
    let value = || {
        let names = arg.get_value_names().map_or_else(
            || arg.get_id().as_str().to_uppercase(),
            |names| {
                names
                    .iter()
                    .map(ToString::to_string)
                    .collect::<Vec<_>>()
                    .join(" ")
            },
        );
        italic(format!("<{names}>"))
    };
    if arg.is_positional() {
        return vec![value()];
    }
    let mut inline = Vec::new();
    if let Some(short) = arg.get_short() {
        inline.push(bold(format!("-{short}")));
    }
    if let Some(long) = arg.get_long() {
        if !inline.is_empty() {
            inline.push(roman("|"));
        }
        inline.push(bold(format!("--{long}")));
    }
    if takes_values {
        inline.push(roman(" "));
        inline.push(value());
    }
    inline
}

/// The SYNOPSIS section of `command`'s page. clap_mangen's (0.3) names each option without its
/// argument (`[-c|--config]`); this one writes it as `--help` does: `[-c|--config <CONFIG>]`,
/// `...` after an option that may be repeated, `<--device <DEVICE>|--listen <HOST:PORT>>` for a
/// group of which one is required.
fn render_synopsis(command: &clap::Command, out: &mut dyn Write) -> std::io::Result<()> {
    let name = command.get_bin_name().unwrap_or(command.get_name());
    let mut line = vec![bold(name)];
    let groups: Vec<Vec<&clap::Arg>> = command
        .get_groups()
        .filter(|group| group.is_required_set())
        .map(|group| {
            let members: Vec<&clap::Id> = group.get_args().collect();
            command
                .get_arguments()
                .filter(|arg| members.contains(&arg.get_id()))
                .collect()
        })
        .collect();
    let grouped = |arg: &clap::Arg| groups.iter().flatten().any(|m| m.get_id() == arg.get_id());
    let shown = |arg: &&clap::Arg| !arg.is_hide_set() && !grouped(arg);
    // Options first, then the groups, then the positionals, as clap's usage line has them.
    let options = command.get_arguments().filter(|a| !a.is_positional());
    let positionals = command.get_arguments().filter(|a| a.is_positional());
    for arg in options.filter(shown) {
        let (open, close) = if arg.is_required_set() {
            ("<", ">")
        } else {
            ("[", "]")
        };
        line.push(roman(format!(" {open}")));
        line.extend(synopsis_arg(arg));
        line.push(roman(close));
        if matches!(arg.get_action(), ArgAction::Append | ArgAction::Count) {
            line.push(roman("..."));
        }
    }
    for members in &groups {
        line.push(roman(" <"));
        for (i, arg) in members.iter().enumerate() {
            if i > 0 {
                line.push(roman("|"));
            }
            line.extend(synopsis_arg(arg));
        }
        line.push(roman(">"));
    }
    for arg in positionals.filter(shown) {
        line.push(roman(if arg.is_required_set() { " " } else { " [" }));
        line.extend(synopsis_arg(arg));
        line.push(roman(if arg.is_required_set() { "" } else { "]" }));
    }
    if command.has_subcommands() {
        let value = command.get_subcommand_value_name().unwrap_or("COMMAND");
        line.extend([roman(" ["), italic(value), roman("]")]);
    }
    let mut roff = Roff::default();
    roff.control("SH", ["SYNOPSIS"]);
    roff.text(line);
    roff.to_writer(out)
}

/// A page: clap's sections from the command line's definition, the synopsis of
/// [`render_synopsis`], and `more` before the version.
fn render_page(command: &clap::Command, more: &str, out: &mut dyn Write) -> std::io::Result<()> {
    let page = clap_mangen::Man::new(command.clone());
    page.render_title(out)?;
    page.render_name_section(out)?;
    render_synopsis(command, out)?;
    page.render_description_section(out)?;
    if command.get_arguments().any(|arg| !arg.is_hide_set()) {
        page.render_options_section(out)?;
    }
    if command.get_subcommands().any(|sub| !sub.is_hide_set()) {
        page.render_subcommands_section(out)?;
    }
    out.write_all(more.as_bytes())?;
    if command.get_version().is_some() {
        page.render_version_section(out)?;
    }
    Ok(())
}

/// The main page, with [`MAN_SECTIONS`].
fn render_main_page(out: &mut dyn Write) -> std::io::Result<()> {
    render_page(&man_command(), MAN_SECTIONS, out)
}

/// `command`'s page and its subcommands' pages, each in its file in `dir`.
fn write_pages(command: &clap::Command, more: &str, dir: &std::path::Path) -> std::io::Result<()> {
    for sub in command.get_subcommands().filter(|sub| !sub.is_hide_set()) {
        write_pages(sub, "", dir)?;
    }
    let name = clap_mangen::Man::new(command.clone()).get_filename();
    let mut file = std::io::BufWriter::new(std::fs::File::create(dir.join(name))?);
    render_page(command, more, &mut file)?;
    file.flush()
}

/// The main page on stdout, or every page in `out_dir`.
fn man_pages(out_dir: Option<&std::path::Path>) -> ExitCode {
    let written = match out_dir {
        None => render_main_page(&mut std::io::stdout()),
        Some(dir) => std::fs::create_dir_all(dir)
            .and_then(|()| write_pages(&man_command(), MAN_SECTIONS, dir)),
    };
    match written {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) if out_dir.is_none() && cli::reader_gone(&error) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("modbus-gateway: cannot write the manual pages: {error}");
            ExitCode::FAILURE
        }
    }
}
