//! What a read's reply says: the registers (or coils and inputs, as 0 and 1) of the block it
//! asked for, and the number each value holds in them, by its type, word and byte order, bit,
//! scale and offset. Pure functions over bytes and words.

use crate::config::{Order, Table, Value, ValueType};

/// Why a reply is not the block's registers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum BadBlock {
    /// The slave answered with this exception code.
    Exception(u8),
    /// Not the reply to the read: another function, or a byte count that is not the block's.
    BadReply,
}

/// The request PDU that reads `count` registers (coils, inputs) of `table` from `first`.
pub(crate) fn request(table: Table, first: u16, count: u16) -> Vec<u8> {
    let [a, b] = first.to_be_bytes();
    let [c, d] = count.to_be_bytes();
    vec![table.function(), a, b, c, d]
}

/// The `count` registers of `table` from the read's reply `pdu`, or coils and inputs as 0 and 1.
pub(crate) fn words(table: Table, count: u16, pdu: &[u8]) -> Result<Vec<u16>, BadBlock> {
    let function = table.function();
    match pdu {
        [f, code] if *f == function | crate::pdu::EXCEPTION_BIT => {
            return Err(BadBlock::Exception(*code))
        }
        [f, ..] if *f != function => return Err(BadBlock::BadReply),
        _ => {}
    }
    let count = usize::from(count);
    let expected = if table.is_bits() {
        count.div_ceil(8)
    } else {
        2 * count
    };
    let data = match pdu {
        [_, n, data @ ..] if usize::from(*n) == expected && data.len() == expected => data,
        _ => return Err(BadBlock::BadReply),
    };
    Ok(if table.is_bits() {
        (0..count)
            .map(|i| u16::from((data[i / 8] >> (i % 8)) & 1))
            .collect()
    } else {
        data.chunks_exact(2)
            .map(|w| u16::from_be_bytes([w[0], w[1]]))
            .collect()
    })
}

/// The number `value` holds in `words`, its registers from its first on: raw x scale + offset.
/// `None` if `words` is too short for it.
pub(crate) fn decode(value: &Value, words: &[u16]) -> Option<f64> {
    let kind = value.kind();
    let words = words.get(..usize::from(kind.registers()))?;
    let raw = match value.bit {
        // The bit of the register as its byte order makes it, as a u16 would read it.
        Some(bit) => {
            let word = match value.byte_order {
                Order::Big => words[0],
                Order::Little => words[0].swap_bytes(),
            };
            f64::from((word >> bit) & 1)
        }
        None => raw(kind, words, value.word_order, value.byte_order),
    };
    Some(scaled(raw, value.scale) + value.offset)
}

/// `raw` x `scale`; a scale that is one over a whole number (0.1, 0.01) divides by that number,
/// which gives the number as written (111 x 0.1 is 11.100000000000001, 111 / 10 is 11.1).
fn scaled(raw: f64, scale: f64) -> f64 {
    let inverse = 1.0 / scale;
    let whole = inverse.round();
    if scale.abs() < 1.0 && (inverse - whole).abs() <= 1e-9 * whole.abs() {
        raw / whole
    } else {
        raw * scale
    }
}

/// `words` read as `kind`, the registers in `word_order` and each one's bytes in `byte_order`.
#[allow(clippy::cast_precision_loss)] // 64-bit integers: Prometheus's values are f64 anyway
fn raw(kind: ValueType, words: &[u16], word_order: Order, byte_order: Order) -> f64 {
    let mut bytes = [0u8; 8];
    let ordered: Box<dyn Iterator<Item = &u16>> = match word_order {
        Order::Big => Box::new(words.iter()),
        Order::Little => Box::new(words.iter().rev()),
    };
    for (at, word) in ordered.enumerate() {
        let [hi, lo] = word.to_be_bytes();
        let pair = match byte_order {
            Order::Big => [hi, lo],
            Order::Little => [lo, hi],
        };
        bytes[2 * at..2 * at + 2].copy_from_slice(&pair);
    }
    let two = [bytes[0], bytes[1]];
    let four = [bytes[0], bytes[1], bytes[2], bytes[3]];
    match kind {
        ValueType::U16 => f64::from(u16::from_be_bytes(two)),
        ValueType::I16 => f64::from(i16::from_be_bytes(two)),
        ValueType::Bool => f64::from(u8::from(words[0] != 0)),
        ValueType::U32 => f64::from(u32::from_be_bytes(four)),
        ValueType::I32 => f64::from(i32::from_be_bytes(four)),
        ValueType::F32 => f64::from(f32::from_be_bytes(four)),
        ValueType::U64 => u64::from_be_bytes(bytes) as f64,
        ValueType::I64 => i64::from_be_bytes(bytes) as f64,
        ValueType::F64 => f64::from_be_bytes(bytes),
    }
}

/// The registers that hold `number` as `value` is held, from its first on: the inverse of
/// [`decode`], raw = (number - offset) / scale, rounded to the nearest whole for an integer
/// type. `None` if the raw number is out of its type's range (or not a number). A bit of a
/// register gives the register with that bit alone set (or none); a `bool` 0 or 1.
pub(crate) fn encode(value: &Value, number: f64) -> Option<Vec<u16>> {
    let raw = unscaled(number - value.offset, value.scale);
    if let Some(bit) = value.bit {
        let word = u16::from(raw != 0.0) << bit;
        return Some(vec![match value.byte_order {
            Order::Big => word,
            Order::Little => word.swap_bytes(),
        }]);
    }
    let kind = value.kind();
    let bytes = raw_bytes(kind, raw)?;
    let mut words: Vec<u16> = bytes
        .chunks_exact(2)
        .take(usize::from(kind.registers()))
        .map(|pair| match value.byte_order {
            Order::Big => u16::from_be_bytes([pair[0], pair[1]]),
            Order::Little => u16::from_le_bytes([pair[0], pair[1]]),
        })
        .collect();
    if value.word_order == Order::Little {
        words.reverse();
    }
    Some(words)
}

/// The request that writes `words` to `table` from `register` on a slave: FC 05 for a coil,
/// FC 06 for one register, FC 10 for more.
pub(crate) fn write_request(table: Table, register: u16, words: &[u16]) -> Vec<u8> {
    let [a, b] = register.to_be_bytes();
    match (table, words) {
        (Table::Coil, [word, ..]) => {
            let on = if *word != 0 { 0xFF } else { 0x00 };
            vec![0x05, a, b, on, 0x00]
        }
        (_, [word]) => {
            let [c, d] = word.to_be_bytes();
            vec![0x06, a, b, c, d]
        }
        _ => {
            let count = u16::try_from(words.len()).unwrap_or(u16::MAX);
            let [c, d] = count.to_be_bytes();
            let mut pdu = vec![0x10, a, b, c, d, u8::try_from(2 * words.len()).unwrap_or(0)];
            pdu.extend(words.iter().flat_map(|w| w.to_be_bytes()));
            pdu
        }
    }
}

/// `number` / `scale`, exact where [`scaled`] is: a scale of one over a whole number
/// multiplies by that number.
fn unscaled(number: f64, scale: f64) -> f64 {
    let inverse = 1.0 / scale;
    let whole = inverse.round();
    if scale.abs() < 1.0 && (inverse - whole).abs() <= 1e-9 * whole.abs() {
        number * whole
    } else {
        number / scale
    }
}

/// `raw` as `kind`'s big-endian bytes (the first `2 x registers` of eight), rounded to the
/// nearest whole for an integer; `None` out of its range.
#[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)] // range checked first
fn raw_bytes(kind: ValueType, raw: f64) -> Option<[u8; 8]> {
    let mut bytes = [0u8; 8];
    if !raw.is_finite() {
        return None;
    }
    let whole = raw.round();
    let within = |low: f64, high: f64| (low..=high).contains(&whole).then_some(whole);
    match kind {
        ValueType::U16 => {
            bytes[..2].copy_from_slice(&(within(0.0, 65_535.0)? as u16).to_be_bytes())
        }
        ValueType::I16 => {
            bytes[..2].copy_from_slice(&(within(-32_768.0, 32_767.0)? as i16).to_be_bytes())
        }
        ValueType::Bool => bytes[..2].copy_from_slice(&u16::from(raw != 0.0).to_be_bytes()),
        ValueType::U32 => {
            bytes[..4].copy_from_slice(&(within(0.0, f64::from(u32::MAX))? as u32).to_be_bytes())
        }
        ValueType::I32 => bytes[..4].copy_from_slice(
            &(within(f64::from(i32::MIN), f64::from(i32::MAX))? as i32).to_be_bytes(),
        ),
        ValueType::F32 => {
            let single = raw as f32;
            if !single.is_finite() {
                return None;
            }
            bytes[..4].copy_from_slice(&single.to_be_bytes());
        }
        // 2^64 and 2^63 are the first numbers past the range an f64 can hold exactly.
        ValueType::U64 => {
            bytes = (within(0.0, 18_446_744_073_709_549_568.0)? as u64).to_be_bytes();
        }
        ValueType::I64 => {
            let bound = 9_223_372_036_854_774_784.0;
            bytes = (within(-bound - 1024.0, bound)? as i64).to_be_bytes();
        }
        ValueType::F64 => bytes = raw.to_be_bytes(),
    }
    Some(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(kind: &str, word_order: &str, byte_order: &str) -> Value {
        toml::from_str(&format!(
            "name = \"v\"\nregister = 0\ntype = \"{kind}\"\nword_order = \"{word_order}\"\n\
             byte_order = \"{byte_order}\"\n"
        ))
        .expect("a value")
    }

    /// The four layouts of docs/plant-values.md: (word order, byte order, registers as read).
    fn layouts(abcd: &[u16]) -> [(&'static str, &'static str, Vec<u16>); 4] {
        let swapped: Vec<u16> = abcd.iter().map(|w| w.swap_bytes()).collect();
        let reversed: Vec<u16> = abcd.iter().rev().copied().collect();
        let both: Vec<u16> = swapped.iter().rev().copied().collect();
        [
            ("big", "big", abcd.to_vec()),
            ("little", "big", reversed),
            ("big", "little", swapped),
            ("little", "little", both),
        ]
    }

    #[test]
    fn f32_1234_5_and_i32_minus_123456_come_out_exactly_in_each_of_the_four_layouts() {
        for (kind, abcd, expected) in [
            ("f32", [0x449A, 0x5000], 1234.5),
            ("i32", [0xFFFE, 0x1DC0], -123_456.0),
            ("u32", [0x0001, 0xE240], 123_456.0),
        ] {
            for (words, bytes, registers) in layouts(&abcd) {
                let got = decode(&value(kind, words, bytes), &registers);
                assert_eq!(
                    got,
                    Some(expected),
                    "{kind} {words}/{bytes} {registers:04X?}"
                );
            }
        }
        // The worked registers of the documentation.
        let cdab = layouts(&[0x449A, 0x5000])[1].2.clone();
        assert_eq!(cdab, [0x5000, 0x449A]);
        assert_eq!(layouts(&[0xFFFE, 0x1DC0])[2].2, [0xFEFF, 0xC01D]);
    }

    #[test]
    fn sixty_four_bit_values_come_out_exactly_in_both_word_orders() {
        // u64 9007199254740993 would round; 2^53 - 1 is the largest f64 holds exactly.
        let u64_abcd = [0x001F, 0xFFFF, 0xFFFF, 0xFFFF];
        let f64_abcd = [0xC0FE, 0x2408, 0x0000, 0x0000]; // -123456.5
        let i64_abcd = [0xFFFF, 0xFFFF, 0xFFFE, 0x1DC0]; // -123456
        for (kind, abcd, expected) in [
            ("u64", u64_abcd, 9_007_199_254_740_991.0),
            ("f64", f64_abcd, -123_456.5),
            ("i64", i64_abcd, -123_456.0),
        ] {
            for (words, bytes, registers) in layouts(&abcd) {
                let got = decode(&value(kind, words, bytes), &registers);
                assert_eq!(got, Some(expected), "{kind} {words}/{bytes}");
            }
        }
    }

    #[test]
    fn sixteen_bit_values_bits_scale_and_offset() {
        assert_eq!(decode(&value("i16", "big", "big"), &[0xFF38]), Some(-200.0));
        assert_eq!(
            decode(&value("u16", "big", "big"), &[0xFF38]),
            Some(65_336.0)
        );
        assert_eq!(
            decode(&value("u16", "big", "little"), &[0x3412]),
            Some(4660.0)
        );
        let mut scaled = value("u16", "big", "big");
        (scaled.scale, scaled.offset) = (0.01, -10.0);
        assert_eq!(decode(&scaled, &[5000]), Some(40.0));
        // As written, not as 111 x 0.1 rounds: 11.1, and 29.25 from 2925 at 0.01.
        scaled.offset = 0.0;
        scaled.scale = 0.1;
        assert_eq!(decode(&scaled, &[111]), Some(11.1));
        scaled.scale = 0.01;
        assert_eq!(decode(&scaled, &[2925]), Some(29.25));
        scaled.scale = 0.25;
        assert_eq!(decode(&scaled, &[3]), Some(0.75));
        let mut bit = value("u16", "big", "big");
        bit.bit = Some(3);
        assert_eq!(decode(&bit, &[0b1000]), Some(1.0));
        assert_eq!(decode(&bit, &[0b0111]), Some(0.0));
        // With its bytes swapped, bit 3 is in the other byte as sent.
        bit.byte_order = Order::Little;
        assert_eq!(decode(&bit, &[0x0800]), Some(1.0));
        assert_eq!(decode(&bit, &[0b1000]), Some(0.0));
        assert_eq!(decode(&value("bool", "big", "big"), &[7]), Some(1.0));
        assert_eq!(
            decode(&value("f32", "big", "big"), &[0x449A]),
            None,
            "too short"
        );
    }

    #[test]
    fn a_reply_gives_its_registers_or_bits_or_says_why_it_does_not() {
        // Goodrive300 manual, 10.4.1: two registers from 0004H, answered 1388H and 0000H.
        assert_eq!(
            request(Table::Holding, 0x0004, 2),
            [0x03, 0x00, 0x04, 0x00, 0x02]
        );
        let reply = [0x03, 0x04, 0x13, 0x88, 0x00, 0x00];
        assert_eq!(words(Table::Holding, 2, &reply), Ok(vec![0x1388, 0]));
        // Ten coils: 0xCD 0x01 = coils 0, 2, 3, 6, 7 and 8 on.
        let coils = words(Table::Coil, 10, &[0x01, 0x02, 0xCD, 0x01]).unwrap();
        assert_eq!(coils, [1, 0, 1, 1, 0, 0, 1, 1, 1, 0]);
        assert_eq!(
            words(Table::Input, 1, &[0x84, 0x02]),
            Err(BadBlock::Exception(2))
        );
        assert_eq!(
            words(Table::Holding, 2, &[0x03, 0x02, 0, 1]),
            Err(BadBlock::BadReply),
            "one register where two were asked for"
        );
        assert_eq!(
            words(Table::Holding, 1, &[0x04, 0x02, 0, 1]),
            Err(BadBlock::BadReply)
        );
    }

    #[test]
    fn encoding_is_decoding_inverted_in_every_layout_and_out_of_range_is_none() {
        for (kind, expected) in [
            ("f32", 1234.5),
            ("i32", -123_456.0),
            ("u32", 123_456.0),
            ("f64", -123_456.5),
            ("i64", -123_456.0),
            ("u64", 9_007_199_254_740_991.0),
        ] {
            for (words, bytes) in [
                ("big", "big"),
                ("little", "big"),
                ("big", "little"),
                ("little", "little"),
            ] {
                let v = value(kind, words, bytes);
                let held = encode(&v, expected).expect("in range");
                assert_eq!(held.len(), usize::from(v.width()));
                assert_eq!(decode(&v, &held), Some(expected), "{kind} {words}/{bytes}");
            }
        }
        // f32 1234.5 in CDAB is 5000 449A, as docs/plant-values.md writes it.
        assert_eq!(
            encode(&value("f32", "little", "big"), 1234.5),
            Some(vec![0x5000, 0x449A])
        );
        let mut hertz = value("u16", "big", "big");
        hertz.scale = 0.01;
        assert_eq!(encode(&hertz, 50.0), Some(vec![5000]));
        assert_eq!(encode(&hertz, 29.25), Some(vec![2925]));
        // Rounded to the nearest: 0.004 Hz is no step of 0.01.
        assert_eq!(encode(&hertz, 50.004), Some(vec![5000]));
        assert_eq!(encode(&hertz, 655.36), None, "past 65535");
        assert_eq!(encode(&hertz, -0.01), None, "below 0");
        let mut offset = value("i16", "big", "big");
        (offset.scale, offset.offset) = (0.1, -40.0);
        assert_eq!(encode(&offset, 21.5), Some(vec![615]));
        assert_eq!(encode(&value("i16", "big", "big"), 32_768.0), None);
        assert_eq!(encode(&value("u16", "big", "big"), f64::NAN), None);
        assert_eq!(encode(&value("f32", "big", "big"), 1e39), None, "no f32");
        assert_eq!(encode(&value("bool", "big", "big"), 3.0), Some(vec![1]));
        let mut bit = value("u16", "big", "big");
        bit.bit = Some(3);
        assert_eq!(encode(&bit, 1.0), Some(vec![0b1000]));
        assert_eq!(encode(&bit, 0.0), Some(vec![0]));
        bit.byte_order = Order::Little;
        assert_eq!(encode(&bit, 1.0), Some(vec![0x0800]));
    }
}
