//! `GET /values`: which plant values a query string asks for (`bus`, `slave`, `history`), or why
//! it is refused. The listing itself is the values' store's.

use crate::values::ValueQuery;
use hyper::StatusCode;

/// The filter `query` asks for, or the status and message that refuse it.
pub(super) fn filter(
    query: Option<&str>,
    buses: &[String],
) -> Result<ValueQuery, (StatusCode, String)> {
    let mut filter = ValueQuery::default();
    for (key, value) in super::query_pairs(query)? {
        let value = value.as_ref();
        match key.as_ref() {
            "bus" => filter.bus = Some(super::bus_named(value, buses)?),
            "slave" => match value.parse::<u8>() {
                Ok(slave) => filter.slave = Some(slave),
                Err(_) => {
                    return Err((
                        StatusCode::BAD_REQUEST,
                        format!("slave must be an address from 0 to 255, not `{value}`\n"),
                    ))
                }
            },
            "history" => match value {
                "1" | "true" | "" => filter.history = true,
                "0" | "false" => filter.history = false,
                _ => {
                    return Err((
                        StatusCode::BAD_REQUEST,
                        format!("history is 1 or 0, not `{value}`\n"),
                    ))
                }
            },
            _ => {
                return Err((
                    StatusCode::BAD_REQUEST,
                    format!("unknown parameter `{key}`; /values takes bus, slave and history\n"),
                ))
            }
        }
    }
    Ok(filter)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_query_picks_a_bus_a_slave_and_the_history_or_is_refused_saying_why() {
        let buses = ["line1".to_owned(), "line2".to_owned()];
        let picked = filter(Some("bus=line2&slave=255&history=1"), &buses).unwrap();
        assert_eq!(
            picked,
            ValueQuery {
                bus: Some("line2".to_owned()),
                slave: Some(255),
                history: true
            }
        );
        assert_eq!(filter(None, &buses).unwrap(), ValueQuery::default());
        let (status, message) = super::filter(Some("bus=line9"), &buses).unwrap_err();
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert!(message.contains("line1, line2"), "{message}");
        for query in ["slave=256", "slave=x", "history=maybe", "colour=red"] {
            let (status, _) = super::filter(Some(query), &buses).unwrap_err();
            assert_eq!(status, StatusCode::BAD_REQUEST, "{query}");
        }
    }

    #[test]
    fn a_query_is_decoded_as_a_form_is_and_a_percent_without_two_hex_digits_is_refused() {
        let buses = ["line_1".to_owned(), "line 2".to_owned()];
        let picked = filter(Some("bus=line%5F1&%73lave=%32%35%35"), &buses).unwrap();
        assert_eq!(picked.bus.as_deref(), Some("line_1"));
        assert_eq!(picked.slave, Some(255));
        // `+` is a space, as in a form; `%2B` a plus.
        let picked = filter(Some("bus=line+2"), &buses).unwrap();
        assert_eq!(picked.bus.as_deref(), Some("line 2"));
        let (status, message) = filter(Some("bus=line%2B2"), &buses).unwrap_err();
        assert_eq!(status, StatusCode::NOT_FOUND, "{message}");
        assert!(message.contains("`line+2`"), "{message}");
        // Bytes that are no UTF-8 cannot name a bus, nor be a number.
        let (status, _) = filter(Some("bus=%FF"), &buses).unwrap_err();
        assert_eq!(status, StatusCode::NOT_FOUND);
        for query in [
            "bus=%zz",
            "bus=%",
            "slave=2%5",
            "%G1=2",
            "bus=line_1&slave=%-1",
        ] {
            let (status, message) = filter(Some(query), &buses).unwrap_err();
            assert_eq!(status, StatusCode::BAD_REQUEST, "{query}");
            assert!(message.starts_with("bad escape `%"), "{query}: {message}");
        }
    }
}
