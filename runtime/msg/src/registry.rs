//! Every message type by name: schema text and a generic decoder to JSON, for tools that
//! handle topics whose type is known only at run time (inspect, diff, the recorder).

use super::{
    CdrDecode, Image, Imu, LineMap, LineObservation, MapFix, Message, MsgError, Odometry, Path, PoseStamped,
    Registration, RegistrationAttempt, RegistrationCheck, StateEstimate, Submap, Sweep, Trace, Trajectory,
    WheelOdometry, decode,
};

/// A message type known to gprflow.
#[derive(Debug, Clone, Copy)]
pub struct MessageType {
    /// Full ROS 2 name, `pkg/msg/Type`.
    pub name: &'static str,
    schema: fn() -> String,
    to_json: fn(&[u8]) -> Result<serde_json::Value, MsgError>,
}

impl MessageType {
    /// The ros2msg schema text.
    pub fn schema_text(&self) -> String {
        (self.schema)()
    }

    /// Decodes a payload of this type into JSON (field names as in the schema).
    ///
    /// # Errors
    /// The decoding error.
    pub fn decode_to_json(&self, payload: &[u8]) -> Result<serde_json::Value, MsgError> {
        (self.to_json)(payload)
    }
}

fn to_json<'de, M: CdrDecode<'de> + serde::Serialize>(payload: &'de [u8]) -> Result<serde_json::Value, MsgError> {
    let msg: M = decode(payload)?;
    serde_json::to_value(&msg).map_err(|e| MsgError::Invalid {
        field: "",
        reason: e.to_string(),
    })
}

macro_rules! registry {
    ($($t:ty),* $(,)?) => {
        &[$(MessageType {
            name: <$t as Message>::TYPE_NAME,
            schema: <$t as Message>::schema_text,
            to_json: |p| to_json::<$t>(p),
        }),*]
    };
}

static TYPES: &[MessageType] = registry!(
    Trace<'_>,
    Sweep<'_>,
    WheelOdometry,
    Submap<'_>,
    Registration,
    RegistrationAttempt,
    RegistrationCheck,
    LineObservation,
    LineMap,
    StateEstimate,
    Trajectory,
    MapFix,
    Imu,
    PoseStamped,
    Odometry,
    Image<'_>,
    Path,
);

/// All message types.
pub fn message_types() -> &'static [MessageType] {
    TYPES
}

/// Looks a type up by its full name (`gprflow_msgs/msg/Trace`).
pub fn message_type(name: &str) -> Option<&'static MessageType> {
    TYPES.iter().find(|t| t.name == name)
}

/// Decodes a payload of the named type into JSON.
///
/// # Errors
/// Unknown type or the decoding error.
pub fn decode_to_json(type_name: &str, payload: &[u8]) -> Result<serde_json::Value, MsgError> {
    let t = message_type(type_name).ok_or_else(|| MsgError::Invalid {
        field: "",
        reason: format!("unknown message type `{type_name}`"),
    })?;
    t.decode_to_json(payload)
}
