//! The ROS 2 messages voxmap reads, as serde structs in their CDR field order, and
//! [`decode`]: a serialized message (the 4-byte encapsulation header, then CDR) to one.
//!
//! Strings are owned (the CDR reader hands them over as owned); `data` is borrowed.
//! Field order and types follow the `.msg` definitions of `sensor_msgs`, `std_msgs`,
//! `geometry_msgs`, `nav_msgs` and `tf2_msgs` (unchanged from Humble to Kilted).

use serde::{Deserialize, Serialize};

/// ROS 2 type names of the messages below, as bags and DDS discovery spell them.
pub mod types {
    pub const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
    pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";
    pub const ODOMETRY: &str = "nav_msgs/msg/Odometry";
    pub const POSE_STAMPED: &str = "geometry_msgs/msg/PoseStamped";
}

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// Nanoseconds since the epoch of the stamp's clock.
    pub fn ns(self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/msg/PointField`.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct PointField {
    pub name: String,
    pub offset: u32,
    pub datatype: u8,
    pub count: u32,
}

/// `sensor_msgs/msg/PointCloud2` with its `data` as `D`: borrowed from the serialized
/// message (`&[u8]`, as bags decode it), received whole ([`serde_bytes::ByteBuf`], one
/// copy, as DDS hands it over) or kept (`Vec<u8>`, a cloud waiting for its transform).
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct PointCloud2<D> {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    pub data: D,
    pub is_dense: bool,
}

impl<D> PointCloud2<D> {
    /// The same cloud with its data in another container.
    pub fn map_data<E>(self, f: impl FnOnce(D) -> E) -> PointCloud2<E> {
        PointCloud2 {
            header: self.header,
            height: self.height,
            width: self.width,
            fields: self.fields,
            is_bigendian: self.is_bigendian,
            point_step: self.point_step,
            row_step: self.row_step,
            data: f(self.data),
            is_dense: self.is_dense,
        }
    }
}

/// `geometry_msgs/msg/Vector3` and `Point` (same layout).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

/// `geometry_msgs/msg/Transform`, and `Pose` (a `Point` and a `Quaternion`: same layout).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`: the pose of `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Debug, Clone, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Transform,
}

/// `geometry_msgs/msg/PoseWithCovariance` (the 6x6 covariance row by row: CDR writes a
/// fixed array without a length, so nested arrays read the same bytes as `double[36]`).
#[derive(Debug, Clone, Copy, Deserialize)]
pub struct PoseWithCovariance {
    pub pose: Transform,
    pub covariance: [[f64; 6]; 6],
}

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Debug, Clone, Copy, Deserialize)]
pub struct TwistWithCovariance {
    pub linear: Vector3,
    pub angular: Vector3,
    pub covariance: [[f64; 6]; 6],
}

/// `nav_msgs/msg/Odometry`: the pose of `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, Deserialize)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    pub pose: PoseWithCovariance,
    pub twist: TwistWithCovariance,
}

/// `octomap_msgs/msg/Octomap`: `data` is what OctoMap's `writeBinaryData` (binary maps)
/// writes, as `octomap_msgs::binaryMapToMsg` fills it.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct Octomap {
    pub header: Header,
    pub binary: bool,
    pub id: String,
    pub resolution: f64,
    pub data: serde_bytes::ByteBuf,
}

/// `geometry_msgs/msg/Pose` (same layout as [`Transform`]).
pub type Pose = Transform;

/// `nav_msgs/msg/MapMetaData`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
pub struct MapMetaData {
    pub map_load_time: Time,
    /// Metres per cell (float32 in the message).
    pub resolution: f32,
    pub width: u32,
    pub height: u32,
    /// The pose of cell (0, 0)'s corner in the header's frame.
    pub origin: Pose,
}

/// `nav_msgs/msg/OccupancyGrid`: row-major from the origin, x fastest; 0 free, 100
/// occupied, -1 unknown.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct OccupancyGrid {
    pub header: Header,
    pub info: MapMetaData,
    /// int8 cells; written as bytes (`-1` is `0xff`).
    pub data: serde_bytes::ByteBuf,
}

/// A serialized message that is not a valid message of its type.
#[derive(Debug, Clone, PartialEq)]
pub enum DecodeError {
    /// Fewer than the 4 bytes of the encapsulation header.
    NoHeader(usize),
    /// An encapsulation other than plain CDR (`00 00` big endian, `00 01` little endian),
    /// for example XCDR2 or a parameter list.
    Encapsulation([u8; 2]),
    /// The CDR body does not hold the type (too short, a bad bool or string, ...).
    Cdr(String),
}

impl std::fmt::Display for DecodeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::NoHeader(n) => write!(f, "{n} bytes: shorter than the CDR encapsulation header"),
            Self::Encapsulation(e) => write!(
                f,
                "encapsulation {:02x} {:02x} is not plain CDR (00 00 or 00 01)",
                e[0], e[1]
            ),
            Self::Cdr(why) => write!(f, "bad CDR: {why}"),
        }
    }
}

impl std::error::Error for DecodeError {}

/// Decode one serialized message: the encapsulation header picks the byte order.
pub fn decode<'a, T: Deserialize<'a>>(bytes: &'a [u8]) -> Result<T, DecodeError> {
    let (head, body) = bytes
        .split_first_chunk::<4>()
        .ok_or(DecodeError::NoHeader(bytes.len()))?;
    let r = match [head[0], head[1]] {
        [0, 0] => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body),
        [0, 1] => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body),
        e => return Err(DecodeError::Encapsulation(e)),
    };
    r.map(|(t, _)| t)
        .map_err(|e| DecodeError::Cdr(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_and_foreign_encapsulations_are_errors() {
        assert_eq!(
            decode::<Time>(&[0, 1]).unwrap_err(),
            DecodeError::NoHeader(2)
        );
        assert_eq!(
            decode::<Time>(&[0, 7, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0]).unwrap_err(),
            DecodeError::Encapsulation([0, 7])
        );
        let t: Time = decode(&[0, 1, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0]).unwrap();
        assert_eq!(t.ns(), 1_000_000_002);
        let t: Time = decode(&[0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 2]).unwrap();
        assert_eq!(t.ns(), 1_000_000_002);
        assert!(matches!(
            decode::<Time>(&[0, 1, 0, 0, 1, 0]),
            Err(DecodeError::Cdr(_))
        ));
    }
}
