//! Messages: defined once, CDR-encoded (XCDR1 little endian), each with its ROS 2 `.msg`
//! schema text.
//!
//! Standard ROS 2 types are reproduced field for field (`std_msgs/Header`,
//! `sensor_msgs/Imu`, `nav_msgs/Odometry`, `geometry_msgs/PoseStamped`, `sensor_msgs/Image`)
//! so that a recording opens in Foxglove or any ROS 2 reader. GPR-specific types live in
//! the `gprflow_msgs` package. The same bytes travel in shared memory, in zenoh payloads and
//! in MCAP. The per-topic sequence number travels beside the payload (the bus frame header
//! and the MCAP message header), because ROS 2 headers have no `seq`.

mod cdr;
mod gpr;
mod payload;
mod registry;
mod std_types;

pub use cdr::{CDR_LE_HEADER, CdrDecode, CdrEncode, CdrReader, CdrSink, CdrSize, CdrWriter, Pod, RosField};
pub use gpr::*;
pub use payload::{PayloadWriter, Written, fill_payload};
pub use registry::{MessageType, decode_to_json, message_type, message_types};
pub use std_types::*;

/// Errors of encoding and decoding.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum MsgError {
    /// The payload ended inside a field.
    #[error("truncated payload: field `{field}` at byte {offset}")]
    Truncated {
        /// Field being read.
        field: &'static str,
        /// Byte offset in the payload.
        offset: usize,
    },
    /// A sequence length larger than the bytes left.
    #[error("field `{field}`: sequence length {len} exceeds the {remaining} bytes left")]
    Length {
        /// Field being read.
        field: &'static str,
        /// Length found.
        len: usize,
        /// Bytes left in the payload.
        remaining: usize,
    },
    /// A field value that the type does not allow.
    #[error("field `{field}`: {reason}")]
    Invalid {
        /// Field being read.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// Not plain little-endian CDR.
    #[error("unsupported CDR encapsulation {0:02x?} (only CDR_LE 00 01 is supported)")]
    Encapsulation([u8; 2]),
    /// Bytes left over after the last field.
    #[error("{0} bytes left after the last field (wrong message type?)")]
    Trailing(usize),
    /// The output buffer does not have the size the encoder needs.
    #[error("buffer holds {actual} bytes, the message needs {expected}")]
    BufferSize {
        /// Bytes needed.
        expected: usize,
        /// Bytes available.
        actual: usize,
    },
    /// A payload fill step returned the [`Written`] token of another buffer than its own.
    #[error("the fill step returned the token of another buffer")]
    ForeignToken,
}

/// Result of message encoding and decoding.
pub type Result<T, E = MsgError> = std::result::Result<T, E>;

/// One message definition in a schema text: full name and field lines.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MessageDef {
    /// `pkg/Type` as it appears after `MSG:`.
    pub name: String,
    /// The `.msg` field lines.
    pub text: String,
}

/// A message type that can travel on the bus and be recorded.
pub trait Message: CdrEncode + RosField + std::fmt::Debug {
    /// Full ROS 2 name, `pkg/msg/Type`, as used for MCAP schemas.
    const TYPE_NAME: &'static str;
    /// Sensor time of the message, nanoseconds.
    fn stamp_ns(&self) -> i64;
    /// The concatenated ros2msg schema text: own fields, then each dependency after a
    /// `MSG:` separator line.
    fn schema_text() -> String {
        let mut deps = Vec::new();
        Self::dependencies(&mut deps);
        // the first entry is the type itself
        let mut out = String::new();
        for (i, def) in deps.iter().enumerate() {
            if i > 0 {
                out.push_str(&"=".repeat(80));
                out.push_str("\nMSG: ");
                out.push_str(&def.name);
                out.push('\n');
            }
            out.push_str(&def.text);
        }
        out
    }
}

/// Number of bytes [`encode_into`] will write for `msg`.
pub fn encoded_len<M: CdrEncode + ?Sized>(msg: &M) -> usize {
    let mut size = CdrSize::default();
    msg.encode(&mut size);
    size.total_len()
}

/// Encodes `msg` into `out`, whose buffer must be exactly [`encoded_len`] bytes long.
///
/// # Errors
/// [`MsgError::BufferSize`] when the buffer has the wrong size.
pub fn encode_into<M: CdrEncode + ?Sized>(msg: &M, out: PayloadWriter<'_>) -> Result<Written> {
    let mut w = CdrWriter::new(out)?;
    msg.encode(&mut w);
    w.finish()
}

/// Encodes `msg` into a new vector.
pub fn encode<M: CdrEncode + ?Sized>(msg: &M) -> Vec<u8> {
    let len = encoded_len(msg);
    let mut buf = Vec::with_capacity(len);
    let filled = fill_payload(&mut buf.spare_capacity_mut()[..len], |out| encode_into(msg, out));
    debug_assert_eq!(filled, Ok(()));
    if filled.is_ok() {
        // SAFETY: `fill_payload` returned Ok, so all `len` bytes were written.
        unsafe { buf.set_len(len) };
    }
    buf
}

/// Decodes a whole payload. Up to 3 trailing bytes (final alignment padding some writers
/// add) are accepted; more means the payload is not of this type.
///
/// # Errors
/// Any [`MsgError`]; never panics on arbitrary bytes.
pub fn decode<'de, M: CdrDecode<'de>>(payload: &'de [u8]) -> Result<M> {
    let mut r = CdrReader::new(payload)?;
    let msg = M::decode(&mut r)?;
    match r.remaining() {
        0..=3 => Ok(msg),
        n => Err(MsgError::Trailing(n)),
    }
}

/// Declares a message struct and derives its CDR encoding and `.msg` definition from the
/// field list, so that the two can never disagree.
macro_rules! message {
    (
        $(#[$meta:meta])*
        pub struct $name:ident $(<$lt:lifetime>)? = $ros:literal {
            $( $(#[$fmeta:meta])* pub $field:ident : $fty:ty ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, PartialEq, Default, serde::Serialize)]
        pub struct $name $(<$lt>)? {
            $( $(#[$fmeta])* pub $field: $fty ),*
        }

        impl $(<$lt>)? $name $(<$lt>)? {
            /// Full ROS 2 type name, `pkg/msg/Type`.
            pub const ROS_NAME: &'static str = $ros;
        }

        impl $(<$lt>)? $crate::CdrEncode for $name $(<$lt>)? {
            fn encode<S: $crate::CdrSink>(&self, sink: &mut S) {
                $( $crate::CdrEncode::encode(&self.$field, sink); )*
            }
        }

        impl<'de $(, $lt)?> $crate::CdrDecode<'de> for $name $(<$lt>)?
        where $($lt: 'de, 'de: $lt)?
        {
            fn decode(r: &mut $crate::CdrReader<'de>) -> $crate::Result<Self> {
                Ok(Self {
                    $( $field: {
                        r.field(concat!($ros, ".", stringify!($field)));
                        <$fty as $crate::CdrDecode<'de>>::decode(r)?
                    }, )*
                })
            }
        }

        impl $(<$lt>)? $crate::RosField for $name $(<$lt>)? {
            fn ros_type() -> String {
                $ros.replace("/msg/", "/")
            }
            fn dependencies(out: &mut Vec<$crate::MessageDef>) {
                let name = Self::ros_type();
                if out.iter().any(|d| d.name == name) {
                    return;
                }
                let mut text = String::new();
                $(
                    text.push_str(&<$fty as $crate::RosField>::ros_type());
                    text.push(' ');
                    text.push_str(stringify!($field));
                    text.push('\n');
                )*
                out.push($crate::MessageDef { name, text });
                $( <$fty as $crate::RosField>::dependencies(out); )*
            }
        }
    };
}
pub(crate) use message;

/// Implements [`Message`] for top-level types whose first field is a `std_msgs/Header`.
macro_rules! stamped {
    ($($name:ident $(<$lt:lifetime>)?),* $(,)?) => {$(
        impl $(<$lt>)? $crate::Message for $name $(<$lt>)? {
            const TYPE_NAME: &'static str = <$name $(<$lt>)?>::ROS_NAME;
            fn stamp_ns(&self) -> i64 {
                self.header.stamp.to_ns()
            }
        }
    )*};
}
pub(crate) use stamped;

#[cfg(test)]
mod tests;
