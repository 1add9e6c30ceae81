//! The `[server.tls]` table: where the Modbus/TCP Security listeners find their certificate, key
//! and client CA, and what each certificate role may do. Paths and names as values; reading the
//! files is the TLS listener's business.

use super::defaults;
use super::serde_adapters::duration;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Tls {
    /// The server's certificate chain (PEM), its own certificate first.
    pub certificate: PathBuf,
    /// The private key of that certificate (PEM: PKCS#8, PKCS#1 or SEC1).
    pub private_key: PathBuf,
    /// The CA certificates (PEM bundle) every master's certificate must chain to.
    pub client_ca: PathBuf,
    /// What each role (the RoleOID extension of a master's certificate) may do.
    #[serde(default)]
    pub roles: BTreeMap<String, RoleAccess>,
    /// What a certificate with no role, or a role not in `roles`, may do.
    #[serde(default)]
    pub default_role_access: RoleAccess,
    /// The TLS handshake must be over this long after the connection is accepted.
    #[serde(with = "duration", default = "defaults::tls_handshake_timeout")]
    pub handshake_timeout: Duration,
}

/// What a role allows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RoleAccess {
    /// Every request.
    ReadWrite,
    /// The requests `server.read_only` allows; anything else gets exception 0x01.
    ReadOnly,
    /// Nothing: every request gets exception 0x01.
    #[default]
    None,
}

impl RoleAccess {
    pub fn name(self) -> &'static str {
        match self {
            RoleAccess::ReadWrite => "read_write",
            RoleAccess::ReadOnly => "read_only",
            RoleAccess::None => "none",
        }
    }
}

/// The `role` label of connections whose certificate has no role, or one not in `roles`.
pub const OTHER_ROLE: &str = "other";

#[cfg(test)]
mod tests {
    use crate::config::testing::{errors, MINIMAL};
    use crate::config::{Config, RoleAccess};

    const TLS: &str = "[server.tls]\ncertificate = \"/etc/mbgw/server.crt\"\n\
                       private_key = \"/etc/mbgw/server.key\"\nclient_ca = \"/etc/mbgw/ca.crt\"\n";

    #[test]
    fn roles_map_names_to_access_and_everyone_else_gets_none_by_default() {
        let c = Config::from_toml_str(&format!(
            "[server]\nlisten_tls = \"127.0.0.1:802\"\n{TLS}\
             roles = {{ operator = \"read_write\", viewer = \"read_only\", Guest = \"none\" }}\n\
             {MINIMAL}"
        ))
        .unwrap();
        let tls = c.server.tls.as_ref().unwrap();
        assert_eq!(tls.roles["operator"], RoleAccess::ReadWrite);
        assert_eq!(tls.roles["viewer"], RoleAccess::ReadOnly);
        assert_eq!(
            tls.roles["Guest"],
            RoleAccess::None,
            "role names keep their case"
        );
        assert_eq!(tls.default_role_access, RoleAccess::None);
        assert_eq!(tls.handshake_timeout, std::time::Duration::from_secs(10));
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
    }

    #[test]
    fn a_tls_listener_needs_the_tls_table_and_the_table_needs_its_three_files() {
        let e = errors(&format!(
            "[server]\nlisten_tls = \"127.0.0.1:802\"\n{MINIMAL}"
        ));
        assert_eq!(
            e,
            [
                "server.tls: server.listen_tls needs a [server.tls] table: certificate, \
              private_key and client_ca"
            ]
        );
        let e = errors(&format!(
            "[server.tls]\ncertificate = \"a\"\nprivate_key = \"b\"\n{MINIMAL}"
        ));
        assert_eq!(e.len(), 1);
        assert!(
            e[0].contains("server.tls") && e[0].contains("client_ca"),
            "{e:?}"
        );
    }

    #[test]
    fn an_unknown_access_a_reserved_role_name_and_a_zero_timeout_are_refused_by_key() {
        let e = errors(&format!(
            "{TLS}roles = {{ operator = \"write\" }}\n{MINIMAL}"
        ));
        assert!(e[0].starts_with("server.tls.roles.operator: "), "{e:?}");
        let e = errors(&format!(
            "{TLS}roles = {{ other = \"read_only\", \"\" = \"none\" }}\n\
             handshake_timeout = \"0s\"\n{MINIMAL}"
        ));
        assert_eq!(
            e,
            [
                "server.tls.roles: a role needs a name",
                "server.tls.roles.other: `other` is the role label of certificates whose role is \
                 not in the table; give the role another name",
                "server.tls.handshake_timeout: must be longer than 0",
            ]
        );
    }
}
