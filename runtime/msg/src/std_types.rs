//! Standard ROS 2 message types, field for field as ROS 2 defines them.

use std::borrow::Cow;

use super::{message, stamped};

message! {
    /// `builtin_interfaces/Time`: seconds and nanoseconds since the epoch of the clock.
    pub struct Time = "builtin_interfaces/msg/Time" {
        pub sec: i32,
        pub nanosec: u32,
    }
}

impl Time {
    /// From nanoseconds; times before the epoch are represented with a negative `sec` and
    /// a positive `nanosec`, as ROS 2 does.
    pub fn from_ns(ns: i64) -> Self {
        let sec = ns.div_euclid(1_000_000_000);
        let nanosec = ns.rem_euclid(1_000_000_000);
        Self {
            sec: i32::try_from(sec).unwrap_or(if sec < 0 { i32::MIN } else { i32::MAX }),
            nanosec: u32::try_from(nanosec).unwrap_or(0),
        }
    }

    /// To nanoseconds.
    pub fn to_ns(&self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }
}

impl Copy for Time {}

message! {
    /// `std_msgs/Header`: stamp and coordinate frame.
    pub struct Header = "std_msgs/msg/Header" {
        pub stamp: Time,
        pub frame_id: String,
    }
}

impl Header {
    /// A header stamped at `stamp_ns` in `frame_id`.
    pub fn new(stamp_ns: i64, frame_id: &str) -> Self {
        Self {
            stamp: Time::from_ns(stamp_ns),
            frame_id: frame_id.to_owned(),
        }
    }
}

message! {
    /// `geometry_msgs/Vector3`.
    pub struct Vector3 = "geometry_msgs/msg/Vector3" {
        pub x: f64,
        pub y: f64,
        pub z: f64,
    }
}
impl Copy for Vector3 {}

message! {
    /// `geometry_msgs/Point`.
    pub struct Point = "geometry_msgs/msg/Point" {
        pub x: f64,
        pub y: f64,
        pub z: f64,
    }
}
impl Copy for Point {}

message! {
    /// `geometry_msgs/Quaternion` (x, y, z, w).
    pub struct Quaternion = "geometry_msgs/msg/Quaternion" {
        pub x: f64,
        pub y: f64,
        pub z: f64,
        pub w: f64,
    }
}
impl Copy for Quaternion {}

impl Quaternion {
    /// The identity rotation.
    pub const IDENTITY: Self = Self {
        x: 0.0,
        y: 0.0,
        z: 0.0,
        w: 1.0,
    };
}

message! {
    /// `geometry_msgs/Pose`: a rigid transform, `parent_from_child`.
    pub struct Pose = "geometry_msgs/msg/Pose" {
        pub position: Point,
        pub orientation: Quaternion,
    }
}
impl Copy for Pose {}

message! {
    /// `geometry_msgs/PoseWithCovariance`; covariance row-major over (x, y, z, rx, ry, rz).
    pub struct PoseWithCovariance = "geometry_msgs/msg/PoseWithCovariance" {
        pub pose: Pose,
        pub covariance: Covariance6,
    }
}

message! {
    /// `geometry_msgs/Twist`.
    pub struct Twist = "geometry_msgs/msg/Twist" {
        pub linear: Vector3,
        pub angular: Vector3,
    }
}

message! {
    /// `geometry_msgs/TwistWithCovariance`.
    pub struct TwistWithCovariance = "geometry_msgs/msg/TwistWithCovariance" {
        pub twist: Twist,
        pub covariance: Covariance6,
    }
}

message! {
    /// `geometry_msgs/PoseStamped`.
    pub struct PoseStamped = "geometry_msgs/msg/PoseStamped" {
        pub header: Header,
        pub pose: Pose,
    }
}

message! {
    /// `sensor_msgs/Imu`: orientation, angular velocity (rad/s), linear acceleration (m/s^2).
    pub struct Imu = "sensor_msgs/msg/Imu" {
        pub header: Header,
        pub orientation: Quaternion,
        pub orientation_covariance: [f64; 9],
        pub angular_velocity: Vector3,
        pub angular_velocity_covariance: [f64; 9],
        pub linear_acceleration: Vector3,
        pub linear_acceleration_covariance: [f64; 9],
    }
}

message! {
    /// `nav_msgs/Odometry`.
    pub struct Odometry = "nav_msgs/msg/Odometry" {
        pub header: Header,
        pub child_frame_id: String,
        pub pose: PoseWithCovariance,
        pub twist: TwistWithCovariance,
    }
}

message! {
    /// `sensor_msgs/Image`; `data` is read in place on the subscriber side.
    pub struct Image<'a> = "sensor_msgs/msg/Image" {
        pub header: Header,
        pub height: u32,
        pub width: u32,
        pub encoding: String,
        pub is_bigendian: u8,
        pub step: u32,
        pub data: Cow<'a, [u8]>,
    }
}

message! {
    /// `nav_msgs/Path`: poses in order (a trajectory as Foxglove's 3D panel draws it).
    pub struct Path = "nav_msgs/msg/Path" {
        pub header: Header,
        pub poses: Vec<PoseStamped>,
    }
}

stamped!(PoseStamped, Imu, Odometry, Image<'a>, Path);

/// A 6x6 covariance, row-major (`float64[36]` on the wire).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(transparent)]
pub struct Covariance6(#[serde(serialize_with = "serialize_array")] pub [f64; 36]);

fn serialize_array<S: serde::Serializer>(v: &[f64; 36], s: S) -> Result<S::Ok, S::Error> {
    serde::Serialize::serialize(&v[..], s)
}

impl Default for Covariance6 {
    fn default() -> Self {
        Self([0.0; 36])
    }
}

impl super::CdrEncode for Covariance6 {
    fn encode<S: super::CdrSink>(&self, sink: &mut S) {
        self.0.encode(sink);
    }
}

impl<'de> super::CdrDecode<'de> for Covariance6 {
    fn decode(r: &mut super::CdrReader<'de>) -> super::Result<Self> {
        Ok(Self(<[f64; 36]>::decode(r)?))
    }
}

impl super::RosField for Covariance6 {
    fn ros_type() -> String {
        "float64[36]".to_owned()
    }
}
