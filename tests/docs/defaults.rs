//! Scenario: an operator leaves a key out because docs/configuration.md (or docs/plant-values.md)
//! gives its default, or uncomments a line of config/gateway.toml that shows one; either way the
//! gateway must run as if nothing had been written. Each documented default, and each commented
//! line of the shipped file, is written into a configuration that gives no optional key, and the
//! configuration printed resolved (what `check-config` prints, every derived value filled in)
//! must not change. A commented line that shows an example, not a default, is listed in
//! [`EXAMPLES`] with why; a default the docs give in words is checked through [`DERIVED`].

use super::page;
use modbus_gateway::Config;

/// A configuration with one of each section and only the keys that have no default, as
/// (section, its header, its lines). `server` and the like are empty: every key defaulted.
const BARE: &[(&str, &str, &[&str])] = &[
    ("server", "[server]", &[]),
    (
        "server.tls",
        "[server.tls]",
        &[
            "certificate = \"server.crt\"",
            "private_key = \"server.key\"",
            "client_ca = \"masters-ca.crt\"",
        ],
    ),
    (
        "server.serial",
        "[[server.serial]]",
        &["name = \"scada\"", "device = \"/dev/ttyS1\""],
    ),
    ("metrics", "[metrics]", &[]),
    ("log", "[log]", &[]),
    (
        "bus",
        "[[bus]]",
        &["name = \"line1\"", "device = \"/dev/ttyUSB0\""],
    ),
    ("bus.rs485", "[bus.rs485]", &[]),
    // The address and name of config/gateway.toml's slave and value, which its virtual unit
    // shows.
    ("bus.slave", "[[bus.slave]]", &["address = 3"]),
    (
        "bus.slave.value",
        "[[bus.slave.value]]",
        &["name = \"pump_pressure_pascals\"", "register = 0"],
    ),
    // [[bus.sim_slave]] is only on a simulated line: a second bus.
    ("sim", "[[bus]]", &["name = \"sim\"", "device = \"sim\""]),
    ("bus.sim_slave", "[[bus.sim_slave]]", &["address = 1"]),
    ("route", "[[route]]", &["units = \"100\"", "bus = \"sim\""]),
    ("rule", "[[rule]]", &["action = \"deny\""]),
    ("audit", "[audit]", &["path = \"writes.jsonl\""]),
    ("mqtt", "[mqtt]", &["url = \"mqtt://127.0.0.1:1883\""]),
];

/// The `[[virtual]]` sections, written after [`BARE`] only while one of theirs is checked: their
/// register shows config/gateway.toml's value, labels and all, which the examples of
/// `[[bus.slave.value]]` rename and label otherwise (a virtual register naming a series that is
/// not there is refused). [`VALUE`] stands for [`BARE`]'s value meanwhile.
const VIRTUAL: &[(&str, &str, &[&str])] = &[
    ("virtual", "[[virtual]]", &["unit = 250", "name = \"copy\""]),
    (
        "virtual.register",
        "[[virtual.register]]",
        &[
            "register = 0",
            "value = \"line1/3/pump_pressure_pascals{site=\\\"north\\\"}\"",
        ],
    ),
];

/// [`BARE`]'s value with the labels config/gateway.toml gives it, beside [`VIRTUAL`].
const VALUE: (&str, &str, &[&str]) = (
    "bus.slave.value",
    "[[bus.slave.value]]",
    &[
        "name = \"pump_pressure_pascals\"",
        "register = 0",
        "labels = { site = \"north\" }",
    ],
);

/// The sections of the bare configuration that `section` is checked in.
fn sections_for(
    section: &str,
) -> Vec<&'static (&'static str, &'static str, &'static [&'static str])> {
    let virtual_too = section.starts_with("virtual");
    let mut sections: Vec<_> = BARE
        .iter()
        .map(|s| {
            if virtual_too && s.0 == VALUE.0 {
                &VALUE
            } else {
                s
            }
        })
        .collect();
    if virtual_too {
        sections.extend(VIRTUAL);
    }
    sections
}

/// Commented lines of config/gateway.toml that show an example, not the default, by section and
/// key, with why, and the lines it needs beside it to be uncommented as it is.
const EXAMPLES: &[(&str, &str, &str, &[&str])] = &[
    ("server", "listen_rtu_over_tcp", "none by default", &[]),
    ("server", "listen_udp", "none by default", &[]),
    ("server", "listen_tls", "none by default", &[]),
    ("server", "allow", "empty by default: anyone", &[]),
    ("server", "read_only", "empty by default", &[]),
    ("server", "priority", "empty by default", &[]),
    (
        "server.tls",
        "certificate",
        "required: the paths an install uses",
        &[],
    ),
    ("server.tls", "private_key", "required", &[]),
    ("server.tls", "client_ca", "required", &[]),
    ("server.tls", "crl", "none by default", &[]),
    ("server.tls", "roles", "empty by default", &[]),
    (
        "bus",
        "inter_frame_delay",
        "default t3.5, which depends on the format",
        &[],
    ),
    (
        "bus",
        "byte_timeout",
        "default t3.5, 20 ms behind a device server",
        &[],
    ),
    (
        "bus",
        "latency_timer",
        "none by default: left as it is",
        &[],
    ),
    ("bus.slave", "response_timeout", "default the bus's", &[]),
    (
        "bus.slave",
        "coalesce_reads",
        "default the bus's; the example turns it off",
        &[],
    ),
    (
        "bus.slave",
        "cache",
        "default off; the line above says so",
        &[],
    ),
    ("bus.slave", "template", "none by default", &[]),
    (
        "bus.slave",
        "max_read_registers",
        "default the template's, else 125",
        &[],
    ),
    ("bus.slave.value", "register", "required", &[]),
    ("bus.slave.value", "unit", "none by default", &[]),
    ("bus.slave.value", "help", "default the name", &[]),
    ("bus.slave.value", "labels", "none by default", &[]),
    (
        "bus.slave.value",
        "poll_interval",
        "default the slave's",
        &[],
    ),
    ("bus.sim_slave", "address", "required", &[]),
    (
        "bus.sim_slave",
        "params",
        "none by default: factory parameters",
        &["model = \"gd20\""],
    ),
    (
        "bus.sim_slave",
        "trip",
        "none by default",
        &["model = \"gd20\""],
    ),
    (
        "bus.sim_slave",
        "late_reply",
        "fault knob, off when left out",
        &[],
    ),
    (
        "bus.sim_slave",
        "reply_address",
        "fault knob, off when left out",
        &[],
    ),
    (
        "bus.sim_slave",
        "reply_function",
        "fault knob, off when left out",
        &[],
    ),
    (
        "bus.sim_slave",
        "truncate_reply",
        "fault knob, off when left out",
        &[],
    ),
    (
        "bus.sim_slave",
        "reply_gap",
        "fault knob, off when left out",
        &["reply_gap_after = 2"],
    ),
    (
        "bus.sim_slave",
        "reply_gap_after",
        "fault knob, off when left out",
        &["reply_gap = \"10ms\""],
    ),
    ("route", "units", "required", &[]),
    ("route", "bus", "required", &[]),
    ("route", "address", "none by default", &[]),
    ("route", "offset", "an example; 0 by default", &[]),
    ("rule", "name", "default its place in the list", &[]),
    ("rule", "masters", "any by default", &[]),
    ("rule", "roles", "any by default", &[]),
    ("rule", "protocols", "any by default", &[]),
    ("rule", "buses", "any by default", &[]),
    ("rule", "units", "any by default", &[]),
    ("rule", "functions", "any by default", &[]),
    ("rule", "registers", "any by default", &[]),
    ("rule", "action", "required", &[]),
    ("audit", "path", "required", &[]),
    ("virtual", "unit", "required", &[]),
    ("virtual", "name", "required", &[]),
    (
        "virtual",
        "template",
        "none by default",
        &["source = { bus = \"line1\", slave = 3 }"],
    ),
    ("virtual", "source", "none by default", &[]),
    (
        "virtual",
        "max_age",
        "default three of the value's poll_interval",
        &[],
    ),
];

/// Defaults the reference gives in words, as (section, key, the value in [`BARE`]): the value
/// must be in the reference's words, and writing it must change nothing.
const DERIVED: &[(&str, &str, &str)] = &[
    ("server", "max_connections_per_address", "1016"),
    ("server.serial", "data_bits", "8"),
    ("server.serial", "stop_bits", "1"),
    ("bus", "data_bits", "8"),
    ("bus", "stop_bits", "1"),
    ("bus.slave", "max_read_registers", "125"),
];

/// [`BARE`] as TOML, with `added` (`key = value` lines) in `section`, each in place of that
/// key's line if the section has one.
fn bare_with(section: &str, added: &[String]) -> String {
    let keys: Vec<String> = added
        .iter()
        .map(|line| line.split_once(" = ").map_or(line.as_str(), |(key, _)| key))
        .map(|key| format!("{key} ="))
        .collect();
    let mut text = String::new();
    for (name, header, lines) in sections_for(section) {
        text.push_str(header);
        text.push('\n');
        let replaced = |line: &&&str| *name == section && keys.iter().any(|k| line.starts_with(k));
        for own in lines.iter().filter(|line| !replaced(line)) {
            text.push_str(own);
            text.push('\n');
        }
        if *name == section {
            for line in added {
                text.push_str(line);
                text.push('\n');
            }
        }
    }
    text
}

/// The configuration `text` printed resolved, or why it cannot be loaded.
fn resolved(text: &str) -> Result<String, String> {
    Config::from_toml_str(text)
        .map(|config| config.to_toml())
        .map_err(|e| e.to_string())
}

/// What writing `lines` into `section` does to the bare configuration: `None` if nothing
/// changes, else what did.
fn changes(section: &str, lines: &[String]) -> Option<String> {
    // With and without the virtual sections.
    static BASES: [std::sync::OnceLock<String>; 2] =
        [std::sync::OnceLock::new(), std::sync::OnceLock::new()];
    let which = usize::from(section.starts_with("virtual"));
    let base = BASES[which].get_or_init(|| {
        resolved(&bare_with(if which == 1 { "virtual" } else { "" }, &[]))
            .expect("the bare one loads")
    });
    match resolved(&bare_with(section, lines)) {
        Err(e) => Some(format!("refused: {e}")),
        Ok(printed) if printed == *base => None,
        Ok(printed) => {
            let added: Vec<&str> = printed.lines().filter(|l| !base.contains(l)).collect();
            Some(format!("prints {added:?}"))
        }
    }
}

/// The rows of the tables with a "Default" column in a Markdown page, as (section, key, default
/// cell), the section from the backticked `[table]` of the `##` heading above.
fn documented(text: &str) -> Vec<(String, String, String)> {
    let mut section = String::new();
    let mut rows = Vec::new();
    let mut default_column = None;
    for line in text.lines() {
        if let Some(heading) = line.strip_prefix("## ") {
            section = heading
                .split('`')
                .nth(1)
                .unwrap_or("")
                .trim_matches(['[', ']'])
                .to_owned();
            default_column = None;
        } else if line.starts_with("| Key |") {
            default_column = line.split('|').position(|cell| cell.trim() == "Default");
        } else if let (Some(column), Some(row)) = (default_column, line.strip_prefix("| `")) {
            let cells: Vec<&str> = line.split('|').collect();
            let keys: Vec<&str> = cells[1].split('`').skip(1).step_by(2).collect();
            let default = cells.get(column).map_or("", |c| c.trim());
            let defaults: Vec<&str> = default.split(", ").collect();
            if keys.len() > 1 && defaults.len() == keys.len() {
                // `scale`, `offset` | 1, 0
                for (key, default) in keys.iter().zip(defaults) {
                    rows.push((section.clone(), (*key).to_owned(), default.to_owned()));
                }
            } else if !row.is_empty() {
                rows.push((section.clone(), keys[0].to_owned(), default.to_owned()));
            }
        }
    }
    rows
}

/// The value a "Default" cell gives as TOML: one backticked value or a bare number, before any
/// words in parentheses (`` `"0s"` (off) ``); `None` for a default in words.
fn literal(cell: &str) -> Option<String> {
    let cell = cell.split(" (").next().unwrap_or(cell).trim();
    let inner = cell.strip_prefix('`').and_then(|c| c.strip_suffix('`'));
    let value = match inner {
        Some(value) if !value.contains('`') => value,
        _ => cell,
    };
    toml::from_str::<toml::Table>(&format!("v = {value}"))
        .ok()
        .map(|_| value.to_owned())
}

/// Every documented default of `text` (a page with "Default" columns) that is not the code's,
/// and how many were checked.
fn wrong_defaults(text: &str) -> (Vec<String>, usize) {
    let known: Vec<&str> = BARE
        .iter()
        .chain(VIRTUAL)
        .map(|(name, _, _)| *name)
        .collect();
    let mut wrong = Vec::new();
    let mut checked = 0;
    for (section, key, default) in documented(text) {
        if !known.contains(&section.as_str()) {
            continue;
        }
        let derived = DERIVED
            .iter()
            .find(|(s, k, _)| *s == section && *k == key)
            .map(|(_, _, value)| (*value).to_owned());
        let Some(value) = literal(&default).or(derived.clone()) else {
            continue;
        };
        if derived.is_some() && !default.contains(&value) {
            wrong.push(format!(
                "{section}.{key}: the default is {value}, not {default:?}"
            ));
        }
        checked += 1;
        if let Some(change) = changes(&section, &[format!("{key} = {value}")]) {
            wrong.push(format!(
                "{section}.{key} = {value} (documented default): {change}"
            ));
        }
    }
    (wrong, checked)
}

#[test]
fn every_default_the_reference_gives_is_the_one_the_gateway_runs_with() {
    let mut wrong = Vec::new();
    let mut checked = 0;
    for path in ["docs/configuration.md", "docs/plant-values.md"] {
        let (found, count) = wrong_defaults(&page(path));
        wrong.extend(found.into_iter().map(|w| format!("{path}: {w}")));
        checked += count;
    }
    assert!(wrong.is_empty(), "{wrong:#?}");
    assert!(checked > 60, "only {checked} defaults read from the pages");
}

#[test]
fn a_default_the_reference_gets_wrong_is_found() {
    let page = "## `[[bus]]`\n\n| Key | Default | Meaning |\n|---|---|---|\n\
                | `baud` | `9600` | Bits per second. |\n| `parity` | `\"even\"` | Parity. |\n\
                | `data_bits` | 7 for RTU | Data bits. |\n";
    let (wrong, checked) = wrong_defaults(page);
    assert_eq!(checked, 3);
    assert_eq!(wrong.len(), 2, "{wrong:#?}");
    assert!(wrong[0].starts_with("bus.baud = 9600 (documented default): prints"));
    assert!(wrong[1].contains("the default is 8, not \"7 for RTU\""));
}

/// The commented `#key = value` lines of config/gateway.toml, as (section, key, value), the
/// section from the header above, commented or not.
fn commented_lines(text: &str) -> Vec<(String, String, String)> {
    let mut section = String::new();
    let mut lines = Vec::new();
    for line in text.lines() {
        let bare = line.strip_prefix('#').unwrap_or(line);
        if bare.starts_with('[') {
            section = bare.trim_matches(['[', ']']).to_owned();
        } else if let Some((key, value)) = line.strip_prefix('#').and_then(|l| l.split_once(" = "))
        {
            if key.bytes().all(|b| b.is_ascii_lowercase() || b == b'_') {
                lines.push((section.clone(), key.to_owned(), value.to_owned()));
            }
        }
    }
    lines
}

/// Every commented line of `lines` (as [`commented_lines`] gives them) that cannot be
/// uncommented as it is, that is not the default though not listed in [`EXAMPLES`], or that is
/// the default though listed there.
fn wrong_lines(lines: &[(String, String, String)]) -> Vec<String> {
    let mut wrong = Vec::new();
    for (section, key, value) in lines {
        let example = EXAMPLES
            .iter()
            .find(|(s, k, _, _)| s == section && k == key);
        let mut written = vec![format!("{key} = {value}")];
        written.extend(
            example
                .iter()
                .flat_map(|e| e.3)
                .map(|line| (*line).to_owned()),
        );
        let example = example.is_some();
        match changes(section, &written) {
            Some(change) if change.starts_with("refused") => {
                wrong.push(format!(
                    "#{key} = {value} in [{section}] cannot be uncommented: {change}"
                ));
            }
            Some(change) if !example => {
                wrong.push(format!(
                    "#{key} = {value} in [{section}] is not the default: {change}"
                ));
            }
            None if example => {
                wrong.push(format!(
                    "#{key} = {value} in [{section}] is the default: not an example"
                ));
            }
            _ => {}
        }
    }
    wrong
}

#[test]
fn a_commented_line_that_is_not_the_default_is_found() {
    let text = "[[bus]]\n#baud = 9600\n#parity = \"even\"\n#inter_frame_delay = \"2ms\"\n\
                #queue_depth = \"many\"\n";
    let wrong = wrong_lines(&commented_lines(text));
    assert_eq!(wrong.len(), 2, "{wrong:#?}");
    assert!(wrong[0].starts_with("#baud = 9600 in [bus] is not the default"));
    assert!(wrong[1].starts_with("#queue_depth = \"many\" in [bus] cannot be uncommented"));
}

#[test]
fn every_commented_line_of_the_shipped_file_is_its_default_or_a_listed_example() {
    let lines = commented_lines(&page("config/gateway.toml"));
    assert!(
        lines.len() > 80,
        "only {} commented lines read",
        lines.len()
    );
    let wrong = wrong_lines(&lines);
    assert!(wrong.is_empty(), "{wrong:#?}");
    let unused: Vec<_> = EXAMPLES
        .iter()
        .filter(|(s, k, _, _)| !lines.iter().any(|(ls, lk, _)| ls == s && lk == k))
        .collect();
    assert!(
        unused.is_empty(),
        "examples the file no longer shows: {unused:?}"
    );
}

#[test]
fn the_shipped_file_names_every_shipped_template() {
    let text = page("config/gateway.toml");
    let dir = std::path::Path::new(super::ROOT).join("config/templates");
    for entry in std::fs::read_dir(dir).expect("config/templates") {
        let name = entry.expect("an entry").file_name();
        let name = name.to_string_lossy();
        let name = name.strip_suffix(".toml").expect("a .toml file");
        assert!(
            text.contains(name),
            "config/gateway.toml does not name the template {name}"
        );
    }
}
