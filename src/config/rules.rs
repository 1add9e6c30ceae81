//! The `[[rule]]` list: which requests the gateway lets through, refuses or acknowledges
//! unsent, by who sends them (address, TLS role, protocol), where they go (bus, unit) and what
//! they ask (function, registers), the first matching rule deciding. Values and their checks
//! only: matching a request is `crate::rules`'s business.

use super::serde_adapters::text_list;
use super::serde_adapters::{words, Choice};
use super::UnitSet;
use crate::master::Protocol;
use ipnet::IpNet;
use serde::{Deserialize, Serialize};
use std::fmt;

/// One `[[rule]]`: every match key given must match (a key left out matches anything), and then
/// `action` decides.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rule {
    /// What the journal and the logs call the rule (default: `rule N`, its place in the list
    /// counting from 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// The masters' addresses or networks, as `server.allow` takes them.
    #[serde(default, with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub masters: Vec<IpNet>,
    /// The roles of TLS masters' certificates, as written in them.
    #[serde(default, with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub roles: Vec<String>,
    /// How the masters talk to the gateway: `tcp`, `rtu_over_tcp`, `udp`, `tls`.
    #[serde(default, with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub protocols: Vec<Protocol>,
    /// The buses the requests' units route to.
    #[serde(default, with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub buses: Vec<String>,
    /// The slaves these unit ids reach through the routes: a request matches by the slave it
    /// reaches, whatever unit id it names, and a broadcast reaches every slave of its bus.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub units: Option<UnitSet>,
    /// Function codes, or the words `read`, `write`, `diagnostic` of the function-code table.
    #[serde(
        default,
        deserialize_with = "one_or_many",
        skip_serializing_if = "Vec::is_empty"
    )]
    pub functions: Vec<Functions>,
    /// Data addresses (`"0x2000-0x2001"`, `"100"`): a request touching any of them matches a
    /// `deny` or `acknowledge` rule; an `allow` rule matches only a request that touches
    /// nothing else.
    #[serde(default, with = "text_list", skip_serializing_if = "Vec::is_empty")]
    pub registers: Vec<Registers>,
    pub action: Action,
}

/// What a matching rule does with a request.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Action {
    /// Sent to the slave, as with no rule.
    Allow,
    /// Refused unsent: exception 0x02 from a rule with `registers`, 0x01 otherwise.
    Deny,
    /// A write is answered with its normal reply, unsent; a read goes on.
    Acknowledge,
}

impl Choice for Action {
    const ALL: &'static [Self] = &[Action::Allow, Action::Deny, Action::Acknowledge];
    fn word(self) -> &'static str {
        self.label()
    }
}

words!(Action);

impl Action {
    pub const ALL: [Action; 3] = [Action::Allow, Action::Deny, Action::Acknowledge];

    /// The `action` label and the journal's word.
    pub fn label(self) -> &'static str {
        match self {
            Action::Allow => "allow",
            Action::Deny => "deny",
            Action::Acknowledge => "acknowledge",
        }
    }
}

/// A name in a list that may be written as one comma-separated string (role names, bus names).
impl text_list::Item for String {
    const EXAMPLE: &'static str = "a name";
    fn parse(text: &str) -> Option<Self> {
        Some(text.to_owned())
    }
}

impl text_list::Item for Protocol {
    const EXAMPLE: &'static str = "one of \"tcp\", \"rtu_over_tcp\", \"udp\", \"tls\"";
    fn parse(text: &str) -> Option<Self> {
        Protocol::ALL.into_iter().find(|p| p.label() == text)
    }
}

impl fmt::Display for Protocol {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.label())
    }
}

/// The functions a rule names: one code, or a class of the function-code table.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Functions {
    /// Function code 1-127.
    Code(u8),
    /// Requests known to change nothing on the slave.
    Read,
    /// Requests that may change the slave: every one not known to be a read, user-defined
    /// codes included.
    Write,
    /// The Modbus Application Protocol's diagnostics functions (07, 08, 0B, 0C, 11, 2B).
    Diagnostic,
    /// The diagnostics that may change the slave: restart, listen only, clearing counters,
    /// every 2B but Read Device Identification.
    DiagnosticWrite,
}

impl Functions {
    /// The classes, by their words.
    const WORDS: [Functions; 4] = [
        Functions::Read,
        Functions::Write,
        Functions::Diagnostic,
        Functions::DiagnosticWrite,
    ];

    fn word(self) -> Option<&'static str> {
        match self {
            Functions::Code(_) => None,
            Functions::Read => Some("read"),
            Functions::Write => Some("write"),
            Functions::Diagnostic => Some("diagnostic"),
            Functions::DiagnosticWrite => Some("diagnostic_write"),
        }
    }

    /// The words, as error messages list them: `"read", "write", ... or "diagnostic_write"`.
    fn words() -> String {
        let quoted: Vec<String> = Self::WORDS
            .iter()
            .filter_map(|w| w.word())
            .map(|w| format!("\"{w}\""))
            .collect();
        match quoted.split_last() {
            Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
            None => String::new(),
        }
    }

    fn parse(text: &str) -> Result<Functions, String> {
        let text = text.trim();
        if let Some(word) = Self::WORDS.into_iter().find(|w| w.word() == Some(text)) {
            return Ok(word);
        }
        let code = match text.strip_prefix("0x").or_else(|| text.strip_prefix("0X")) {
            Some(hex) => u8::from_str_radix(hex, 16).ok(),
            None => text.parse::<u8>().ok(),
        };
        match code {
            Some(code) => Functions::code(i64::from(code)),
            None => Err(format!(
                "`{text}` is no function code (1-127, or 0x01-0x7F) and not {}",
                Self::words()
            )),
        }
    }

    fn code(code: i64) -> Result<Functions, String> {
        match u8::try_from(code) {
            Ok(code @ 1..=0x7F) => Ok(Functions::Code(code)),
            _ => Err(format!(
                "{code} is no function code a master may send (1-127)"
            )),
        }
    }
}

impl Serialize for Functions {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match (self, self.word()) {
            (Functions::Code(code), _) => s.serialize_u8(*code),
            (_, Some(word)) => s.serialize_str(word),
            (_, None) => unreachable!("only codes have no word"),
        }
    }
}

impl<'de> Deserialize<'de> for Functions {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = Functions;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                write!(f, "a function code, or {}", Functions::words())
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Functions, E> {
                Functions::code(v).map_err(E::custom)
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<Functions, E> {
                self.visit_i64(i64::try_from(v).unwrap_or(i64::MAX))
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<Functions, E> {
                Functions::parse(v).map_err(E::custom)
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// `functions` as one code or word, or a list of them.
fn one_or_many<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<Functions>, D::Error> {
    struct Visitor;
    impl<'de> serde::de::Visitor<'de> for Visitor {
        type Value = Vec<Functions>;
        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            write!(
                f,
                "a function code or {}, or a list of them",
                Functions::words()
            )
        }
        fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Self::Value, E> {
            Functions::code(v).map(|f| vec![f]).map_err(E::custom)
        }
        fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<Self::Value, E> {
            self.visit_i64(i64::try_from(v).unwrap_or(i64::MAX))
        }
        fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<Self::Value, E> {
            Functions::parse(v).map(|f| vec![f]).map_err(E::custom)
        }
        fn visit_seq<A: serde::de::SeqAccess<'de>>(
            self,
            mut seq: A,
        ) -> Result<Self::Value, A::Error> {
            let mut all = Vec::new();
            while let Some(one) = seq.next_element::<Functions>()? {
                all.push(one);
            }
            Ok(all)
        }
    }
    d.deserialize_any(Visitor)
}

/// Data addresses from `first` to `last`, both included.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Registers {
    pub first: u16,
    pub last: u16,
}

impl Registers {
    fn parse(text: &str) -> Option<Registers> {
        let number = |s: &str| {
            let s = s.trim();
            match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
                Some(hex) => u16::from_str_radix(hex, 16).ok(),
                None => s.parse::<u16>().ok(),
            }
        };
        let (first, last) = match text.split_once('-') {
            Some((first, last)) => (number(first)?, number(last)?),
            None => (number(text)?, number(text)?),
        };
        (first <= last).then_some(Registers { first, last })
    }

    /// Whether any address of `first..=last` is one of these.
    pub fn overlaps(&self, first: u16, last: u16) -> bool {
        first <= self.last && self.first <= last
    }
}

impl text_list::Item for Registers {
    const EXAMPLE: &'static str =
        "a data address or a range of them like \"0x2000-0x2001\" or \"100-199\" (0-65535, \
         the first not above the last)";
    fn parse(text: &str) -> Option<Self> {
        Registers::parse(text)
    }
}

impl fmt::Display for Registers {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.first == self.last {
            write!(f, "0x{:04X}", self.first)
        } else {
            write!(f, "0x{:04X}-0x{:04X}", self.first, self.last)
        }
    }
}

impl Rule {
    /// What the journal and logs call the rule at `index` (from 0) of the list.
    pub fn display_name(&self, index: usize) -> String {
        match &self.name {
            Some(name) => name.clone(),
            None => format!("rule {}", index + 1),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::config::testing::{errors, MINIMAL};
    use crate::config::Config;

    use super::*;

    /// Every match key, in its short and its long form.
    #[test]
    fn a_rule_takes_short_and_long_match_keys_and_prints_back_the_same() {
        let c = Config::from_toml_str(&format!(
            r#"{MINIMAL}
            [[rule]]
            name = "wallbox setpoint"
            masters = "192.168.20.0/24, 10.0.0.7"
            protocols = ["tcp", "tls"]
            buses = "line1"
            units = "1-4"
            functions = [6, "0x10", "write"]
            registers = ["0x2000-0x2001", "100"]
            action = "allow"

            [[rule]]
            functions = "diagnostic"
            action = "acknowledge"
            "#
        ))
        .unwrap();
        let rule = &c.rule[0];
        assert_eq!(rule.masters.len(), 2);
        assert_eq!(rule.protocols, [Protocol::Tcp, Protocol::Tls]);
        assert_eq!(
            rule.functions,
            [Functions::Code(6), Functions::Code(16), Functions::Write]
        );
        assert_eq!(
            rule.registers,
            [
                Registers {
                    first: 0x2000,
                    last: 0x2001
                },
                Registers {
                    first: 100,
                    last: 100
                }
            ]
        );
        assert_eq!(c.rule[1].functions, [Functions::Diagnostic]);
        assert_eq!(c.rule[1].display_name(1), "rule 2");
        assert_eq!(Config::from_toml_str(&c.to_toml()).unwrap(), c);
    }

    #[test]
    fn a_bad_rule_is_refused_naming_its_key() {
        let found = errors(&format!(
            r#"{MINIMAL}
            [[rule]]
            functions = [0x80]
            action = "deny"
            [[rule]]
            registers = "0x2001-0x2000"
            action = "deny"
            [[rule]]
            protocols = "modbus"
            action = "deny"
            [[rule]]
            action = "block"
            "#
        ));
        let text = found.join("\n");
        assert!(text.contains("rule[0].functions"), "{text}");
        assert!(
            text.contains("no function code a master may send"),
            "{text}"
        );
        assert!(text.contains("rule[1].registers"), "{text}");
        assert!(text.contains("rule[2].protocols"), "{text}");
        assert!(text.contains("rule[3].action"), "{text}");
    }
}
