//! Loading: the TOML file with the `MBGW__` environment over it (or TOML text), deserialized with
//! every error named by its key path, then checked and resolved; and printing the resolved
//! configuration back. Owns [`ConfigError`] and [`ConfigErrors`]. Knows nothing of what the
//! values are used for.

use super::{Config, DriveCheck, Templates, TlsFilesCheck};
use std::fmt;
use std::path::Path;

/// Where the daemon looks for its file unless told otherwise.
pub const DEFAULT_PATH: &str = "/etc/modbus-gateway/gateway.toml";
/// Environment variables starting with this override file keys: `MBGW__SERVER__LISTEN`,
/// `MBGW__BUS__0__BAUD` (array entries by index).
pub(crate) const ENV_PREFIX: &str = "MBGW__";
const ENV_SEPARATOR: &str = "__";

/// One thing wrong with the configuration: the key path and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConfigError {
    pub key: String,
    pub reason: String,
}

/// `key: reason`; the reason alone for a problem of the whole file (its key is empty), which
/// the caller names by the file.
impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.key.is_empty() {
            f.write_str(&self.reason)
        } else {
            write!(f, "{}: {}", self.key, self.reason)
        }
    }
}

/// Everything wrong with a configuration, reported together.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub struct ConfigErrors(pub Vec<ConfigError>);

impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

impl ConfigErrors {
    /// One problem, at `key`.
    pub(crate) fn one(key: impl Into<String>, reason: impl fmt::Display) -> Self {
        ConfigErrors(vec![ConfigError {
            key: key.into(),
            reason: reason.to_string(),
        }])
    }
}

/// `SERVER__LISTEN` -> `server.listen`; `BUS__0__SLAVE__1__ADDRESS` -> `bus[0].slave[1].address`.
fn env_key_path(rest: &str) -> String {
    let mut path = String::new();
    for part in rest.split(ENV_SEPARATOR) {
        if !part.is_empty() && part.bytes().all(|b| b.is_ascii_digit()) {
            path.push_str(&format!("[{part}]"));
        } else {
            if !path.is_empty() {
                path.push('.');
            }
            path.push_str(&part.to_ascii_lowercase());
        }
    }
    path
}

/// A text that is no TOML: config-rs's reason, a problem of the whole file.
fn unparsable(e: config::ConfigError) -> ConfigErrors {
    ConfigErrors::one("", e.to_string().trim_end())
}

/// Why the override `MBGW__{rest}` cannot be used, if it names an entry of a list that the file
/// `from_file` does not have (`BUS__0__SLAVE__1__...` with fewer than two `[[bus.slave]]`): it
/// would make an entry of its own out of that one key, and the entries before it out of nothing.
fn entry_not_in_file(from_file: &config::Config, rest: &str) -> Option<String> {
    let mut list = String::new();
    for part in rest.split(ENV_SEPARATOR) {
        if part.is_empty() || !part.bytes().all(|b| b.is_ascii_digit()) {
            if !list.is_empty() {
                list.push('.');
            }
            list.push_str(&part.to_ascii_lowercase());
            continue;
        }
        let entries = from_file
            .get_array(&list)
            .map_or(0, |entries| entries.len());
        if part.parse::<usize>().is_ok_and(|index| index < entries) {
            list.push_str(&format!("[{part}]"));
            continue;
        }
        let table = without_indices(&list);
        return Some(format!(
            "the file has no `{list}[{part}]` (it has {entries} [[{table}]]): an override changes \
             a key of an entry the file has, it does not add one"
        ));
    }
    None
}

impl Config {
    /// Read `path`, apply the `MBGW__` variables among `env`, fill in defaults and validate. The
    /// simulated drives' parameters are not checked: `Config::load_with` checks them.
    pub fn load(
        path: &Path,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Config, ConfigErrors> {
        Self::finish(Self::read(path, env)?, path.parent(), None, None)
    }

    /// [`Config::load`], with the simulated drives' parameters checked by `drives` and the
    /// `[server.tls]` files read by `tls`, their problems reported with the others.
    pub(crate) fn load_with(
        path: &Path,
        env: impl IntoIterator<Item = (String, String)>,
        drives: &dyn DriveCheck,
        tls: &dyn TlsFilesCheck,
    ) -> Result<Config, ConfigErrors> {
        Self::finish(
            Self::read(path, env)?,
            path.parent(),
            Some(drives),
            Some(tls),
        )
    }

    /// Parse TOML text with no environment, fill in defaults and validate. The simulated
    /// drives' parameters are not checked: `Config::from_toml_str_with` checks them.
    pub fn from_toml_str(text: &str) -> Result<Config, ConfigErrors> {
        Self::finish(Self::parse(text)?, None, None, None)
    }

    /// [`Config::from_toml_str`], with the simulated drives' parameters checked by `drives`.
    pub(crate) fn from_toml_str_with(
        text: &str,
        drives: &dyn DriveCheck,
    ) -> Result<Config, ConfigErrors> {
        Self::finish(Self::parse(text)?, None, Some(drives), None)
    }

    fn read(
        path: &Path,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<config::Config, ConfigErrors> {
        // Read here, not by config-rs, whose errors name the file again (the caller names it).
        let text = std::fs::read_to_string(path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => {
                ConfigErrors::one("", "not found (`--config FILE` reads another)")
            }
            _ => ConfigErrors::one("", format!("cannot be read: {e}")),
        })?;
        let from_file = config::Config::builder()
            .add_source(config::File::from_str(&text, config::FileFormat::Toml))
            .build()
            .map_err(unparsable)?;
        // The file as parsed, once: its entries are what the overrides are checked against.
        let mut builder = config::Config::builder().add_source(from_file.clone());
        let mut errors = Vec::new();
        for (name, value) in env {
            let Some(rest) = name.strip_prefix(ENV_PREFIX) else {
                continue;
            };
            if let Some(reason) = entry_not_in_file(&from_file, rest) {
                errors.push(ConfigError { key: name, reason });
                continue;
            }
            let key = env_key_path(rest);
            builder = builder
                .set_override(&key, value)
                .map_err(|e| ConfigErrors::one(&name, format!("cannot be used as `{key}`: {e}")))?;
        }
        if !errors.is_empty() {
            return Err(ConfigErrors(errors));
        }
        builder.build().map_err(|e| ConfigErrors::one("", e))
    }

    fn parse(text: &str) -> Result<config::Config, ConfigErrors> {
        config::Config::builder()
            .add_source(config::File::from_str(text, config::FileFormat::Toml))
            .build()
            .map_err(unparsable)
    }

    /// Deserialize, check and resolve. A key that cannot be read is reported and taken out, and
    /// the rest read again, so one run names every unknown key and unreadable value (up to
    /// [`MAX_REPORTED`]); the checks run on what remains, and report what the removed keys do not
    /// explain. A required key missing, or unreadable, takes out what holds it (a `[[rule]]`
    /// without a readable `action`: the whole `rule` list, which its checks then skip), and the
    /// reading goes on; one missing at the top level ends it. The
    /// templates are read from `template_dir`, taken from `base` (the file's folder) if relative.
    fn finish(
        raw: config::Config,
        base: Option<&Path>,
        drives: Option<&dyn DriveCheck>,
        tls: Option<&dyn TlsFilesCheck>,
    ) -> Result<Config, ConfigErrors> {
        let mut root: config::Value = raw
            .try_deserialize()
            .map_err(|e| ConfigErrors::one("", e))?;
        fractions_as_text(&mut root);
        let mut errors = Vec::new();
        let mut removed: Vec<String> = Vec::new();
        loop {
            let error = match serde_path_to_error::deserialize::<_, Config>(root.clone()) {
                Ok(mut config) => {
                    // Tables are read in no particular order: report in key order.
                    errors.sort_by(|a: &ConfigError, b| a.key.cmp(&b.key));
                    let dir = config.template_dir.as_ref().map(|dir| match base {
                        Some(base) => base.join(dir),
                        None => dir.clone(),
                    });
                    let templates = Templates::load(dir.as_deref(), "template_dir");
                    let unread = match templates {
                        Ok(templates) => {
                            config.templates = templates;
                            None
                        }
                        Err(unread) => Some(unread),
                    };
                    let mut checked = config.check(drives);
                    if let Some(unread) = unread {
                        match &mut checked {
                            Err(found) => found.0.splice(0..0, unread.0).for_each(drop),
                            Ok(()) => checked = Err(unread),
                        }
                    }
                    let files = tls.zip(config.server.tls.as_ref());
                    if let Some(Err(more)) = files.map(|(tls, settings)| tls.read_files(settings)) {
                        match &mut checked {
                            Err(found) => found.0.extend(more.0),
                            Ok(()) => checked = Err(more),
                        }
                    }
                    if errors.is_empty() {
                        checked?;
                        config.resolve();
                        return Ok(config);
                    }
                    if let Err(more) = checked {
                        let explained = |e: &ConfigError| removed.iter().any(|r| under(&e.key, r));
                        errors.extend(more.0.into_iter().filter(|e| !explained(e)));
                    }
                    return Err(ConfigErrors(errors));
                }
                Err(error) => error,
            };
            let segments: Vec<_> = error.path().iter().cloned().collect();
            let named = named(error);
            if removed.iter().any(|r| under(&named.key, r)) {
                // Already reported. A required key taken out (`action = "block"`) leaves its table
                // unreadable: take out what holds it (the whole `rule` list), and read on.
                if let (REQUIRED, Some(key)) = (named.reason.as_str(), remove(&mut root, &segments))
                {
                    removed.push(key);
                    continue;
                }
                break;
            }
            errors.push(named);
            match remove(&mut root, &segments) {
                Some(key) if errors.len() < MAX_REPORTED => removed.push(key),
                _ => break,
            }
        }
        errors.sort_by(|a, b| a.key.cmp(&b.key));
        Err(ConfigErrors(errors))
    }

    /// The resolved configuration as TOML, defaults included.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# cannot print the configuration: {e}\n"))
    }
}

/// Every number with a fraction in `value`, as its text. config-rs rounds a float read as an
/// integer (`stop_bits = 1.5` would be 2); as text, an integer key refuses it (see
/// [`whole_number`]) and a float key reads it as before.
fn fractions_as_text(value: &mut config::Value) {
    use config::ValueKind;
    match &mut value.kind {
        ValueKind::Float(f) if f.fract() != 0.0 => value.kind = ValueKind::String(f.to_string()),
        ValueKind::Table(table) => table.values_mut().for_each(fractions_as_text),
        ValueKind::Array(items) => items.iter_mut().for_each(fractions_as_text),
        _ => {}
    }
}

/// config-rs's reason for text that is no integer, when the text is a number with a fraction:
/// the file's fraction (see [`fractions_as_text`]), or the same written in quotes.
fn whole_number(reason: &str) -> Option<String> {
    let text = reason
        .strip_prefix("invalid type: string \"")?
        .split_once("\", expected an integer")?
        .0;
    text.parse::<f64>()
        .is_ok_and(f64::is_finite)
        .then(|| format!("`{text}` is not a whole number"))
}

/// The reason a missing required key is reported with.
const REQUIRED: &str = "is required";

/// Most errors one run reports; a file past this is probably not a gateway configuration.
const MAX_REPORTED: usize = 50;

/// Whether `key` is `prefix` or a key inside it (`bus[0].baud` is under `bus[0]`).
fn under(key: &str, prefix: &str) -> bool {
    key.strip_prefix(prefix)
        .is_some_and(|rest| rest.is_empty() || rest.starts_with(['.', '[']))
}

/// Take the table key at `path` out of `root`; for a path ending inside an array, the key that
/// holds the array (taking one element out would renumber the others). Returns the path of what
/// was taken out, or `None` when there is nothing there to take.
fn remove(root: &mut config::Value, path: &[serde_path_to_error::Segment]) -> Option<String> {
    use config::ValueKind;
    use serde_path_to_error::Segment;
    let last_key = path
        .iter()
        .rposition(|s| matches!(s, Segment::Map { .. }))?;
    let mut node = root;
    let mut taken = String::new();
    for segment in &path[..last_key] {
        match (segment, &mut node.kind) {
            (Segment::Map { key }, ValueKind::Table(table)) => {
                if !taken.is_empty() {
                    taken.push('.');
                }
                taken.push_str(key);
                node = table.get_mut(key)?;
            }
            (Segment::Seq { index }, ValueKind::Array(items)) => {
                taken.push_str(&format!("[{index}]"));
                node = items.get_mut(*index)?;
            }
            _ => return None,
        }
    }
    let Segment::Map { key } = &path[last_key] else {
        return None;
    };
    let ValueKind::Table(table) = &mut node.kind else {
        return None;
    };
    table.remove(key)?;
    if !taken.is_empty() {
        taken.push('.');
    }
    taken.push_str(key);
    Some(taken)
}

/// serde's reason for an unknown key (`unknown field `party`, expected one of `name`, `parity`,
/// ...`), with the nearest expected name suggested when one is close, as cargo and clap do:
/// `unknown field `party`; did you mean `parity`?`.
fn with_suggestion(reason: String) -> String {
    let Some(rest) = reason.strip_prefix("unknown field `") else {
        return reason;
    };
    let Some((given, expected)) = rest.split_once('`') else {
        return reason;
    };
    let candidates: Vec<&str> = expected.split('`').skip(1).step_by(2).collect();
    // Close in spelling (clap's measure and threshold), or else the one key that has the name as
    // a word of its own (`timeout` for `response_timeout`).
    let close = candidates
        .iter()
        .map(|c| (strsim::jaro(given, c), *c))
        .filter(|(score, _)| *score > 0.7)
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, c)| c);
    let mut containing = candidates
        .iter()
        .filter(|c| c.split('_').any(|word| word == given));
    let word = match (containing.next(), containing.next()) {
        (Some(only), None) => Some(*only),
        _ => None,
    };
    match close.or(word) {
        Some(name) => format!("unknown field `{given}`; did you mean `{name}`?"),
        None => reason,
    }
}

/// For a table written `[bus]` where a list of tables is expected (`bus[0].slave` is
/// `[[bus.slave]]`): how to write it.
fn list_of_tables(key: &str) -> Option<String> {
    let field = key.rsplit('.').next()?;
    let table = without_indices(key);
    Some(format!("`{field}` is a list of tables: write [[{table}]]"))
}

/// A key path as its table's header names it: `bus[0].slave` is `bus.slave`.
fn without_indices(key: &str) -> String {
    let mut table = String::new();
    let mut in_index = false;
    for c in key.chars() {
        match c {
            '[' => in_index = true,
            ']' => in_index = false,
            c if !in_index => table.push(c),
            _ => {}
        }
    }
    table
}

/// A deserialization error as the key path it happened at and why.
fn named(e: serde_path_to_error::Error<config::ConfigError>) -> ConfigError {
    let path = e.path().to_string();
    let path = if path == "." { String::new() } else { path };
    let join = |field: &str| match path.as_str() {
        "" => field.to_owned(),
        p => format!("{p}.{field}"),
    };
    match e.into_inner() {
        // config-rs names a missing field by its whole (unseparated) path: keep the field.
        config::ConfigError::NotFound(missing) => {
            let field = missing.rsplit([']', '.']).next().unwrap_or(&missing);
            ConfigError {
                key: join(field),
                reason: REQUIRED.to_owned(),
            }
        }
        other => {
            let mut reason = other.to_string();
            if let Some(at) = reason.find(" for key `") {
                reason.truncate(at);
            }
            let key = if path.is_empty() {
                "(top level)".to_owned()
            } else {
                path
            };
            let reason = if reason == "invalid type: map, expected a sequence" {
                list_of_tables(&key).unwrap_or(reason)
            } else if let Some(fraction) = whole_number(&reason) {
                fraction
            } else {
                with_suggestion(reason)
            };
            ConfigError { key, reason }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::testing::{errors, MINIMAL};
    use crate::config::{defaults, LogFormat, Server};
    use crate::line::Parity;
    use std::time::Duration;

    #[test]
    fn a_minimal_file_gets_every_default() {
        let c = Config::from_toml_str(MINIMAL).unwrap();
        let per_address = defaults::max_connections_per_address(defaults::MAX_CONNECTIONS);
        let server = Server {
            max_connections_per_address: Some(per_address),
            ..Server::default()
        };
        assert_eq!(c.server, server);
        assert_eq!(c.metrics.listen, defaults::metrics_listen());
        assert_eq!(
            (c.log.level.as_str(), c.log.format),
            ("info", LogFormat::Text)
        );
        let bus = &c.bus[0];
        assert_eq!(
            (bus.baud, bus.data_bits, bus.parity),
            (19_200, Some(8), Parity::Even)
        );
        assert_eq!(bus.stop_bits, Some(1), "parity even means one stop bit");
        assert_eq!(bus.response_timeout, Duration::from_secs(1));
        assert_eq!(bus.turnaround_delay, Duration::from_millis(100));
        assert!(bus.broadcast_reply);
        assert!(!bus.retry_writes);
    }

    #[test]
    fn an_unknown_key_is_named_with_its_path() {
        let e = errors(&format!("{MINIMAL}\nbaud_rate = 9600"));
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("bus[0]"), "{e:?}");
        assert!(e[0].contains("baud_rate"), "{e:?}");
    }

    #[test]
    fn a_wrong_value_is_named_with_its_path_and_reason() {
        let e = errors(&format!("{MINIMAL}\nparity = \"evn\""));
        assert!(e[0].starts_with("bus[0].parity:"), "{e:?}");
        assert!(!e[0].contains("for key"), "{e:?}");
        let e = errors(&format!("{MINIMAL}\nresponse_timeout = \"soon\""));
        assert!(e[0].starts_with("bus[0].response_timeout:"), "{e:?}");
        assert!(e[0].contains("soon"), "{e:?}");
        let e = errors(&format!("[server]\nlisten = \"localhost\"\n{MINIMAL}"));
        assert!(e[0].starts_with("server.listen:"), "{e:?}");
    }

    #[test]
    fn every_unknown_key_and_unreadable_value_is_reported_in_one_run_with_suggestions() {
        let text = format!(
            "{MINIMAL}\nparty = \"even\"\nbaud = \"fast\"\nresponse_timeout = \"0s\"\n\
             [metrics]\nlistne = \"127.0.0.1:9000\"\nzzz = 1\n"
        );
        let e = errors(&text);
        assert_eq!(
            e,
            [
                "bus[0].baud: invalid type: string \"fast\", expected an integer",
                "bus[0].party: unknown field `party`; did you mean `parity`?",
                "metrics.listne: unknown field `listne`; did you mean `listen`?",
                "metrics.zzz: unknown field `zzz`, expected `listen`",
                "bus[0].response_timeout: must be longer than 0",
            ],
        );
    }

    #[test]
    fn the_checks_run_on_what_remains_once_the_unreadable_keys_are_out() {
        let text = format!(
            "[server]\nmax_connections = \"many\"\n{MINIMAL}\nparty = \"even\"\nresponse_timeout = \"0s\"\n"
        );
        let e = errors(&text);
        assert_eq!(e.len(), 3, "{e:?}");
        assert_eq!(
            e[0],
            "bus[0].party: unknown field `party`; did you mean `parity`?"
        );
        assert!(e[1].starts_with("server.max_connections: invalid"), "{e:?}");
        assert_eq!(e[2], "bus[0].response_timeout: must be longer than 0");
    }

    #[test]
    fn a_name_close_to_nothing_gets_the_list_of_what_is_expected() {
        assert_eq!(
            with_suggestion("unknown field `q`, expected one of `name`, `parity`".into()),
            "unknown field `q`, expected one of `name`, `parity`"
        );
        assert_eq!(
            with_suggestion("invalid type: string".into()),
            "invalid type: string"
        );
    }

    #[test]
    fn a_single_table_where_a_list_of_tables_belongs_says_to_write_double_brackets() {
        for (text, expected) in [
            (
                "[bus]\nname = \"a\"\ndevice = \"sim\"\n",
                "bus: `bus` is a list of tables: write [[bus]]",
            ),
            (
                "[[bus]]\nname = \"a\"\ndevice = \"sim\"\n[bus.slave]\naddress = 1\n",
                "bus[0].slave: `slave` is a list of tables: write [[bus.slave]]",
            ),
            (
                "[[bus]]\nname = \"a\"\ndevice = \"sim\"\n[bus.sim_slave]\naddress = 1\n",
                "bus[0].sim_slave: `sim_slave` is a list of tables: write [[bus.sim_slave]]",
            ),
            (
                "[[bus]]\nname = \"a\"\ndevice = \"sim\"\n[route]\nbus = \"a\"\n",
                "route: `route` is a list of tables: write [[route]]",
            ),
        ] {
            assert_eq!(errors(text), [expected], "{text}");
        }
    }

    #[test]
    fn a_duration_written_as_a_number_or_negative_names_the_key_and_shows_a_valid_one() {
        for (value, why) in [
            ("0.5", "a duration needs its unit, as a string"),
            ("\"-1s\"", "a duration cannot be negative"),
        ] {
            let text =
                format!("[[bus]]\nname = \"a\"\ndevice = \"sim\"\nresponse_timeout = {value}\n");
            let e = errors(&text);
            assert_eq!(e.len(), 1, "{e:?}");
            assert!(e[0].starts_with("bus[0].response_timeout: "), "{e:?}");
            assert!(e[0].contains("\"500ms\"") && e[0].contains(why), "{e:?}");
        }
    }

    #[test]
    fn a_missing_required_key_is_named() {
        let e = errors("[[bus]]\nname = \"a\"\n");
        assert_eq!(e, ["bus[0].device: is required"]);
    }

    #[test]
    fn environment_variables_override_the_file_including_array_entries() {
        let dir = std::env::temp_dir().join(format!("mbgw-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("gateway.toml");
        std::fs::write(&path, MINIMAL).unwrap();
        let env = [
            ("MBGW__SERVER__LISTEN", "127.0.0.1:5020,[::1]:5020"),
            ("MBGW__BUS__0__BAUD", "9600"),
            ("MBGW__BUS__0__RETRY_WRITES", "true"),
            ("MBGW__BUS__0__RESPONSE_TIMEOUT", "250ms"),
            ("PATH", "/usr/bin"),
        ]
        .map(|(k, v)| (k.to_owned(), v.to_owned()));
        let c = Config::load(&path, env).unwrap();
        assert_eq!(c.server.listen.len(), 2);
        assert_eq!(c.server.listen[1], "[::1]:5020".parse().unwrap());
        assert_eq!(c.bus[0].baud, 9600);
        assert!(c.bus[0].retry_writes);
        assert_eq!(c.bus[0].response_timeout, Duration::from_millis(250));

        let typo = [("MBGW__SERVER__LISTN".to_owned(), "x".to_owned())];
        let e = Config::load(&path, typo).unwrap_err().to_string();
        assert!(e.starts_with("server"), "{e}");
        assert!(e.contains("listn"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_missing_file_says_so_once_for_the_caller_to_name_it() {
        let e = Config::load(Path::new("/nonexistent/gateway.toml"), []).unwrap_err();
        assert_eq!(e.to_string(), "not found (`--config FILE` reads another)");
        let e = Config::from_toml_str("[[bus]\n").unwrap_err().to_string();
        assert!(e.starts_with("TOML parse error at line 1, column 7"), "{e}");
        assert!(!e.ends_with('\n'), "{e:?}");
    }

    #[test]
    fn every_enum_key_names_its_value_and_the_allowed_ones_beside_the_other_errors() {
        let text = "[server]\nwhen_full = \"wait\"\n[log]\nformat = \"xml\"\n\
                    [[bus]]\nname = \"a\"\ndevice = \"sim\"\nframing = \"rtux\"\n\
                    response_timeout = \"0s\"\n[bus.rs485]\nmode = \"auto\"\n\
                    [[bus.sim_slave]]\naddress = 1\nmodel = \"gd99\"\n\
                    [[rule]]\naction = \"block\"\n[[rule]]\naction = \"deny\"\n\
                    [audit]\npath = \"/tmp/j\"\non_error = \"maybe\"\n";
        assert_eq!(
            errors(text),
            [
                "audit.on_error: `maybe` is not deny_writes or allow",
                "bus[0].framing: `rtux` is not rtu, ascii or tcp",
                "bus[0].rs485.mode: `auto` is not off, kernel or rts",
                "bus[0].sim_slave[0].model: `gd99` is not registers, gd20, gd300, gd10, \
                 pd-inverter or sdm120",
                "log.format: `xml` is not text or json",
                "rule[0].action: `block` is not allow, deny or acknowledge",
                "server.when_full: `wait` is not close_oldest_idle or refuse",
                // The checks ran on the rest.
                "bus[0].response_timeout: must be longer than 0",
            ]
        );
    }

    #[test]
    fn an_integer_key_refuses_a_fraction_and_a_float_key_reads_it() {
        let text = format!(
            "{MINIMAL}\nbaud = 9600.7\nstop_bits = 1.5\n[[bus.slave]]\naddress = 2\n\
             [[bus.slave.value]]\nname = \"speed\"\nregister = 4\nscale = 0.1\n"
        );
        assert_eq!(
            errors(&text),
            [
                "bus[0].baud: `9600.7` is not a whole number",
                "bus[0].stop_bits: `1.5` is not a whole number",
            ]
        );
        let text = format!(
            "[server]\npriority_share = 0.5\n{MINIMAL}\nbaud = 9600.0\n[[bus.slave]]\n\
             address = 2\n[[bus.slave.value]]\nname = \"speed\"\nregister = 4\nscale = 0.1\n"
        );
        let c = Config::from_toml_str(&text).unwrap();
        assert_eq!(c.bus[0].baud, 9600);
        assert_eq!(c.bus[0].slave[0].value[0].scale, 0.1);
    }

    #[test]
    fn an_override_of_an_entry_the_file_lacks_is_refused_naming_the_variable() {
        let dir = std::env::temp_dir().join(format!("mbgw-entries-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("gateway.toml");
        std::fs::write(&path, format!("{MINIMAL}\n[[bus.slave]]\naddress = 3\n")).unwrap();
        let env = [
            ("MBGW__BUS__0__SLAVE__0__RESPONSE_TIMEOUT", "2s"),
            ("MBGW__BUS__0__SLAVE__1__RESPONSE_TIMEOUT", "2s"),
            ("MBGW__BUS__1__BAUD", "9600"),
        ]
        .map(|(k, v)| (k.to_owned(), v.to_owned()));
        let e: Vec<String> = Config::load(&path, env)
            .unwrap_err()
            .0
            .iter()
            .map(ToString::to_string)
            .collect();
        let why = "an override changes a key of an entry the file has, it does not add one";
        assert_eq!(
            e,
            [
                format!(
                    "MBGW__BUS__0__SLAVE__1__RESPONSE_TIMEOUT: the file has no \
                     `bus[0].slave[1]` (it has 1 [[bus.slave]]): {why}"
                ),
                format!("MBGW__BUS__1__BAUD: the file has no `bus[1]` (it has 1 [[bus]]): {why}"),
            ]
        );
        let env = [("MBGW__BUS__0__SLAVE__0__RESPONSE_TIMEOUT", "2s")]
            .map(|(k, v)| (k.to_owned(), v.to_owned()));
        let c = Config::load(&path, env).unwrap();
        assert_eq!(
            c.bus[0].slave[0].response_timeout,
            Some(Duration::from_secs(2))
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_printed_configuration_reads_back_the_same() {
        let text = format!(
            "{MINIMAL}\ninter_frame_delay = \"5ms\"\n[[bus.slave]]\naddress = 3\nresponse_timeout = \"2s\"\n\
             [[route]]\nunits = \"255\"\nbus = \"line1\"\naddress = 17\n"
        );
        let c = Config::from_toml_str(&text).unwrap();
        let again = Config::from_toml_str(&c.to_toml()).unwrap();
        assert_eq!(c, again, "{}", c.to_toml());
    }
}
