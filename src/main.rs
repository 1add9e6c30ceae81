//! The `modbus-gateway` command: `run` (the default) serves the configured gateway until SIGINT or
//! SIGTERM; `check-config` validates the file and prints the resolved configuration; `simulate`
//! serves a bus's simulated slaves on a real serial device or a pty. This file is the command
//! line and the dispatch; each subcommand is in the library's [`modbus_gateway::cli`].

use clap::{Parser, Subcommand};
use modbus_gateway::cli::{self, check_config::check_config, run::run, simulate::simulate};
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
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let config = match cli::load(&cli.config) {
        Ok(config) => config,
        Err(code) => return code,
    };
    match cli.command.unwrap_or(Command::Run) {
        Command::CheckConfig { quiet } => check_config(&cli.config, &config, quiet),
        Command::Run => run(&cli.config, config),
        Command::Simulate { device, bus } => simulate(config, bus.as_deref(), &device),
    }
}
