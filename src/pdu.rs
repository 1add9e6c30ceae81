//! Facts about Modbus PDUs that both sides of the gateway share: exception codes, and one table of
//! what the gateway knows about each function code (name, request and reply lengths, whether it
//! reads, what a broadcast of it is answered with, the shape of its reply).
//! Knows nothing of MBAP, RTU framing, sockets or serial ports.

/// Largest PDU a Modbus ADU can carry (256-byte RTU frame minus address and CRC).
pub(crate) const MAX_PDU_LEN: usize = 253;

/// Set in the function code of a reply that is an exception.
pub(crate) const EXCEPTION_BIT: u8 = 0x80;

use code::*;
use Broadcast::{EchoFirst, EchoRequest, Refused};
use Effect::{Read, ReadIf, Write};

/// Exception replies: function | 0x80, exception code.
pub(crate) const EXCEPTION_PDU_LEN: usize = 2;
/// Exception codes the gateway itself sends. Slave exceptions pass through as raw bytes and are
/// never converted to this type, so vendor codes (05-09 on the reference drives) survive.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum ExceptionCode {
    IllegalFunction = 0x01,
    IllegalDataAddress = 0x02,
    IllegalDataValue = 0x03,
    ServerDeviceFailure = 0x04,
    ServerDeviceBusy = 0x06,
    GatewayPathUnavailable = 0x0A,
    GatewayTargetFailedToRespond = 0x0B,
}

/// The name the Modbus Application Protocol V1.1b3 gives exception code `code`, if it names it.
/// Codes it does not name are the vendor's own, and are called so wherever the gateway words an
/// exception (the journal's detail, the status page): 07 among them, Negative Acknowledge in the
/// older Modicon PI-MBUS-300 (as libmodbus and mbpoll still name it) but not in V1.1b3, and
/// "written not allowed" on the reference drives, which use 05-09 in their own senses.
pub(crate) fn exception_name(code: u8) -> Option<&'static str> {
    Some(match code {
        0x01 => "illegal function",
        0x02 => "illegal data address",
        0x03 => "illegal data value",
        0x04 => "server device failure",
        0x05 => "acknowledge",
        0x06 => "server device busy",
        0x08 => "memory parity error",
        0x0A => "gateway path unavailable",
        0x0B => "gateway target device failed to respond",
        _ => return None,
    })
}

/// The public function codes of the Modbus Application Protocol V1.1b3, by the spec's names.
pub(crate) mod code {
    pub(crate) const READ_COILS: u8 = 0x01;
    pub(crate) const READ_DISCRETE_INPUTS: u8 = 0x02;
    pub(crate) const READ_HOLDING_REGISTERS: u8 = 0x03;
    pub(crate) const READ_INPUT_REGISTERS: u8 = 0x04;
    pub(crate) const WRITE_SINGLE_COIL: u8 = 0x05;
    pub(crate) const WRITE_SINGLE_REGISTER: u8 = 0x06;
    pub(crate) const READ_EXCEPTION_STATUS: u8 = 0x07;
    pub(crate) const DIAGNOSTICS: u8 = 0x08;
    pub(crate) const GET_COMM_EVENT_COUNTER: u8 = 0x0B;
    pub(crate) const GET_COMM_EVENT_LOG: u8 = 0x0C;
    pub(crate) const WRITE_MULTIPLE_COILS: u8 = 0x0F;
    pub(crate) const WRITE_MULTIPLE_REGISTERS: u8 = 0x10;
    pub(crate) const REPORT_SERVER_ID: u8 = 0x11;
    pub(crate) const READ_FILE_RECORD: u8 = 0x14;
    pub(crate) const WRITE_FILE_RECORD: u8 = 0x15;
    pub(crate) const MASK_WRITE_REGISTER: u8 = 0x16;
    pub(crate) const READ_WRITE_MULTIPLE_REGISTERS: u8 = 0x17;
    pub(crate) const READ_FIFO_QUEUE: u8 = 0x18;
    pub(crate) const ENCAPSULATED_INTERFACE: u8 = 0x2B;
}

/// The two-byte exception PDU for a request with function code `function`.
pub(crate) fn exception_pdu(function: u8, code: ExceptionCode) -> [u8; 2] {
    [function | EXCEPTION_BIT, code as u8]
}

/// A function code a master may send: 1..=127. Codes with the high bit set only exist in replies.
pub(crate) fn is_valid_request_function(function: u8) -> bool {
    function != 0 && function & EXCEPTION_BIT == 0
}

/// What the gateway knows about one function code. Codes without a row are user-defined or
/// unknown: their PDUs end by silence, count as writes, cannot be broadcast and fit any reply.
#[derive(Clone, Copy, Debug)]
pub struct Function {
    pub code: u8,
    /// The name the Modbus Application Protocol V1.1b3 gives it.
    pub name: &'static str,
    /// How long a request PDU is.
    pub request: Len,
    /// How long a normal reply PDU is (an exception is always `EXCEPTION_PDU_LEN`).
    pub reply: Len,
    pub access: Effect,
    /// What a broadcast of it is answered with, by the gateway since no slave answers.
    pub broadcast: Broadcast,
    /// What a normal reply must look like to answer the request.
    pub(crate) reply_shape: Shape,
    /// The quantity a multiple write names, which its byte count must agree with.
    pub(crate) quantity: Option<Quantity>,
}

/// A multiple write's quantity (a word at `at`) and the byte count (at `count_at`) of the values
/// after it: the count must be what the quantity gives, the quantity from 1 to `max` (the
/// Modbus Application Protocol's bounds). A slave may go by either, so a request whose two
/// disagree would write what its quantity does not say (some firmware writes `count / 2`
/// registers): the gateway does not send it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Quantity {
    pub(crate) at: usize,
    pub(crate) count_at: usize,
    pub(crate) unit: Unit,
    pub(crate) max: u16,
}

impl Quantity {
    /// The length the request must have by its quantity; `None` when the quantity is out of
    /// bounds or the bytes too short to hold it.
    fn request_len(self, pdu: &[u8]) -> Option<usize> {
        let quantity = word_at(pdu, self.at).filter(|q| (1..=self.max).contains(q))?;
        Some(self.count_at + 1 + self.unit.bytes(quantity))
    }
}

/// How the length of a PDU follows from its first bytes (offsets within the PDU).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Len {
    /// Always this many bytes.
    Fixed(usize),
    /// A byte count at `at` (one byte, or two big-endian bytes when `wide`), then that many bytes.
    Counted { at: usize, wide: bool },
    /// As long as the request it answers (diagnostics echo their request's data).
    Echo,
    /// Byte 1 is the MEI type: Read Device Identification (0x0E) follows `read_device_id`, other
    /// MEI types are unknown.
    Mei { read_device_id: &'static Len },
    /// A header of `count_at + 1` bytes whose last byte counts objects, each an id byte, a
    /// length byte and that many value bytes (Read Device Identification replies).
    Objects { count_at: usize },
    /// Diagnostics requests: bytes 1-2 are the sub-function. Those the spec defines with one
    /// data word are five bytes; Return Query Data (0000H) and sub-functions the spec does not
    /// define end by silence.
    SubFunction,
}

/// What [`Len::of`] can tell from the bytes received so far.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PduLen {
    /// The length is known once at least this many bytes are in.
    Need(usize),
    /// The PDU is exactly this many bytes long.
    Exact(usize),
    /// The bytes cannot tell.
    Unknown,
    /// The header announces more than `MAX_PDU_LEN`: these bytes are not a PDU.
    Invalid,
}

/// Whether a request changes anything on the slave.
#[derive(Clone, Copy, Debug)]
pub enum Effect {
    Read,
    Write,
    /// Reads when the PDU says so (a sub-function or MEI type), writes otherwise.
    ReadIf(fn(&[u8]) -> bool),
}

/// The normal response to a broadcast request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Broadcast {
    /// The serial line spec allows no broadcast of it: the gateway refuses it.
    Refused,
    /// The response echoes the whole request.
    EchoRequest,
    /// The response echoes the first `n` bytes of the request.
    EchoFirst(usize),
}

/// What a normal reply must hold to answer its request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Shape {
    /// Byte 1 counts the bytes of the quantity the request asks for at bytes `quantity_at..+2`.
    ByteCount { quantity_at: usize, unit: Unit },
    /// Bytes `from..to` are those of the request.
    Echo { from: usize, to: usize },
    /// Anything with the right function code.
    Any,
}

/// What a read quantity counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Unit {
    /// Coils and inputs, eight to a byte.
    Bits,
    /// Registers, two bytes each.
    Words,
}

impl Unit {
    /// The bytes `quantity` of them take.
    pub(crate) fn bytes(self, quantity: u16) -> usize {
        match self {
            Unit::Bits => usize::from(quantity).div_ceil(8),
            Unit::Words => usize::from(quantity) * 2,
        }
    }
}

/// Diagnostics: echo, diagnostic register and the counters read; the rest restart or clear.
/// Return Query Data (0000H) reads only with one word of data: its length is the master's to
/// choose, so longer data could hold a whole frame that a slave framing by length would take as
/// the next request, and a master that may only read must not be able to send one.
fn diagnostics_reads(pdu: &[u8]) -> bool {
    match sub_function(pdu) {
        Some(RETURN_QUERY_DATA) => pdu.len() == 5,
        Some(sub) => matches!(sub, 0x0002 | 0x000B..=0x0012),
        None => false,
    }
}

/// Read File Record reads only when its sub-requests are what the Modbus Application Protocol
/// says: seven bytes each, reference type 6, a record number up to 270FH. Its bytes are the
/// master's to choose, and a slave that does not implement the function may frame them its own
/// way (libmodbus takes four bytes of any function it does not know as a frame, and what follows
/// as the next request): a master that may only read does not get to choose them freely.
fn file_records_read(pdu: &[u8]) -> bool {
    let Some((&count, records)) = pdu.get(1..).and_then(<[u8]>::split_first) else {
        return false;
    };
    usize::from(count) == records.len()
        && !records.is_empty()
        && records.len() % FILE_SUB_REQUEST == 0
        && records.chunks(FILE_SUB_REQUEST).all(|record| {
            record[0] == FILE_REFERENCE_TYPE
                && u16::from_be_bytes([record[3], record[4]]) <= MAX_RECORD_NUMBER
        })
}

/// A Read File Record sub-request: reference type, file number, record number, record length.
const FILE_SUB_REQUEST: usize = 7;
const FILE_REFERENCE_TYPE: u8 = 6;
const MAX_RECORD_NUMBER: u16 = 0x270F;

/// The diagnostics sub-function whose data is the master's to choose (any number of words).
const RETURN_QUERY_DATA: u16 = 0x0000;
/// The diagnostics sub-functions of the Modbus Application Protocol V1.1b3 with one data word:
/// restart, diagnostic register, ASCII delimiter, listen only, clear counters, the eight
/// counters, clear overrun.
const DIAGNOSTICS_WITH_ONE_WORD: [u16; 14] = [
    0x0001, 0x0002, 0x0003, 0x0004, 0x000A, 0x000B, 0x000C, 0x000D, 0x000E, 0x000F, 0x0010, 0x0011,
    0x0012, 0x0014,
];

/// Encapsulated interface: only Read Device Identification is known to be a read.
fn mei_reads(pdu: &[u8]) -> bool {
    pdu.get(1) == Some(&MEI_READ_DEVICE_ID)
}

fn sub_function(pdu: &[u8]) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(1)?, *pdu.get(2)?]))
}

/// The MEI type of Read Device Identification.
const MEI_READ_DEVICE_ID: u8 = 0x0E;

const fn row(
    code: u8,
    name: &'static str,
    request: Len,
    reply: Len,
    access: Effect,
    broadcast: Broadcast,
    reply_shape: Shape,
) -> Function {
    Function {
        code,
        name,
        request,
        reply,
        access,
        broadcast,
        reply_shape,
        quantity: None,
    }
}

impl Function {
    /// The row, its requests' byte count checked against their `quantity`.
    const fn counting(self, quantity: Quantity) -> Function {
        Function {
            quantity: Some(quantity),
            ..self
        }
    }
}

/// A byte count right after the function code.
const COUNT: Len = Len::Counted { at: 1, wide: false };
/// Function code alone.
const BARE: Len = Len::Fixed(1);
/// Function code, then two words: address and quantity, or address and value.
const TWO_WORDS: Len = Len::Fixed(5);
const BITS: Shape = Shape::ByteCount {
    quantity_at: 3,
    unit: Unit::Bits,
};
const WORDS: Shape = Shape::ByteCount {
    quantity_at: 3,
    unit: Unit::Words,
};
/// Single writes echo the whole request: a late echo of an earlier write of another value to the
/// same address is not this write's answer.
const ECHO_SINGLE_WRITE: Shape = Shape::Echo { from: 0, to: 5 };
/// Multiple writes echo the address and quantity they wrote.
const ECHO_ADDRESS_AND_QUANTITY: Shape = Shape::Echo { from: 1, to: 5 };
/// Diagnostics echo the sub-function.
const ECHO_SUB_FUNCTION: Shape = Shape::Echo { from: 1, to: 3 };
/// Encapsulated interface transports echo the MEI type.
const ECHO_MEI_TYPE: Shape = Shape::Echo { from: 1, to: 2 };

/// Every function code the gateway knows, in code order. Diagnostics replies echo their request,
/// so only the request tells their length.
#[rustfmt::skip]
pub(crate) const FUNCTIONS: &[Function] = &[
    // code, name,
    //     request, reply, access, broadcast answer, reply shape
    row(READ_COILS, "Read Coils",
        TWO_WORDS, COUNT, Read, Refused, BITS),
    row(READ_DISCRETE_INPUTS, "Read Discrete Inputs",
        TWO_WORDS, COUNT, Read, Refused, BITS),
    row(READ_HOLDING_REGISTERS, "Read Holding Registers",
        TWO_WORDS, COUNT, Read, Refused, WORDS),
    row(READ_INPUT_REGISTERS, "Read Input Registers",
        TWO_WORDS, COUNT, Read, Refused, WORDS),
    row(WRITE_SINGLE_COIL, "Write Single Coil",
        TWO_WORDS, TWO_WORDS, Write, EchoRequest, ECHO_SINGLE_WRITE),
    row(WRITE_SINGLE_REGISTER, "Write Single Register",
        TWO_WORDS, TWO_WORDS, Write, EchoRequest, ECHO_SINGLE_WRITE),
    row(READ_EXCEPTION_STATUS, "Read Exception Status",
        BARE, Len::Fixed(2), Read, Refused, Shape::Any),
    row(DIAGNOSTICS, "Diagnostics",
        Len::SubFunction, Len::Echo, ReadIf(diagnostics_reads), Refused, ECHO_SUB_FUNCTION),
    row(GET_COMM_EVENT_COUNTER, "Get Comm Event Counter",
        BARE, TWO_WORDS, Read, Refused, Shape::Any),
    row(GET_COMM_EVENT_LOG, "Get Comm Event Log",
        BARE, COUNT, Read, Refused, Shape::Any),
    row(WRITE_MULTIPLE_COILS, "Write Multiple Coils",
        Len::Counted { at: 5, wide: false }, TWO_WORDS, Write, EchoFirst(5), ECHO_ADDRESS_AND_QUANTITY)
        .counting(Quantity { at: 3, count_at: 5, unit: Unit::Bits, max: 0x07B0 }),
    row(WRITE_MULTIPLE_REGISTERS, "Write Multiple Registers",
        Len::Counted { at: 5, wide: false }, TWO_WORDS, Write, EchoFirst(5), ECHO_ADDRESS_AND_QUANTITY)
        .counting(Quantity { at: 3, count_at: 5, unit: Unit::Words, max: 0x007B }),
    row(REPORT_SERVER_ID, "Report Server ID",
        BARE, COUNT, Read, Refused, Shape::Any),
    row(READ_FILE_RECORD, "Read File Record",
        COUNT, COUNT, ReadIf(file_records_read), Refused, Shape::Any),
    row(WRITE_FILE_RECORD, "Write File Record",
        COUNT, COUNT, Write, EchoRequest, Shape::Any),
    row(MASK_WRITE_REGISTER, "Mask Write Register",
        Len::Fixed(7), Len::Fixed(7), Write, EchoRequest, Shape::Echo { from: 0, to: 7 }),
    row(READ_WRITE_MULTIPLE_REGISTERS, "Read/Write Multiple Registers",
        Len::Counted { at: 9, wide: false }, COUNT, Write, Refused, WORDS)
        .counting(Quantity { at: 7, count_at: 9, unit: Unit::Words, max: 0x0079 }),
    row(READ_FIFO_QUEUE, "Read FIFO Queue",
        Len::Fixed(3), Len::Counted { at: 1, wide: true }, Read, Refused, Shape::Any),
    row(ENCAPSULATED_INTERFACE, "Encapsulated Interface Transport",
        Len::Mei { read_device_id: &Len::Fixed(4) },
        Len::Mei { read_device_id: &Len::Objects { count_at: 6 } },
        ReadIf(mei_reads), Refused, ECHO_MEI_TYPE),
];

/// No row: the index's value for codes the table lacks.
const NO_ROW: u8 = u8::MAX;

/// Row of each function code in [`FUNCTIONS`], built once at compile time so the per-frame lookup
/// is one array access.
const INDEX: [u8; 256] = {
    let mut index = [NO_ROW; 256];
    assert!(
        FUNCTIONS.len() < NO_ROW as usize,
        "more rows than the index can number"
    );
    let mut row = 0;
    while row < FUNCTIONS.len() {
        let code = FUNCTIONS[row].code as usize;
        assert!(index[code] == NO_ROW, "a function code has two rows");
        // `try_from` is not const; the assert above keeps `row` below 255.
        #[allow(clippy::cast_possible_truncation)]
        {
            index[code] = row as u8;
        }
        row += 1;
    }
    index
};

/// What the gateway knows about function code `code`, if anything.
pub fn function(code: u8) -> Option<&'static Function> {
    match INDEX[usize::from(code)] {
        NO_ROW => None,
        row => Some(&FUNCTIONS[usize::from(row)]),
    }
}

impl Len {
    /// The length of the PDU whose first bytes are `pdu`, as far as they tell. `request` is the
    /// request a reply answers, `None` when the bytes are a request or claim to answer another.
    pub fn of(&self, pdu: &[u8], request: Option<&[u8]>) -> PduLen {
        match *self {
            Len::Fixed(len) => PduLen::Exact(len),
            Len::Counted { at, wide } => counted(pdu, at, wide),
            Len::Echo => request.map_or(PduLen::Unknown, |request| exact(request.len())),
            Len::Mei { read_device_id } => match pdu.get(1) {
                None => PduLen::Need(2),
                Some(&MEI_READ_DEVICE_ID) => read_device_id.of(pdu, request),
                Some(_) => PduLen::Unknown,
            },
            Len::Objects { count_at } => objects(pdu, count_at),
            Len::SubFunction => match sub_function(pdu) {
                None => PduLen::Need(3),
                Some(sub) if DIAGNOSTICS_WITH_ONE_WORD.contains(&sub) => PduLen::Exact(5),
                Some(_) => PduLen::Unknown,
            },
        }
    }
}

fn exact(len: usize) -> PduLen {
    if len > MAX_PDU_LEN {
        PduLen::Invalid
    } else {
        PduLen::Exact(len)
    }
}

fn counted(pdu: &[u8], at: usize, wide: bool) -> PduLen {
    let header = at + if wide { 2 } else { 1 };
    if pdu.len() < header {
        return PduLen::Need(header);
    }
    let count = if wide {
        usize::from(u16::from_be_bytes([pdu[at], pdu[at + 1]]))
    } else {
        usize::from(pdu[at])
    };
    exact(header + count)
}

fn objects(pdu: &[u8], count_at: usize) -> PduLen {
    let header = count_at + 1;
    if pdu.len() < header {
        return PduLen::Need(header);
    }
    let mut end = header;
    for _ in 0..pdu[count_at] {
        if pdu.len() < end + 2 {
            return PduLen::Need(end + 2);
        }
        end += 2 + usize::from(pdu[end + 1]);
        if end > MAX_PDU_LEN {
            return PduLen::Invalid;
        }
    }
    exact(end)
}

/// How a request PDU's length compares with what its function code says.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum RequestLen {
    /// Exactly as long as its function says.
    Fits,
    /// Its bytes cannot tell how long it should be (a user-defined function code, a sub-function
    /// or MEI type the table does not know, Return Query Data): it goes byte for byte.
    Unchecked,
    /// Shorter or longer than its function says: `expected` bytes, where the bytes tell.
    Wrong { expected: Option<usize> },
}

/// Check `pdu`, a request, against the length its function code gives it. A longer PDU would
/// carry bytes after the request that a slave framing by length takes as a request of its own
/// (a hidden write, or a read whose answer comes late to another master); a shorter one is no
/// request a slave can answer. A multiple write must also be as long as its quantity says, the
/// quantity within the spec's bounds: a byte count that disagrees with it is wrong too.
pub(crate) fn request_len(pdu: &[u8]) -> RequestLen {
    let Some(row) = pdu.first().and_then(|&code| function(code)) else {
        return RequestLen::Unchecked;
    };
    match row.request.of(pdu, None) {
        PduLen::Exact(len) if len == pdu.len() => match row.quantity {
            Some(quantity) => match quantity.request_len(pdu) {
                Some(by_quantity) if by_quantity == len => RequestLen::Fits,
                expected => RequestLen::Wrong { expected },
            },
            None => RequestLen::Fits,
        },
        PduLen::Exact(len) => RequestLen::Wrong {
            expected: Some(len),
        },
        PduLen::Need(_) | PduLen::Invalid => RequestLen::Wrong { expected: None },
        PduLen::Unknown => RequestLen::Unchecked,
    }
}

/// Requests that change nothing on the slave, so repeating them after a lost reply is harmless.
/// Anything not known to be a read (user-defined codes included) counts as a write.
pub(crate) fn is_read_only(pdu: &[u8]) -> bool {
    let Some(row) = pdu.first().and_then(|&code| function(code)) else {
        return false;
    };
    match row.access {
        Effect::Read => true,
        Effect::Write => false,
        Effect::ReadIf(reads) => reads(pdu),
    }
}

/// The normal response to a broadcast write, which the gateway makes itself because no slave
/// answers a broadcast. `None` for requests that cannot be broadcast or are too short to answer.
pub(crate) fn broadcast_response(pdu: &[u8]) -> Option<Vec<u8>> {
    match function(*pdu.first()?)?.broadcast {
        Broadcast::EchoRequest => Some(pdu.to_vec()),
        Broadcast::EchoFirst(n) => pdu.get(..n).map(<[u8]>::to_vec),
        Broadcast::Refused => None,
    }
}

/// The data tables of the Modbus data model, as the journal names them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum DataTable {
    Coils,
    DiscreteInputs,
    HoldingRegisters,
    InputRegisters,
}

impl DataTable {
    /// The word the journal and `[[bus.slave.value]]`'s `table` use.
    pub(crate) fn word(self) -> &'static str {
        match self {
            DataTable::Coils => "coil",
            DataTable::DiscreteInputs => "discrete",
            DataTable::HoldingRegisters => "holding",
            DataTable::InputRegisters => "input",
        }
    }
}

/// Data addresses `first` to `last` of one table that a request touches. `last` may run past
/// 65535 when a request asks for more than the table holds: such a span is seen whole.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Span {
    pub table: DataTable,
    pub first: u16,
    pub last: u32,
}

impl Span {
    /// `quantity` addresses from `first` (a quantity of 0, which no slave accepts, touches the
    /// first address only).
    fn of(table: DataTable, first: u16, quantity: u16) -> Span {
        Span {
            table,
            first,
            last: u32::from(first) + u32::from(quantity.max(1)) - 1,
        }
    }

    /// How many addresses it spans.
    pub(crate) fn count(&self) -> u32 {
        self.last - u32::from(self.first) + 1
    }
}

/// The data addresses a request touches, as far as its bytes tell.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Touches {
    /// No data address: diagnostics, identification, event counters.
    Nothing,
    /// One span, or two (Read/Write Multiple Registers reads one and writes another).
    Spans(Span, Option<Span>),
    /// The bytes cannot tell (user-defined codes, file records, a request too short to say):
    /// it may touch any.
    Unknown,
}

fn word_at(pdu: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]))
}

/// The data addresses `pdu`, a request, touches.
pub(crate) fn touches(pdu: &[u8]) -> Touches {
    use DataTable::{Coils, DiscreteInputs, HoldingRegisters, InputRegisters};
    let Some(&function) = pdu.first() else {
        return Touches::Unknown;
    };
    let span = |table, quantity: Option<u16>| {
        let first = word_at(pdu, 1)?;
        Some(Span::of(table, first, quantity?))
    };
    let one = |span: Option<Span>| span.map_or(Touches::Unknown, |s| Touches::Spans(s, None));
    match function {
        READ_COILS => one(span(Coils, word_at(pdu, 3))),
        READ_DISCRETE_INPUTS => one(span(DiscreteInputs, word_at(pdu, 3))),
        READ_HOLDING_REGISTERS => one(span(HoldingRegisters, word_at(pdu, 3))),
        READ_INPUT_REGISTERS => one(span(InputRegisters, word_at(pdu, 3))),
        WRITE_SINGLE_COIL | WRITE_MULTIPLE_COILS => {
            let quantity = if function == WRITE_SINGLE_COIL {
                Some(1)
            } else {
                word_at(pdu, 3)
            };
            one(span(Coils, quantity))
        }
        WRITE_SINGLE_REGISTER | MASK_WRITE_REGISTER | READ_FIFO_QUEUE => {
            one(span(HoldingRegisters, Some(1)))
        }
        WRITE_MULTIPLE_REGISTERS => one(span(HoldingRegisters, word_at(pdu, 3))),
        READ_WRITE_MULTIPLE_REGISTERS => {
            let read = span(HoldingRegisters, word_at(pdu, 3));
            let write = word_at(pdu, 5)
                .zip(word_at(pdu, 7))
                .map(|(first, quantity)| Span::of(HoldingRegisters, first, quantity));
            match (read, write) {
                (Some(read), Some(write)) => Touches::Spans(read, Some(write)),
                _ => Touches::Unknown,
            }
        }
        // Read Device Identification reads no data address; the other MEI types (CANopen
        // General Reference, 0DH, reads and writes a device's objects) may touch any.
        ENCAPSULATED_INTERFACE if mei_reads(pdu) => Touches::Nothing,
        READ_EXCEPTION_STATUS
        | DIAGNOSTICS
        | GET_COMM_EVENT_COUNTER
        | GET_COMM_EVENT_LOG
        | REPORT_SERVER_ID => Touches::Nothing,
        _ => Touches::Unknown,
    }
}

/// What a write request sets: the span it writes, if its bytes say, and the bytes of the values
/// (for a write the table does not know, everything after the function code).
pub(crate) fn written(pdu: &[u8]) -> (Option<Span>, &[u8]) {
    let after = |at: usize| pdu.get(at..).unwrap_or_default();
    let span = match touches(pdu) {
        Touches::Spans(_, Some(write)) => Some(write),
        Touches::Spans(span, None) => Some(span),
        Touches::Nothing | Touches::Unknown => None,
    };
    let values = match pdu.first().copied() {
        Some(WRITE_SINGLE_COIL | WRITE_SINGLE_REGISTER | MASK_WRITE_REGISTER) => after(3),
        Some(WRITE_MULTIPLE_COILS | WRITE_MULTIPLE_REGISTERS) => after(6),
        Some(READ_WRITE_MULTIPLE_REGISTERS) => after(10),
        _ => after(1),
    };
    (span, values)
}

/// The Modbus Application Protocol's diagnostics functions (its function-code categories):
/// Read Exception Status, Diagnostics, Get Comm Event Counter and Log, Report Server ID, and the
/// Encapsulated Interface Transport (Read Device Identification).
pub(crate) fn is_diagnostic(function: u8) -> bool {
    matches!(
        function,
        READ_EXCEPTION_STATUS
            | DIAGNOSTICS
            | GET_COMM_EVENT_COUNTER
            | GET_COMM_EVENT_LOG
            | REPORT_SERVER_ID
            | ENCAPSULATED_INTERFACE
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gateway_exceptions_set_the_high_bit_of_the_request_function() {
        assert_eq!(
            exception_pdu(0x03, ExceptionCode::GatewayTargetFailedToRespond),
            [0x83, 0x0B]
        );
        assert_eq!(
            exception_pdu(0x41, ExceptionCode::GatewayPathUnavailable),
            [0xC1, 0x0A]
        );
    }

    #[test]
    fn reads_are_recognised_and_everything_unknown_counts_as_a_write() {
        assert!(is_read_only(&[0x03, 0, 0, 0, 1]));
        assert!(is_read_only(&[0x08, 0x00, 0x00, 0x12, 0xAB]));
        assert!(
            !is_read_only(&[0x08, 0x00, 0x01, 0x00, 0x00]),
            "restart comms"
        );
        assert!(
            !is_read_only(&[0x08, 0x00, 0x0A, 0x00, 0x00]),
            "clear counters"
        );
        assert!(is_read_only(&[0x2B, 0x0E, 0x01, 0x00]));
        assert!(!is_read_only(&[0x2B, 0x0D]));
        assert!(!is_read_only(&[0x06, 0, 1, 0, 1]));
        assert!(!is_read_only(&[0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0, 0]));
        assert!(!is_read_only(&[0x41, 1, 2]));
        assert!(!is_read_only(&[]));
    }

    #[test]
    fn broadcast_writes_are_answered_like_the_slave_would() {
        // Write multiple registers 0004H..0005H (the Goodrive300 manual's FC 10 example).
        let pdu = [0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32];
        assert_eq!(
            broadcast_response(&pdu),
            Some(vec![0x10, 0x00, 0x04, 0x00, 0x02])
        );
        let pdu = [0x06, 0x00, 0x04, 0x13, 0x88];
        assert_eq!(broadcast_response(&pdu), Some(pdu.to_vec()));
        assert_eq!(broadcast_response(&[0x03, 0, 0, 0, 1]), None);
        assert_eq!(broadcast_response(&[0x10, 0x00]), None);
    }

    #[test]
    fn only_user_visible_function_codes_are_valid_in_requests() {
        assert!(!is_valid_request_function(0x00));
        assert!(is_valid_request_function(0x41));
        assert!(!is_valid_request_function(0x83));
    }

    #[test]
    fn the_table_knows_each_code_once_by_its_name_and_finds_it_by_code() {
        for (i, row) in FUNCTIONS.iter().enumerate() {
            assert!(!row.name.is_empty(), "{:02X} has no name", row.code);
            assert!(is_valid_request_function(row.code), "{:02X}", row.code);
            let later = &FUNCTIONS[i + 1..];
            assert!(
                later.iter().all(|other| other.code > row.code),
                "{:02X}",
                row.code
            );
            assert_eq!(function(row.code).map(|found| found.code), Some(row.code));
        }
        let known = [
            0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0B, 0x0C, 0x0F, 0x10, 0x11, 0x14,
            0x15, 0x16, 0x17, 0x18, 0x2B,
        ];
        for code in 0..=u8::MAX {
            assert_eq!(
                function(code).is_some(),
                known.contains(&code),
                "{code:02X}"
            );
        }
        assert_eq!(
            function(code::READ_HOLDING_REGISTERS).map(|f| f.name),
            Some("Read Holding Registers")
        );
    }

    /// Reads `pdu` byte by byte with `rule`: every prefix must ask for more bytes, up to and no
    /// further than the whole PDU, which must then be exactly its length.
    fn assert_measures_whole(rule: Len, pdu: &[u8], request: Option<&[u8]>) {
        for k in 0..pdu.len() {
            match rule.of(&pdu[..k], request) {
                PduLen::Need(n) => assert!(k < n && n <= pdu.len(), "Need({n}) at {k}"),
                PduLen::Exact(n) => assert_eq!(n, pdu.len(), "at {k} of {pdu:02X?}"),
                other => panic!("{other:?} at {k} of {pdu:02X?}"),
            }
        }
        assert_eq!(
            rule.of(pdu, request),
            PduLen::Exact(pdu.len()),
            "{pdu:02X?}"
        );
    }

    /// One worked (request PDU, reply PDU) for every row: the Goodrive300 manual 10.4 (03, 06, 08,
    /// 10) and the examples of the Modbus Application Protocol V1.1b3 (the rest).
    const WORKED: [(&[u8], &[u8]); 19] = [
        // Read coils 20-22 (0013H, 3 coils): one data byte.
        (&[0x01, 0x00, 0x13, 0x00, 0x03], &[0x01, 0x01, 0x05]),
        // Read discrete inputs 197-218 (00C4H, 22 inputs): three data bytes.
        (
            &[0x02, 0x00, 0xC4, 0x00, 0x16],
            &[0x02, 0x03, 0xAC, 0xDB, 0x35],
        ),
        // Read 2 words from 0004H; 0004H = 1388H, 0005H = 0.
        (
            &[0x03, 0x00, 0x04, 0x00, 0x02],
            &[0x03, 0x04, 0x13, 0x88, 0x00, 0x00],
        ),
        // Read input register 9 (0008H): 000AH.
        (&[0x04, 0x00, 0x08, 0x00, 0x01], &[0x04, 0x02, 0x00, 0x0A]),
        // Write coil 173 (00ACH) ON: the reply is the echo.
        (
            &[0x05, 0x00, 0xAC, 0xFF, 0x00],
            &[0x05, 0x00, 0xAC, 0xFF, 0x00],
        ),
        // Write 1388H to 0004H: the reply is the echo.
        (
            &[0x06, 0x00, 0x04, 0x13, 0x88],
            &[0x06, 0x00, 0x04, 0x13, 0x88],
        ),
        // Read exception status: one status byte.
        (&[0x07], &[0x07, 0x6D]),
        // Diagnostics, return query data 12ABH: echoed.
        (
            &[0x08, 0x00, 0x00, 0x12, 0xAB],
            &[0x08, 0x00, 0x00, 0x12, 0xAB],
        ),
        // Get comm event counter: status FFFFH, count 0108H.
        (&[0x0B], &[0x0B, 0xFF, 0xFF, 0x01, 0x08]),
        // Get comm event log: count 8, status, event count, message count, two events.
        (
            &[0x0C],
            &[0x0C, 0x08, 0x00, 0x00, 0x01, 0x08, 0x01, 0x21, 0x20, 0x00],
        ),
        // Write 10 coils from 0013H (two data bytes): address and quantity echoed.
        (
            &[0x0F, 0x00, 0x13, 0x00, 0x0A, 0x02, 0xCD, 0x01],
            &[0x0F, 0x00, 0x13, 0x00, 0x0A],
        ),
        // Write 1388H, 0032H to 0004H-0005H: address and quantity echoed.
        (
            &[0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32],
            &[0x10, 0x00, 0x04, 0x00, 0x02],
        ),
        // Report server ID: count 3, server id, run indicator ON, one more byte.
        (&[0x11], &[0x11, 0x03, 0x42, 0xFF, 0x00]),
        // Read file record: two sub-requests (14 bytes), two records back (12 bytes).
        (
            &[
                0x14, 0x0E, 0x06, 0x00, 0x04, 0x00, 0x01, 0x00, 0x02, 0x06, 0x00, 0x03, 0x00, 0x09,
                0x00, 0x02,
            ],
            &[
                0x14, 0x0C, 0x05, 0x06, 0x0D, 0xFE, 0x00, 0x20, 0x05, 0x06, 0x33, 0xCD, 0x00, 0x40,
            ],
        ),
        // Write file record: one sub-request of three words (13 bytes), echoed.
        (
            &[
                0x15, 0x0D, 0x06, 0x00, 0x04, 0x00, 0x07, 0x00, 0x03, 0x06, 0xAF, 0x04, 0xBE, 0x10,
                0x0D,
            ],
            &[
                0x15, 0x0D, 0x06, 0x00, 0x04, 0x00, 0x07, 0x00, 0x03, 0x06, 0xAF, 0x04, 0xBE, 0x10,
                0x0D,
            ],
        ),
        // Mask write 0004H, AND 00F2H, OR 0025H: echoed.
        (
            &[0x16, 0x00, 0x04, 0x00, 0xF2, 0x00, 0x25],
            &[0x16, 0x00, 0x04, 0x00, 0xF2, 0x00, 0x25],
        ),
        // Read 6 words from 0003H, write 3 words (6 bytes) to 000EH: twelve bytes back.
        (
            &[
                0x17, 0x00, 0x03, 0x00, 0x06, 0x00, 0x0E, 0x00, 0x03, 0x06, 0x00, 0xFF, 0x00, 0xFF,
                0x00, 0xFF,
            ],
            &[
                0x17, 0x0C, 0x00, 0xFE, 0x0A, 0xCD, 0x00, 0x01, 0x00, 0x03, 0x00, 0x0D, 0x00, 0xFF,
            ],
        ),
        // Read FIFO queue at 04DEH: two-byte count, two values.
        (
            &[0x18, 0x04, 0xDE],
            &[0x18, 0x00, 0x06, 0x00, 0x02, 0x01, 0xB8, 0x12, 0x84],
        ),
        // Read device identification, basic: objects "AB" and "C".
        (
            &[0x2B, 0x0E, 0x01, 0x00],
            &[
                0x2B, 0x0E, 0x01, 0x01, 0x00, 0x00, 0x02, // header, two objects
                0x00, 0x02, b'A', b'B', // object 0, two bytes
                0x01, 0x01, b'C', // object 1, one byte
            ],
        ),
    ];

    #[test]
    fn every_rows_length_rules_measure_its_worked_frames_byte_by_byte() {
        for row in FUNCTIONS {
            let (request, reply) = WORKED
                .iter()
                .find(|(request, _)| request[0] == row.code)
                .unwrap_or_else(|| panic!("no worked frames for {:02X}", row.code));
            assert_eq!(reply[0], row.code);
            if row.code == DIAGNOSTICS {
                // Return Query Data: its data is the master's to choose, silence ends it.
                assert_eq!(row.request.of(request, None), PduLen::Unknown);
            } else {
                assert_measures_whole(row.request, request, None);
            }
            assert_measures_whole(row.reply, reply, Some(request));
        }
    }

    /// Wrong: longer or shorter than its function code says.
    #[test]
    fn a_request_of_the_wrong_length_is_wrong_and_unknown_lengths_pass() {
        // The hidden write of issue 25: a read, the CRC a slave expects, then a whole write frame.
        let smuggled = [
            0x03, 0x00, 0x00, 0x00, 0x01, // read 1 register from 0000H
            0x84, 0x0A, // the CRC of 01 03 00 00 00 01
            0x01, 0x06, 0x00, 0x05, 0x12, 0x34, 0x94, 0xBC, // write 1234H to 0005H of slave 1
        ];
        assert_eq!(
            request_len(&smuggled),
            RequestLen::Wrong { expected: Some(5) }
        );
        assert_eq!(request_len(&smuggled[..5]), RequestLen::Fits);
        assert_eq!(
            request_len(&[0x03, 0x00]),
            RequestLen::Wrong { expected: Some(5) }
        );
        // Write multiple registers: its byte count says 4 bytes of data follow.
        let write = [0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32];
        assert_eq!(request_len(&write), RequestLen::Fits);
        assert_eq!(
            request_len(&write[..9]),
            RequestLen::Wrong { expected: Some(10) }
        );
        // Diagnostics: the defined sub-functions have one data word; Return Query Data and
        // sub-functions the spec does not define go as they are.
        assert_eq!(
            request_len(&[0x08, 0x00, 0x0A, 0x00, 0x00]),
            RequestLen::Fits
        );
        assert_eq!(
            request_len(&[0x08, 0x00, 0x0A, 0x00, 0x00, 0x00]),
            RequestLen::Wrong { expected: Some(5) }
        );
        assert_eq!(
            request_len(&[0x08, 0x00]),
            RequestLen::Wrong { expected: None }
        );
        assert_eq!(
            request_len(&[0x08, 0x00, 0x00, 0x12, 0xAB, 0x12, 0xAB]),
            RequestLen::Unchecked
        );
        assert_eq!(
            request_len(&[0x08, 0x00, 0x15, 0, 0]),
            RequestLen::Unchecked
        );
        // Read Device Identification is four bytes; other MEI types are unknown.
        assert_eq!(request_len(&[0x2B, 0x0E, 0x01, 0x00]), RequestLen::Fits);
        assert_eq!(
            request_len(&[0x2B, 0x0E, 0x01, 0x00, 0x00]),
            RequestLen::Wrong { expected: Some(4) }
        );
        assert_eq!(request_len(&[0x2B, 0x0D, 1, 2, 3]), RequestLen::Unchecked);
        // User-defined codes.
        assert_eq!(request_len(&[0x41, 1, 2, 3]), RequestLen::Unchecked);
    }

    #[test]
    fn a_multiple_write_whose_byte_count_disagrees_with_its_quantity_is_wrong() {
        let wrong = |expected| RequestLen::Wrong { expected };
        // One register by its quantity, two by its byte count: as long as one register says.
        let one_by_quantity = [0x10, 0x20, 0x01, 0x00, 0x01, 0x04, 0x0D, 0x0D, 0xBE, 0xEF];
        assert_eq!(request_len(&one_by_quantity), wrong(Some(8)));
        // Two registers by quantity, one by byte count.
        let two_by_quantity = [0x10, 0x20, 0x00, 0x00, 0x02, 0x02, 0x0D, 0x0D];
        assert_eq!(request_len(&two_by_quantity), wrong(Some(10)));
        // Quantities out of the spec's bounds: 0, and 124 registers (248 bytes fit no PDU).
        assert_eq!(
            request_len(&[0x10, 0x20, 0x00, 0x00, 0x00, 0x00]),
            wrong(None)
        );
        let mut many = vec![0x10, 0x00, 0x00, 0x00, 0x7C, 0xF6];
        many.resize(6 + 0xF6, 0);
        assert_eq!(request_len(&many), wrong(None));
        // Coils: nine take two bytes; 1968 is the most, 1969 one too many.
        assert_eq!(request_len(&[0x0F, 0, 0, 0, 9, 1, 0xFF]), wrong(Some(8)));
        assert_eq!(
            request_len(&[0x0F, 0, 0, 0, 9, 2, 0xFF, 0x01]),
            RequestLen::Fits
        );
        let coils = |quantity: u16, count: u8| {
            let mut pdu = vec![0x0F, 0, 0];
            pdu.extend_from_slice(&quantity.to_be_bytes());
            pdu.push(count);
            pdu.resize(6 + usize::from(count), 0xFF);
            pdu
        };
        assert_eq!(request_len(&coils(1968, 246)), RequestLen::Fits);
        assert_eq!(request_len(&coils(1969, 247)), wrong(None));
        // Read/Write Multiple Registers: its write part, 1 to 121 registers.
        let rw = [
            0x17, 0x20, 0x00, 0, 1, 0x20, 0x01, 0, 1, 4, 0x0D, 0x0D, 0xBE, 0xEF,
        ];
        assert_eq!(request_len(&rw), wrong(Some(12)));
        let rw = [0x17, 0x20, 0x00, 0, 1, 0x20, 0x01, 0, 1, 2, 0x0D, 0x0D];
        assert_eq!(request_len(&rw), RequestLen::Fits);
        // 122 registers to write: past the bounds (and past what a PDU holds).
        let mut rw_many = vec![0x17, 0, 0, 0, 1, 0, 0, 0, 0x7A, 0xF4];
        rw_many.resize(10 + 0xF4, 0);
        assert_eq!(request_len(&rw_many), wrong(None));
        // What the rules and the journal read is then the quantity every byte agrees with.
        let agreed = [0x10, 0x20, 0x01, 0x00, 0x02, 0x04, 0x0D, 0x0D, 0xBE, 0xEF];
        assert_eq!(request_len(&agreed), RequestLen::Fits);
        assert_eq!(written(&agreed).0.map(|span| span.count()), Some(2));
    }

    #[test]
    fn read_file_record_is_a_read_only_with_the_sub_requests_the_spec_gives_it() {
        // File 4, record 1, two words; file 3, record 9, two words (the spec's example).
        let spec = [
            0x14, 0x0E, 0x06, 0x00, 0x04, 0x00, 0x01, 0x00, 0x02, 0x06, 0x00, 0x03, 0x00, 0x09,
            0x00, 0x02,
        ];
        assert!(is_read_only(&spec));
        let mut other_type = spec;
        other_type[9] = 0x01;
        assert!(!is_read_only(&other_type), "a reference type other than 6");
        let mut record = spec;
        record[5] = 0x27;
        record[6] = 0x10;
        assert!(!is_read_only(&record), "record number 2710H");
        // Not whole sub-requests: room for bytes the spec does not give.
        let mut short = spec[..15].to_vec();
        short[1] = 0x0D;
        assert!(!is_read_only(&short));
        assert!(!is_read_only(&[0x14, 0x00]), "no sub-request");
    }

    #[test]
    fn return_query_data_is_a_read_only_with_one_word_of_data() {
        assert!(is_read_only(&[0x08, 0x00, 0x00, 0x12, 0xAB]));
        // Room for a whole frame after the sub-function: not for a master that may only read.
        let long = [
            0x08, 0x00, 0x00, 0x01, 0x06, 0x00, 0x05, 0x12, 0x34, 0x94, 0xBC,
        ];
        assert!(!is_read_only(&long));
        assert!(!is_read_only(&[0x08, 0x00, 0x00]));
    }
    #[test]
    fn a_request_touches_the_addresses_its_bytes_name_and_an_unknown_one_may_touch_any() {
        use DataTable::*;
        let span = |table, first, last| Span { table, first, last };
        assert_eq!(
            touches(&[0x03, 0x20, 0x00, 0x00, 0x02]),
            Touches::Spans(span(HoldingRegisters, 0x2000, 0x2001), None)
        );
        assert_eq!(
            touches(&[0x05, 0x00, 0x07, 0xFF, 0x00]),
            Touches::Spans(span(Coils, 7, 7), None)
        );
        // Past the end of the table: seen whole, not cut at 65535.
        assert_eq!(
            touches(&[0x10, 0xFF, 0xFF, 0x00, 0x02, 0x04, 0, 1, 0, 2]),
            Touches::Spans(span(HoldingRegisters, 0xFFFF, 0x10000), None)
        );
        assert_eq!(
            touches(&[0x17, 0, 0x10, 0, 2, 0x20, 0, 0, 1, 2, 0xAB, 0xCD]),
            Touches::Spans(
                span(HoldingRegisters, 0x10, 0x11),
                Some(span(HoldingRegisters, 0x2000, 0x2000))
            )
        );
        assert_eq!(touches(&[0x08, 0x00, 0x01, 0x00, 0x00]), Touches::Nothing);
        // Read Device Identification touches nothing; a CANopen General Reference may touch any.
        assert_eq!(touches(&[0x2B, 0x0E, 0x01, 0x00]), Touches::Nothing);
        assert_eq!(touches(&[0x2B, 0x0D, 0x00, 0x20, 0x00]), Touches::Unknown);
        assert_eq!(touches(&[0x41, 0x20, 0x00]), Touches::Unknown);
        assert_eq!(touches(&[0x06, 0x20]), Touches::Unknown);
        assert_eq!(touches(&[]), Touches::Unknown);
        assert_eq!(
            written(&[0x17, 0, 0x10, 0, 2, 0x20, 0, 0, 1, 2, 0xAB, 0xCD]),
            (
                Some(span(HoldingRegisters, 0x2000, 0x2000)),
                &[0xAB, 0xCD][..]
            )
        );
        assert_eq!(
            written(&[0x10, 0x00, 0x04, 0x00, 0x02, 0x04, 0x13, 0x88, 0x00, 0x32]),
            (
                Some(span(HoldingRegisters, 4, 5)),
                &[0x13, 0x88, 0x00, 0x32][..]
            )
        );
        assert_eq!(written(&[0x41, 1, 2]), (None, &[1, 2][..]));
    }
}
