//! The simulated drives (VFDs), with what they share written once. [`Drive`] is the slave on the
//! line: it carries each request through the pipeline every drive of the reference manuals follows
//! (communication timeout, function dispatch, broadcasts carried out and never answered, exception
//! replies, the response delay) and asks its [`Model`] only what the model's manual decides: what
//! a register reads, what a write does, which requests it serves and which exception a malformed
//! one gets. [`params`], [`ramp`] and [`motor`] are the parts the models build on; [`goodrive`] and
//! [`pd_inverter`] are the models, each with its own tables, register map and quirks. Knows nothing
//! of the line's timing, the bus queue or TCP.

pub(crate) mod goodrive;
pub(crate) mod motor;
pub(crate) mod params;
pub(crate) mod pd_inverter;
pub(crate) mod ramp;

pub(crate) use motor::Motor;
pub(crate) use params::{Limit, Modify, ParamRefusal, ParamSpec, Params};
pub(crate) use ramp::{Ramp, Rates};

use super::{Simulated, Transmission};
use crate::line::{Parity, SerialFormat};
use crate::pdu::{code, ExceptionCode, EXCEPTION_BIT};
use std::collections::BTreeMap;
use std::time::Duration;
use tokio::time::Instant;

/// What the configuration tells a simulated drive at power-on.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct DriveSettings {
    /// The drive's own slave address on the line.
    pub address: u8,
    /// The line's format, which the drive's communication parameters report.
    pub format: SerialFormat,
    /// The shortest time the drive takes to answer once it has recognised a request; its
    /// response-delay parameter can make it longer.
    pub processing_delay: Duration,
    /// Parameter values that replace the factory defaults, by the manual's name ("P00.11",
    /// "Pd-05") in fieldbus units (50.00 Hz is 5000). May set read-only records too.
    pub params: BTreeMap<String, u16>,
    /// A fault the drive has tripped with at power-on (the manual's fault code).
    pub trip: Option<u16>,
}

impl DriveSettings {
    /// Settings with no parameters, delay or trip (for tests; the loader builds them from
    /// the configuration).
    #[cfg(test)]
    pub(crate) fn new(address: u8, format: SerialFormat) -> Self {
        DriveSettings {
            address,
            format,
            processing_delay: Duration::ZERO,
            params: BTreeMap::new(),
            trip: None,
        }
    }
}

/// A setting a drive model cannot accept, named by the parameter (or `trip`).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{param}: {reason}")]
pub(crate) struct SetupError {
    pub param: String,
    pub reason: String,
}

/// An exception code a drive answers with: a standard one, or one its manual gives a meaning of
/// its own (05-09 mean other things on the reference drives, so they are not [`ExceptionCode`]s).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Exception(pub u8);

impl Exception {
    pub(crate) const fn standard(code: ExceptionCode) -> Self {
        Exception(code as u8)
    }

    /// The exception response PDU to a request with `function`.
    fn pdu(self, function: u8) -> [u8; 2] {
        [function | EXCEPTION_BIT, self.0]
    }
}

impl From<ExceptionCode> for Exception {
    fn from(code: ExceptionCode) -> Self {
        Exception::standard(code)
    }
}

/// What a model's manual says about requests as such, whatever their registers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct DriveProtocol {
    /// Most words one read, or one write of several, may carry.
    pub(crate) max_words: u16,
    /// Whether the drive serves FC 08 (return query data only) and FC 10 besides FC 03 and 06.
    pub diagnostics: bool,
    pub(crate) write_multiple: bool,
    /// The answer to a PDU whose length does not fit its function code.
    pub malformed: Exception,
}

/// A manual's indices for the baud rate and the data format (always 8 data bits), and the
/// factory index a drive reports for a line with none.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct LineIndices {
    pub(crate) bauds: &'static [u32],
    pub(crate) factory_baud: u16,
    /// (parity, stop bits).
    pub(crate) formats: &'static [(Parity, u8)],
    pub(crate) factory_format: u16,
}

impl LineIndices {
    pub(crate) fn baud(&self, baud: u32) -> u16 {
        index_or(
            self.bauds.iter().position(|&b| b == baud),
            self.factory_baud,
        )
    }

    pub(crate) fn format(&self, format: &SerialFormat) -> u16 {
        if format.data_bits != 8 {
            return self.factory_format;
        }
        let position = self
            .formats
            .iter()
            .position(|&f| f == (format.parity, format.stop_bits));
        index_or(position, self.factory_format)
    }
}

fn index_or(position: Option<usize>, factory: u16) -> u16 {
    position
        .and_then(|i| u16::try_from(i).ok())
        .unwrap_or(factory)
}

/// The parameters in which a drive reports the line it hangs on. The line's configuration owns
/// them: a write may only repeat the value they hold, and a configured value must agree.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LineParams {
    pub address: u16,
    pub baud: u16,
    pub format: u16,
    pub(crate) indices: LineIndices,
    /// The setup error for a configured value that is not the line's (`value`, `configured`).
    pub(crate) differs: fn(u16, u16) -> String,
    /// The setup error for a line value the parameter's range cannot hold.
    pub outside: fn(u16) -> String,
}

impl LineParams {
    pub(crate) fn holds(&self, address: u16) -> bool {
        [self.address, self.baud, self.format].contains(&address)
    }

    /// Set them from the line, after the configured values have been applied.
    pub(crate) fn power_on(
        &self,
        params: &mut Params,
        settings: &DriveSettings,
    ) -> Result<(), SetupError> {
        let line = [
            (self.address, u16::from(settings.address)),
            (self.baud, self.indices.baud(settings.format.baud)),
            (self.format, self.indices.format(&settings.format)),
        ];
        for (address, value) in line {
            let name = params.spec(address).map_or("", |spec| spec.name);
            let refuse = |reason| SetupError {
                param: name.to_owned(),
                reason,
            };
            if let Some(&configured) = settings.params.get(name) {
                if configured != value {
                    return Err(refuse((self.differs)(value, configured)));
                }
            }
            params
                .force(address, value)
                .map_err(|_| refuse((self.outside)(value)))?;
        }
        Ok(())
    }
}

/// The fault a drive is configured to have tripped with, if it is one of its `1..=last` codes.
pub(crate) fn power_on_trip(
    settings: &DriveSettings,
    last: u16,
) -> Result<Option<u16>, SetupError> {
    match settings.trip {
        Some(code) if !(1..=last).contains(&code) => Err(SetupError {
            param: "trip".into(),
            reason: format!("{code} is not a fault code (1..={last})"),
        }),
        trip => Ok(trip),
    }
}

/// What a drive model decides; [`Drive`] does the rest.
pub(crate) trait Model: Clone + Send {
    const PROTOCOL: DriveProtocol;

    /// The word at `address`, or why it cannot be read.
    fn read(&self, address: u16) -> Result<u16, Exception>;

    /// Carry out one word written at `at`; the model has been advanced to `at`.
    fn write(&mut self, address: u16, value: u16, at: Instant) -> Result<(), Exception>;

    /// Bring the ramp (and any clock) up to `at`, when a request arrives.
    fn advance(&mut self, at: Instant);

    /// How long the drive may go without a request; zero is never.
    fn communication_timeout(&self) -> Duration;

    /// The communication timeout ran out at `expired`, before the request now arriving.
    fn communication_lost(&mut self, expired: Instant);

    /// The response delay the drive's parameters ask for.
    fn response_delay(&self) -> Duration;

    /// Whether a write is answered, as the drive stands once it is carried out.
    fn answers_writes(&self) -> bool {
        true
    }

    /// Whether a read reply counts its bytes in two (big-endian) instead of one.
    fn wide_byte_count(&self) -> bool {
        false
    }
}

/// FC 08 sub-function 0000H: the request comes back unchanged.
const RETURN_QUERY_DATA: u16 = 0x0000;
/// The length of FC 03 and FC 06 requests: function code, then two words.
const TWO_WORD_REQUEST: usize = 5;

type Reply = Result<Vec<u8>, Exception>;

/// A simulated drive on the line: a [`Model`] behind the pipeline all the drives share.
#[derive(Clone, Debug)]
pub(crate) struct Drive<M> {
    model: M,
    address: u8,
    processing_delay: Duration,
    last_request: Option<Instant>,
}

impl<M: Model> Drive<M> {
    /// `model`, powered on with `settings`.
    pub(crate) fn new(model: M, settings: &DriveSettings) -> Self {
        Drive {
            model,
            address: settings.address,
            processing_delay: settings.processing_delay,
            last_request: None,
        }
    }

    /// When the communication timeout ran out, if it did before `at`.
    fn timeout_expiry(&self, at: Instant) -> Option<Instant> {
        let timeout = self.model.communication_timeout();
        let previous = self.last_request?;
        if timeout.is_zero() || at.saturating_duration_since(previous) <= timeout {
            return None;
        }
        Some(previous + timeout)
    }

    /// Answer a request PDU.
    fn respond(&mut self, request: &[u8], at: Instant) -> Reply {
        let protocol = M::PROTOCOL;
        match request.first().copied() {
            Some(code::READ_HOLDING_REGISTERS) => self.read_registers(request),
            Some(code::WRITE_SINGLE_REGISTER) => self.write_register(request, at),
            Some(code::DIAGNOSTICS) if protocol.diagnostics => diagnostics::<M>(request),
            Some(code::WRITE_MULTIPLE_REGISTERS) if protocol.write_multiple => {
                self.write_registers(request, at)
            }
            _ => Err(ExceptionCode::IllegalFunction.into()),
        }
    }

    fn quantity_ok(quantity: u16) -> Result<(), Exception> {
        if quantity == 0 || quantity > M::PROTOCOL.max_words {
            return Err(ExceptionCode::IllegalDataValue.into());
        }
        Ok(())
    }

    fn read_registers(&self, request: &[u8]) -> Reply {
        let (TWO_WORD_REQUEST, Some(start), Some(quantity)) =
            (request.len(), word(request, 1), word(request, 3))
        else {
            return Err(M::PROTOCOL.malformed);
        };
        Self::quantity_ok(quantity)?;
        let mut data = Vec::with_capacity(2 * usize::from(quantity));
        for offset in 0..quantity {
            let address = start
                .checked_add(offset)
                .ok_or(ExceptionCode::IllegalDataAddress)?;
            data.extend(self.model.read(address)?.to_be_bytes());
        }
        // A model's word limit is far below 128, so this never fails; were it above, the
        // quantity would be illegal anyway.
        let count = u8::try_from(data.len()).map_err(|_| ExceptionCode::IllegalDataValue)?;
        let mut reply = vec![code::READ_HOLDING_REGISTERS];
        if self.model.wide_byte_count() {
            reply.extend(u16::from(count).to_be_bytes());
        } else {
            reply.push(count);
        }
        reply.extend(data);
        Ok(reply)
    }

    fn write_register(&mut self, request: &[u8], at: Instant) -> Reply {
        let (TWO_WORD_REQUEST, Some(address), Some(value)) =
            (request.len(), word(request, 1), word(request, 3))
        else {
            return Err(M::PROTOCOL.malformed);
        };
        self.model.write(address, value, at)?;
        Ok(request.to_vec())
    }

    /// All or nothing: the words are carried out in order on a copy of the model, so a later word
    /// sees an earlier one, and a refusal anywhere changes nothing.
    fn write_registers(&mut self, request: &[u8], at: Instant) -> Reply {
        let (Some(start), Some(quantity), Some(&count)) =
            (word(request, 1), word(request, 3), request.get(5))
        else {
            return Err(M::PROTOCOL.malformed);
        };
        Self::quantity_ok(quantity)?;
        let values = &request[6..];
        if usize::from(count) != 2 * usize::from(quantity) || values.len() != usize::from(count) {
            return Err(M::PROTOCOL.malformed);
        }
        let mut trial = self.model.clone();
        for (offset, value) in (0..quantity).zip(values.chunks_exact(2)) {
            let address = start
                .checked_add(offset)
                .ok_or(ExceptionCode::IllegalDataAddress)?;
            trial.write(address, u16::from_be_bytes([value[0], value[1]]), at)?;
        }
        self.model = trial;
        Ok(request[..5].to_vec())
    }
}

fn diagnostics<M: Model>(request: &[u8]) -> Reply {
    match word(request, 1) {
        Some(RETURN_QUERY_DATA) => Ok(request.to_vec()),
        Some(_) => Err(ExceptionCode::IllegalFunction.into()),
        None => Err(M::PROTOCOL.malformed),
    }
}

impl<M: Model> Simulated for Drive<M> {
    fn handle(&mut self, address: u8, request: &[u8], at: Instant) -> Option<Transmission> {
        if let Some(expired) = self.timeout_expiry(at) {
            self.model.communication_lost(expired);
        }
        self.last_request = Some(at);
        self.model.advance(at);
        let function = request.first().copied().unwrap_or(0);
        let write = matches!(
            function,
            code::WRITE_SINGLE_REGISTER | code::WRITE_MULTIPLE_REGISTERS
        );
        if address == crate::line::BROADCAST {
            // Only writes have an effect to carry out; nothing is answered.
            if write {
                let _ = self.respond(request, at);
            }
            return None;
        }
        let reply = self.respond(request, at);
        if write && !self.model.answers_writes() {
            return None;
        }
        let pdu = reply.unwrap_or_else(|e| e.pdu(function).to_vec());
        let delay = self.model.response_delay().max(self.processing_delay);
        Some(Transmission::frame(self.address, &pdu, delay))
    }
}

/// The big-endian word at `at` in a PDU.
pub(crate) fn word(pdu: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]))
}
