//! How values the file writes as text become typed values and back: durations as humantime
//! strings, lists written as one comma-separated string or as a list, keys whose value is one of
//! a few words, and the `skip_serializing_if` helpers that keep the printed configuration short.
//! Knows nothing of which key uses what.

use ipnet::IpNet;
use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

pub(super) fn is_false(value: &bool) -> bool {
    !value
}

/// For serde: a key whose default is `true` is left out when it has it.
#[allow(clippy::trivially_copy_pass_by_ref)] // serde's signature
pub(super) fn is_true(value: &bool) -> bool {
    *value
}

pub(super) fn is_zero(value: &Duration) -> bool {
    value.is_zero()
}

pub(super) fn is_zero_usize(value: &usize) -> bool {
    *value == 0
}

pub(super) fn is_zero_f64(value: &f64) -> bool {
    *value == 0.0
}

/// A key whose value is one of a few words (`action`, `framing`, `on_error`, ...): written as
/// its word, and a word that is none of them refused naming the word given and every word
/// allowed, as a reason the key's path goes before (`rule[0].action: `block` is not allow, deny
/// or acknowledge`). [`words!`] gives such a type its serde.
pub(crate) trait Choice: Copy + 'static {
    /// Every value, in the order the error lists them.
    const ALL: &'static [Self];
    /// As the file spells it.
    fn word(self) -> &'static str;
}

/// The reason a word that is none of `T`'s is refused with.
pub(crate) fn not_a_choice<T: Choice>(given: &str) -> String {
    let words: Vec<&str> = T::ALL.iter().map(|c| c.word()).collect();
    let allowed = match words.split_last() {
        Some((last, [])) => (*last).to_owned(),
        Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
        None => String::new(),
    };
    format!("`{given}` is not {allowed}")
}

/// Serialize and Deserialize for each [`Choice`] type named.
macro_rules! words {
    ($($kind:ty),* $(,)?) => {$(
        impl serde::Serialize for $kind {
            fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.serialize_str($crate::config::serde_adapters::Choice::word(*self))
            }
        }

        impl<'de> serde::Deserialize<'de> for $kind {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                use $crate::config::serde_adapters::{not_a_choice, Choice};
                let text = <String as serde::Deserialize>::deserialize(d)?;
                <$kind as Choice>::ALL
                    .iter()
                    .copied()
                    .find(|c| c.word() == text)
                    .ok_or_else(|| serde::de::Error::custom(not_a_choice::<$kind>(&text)))
            }
        }
    )*};
}
pub(crate) use words;

/// Durations as humantime strings: "1s", "250ms", "10m".
pub(super) mod duration {
    use serde::{Deserialize, Deserializer, Serializer};
    use std::time::Duration;

    pub(crate) fn serialize<S: Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(&humantime::format_duration(*d))
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Duration, D::Error> {
        let text = String::deserialize(d)?;
        humantime::parse_duration(&text).map_err(|e| {
            // The file's numbers arrive here as text: `0.5` was a number, without its unit.
            let why = if text.trim_start().starts_with('-') {
                "a duration cannot be negative".to_owned()
            } else if text.trim().parse::<f64>().is_ok() {
                "a duration needs its unit, as a string".to_owned()
            } else {
                e.to_string()
            };
            serde::de::Error::custom(format!(
                "`{text}` is not a duration like \"500ms\" or \"2s\": {why}"
            ))
        })
    }
}

pub(super) mod opt_duration {
    use serde::{Deserializer, Serializer};
    use std::time::Duration;

    pub(crate) fn serialize<S: Serializer>(d: &Option<Duration>, s: S) -> Result<S::Ok, S::Error> {
        match d {
            Some(d) => super::duration::serialize(d, s),
            None => s.serialize_none(),
        }
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(
        d: D,
    ) -> Result<Option<Duration>, D::Error> {
        super::duration::deserialize(d).map(Some)
    }
}

/// Lists written as one string, a comma-separated string (handy in the environment), or a list
/// of strings: listen addresses, allowed networks.
pub(super) mod text_list {
    use serde::{Deserializer, Serializer};
    use std::marker::PhantomData;

    /// An item of such a list.
    pub(crate) trait Item: Sized + std::fmt::Display {
        /// What one item looks like, for error messages.
        const EXAMPLE: &'static str;
        fn parse(text: &str) -> Option<Self>;
    }

    pub(crate) fn serialize<T: Item, S: Serializer>(items: &[T], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(items.iter().map(ToString::to_string))
    }

    fn parse<T: Item, E: serde::de::Error>(text: &str, out: &mut Vec<T>) -> Result<(), E> {
        for part in text
            .split(',')
            .map(str::trim)
            .filter(|part| !part.is_empty())
        {
            out.push(
                T::parse(part)
                    .ok_or_else(|| E::custom(format!("`{part}` is not {}", T::EXAMPLE)))?,
            );
        }
        Ok(())
    }

    struct Visitor<T>(PhantomData<T>);

    impl<'de, T: Item> serde::de::Visitor<'de> for Visitor<T> {
        type Value = Vec<T>;

        fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "{}, or a list of them", T::EXAMPLE)
        }

        fn visit_str<E: serde::de::Error>(self, text: &str) -> Result<Self::Value, E> {
            let mut out = Vec::new();
            parse(text, &mut out)?;
            Ok(out)
        }

        fn visit_seq<A: serde::de::SeqAccess<'de>>(
            self,
            mut seq: A,
        ) -> Result<Self::Value, A::Error> {
            let mut out = Vec::new();
            while let Some(text) = seq.next_element::<String>()? {
                parse(&text, &mut out)?;
            }
            Ok(out)
        }
    }

    pub(crate) fn deserialize<'de, T: Item, D: Deserializer<'de>>(
        d: D,
    ) -> Result<Vec<T>, D::Error> {
        d.deserialize_any(Visitor(PhantomData))
    }
}

impl text_list::Item for SocketAddr {
    const EXAMPLE: &'static str = "a socket address like \"0.0.0.0:502\" or \"[::1]:502\"";
    fn parse(text: &str) -> Option<Self> {
        text.parse().ok()
    }
}

/// A network in `server.allow` or `server.read_only`: CIDR, or a single address.
impl text_list::Item for IpNet {
    const EXAMPLE: &'static str = "an address or a network like \"192.168.10.0/24\"";
    fn parse(text: &str) -> Option<Self> {
        text.parse()
            .ok()
            .or_else(|| text.parse::<IpAddr>().ok().map(IpNet::from))
            .map(|net| net.trunc())
    }
}
