//! [`UnitSet`]: a set of unit ids or slave addresses, as written in the file (`5`, `"1-10,20"`,
//! `[1, 2, 3]`), parsed and printed back canonically. Knows nothing of what the ids mean.

use serde::{Deserialize, Serialize};
use std::fmt;

/// A set of unit ids or slave addresses (0-255), written `5`, `"1-10,20"` or `[1, 2, 3]`.
#[derive(Clone, Copy, PartialEq, Eq, Default)]
pub struct UnitSet([u64; 4]);

impl UnitSet {
    pub fn insert(&mut self, unit: u8) {
        self.0[usize::from(unit / 64)] |= 1 << (unit % 64);
    }

    pub fn remove(&mut self, unit: u8) {
        self.0[usize::from(unit / 64)] &= !(1 << (unit % 64));
    }

    pub fn contains(&self, unit: u8) -> bool {
        self.0[usize::from(unit / 64)] & (1 << (unit % 64)) != 0
    }

    pub fn iter(&self) -> impl Iterator<Item = u8> + '_ {
        (0..=255u8).filter(|&u| self.contains(u))
    }

    pub fn is_empty(&self) -> bool {
        self.0 == [0; 4]
    }
}

impl std::str::FromStr for UnitSet {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let number = |s: &str| -> Result<u8, String> {
            s.trim()
                .parse::<u8>()
                .map_err(|_| format!("`{}` is not a number from 0 to 255", s.trim()))
        };
        let mut set = UnitSet::default();
        for part in text.split(',') {
            match part.split_once('-') {
                Some((low, high)) => {
                    let (low, high) = (number(low)?, number(high)?);
                    if low > high {
                        return Err(format!("range `{}` runs backwards", part.trim()));
                    }
                    (low..=high).for_each(|u| set.insert(u));
                }
                None => set.insert(number(part)?),
            }
        }
        Ok(set)
    }
}

impl fmt::Display for UnitSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut first = true;
        let mut units = self.iter().peekable();
        while let Some(low) = units.next() {
            let mut high = low;
            while units.peek() == Some(&high.wrapping_add(1)) && high != 255 {
                high = units.next().unwrap_or(high);
            }
            let sep = if first { "" } else { "," };
            first = false;
            if low == high {
                write!(f, "{sep}{low}")?;
            } else {
                write!(f, "{sep}{low}-{high}")?;
            }
        }
        Ok(())
    }
}

impl fmt::Debug for UnitSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "UnitSet({self})")
    }
}

impl Serialize for UnitSet {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for UnitSet {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = UnitSet;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a unit id, a list of them, or ranges like \"1-10,20\"")
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<UnitSet, E> {
                let unit = u8::try_from(v)
                    .map_err(|_| E::custom(format!("{v} is not a number from 0 to 255")))?;
                let mut set = UnitSet::default();
                set.insert(unit);
                Ok(set)
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<UnitSet, E> {
                self.visit_i64(i64::try_from(v).unwrap_or(i64::MAX))
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<UnitSet, E> {
                v.parse().map_err(E::custom)
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<UnitSet, A::Error> {
                let mut set = UnitSet::default();
                while let Some(part) = seq.next_element::<UnitSet>()? {
                    part.iter().for_each(|u| set.insert(u));
                }
                Ok(set)
            }
        }
        d.deserialize_any(Visitor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_sets_parse_ids_lists_and_ranges_and_print_canonically() {
        let set: UnitSet = "1-4, 7,10-11".parse().unwrap();
        assert_eq!(set.iter().collect::<Vec<_>>(), [1, 2, 3, 4, 7, 10, 11]);
        assert_eq!(set.to_string(), "1-4,7,10-11");
        assert_eq!("255".parse::<UnitSet>().unwrap().to_string(), "255");
        assert_eq!("0-255".parse::<UnitSet>().unwrap().iter().count(), 256);
        assert!("4-1".parse::<UnitSet>().is_err());
        assert!("256".parse::<UnitSet>().is_err());
        assert!("".parse::<UnitSet>().is_err());
    }
}
