//! `check-config`: the resolved configuration, preceded by what it means on each line (timing
//! worked out from the baud and format). Knows nothing of serving.

use crate::config::Config;
use crate::line::Parity;
use std::path::Path;
use std::process::ExitCode;

/// Print the description of the valid configuration `config` read from `path`, unless `quiet`.
pub fn check_config(path: &Path, config: &Config, quiet: bool) -> ExitCode {
    if !quiet {
        print!("{}", describe(path, config));
    }
    ExitCode::SUCCESS
}

pub(crate) fn format_name(parity: Parity) -> char {
    match parity {
        Parity::None => 'N',
        Parity::Even => 'E',
        Parity::Odd => 'O',
    }
}

fn ms(d: std::time::Duration) -> String {
    format!("{:.3} ms", d.as_secs_f64() * 1e3)
}

/// The resolved configuration, preceded by what it means on each line.
fn describe(path: &Path, config: &Config) -> String {
    let mut out = format!("# {} is valid.\n", path.display());
    for bus in &config.bus {
        let format = bus.format();
        let master = bus.master_timing();
        let line = master.line;
        out += &format!(
            "# bus {}: {} baud {}{}{}, character {}, t3.5 {}; frames start {} after the line \
             falls silent; replies of unknown length end after {} of silence.\n",
            bus.name,
            format.baud,
            format.data_bits,
            format_name(format.parity),
            format.stop_bits,
            ms(line.char_time),
            ms(line.t35),
            ms(master.gap),
            ms(master.silence),
        );
    }
    out + "\n" + &config.to_toml()
}
