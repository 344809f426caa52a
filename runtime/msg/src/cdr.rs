//! CDR (XCDR1, little endian) encoding, the wire format of ROS 2, rmw_zenoh and MCAP `cdr`.
//!
//! A payload starts with the 4-byte encapsulation header `00 01 00 00` (CDR_LE); every
//! primitive is aligned to its own size relative to the first byte after that header.
//! Sequences are a `u32` element count followed by the elements; strings are a `u32` byte
//! count that includes the terminating NUL.
//!
//! Encoding runs in two passes: [`CdrSize`] computes the exact byte count, then a
//! [`CdrWriter`] writes every byte (padding included) into a buffer of that size — which
//! may be uninitialised shared memory loaned from the bus. Decoding borrows: arrays of
//! primitives are handed back as slices into the received buffer when alignment allows.

use std::borrow::Cow;

use super::payload::{PayloadWriter, Written};
use super::{MsgError, Result};

/// Encapsulation header for plain CDR, little endian.
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];
const HEADER_LEN: usize = CDR_LE_HEADER.len();

/// Anything that can be written field by field in CDR.
pub trait CdrSink {
    /// Current offset relative to the start of the CDR body (after the encapsulation header).
    fn position(&self) -> usize;
    /// Write `count` zero bytes of padding.
    fn pad(&mut self, count: usize);
    /// Write raw bytes.
    fn bytes(&mut self, data: &[u8]);

    /// Pad so that the next write starts at a multiple of `align`.
    fn align(&mut self, align: usize) {
        let rem = self.position() % align;
        if rem != 0 {
            self.pad(align - rem);
        }
    }
}

/// A sink that only counts: the first pass of an encode.
#[derive(Debug, Default)]
pub struct CdrSize {
    len: usize,
}

impl CdrSize {
    /// Total payload size including the encapsulation header.
    pub fn total_len(&self) -> usize {
        self.len + HEADER_LEN
    }
}

impl CdrSink for CdrSize {
    fn position(&self) -> usize {
        self.len
    }
    fn pad(&mut self, count: usize) {
        self.len += count;
    }
    fn bytes(&mut self, data: &[u8]) {
        self.len += data.len();
    }
}

/// Writes CDR into a buffer of exactly the size [`CdrSize`] computed. The buffer may be
/// uninitialised: every byte, padding included, is written exactly once, and
/// [`finish`](Self::finish) hands back the buffer's [`Written`] token.
#[derive(Debug)]
pub struct CdrWriter<'a> {
    out: PayloadWriter<'a>,
    /// Bytes the encoder produced, header included (past the buffer's end on a size mismatch).
    pos: usize,
}

impl<'a> CdrWriter<'a> {
    /// Starts a payload in `out` and writes the encapsulation header.
    ///
    /// # Errors
    /// [`MsgError::BufferSize`] when the buffer cannot even hold the header.
    pub fn new(mut out: PayloadWriter<'a>) -> Result<Self> {
        out.put(&CDR_LE_HEADER)?;
        Ok(Self { out, pos: HEADER_LEN })
    }

    /// Bytes written so far, header included.
    pub fn written(&self) -> usize {
        self.pos
    }

    /// Checks that the whole buffer was written.
    ///
    /// # Errors
    /// [`MsgError::BufferSize`] when the encoder wrote fewer or more bytes than the buffer
    /// holds.
    pub fn finish(self) -> Result<Written> {
        if self.pos != self.out.len() {
            return Err(MsgError::BufferSize {
                expected: self.out.len(),
                actual: self.pos,
            });
        }
        self.out.finish()
    }
}

impl CdrSink for CdrWriter<'_> {
    fn position(&self) -> usize {
        self.pos - HEADER_LEN
    }
    fn pad(&mut self, count: usize) {
        // The size pass guarantees the room; a mismatch is caught by `finish`.
        let _fits = self.out.zeros(count.min(self.out.remaining()));
        self.pos += count;
    }
    fn bytes(&mut self, data: &[u8]) {
        let n = data.len().min(self.out.remaining());
        let _fits = self.out.put(&data[..n]);
        self.pos += data.len();
    }
}

/// Reads a CDR payload, borrowing from the buffer.
#[derive(Debug, Clone)]
pub struct CdrReader<'de> {
    body: &'de [u8],
    pos: usize,
    /// Dotted path of the field being read, for error messages.
    field: &'static str,
}

impl<'de> CdrReader<'de> {
    /// Checks the encapsulation header and positions the reader on the first field.
    ///
    /// # Errors
    /// [`MsgError::Encapsulation`] for anything but plain little-endian CDR.
    pub fn new(payload: &'de [u8]) -> Result<Self> {
        match payload.get(..HEADER_LEN) {
            Some(h) if h[..2] == CDR_LE_HEADER[..2] => Ok(Self {
                body: &payload[HEADER_LEN..],
                pos: 0,
                field: "",
            }),
            Some(h) => Err(MsgError::Encapsulation([h[0], h[1]])),
            None => Err(MsgError::Truncated {
                field: "encapsulation header",
                offset: 0,
            }),
        }
    }

    /// Names the field being decoded (used in errors).
    pub fn field(&mut self, name: &'static str) {
        self.field = name;
    }

    /// Bytes left unread.
    pub fn remaining(&self) -> usize {
        self.body.len().saturating_sub(self.pos)
    }

    fn align(&mut self, align: usize) -> Result<()> {
        let rem = self.pos % align;
        if rem != 0 {
            let skip = align - rem;
            if self.remaining() < skip {
                return Err(self.truncated());
            }
            self.pos += skip;
        }
        Ok(())
    }

    fn truncated(&self) -> MsgError {
        MsgError::Truncated {
            field: self.field,
            offset: self.pos + HEADER_LEN,
        }
    }

    fn take(&mut self, n: usize) -> Result<&'de [u8]> {
        if self.remaining() < n {
            return Err(self.truncated());
        }
        let s = &self.body[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn take_array<const N: usize>(&mut self) -> Result<[u8; N]> {
        let s = self.take(N)?;
        let mut out = [0u8; N];
        out.copy_from_slice(s);
        Ok(out)
    }

    /// Reads a sequence length and checks that `len * elem_size` bytes remain, so a corrupt
    /// length cannot make the decoder allocate without bound.
    fn seq_len(&mut self, elem_size: usize) -> Result<usize> {
        let len = u32::decode(self)? as usize;
        if elem_size > 0 && len.checked_mul(elem_size).is_none_or(|b| b > self.remaining()) {
            return Err(MsgError::Length {
                field: self.field,
                len,
                remaining: self.remaining(),
            });
        }
        Ok(len)
    }
}

/// A value that knows its CDR encoding and ROS 2 type name.
pub trait CdrEncode {
    /// Writes the value at the sink's position.
    fn encode<S: CdrSink>(&self, sink: &mut S);
}

/// A value that decodes from CDR, possibly borrowing from the buffer.
pub trait CdrDecode<'de>: Sized {
    /// Reads the value at the reader's position.
    ///
    /// # Errors
    /// Truncation, bad lengths, invalid UTF-8 or values out of range, naming the field.
    fn decode(reader: &mut CdrReader<'de>) -> Result<Self>;
}

/// A ROS 2 field type: how it is named in a `.msg` definition.
pub trait RosField {
    /// The type as written in a `.msg` file (`float64`, `geometry_msgs/Pose`, `int16[]`).
    fn ros_type() -> String;
    /// Adds the full names of nested message types this field depends on.
    fn dependencies(_out: &mut Vec<super::MessageDef>) {}
}

macro_rules! primitive {
    ($($t:ty => $ros:literal),* $(,)?) => {$(
        impl CdrEncode for $t {
            fn encode<S: CdrSink>(&self, sink: &mut S) {
                sink.align(std::mem::size_of::<$t>());
                sink.bytes(&self.to_le_bytes());
            }
        }
        impl<'de> CdrDecode<'de> for $t {
            fn decode(r: &mut CdrReader<'de>) -> Result<Self> {
                r.align(std::mem::size_of::<$t>())?;
                Ok(<$t>::from_le_bytes(r.take_array()?))
            }
        }
        impl RosField for $t {
            fn ros_type() -> String { $ros.to_owned() }
        }
    )*};
}

primitive!(
    u8 => "uint8", i8 => "int8", u16 => "uint16", i16 => "int16",
    u32 => "uint32", i32 => "int32", u64 => "uint64", i64 => "int64",
    f32 => "float32", f64 => "float64",
);

impl CdrEncode for bool {
    fn encode<S: CdrSink>(&self, sink: &mut S) {
        sink.bytes(&[u8::from(*self)]);
    }
}
impl<'de> CdrDecode<'de> for bool {
    fn decode(r: &mut CdrReader<'de>) -> Result<Self> {
        match r.take(1)?[0] {
            0 => Ok(false),
            1 => Ok(true),
            v => Err(MsgError::Invalid {
                field: r.field,
                reason: format!("bool byte {v}"),
            }),
        }
    }
}
impl RosField for bool {
    fn ros_type() -> String {
        "bool".to_owned()
    }
}

impl CdrEncode for String {
    fn encode<S: CdrSink>(&self, sink: &mut S) {
        self.as_str().encode(sink);
    }
}
impl CdrEncode for str {
    fn encode<S: CdrSink>(&self, sink: &mut S) {
        // Lengths beyond u32 cannot be represented in CDR; messages never carry such strings.
        let len = u32::try_from(self.len() + 1).unwrap_or(u32::MAX);
        len.encode(sink);
        sink.bytes(self.as_bytes());
        sink.bytes(&[0]);
    }
}
impl<'de> CdrDecode<'de> for String {
    fn decode(r: &mut CdrReader<'de>) -> Result<Self> {
        let len = r.seq_len(1)?;
        let raw = r.take(len)?;
        let text = match raw.split_last() {
            Some((0, text)) => text,
            Some(_) => raw, // tolerate a missing NUL, as other readers do
            None => raw,
        };
        String::from_utf8(text.to_vec()).map_err(|e| MsgError::Invalid {
            field: r.field,
            reason: format!("string is not UTF-8: {e}"),
        })
    }
}
impl RosField for String {
    fn ros_type() -> String {
        "string".to_owned()
    }
}

/// Primitive element types that can be viewed in place inside a received buffer.
pub trait Pod: bytemuck::Pod + CdrEncode + RosField {}
impl Pod for u8 {}
impl Pod for i16 {}
impl Pod for i32 {}
impl Pod for u32 {}
impl Pod for i64 {}
impl Pod for u64 {}
impl Pod for f32 {}
impl Pod for f64 {}

/// An unbounded sequence of primitives (`float32[]`). Decoding borrows the elements in
/// place when the buffer is suitably aligned (zero copy) and copies otherwise.
impl<T: Pod> CdrEncode for Cow<'_, [T]> {
    fn encode<S: CdrSink>(&self, sink: &mut S) {
        encode_pod_seq(self, sink);
    }
}

fn encode_pod_seq<T: Pod, S: CdrSink>(items: &[T], sink: &mut S) {
    let len = u32::try_from(items.len()).unwrap_or(u32::MAX);
    len.encode(sink);
    if !items.is_empty() {
        sink.align(std::mem::size_of::<T>());
        // Little-endian host: the in-memory bytes are the CDR bytes.
        sink.bytes(bytemuck::cast_slice(items));
    }
}

impl<'de, T: Pod> CdrDecode<'de> for Cow<'de, [T]> {
    fn decode(r: &mut CdrReader<'de>) -> Result<Self> {
        let size = std::mem::size_of::<T>();
        let len = r.seq_len(size)?;
        if len == 0 {
            return Ok(Cow::Borrowed(&[]));
        }
        r.align(size)?;
        let raw = r.take(len * size)?;
        Ok(match bytemuck::try_cast_slice(raw) {
            Ok(view) => Cow::Borrowed(view),
            Err(_) => Cow::Owned(bytemuck::pod_collect_to_vec(raw)),
        })
    }
}

impl<T: Pod> RosField for Cow<'_, [T]> {
    fn ros_type() -> String {
        format!("{}[]", T::ros_type())
    }
}

/// Fixed-size arrays (`float64[36]`): no length prefix.
impl<T: CdrEncode, const N: usize> CdrEncode for [T; N] {
    fn encode<S: CdrSink>(&self, sink: &mut S) {
        for item in self {
            item.encode(sink);
        }
    }
}
impl<'de, T: CdrDecode<'de> + Copy + Default, const N: usize> CdrDecode<'de> for [T; N] {
    fn decode(r: &mut CdrReader<'de>) -> Result<Self> {
        let mut out = [T::default(); N];
        for slot in &mut out {
            *slot = T::decode(r)?;
        }
        Ok(out)
    }
}
impl<T: RosField, const N: usize> RosField for [T; N] {
    fn ros_type() -> String {
        format!("{}[{N}]", T::ros_type())
    }
    fn dependencies(out: &mut Vec<super::MessageDef>) {
        T::dependencies(out);
    }
}

/// Unbounded sequences of nested messages (`geometry_msgs/PoseStamped[]`).
impl<T: CdrEncode> CdrEncode for Vec<T> {
    fn encode<S: CdrSink>(&self, sink: &mut S) {
        let len = u32::try_from(self.len()).unwrap_or(u32::MAX);
        len.encode(sink);
        for item in self {
            item.encode(sink);
        }
    }
}
impl<'de, T: CdrDecode<'de>> CdrDecode<'de> for Vec<T> {
    fn decode(r: &mut CdrReader<'de>) -> Result<Self> {
        // Every element takes at least one byte, which bounds the allocation.
        let len = r.seq_len(1)?;
        let mut out = Vec::with_capacity(len);
        for _ in 0..len {
            out.push(T::decode(r)?);
        }
        Ok(out)
    }
}
impl<T: RosField> RosField for Vec<T> {
    fn ros_type() -> String {
        format!("{}[]", T::ros_type())
    }
    fn dependencies(out: &mut Vec<super::MessageDef>) {
        T::dependencies(out);
    }
}
