//! Loading: the TOML file with the `MBGW__` environment over it (or TOML text), deserialized with
//! every error named by its key path, then checked and resolved; and printing the resolved
//! configuration back. Owns [`ConfigError`] and [`ConfigErrors`]. Knows nothing of what the
//! values are used for.

use super::{Config, DriveCheck};
use std::fmt;
use std::path::Path;

/// Where the daemon looks for its file unless told otherwise.
pub const DEFAULT_PATH: &str = "/etc/modbus-gateway/gateway.toml";
/// Environment variables starting with this override file keys: `MBGW__SERVER__LISTEN`,
/// `MBGW__BUS__0__BAUD` (array entries by index).
pub const ENV_PREFIX: &str = "MBGW__";
const ENV_SEPARATOR: &str = "__";

/// One thing wrong with the configuration: the key path and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConfigError {
    pub key: String,
    pub reason: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.key, self.reason)
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

impl Config {
    /// Read `path`, apply the `MBGW__` variables among `env`, fill in defaults and validate. The
    /// simulated drives' parameters are not checked: [`Config::load_with`] checks them.
    pub fn load(
        path: &Path,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Config, ConfigErrors> {
        Self::finish(Self::read(path, env)?, None)
    }

    /// [`Config::load`], with the simulated drives' parameters checked by `drives`.
    pub fn load_with(
        path: &Path,
        env: impl IntoIterator<Item = (String, String)>,
        drives: &dyn DriveCheck,
    ) -> Result<Config, ConfigErrors> {
        Self::finish(Self::read(path, env)?, Some(drives))
    }

    /// Parse TOML text with no environment, fill in defaults and validate. The simulated
    /// drives' parameters are not checked: [`Config::from_toml_str_with`] checks them.
    pub fn from_toml_str(text: &str) -> Result<Config, ConfigErrors> {
        Self::finish(Self::parse(text)?, None)
    }

    /// [`Config::from_toml_str`], with the simulated drives' parameters checked by `drives`.
    pub fn from_toml_str_with(text: &str, drives: &dyn DriveCheck) -> Result<Config, ConfigErrors> {
        Self::finish(Self::parse(text)?, Some(drives))
    }

    fn read(
        path: &Path,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<config::Config, ConfigErrors> {
        let file = config::File::from(path)
            .format(config::FileFormat::Toml)
            .required(true);
        let mut builder = config::Config::builder().add_source(file);
        for (name, value) in env {
            let Some(rest) = name.strip_prefix(ENV_PREFIX) else {
                continue;
            };
            let key = env_key_path(rest);
            builder = builder
                .set_override(&key, value)
                .map_err(|e| ConfigErrors::one(&name, format!("cannot be used as `{key}`: {e}")))?;
        }
        builder
            .build()
            .map_err(|e| ConfigErrors::one(path.display().to_string(), e))
    }

    fn parse(text: &str) -> Result<config::Config, ConfigErrors> {
        config::Config::builder()
            .add_source(config::File::from_str(text, config::FileFormat::Toml))
            .build()
            .map_err(|e| ConfigErrors::one("(config)", e))
    }

    fn finish(
        raw: config::Config,
        drives: Option<&dyn DriveCheck>,
    ) -> Result<Config, ConfigErrors> {
        let mut config: Config = serde_path_to_error::deserialize(raw).map_err(named)?;
        config.check(drives)?;
        config.resolve();
        Ok(config)
    }

    /// The resolved configuration as TOML, defaults included.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# cannot print the configuration: {e}\n"))
    }
}

/// A deserialization error as the key path it happened at and why.
fn named(e: serde_path_to_error::Error<config::ConfigError>) -> ConfigErrors {
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
            ConfigErrors::one(join(field), "is required")
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
            ConfigErrors::one(key, reason)
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
        assert_eq!(c.server, Server::default());
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
    fn a_missing_file_is_an_error_naming_it() {
        let e = Config::load(Path::new("/nonexistent/gateway.toml"), []).unwrap_err();
        assert!(
            e.to_string().starts_with("/nonexistent/gateway.toml:"),
            "{e}"
        );
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
