//! The `modbus-gateway` command: `run` (the default) serves the configured gateway until SIGINT or
//! SIGTERM; `check-config` validates the file and prints the resolved configuration; `simulate`
//! serves a bus's simulated slaves on a real serial device or a pty; `trace` prints the frames on
//! the lines of a running gateway. This file is the command line and the dispatch; each
//! subcommand is in the library's [`modbus_gateway::cli`].

use clap::{Parser, Subcommand};
use modbus_gateway::cli::{self, check_config::check_config, run::run, simulate::simulate, trace};
use modbus_gateway::config::DEFAULT_PATH;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(version, about = "Modbus TCP to Modbus RTU (RS-485) gateway")]
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
    /// Serve a bus's simulated slaves as RTU slaves on a serial device, at its baud and format.
    Simulate {
        /// The serial device to answer on, or `pty` for a new pty pair (its path is printed).
        #[arg(long)]
        device: String,
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
        /// Only the frames to and from this slave address (0-247).
        #[arg(long, value_parser = clap::value_parser!(u8).range(0..=247))]
        slave: Option<u8>,
        /// The trace's URL (default: `metrics.listen` of the configuration, path /trace).
        #[arg(long)]
        url: Option<String>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Given its URL, the trace needs no configuration: it may run on another machine.
    if let Some(Command::Trace {
        bus,
        slave,
        url: Some(url),
    }) = &cli.command
    {
        return trace::trace(url, bus.as_deref(), *slave);
    }
    let config = match cli::load(&cli.config) {
        Ok(config) => config,
        Err(code) => return code,
    };
    match cli.command.unwrap_or(Command::Run) {
        Command::CheckConfig { quiet } => check_config(&cli.config, &config, quiet),
        Command::Run => run(&cli.config, config),
        Command::Simulate { device, bus } => simulate(config, bus.as_deref(), &device),
        Command::Trace { bus, slave, .. } => {
            let url = trace::url_of(config.metrics.listen);
            trace::trace(&url, bus.as_deref(), slave)
        }
    }
}
