//! The frame and snapshot samples' headers: `#[repr(C)]`, fixed layout, with explicit
//! iceoryx2 type names (the default name holds the module path), versioned.

use iceoryx2::prelude::ZeroCopySend;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

/// Wire format version of [`FrameHeader`].
pub const FRAME_VERSION: u32 = 1;
/// Wire format version of [`SnapshotHeader`].
pub const SNAPSHOT_WIRE_VERSION: u32 = 1;
/// Most points one frame may carry.
pub const MAX_FRAME_POINTS: u64 = 1 << 24;

/// User header of a frame sample; the payload is `[[f32; 3]]`, points in the sensor frame.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("voxmap::FrameHeader::v1")]
#[repr(C)]
pub struct FrameHeader {
    pub version: u32,
    pub flags: u32,
    pub sequence: u64,
    pub timestamp_ns: u64,
    /// Sensor pose in the map frame: translation (m) and unit quaternion (x, y, z, w).
    pub translation: [f64; 3],
    pub rotation_xyzw: [f64; 4],
    /// Points in the payload.
    pub point_count: u64,
}

impl Default for FrameHeader {
    fn default() -> Self {
        Self {
            version: FRAME_VERSION,
            flags: 0,
            sequence: 0,
            timestamp_ns: 0,
            translation: [0.0; 3],
            rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
            point_count: 0,
        }
    }
}

/// Why a frame was rejected whole.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum FrameRejected {
    UnsupportedVersion(u32),
    /// The header's point count disagrees with the payload.
    CountMismatch {
        header: u64,
        payload: u64,
    },
    TooManyPoints(u64),
    NonFinitePose,
    /// The rotation quaternion's norm is not 1 (within 1e-3).
    NonUnitQuaternion(f64),
}

impl std::fmt::Display for FrameRejected {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::UnsupportedVersion(v) => write!(
                f,
                "unsupported frame version {v} (expected {FRAME_VERSION})"
            ),
            Self::CountMismatch { header, payload } => {
                write!(f, "header says {header} points, payload holds {payload}")
            }
            Self::TooManyPoints(n) => {
                write!(f, "{n} points exceed the limit of {MAX_FRAME_POINTS}")
            }
            Self::NonFinitePose => write!(f, "sensor pose is not finite"),
            Self::NonUnitQuaternion(n) => write!(f, "rotation quaternion has norm {n}, not 1"),
        }
    }
}

impl std::error::Error for FrameRejected {}

impl FrameRejected {
    /// A short name of the reason, for counting.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::UnsupportedVersion(_) => "unsupported version",
            Self::CountMismatch { .. } => "point count mismatch",
            Self::TooManyPoints(_) => "too many points",
            Self::NonFinitePose => "pose not finite",
            Self::NonUnitQuaternion(_) => "quaternion not unit",
        }
    }
}

impl FrameHeader {
    pub fn with_pose(pose: &Isometry3<f64>) -> Self {
        let q = pose.rotation.quaternion();
        Self {
            translation: pose.translation.vector.into(),
            rotation_xyzw: [q.i, q.j, q.k, q.w],
            ..Default::default()
        }
    }

    /// Check the header against a payload of `payload_points` points; the pose on success.
    pub fn validate(&self, payload_points: usize) -> Result<Isometry3<f64>, FrameRejected> {
        if self.version != FRAME_VERSION {
            return Err(FrameRejected::UnsupportedVersion(self.version));
        }
        if self.point_count > MAX_FRAME_POINTS {
            return Err(FrameRejected::TooManyPoints(self.point_count));
        }
        if self.point_count != payload_points as u64 {
            return Err(FrameRejected::CountMismatch {
                header: self.point_count,
                payload: payload_points as u64,
            });
        }
        if !self
            .translation
            .iter()
            .chain(&self.rotation_xyzw)
            .all(|c| c.is_finite())
        {
            return Err(FrameRejected::NonFinitePose);
        }
        let [x, y, z, w] = self.rotation_xyzw;
        let q = Quaternion::new(w, x, y, z);
        let n = q.norm();
        if (n - 1.0).abs() > 1e-3 {
            return Err(FrameRejected::NonUnitQuaternion(n));
        }
        let [tx, ty, tz] = self.translation;
        Ok(Isometry3::from_parts(
            Translation3::new(tx, ty, tz),
            UnitQuaternion::from_quaternion(q),
        ))
    }
}

/// User header of a snapshot sample; the payload is the snapshot bytes (`[u8]`), of which
/// the first `len` are the snapshot (the sample may be larger).
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("voxmap::SnapshotHeader::v2")]
#[repr(C)]
pub struct SnapshotHeader {
    pub version: u32,
    pub reserved: u32,
    pub sequence: u64,
    pub len: u64,
    /// When the service sent the sample (ns since the Unix epoch): with the planner's
    /// receive time, the hand-over latency.
    pub published_ns: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_rejects_lying_headers() {
        let pose = Isometry3::translation(1.0, 2.0, 3.0);
        let mut h = FrameHeader::with_pose(&pose);
        h.point_count = 10;
        assert_eq!(h.validate(10).unwrap(), pose);
        assert_eq!(
            h.validate(9),
            Err(FrameRejected::CountMismatch {
                header: 10,
                payload: 9
            })
        );
        let bad = [
            FrameHeader { version: 2, ..h },
            FrameHeader {
                point_count: u64::MAX,
                ..h
            },
            FrameHeader {
                translation: [f64::NAN, 0.0, 0.0],
                ..h
            },
            FrameHeader {
                rotation_xyzw: [0.0, 0.0, 0.0, 2.0],
                ..h
            },
            FrameHeader {
                rotation_xyzw: [0.0; 4],
                ..h
            },
        ];
        for b in bad {
            assert!(b.validate(10).is_err(), "{b:?}");
        }
    }
}
