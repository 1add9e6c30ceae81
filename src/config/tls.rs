//! The `[server.tls]` table: where the Modbus/TCP Security listeners find their certificate, key
//! and client CA, and what each certificate role may do; and a `tls://` device's `[bus.tls]`:
//! the gateway's client certificate and the CA its device must chain to. Paths and names as
//! values; reading the files is the TLS side's business.

use super::defaults;
use super::serde_adapters::duration;
use super::serde_adapters::{words, Choice};
use super::UnitSet;
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
    /// Certificate revocation lists (PEM) of the CAs in `client_ca`: a master's certificate
    /// listed there is refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crl: Option<PathBuf>,
    /// What each role (the RoleOID extension of a master's certificate) may do.
    #[serde(default)]
    pub roles: BTreeMap<String, Role>,
    /// What a certificate with no role, or a role not in `roles`, may do.
    #[serde(default)]
    pub default_role_access: RoleAccess,
    /// The TLS handshake must be over this long after the connection is accepted.
    #[serde(with = "duration", default = "defaults::tls_handshake_timeout")]
    pub handshake_timeout: Duration,
}

/// `[bus.tls]`: the gateway as a Modbus/TCP Security client of a `tls://` device.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeviceTls {
    /// The gateway's certificate chain (PEM), its own first; it may carry a role.
    pub certificate: PathBuf,
    /// The private key of that certificate (PEM: PKCS#8, PKCS#1 or SEC1).
    pub private_key: PathBuf,
    /// The CA certificates (PEM bundle) the device's certificate must chain to.
    pub ca: PathBuf,
    /// The name the device's certificate must carry, when the device's HOST is an address (or
    /// another name) its certificate does not name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub server_name: Option<String>,
}

/// What one role may do: its access, and the unit ids it may address (`None`: any). Written
/// `"read_only"`, or `{ access = "read_write", units = "1-10" }`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Role {
    pub access: RoleAccess,
    pub units: Option<UnitSet>,
}

impl From<RoleAccess> for Role {
    fn from(access: RoleAccess) -> Role {
        Role {
            access,
            units: None,
        }
    }
}

/// The table form of a role.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RoleTable {
    access: RoleAccess,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    units: Option<UnitSet>,
}

impl Serialize for Role {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self.units {
            None => self.access.serialize(s),
            Some(units) => RoleTable {
                access: self.access,
                units: Some(units),
            }
            .serialize(s),
        }
    }
}

impl<'de> Deserialize<'de> for Role {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = Role;

            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(
                    "\"read_write\", \"read_only\", \"none\", or a table like \
                     { access = \"read_write\", units = \"1-10\" }",
                )
            }

            fn visit_str<E: serde::de::Error>(self, text: &str) -> Result<Role, E> {
                RoleAccess::deserialize(serde::de::value::StrDeserializer::<E>::new(text))
                    .map(Role::from)
            }

            fn visit_map<A: serde::de::MapAccess<'de>>(self, map: A) -> Result<Role, A::Error> {
                let table =
                    RoleTable::deserialize(serde::de::value::MapAccessDeserializer::new(map))?;
                Ok(Role {
                    access: table.access,
                    units: table.units,
                })
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// What a role allows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum RoleAccess {
    /// Every request.
    ReadWrite,
    /// The requests `server.read_only` allows; anything else gets exception 0x01.
    ReadOnly,
    /// Nothing: every request gets exception 0x01.
    #[default]
    None,
}

impl Choice for RoleAccess {
    const ALL: &'static [Self] = &[
        RoleAccess::ReadWrite,
        RoleAccess::ReadOnly,
        RoleAccess::None,
    ];
    fn word(self) -> &'static str {
        self.name()
    }
}

words!(RoleAccess);

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
pub(crate) const OTHER_ROLE: &str = "other";

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
        assert_eq!(tls.roles["operator"], RoleAccess::ReadWrite.into());
        assert_eq!(tls.roles["viewer"], RoleAccess::ReadOnly.into());
        assert_eq!(
            tls.roles["Guest"],
            RoleAccess::None.into(),
            "role names keep their case"
        );
        assert_eq!(tls.default_role_access, RoleAccess::None);
        assert_eq!(tls.handshake_timeout, std::time::Duration::from_secs(10));
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
    }

    #[test]
    fn a_role_may_be_a_table_that_also_names_the_units_it_may_address() {
        let c = Config::from_toml_str(&format!(
            "{TLS}roles = {{ operator = \"read_write\", \
             line2 = {{ access = \"read_write\", units = \"10-19,30\" }}, \
             auditor = {{ access = \"read_only\" }} }}\n{MINIMAL}"
        ))
        .unwrap();
        let roles = &c.server.tls.as_ref().unwrap().roles;
        let line2 = roles["line2"];
        assert_eq!(line2.access, RoleAccess::ReadWrite);
        let units = line2.units.unwrap();
        assert!(units.contains(10) && units.contains(19) && units.contains(30));
        assert!(!units.contains(20) && !units.contains(1));
        assert_eq!(roles["auditor"], RoleAccess::ReadOnly.into());
        assert_eq!(roles["operator"], RoleAccess::ReadWrite.into());
        // Printed back: the simple form where it suffices.
        let printed = c.to_toml();
        assert!(printed.contains("operator = \"read_write\""), "{printed}");
        assert_eq!(Config::from_toml_str(&printed).unwrap(), c);
        let e = errors(&format!(
            "{TLS}roles = {{ line2 = {{ access = \"read_write\", unit = 5 }} }}\n{MINIMAL}"
        ));
        assert!(e[0].starts_with("server.tls.roles.line2"), "{e:?}");
        assert!(e[0].contains("unknown field `unit`"), "{e:?}");
        let e = errors(&format!(
            "{TLS}roles = {{ line2 = {{ access = \"read_write\", units = [] }} }}\n{MINIMAL}"
        ));
        assert_eq!(e.len(), 1, "{e:?}");
        assert!(
            e[0].starts_with("server.tls.roles.line2.units: names no unit"),
            "{e:?}"
        );
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
