//! `check-config`: the resolved configuration, preceded by what it means on each line (timing
//! worked out from the baud and format). Knows nothing of serving.

use crate::config::Config;
use crate::line::Framing;
use std::path::Path;
use std::process::ExitCode;

/// Print the description of the valid configuration `config` read from `path`, unless `quiet`.
pub fn check_config(path: &Path, config: &Config, quiet: bool) -> ExitCode {
    if !quiet {
        print!("{}", describe(path, config));
    }
    ExitCode::SUCCESS
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
        out += &match bus.framing {
            Framing::Rtu => format!(
                "# bus {}: {format}, character {}, t3.5 {}; frames start {} after the line \
                 falls silent; replies of unknown length end after {} of silence.\n",
                bus.name,
                ms(line.char_time),
                ms(line.t35),
                ms(master.gap),
                ms(master.silence),
            ),
            Framing::Ascii => format!(
                "# bus {}: Modbus ASCII at {format}, character {}; frames start {} after the \
                 line falls silent; a reply that stops for {} before its CR LF is dropped.\n",
                bus.name,
                ms(line.char_time),
                ms(master.gap),
                ms(master.silence),
            ),
        };
    }
    out + "\n" + &config.to_toml()
}
