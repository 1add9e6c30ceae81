//! A value's `set` message (`PREFIX/BUS/SLAVE/NAME/set`, with `writes = true`): the payload is
//! the value in its units, encoded as it is decoded (scale, offset, type, word and byte order)
//! and written with FC 06 or 16 (05 for a coil) by the master `mqtt`, through the dispatcher as
//! any master's write: decided by the rules (`protocols = ["mqtt"]`), journaled, queued. What
//! became of it is published at `.../set/result` as JSON. A `set` the broker hands over as
//! retained (its stored message, at a subscription) is refused: it may have been carried out
//! already, and a write must never be sent twice. (MQTT 3.1.1 does not flag a retained message
//! delivered live: that one is carried out, once.)

use super::catalogue::Publishable;
use crate::dispatch::{Client, Dispatcher};
use crate::error::{Answer, Outcome, RequestError};
use crate::pdu::EXCEPTION_BIT;
use crate::values::{decode, encode, write_request};
use serde_json::{json, Value};
use tokio::sync::oneshot;

/// A `set` as it was refused before any write, or sent.
pub(super) enum Set {
    Refused(String),
    Sent {
        /// The value as the slave will hold it (the payload rounded to its registers).
        value: f64,
        /// The rule that decided it, by name.
        rule: Option<String>,
        outcome: oneshot::Receiver<Outcome>,
    },
}

/// The number `payload` says for `item`: a decimal number, or for a bit also `true`/`false`
/// and `ON`/`OFF` (what Home Assistant's switches send).
fn number(item: &Publishable, payload: &[u8]) -> Result<f64, String> {
    let text = std::str::from_utf8(payload)
        .map_err(|_| "the payload is not UTF-8 text".to_owned())?
        .trim();
    if item.is_bool() {
        match text.to_ascii_lowercase().as_str() {
            "1" | "true" | "on" => return Ok(1.0),
            "0" | "false" | "off" => return Ok(0.0),
            _ => {
                return Err(format!(
                    "`{}` is not 0, 1, true, false, ON or OFF",
                    shown(text)
                ))
            }
        }
    }
    match text.parse::<f64>() {
        Ok(number) if number.is_finite() => Ok(number),
        _ => Err(format!("`{}` is not a decimal number", shown(text))),
    }
}

/// At most 40 characters of a payload, for a result.
fn shown(text: &str) -> String {
    text.chars().take(40).collect()
}

/// Carry out a `set` of `item` with `payload` (`retained` as the broker delivered it) as
/// `client`, through `dispatcher`.
pub(super) fn set(
    dispatcher: &Dispatcher,
    client: &Client,
    item: &Publishable,
    payload: &[u8],
    retained: bool,
) -> Set {
    if retained {
        return Set::Refused(
            "a retained set handed over at a subscription is not carried out: it may have \
             been carried out already; publish sets without retain"
                .to_owned(),
        );
    }
    let number = match number(item, payload) {
        Ok(number) => number,
        Err(why) => return Set::Refused(why),
    };
    let Some(words) = encode(&item.value, number) else {
        return Set::Refused(format!(
            "{number} is out of the range its registers hold ({}, scale {}, offset {})",
            item.value.kind().name(),
            item.value.scale,
            item.value.offset
        ));
    };
    let value = decode(&item.value, &words).unwrap_or(number);
    let register = u16::try_from(item.value.register).unwrap_or(u16::MAX);
    let pdu = write_request(item.value.table, register, &words);
    match dispatcher.submit_to_slave(client, (&item.bus, item.slave), &pdu) {
        Some((rule, outcome)) => Set::Sent {
            value,
            rule,
            outcome,
        },
        None => Set::Refused(format!("bus {} is no longer configured", item.bus)),
    }
}

/// The result of a refused `set`.
pub(super) fn refused(why: &str) -> String {
    json!({"result": "refused", "reason": why}).to_string()
}

/// The result of a `set` sent as `value`, decided by `rule`, that ended in `outcome`.
pub(super) fn result(value: f64, rule: Option<&str>, outcome: Outcome) -> String {
    let result: Value = match outcome {
        Ok(Answer::Reply(pdu)) if pdu.first().is_some_and(|f| f & EXCEPTION_BIT != 0) => {
            let code = pdu.get(1).copied().unwrap_or(0);
            json!({"result": "exception", "exception": code, "source": "slave",
                   "reason": format!("the slave answered exception {code:#04x}")})
        }
        Ok(Answer::Reply(_) | Answer::Nothing) => json!({"result": "ok", "value": value}),
        Ok(Answer::Acknowledged(_)) => json!({"result": "acknowledged", "value": value,
            "rule": rule, "reason": "acknowledged by a rule, not sent"}),
        Ok(Answer::Malformed(_)) => json!({"result": "failed",
            "reason": "the slave's reply does not fit the write"}),
        Err(error @ RequestError::Denied { .. }) => json!({"result": "denied", "rule": rule,
            "exception": error.exception_code() as u8,
            "reason": format!("denied by rule {}", rule.unwrap_or("?"))}),
        Err(error) => json!({"result": "failed", "exception": error.exception_code() as u8,
            "source": "gateway", "reason": error.to_string()}),
    };
    result.to_string()
}
