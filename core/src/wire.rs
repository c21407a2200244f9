//! Types that cross process boundaries over iceoryx2, shared by service and client so
//! they cannot drift apart. All `#[repr(C)]`, fixed layout, with explicit type names.

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

/// iceoryx2 service names of one map under a prefix.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServiceNames {
    pub frames: String,
    pub frames_event: String,
    pub snapshot: String,
    pub snapshot_event: String,
    pub control: String,
}

impl ServiceNames {
    /// `<prefix>/<map>/frames` and friends.
    pub fn new(prefix: &str, map: &str) -> Self {
        let base = format!("{prefix}/{map}");
        Self {
            frames: format!("{base}/frames"),
            frames_event: format!("{base}/frames/event"),
            snapshot: format!("{base}/snapshot"),
            snapshot_event: format!("{base}/snapshot/event"),
            control: format!("{base}/control"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_paths_and_messages_are_bounded() {
        let r = ControlRequest::with_path(ControlKind::Save, "/tmp/m.vxm").unwrap();
        assert_eq!(r.path(), Some("/tmp/m.vxm"));
        assert!(
            ControlRequest::with_path(ControlKind::Save, &"x".repeat(CONTROL_PATH_MAX + 1))
                .is_none()
        );
        let lying = ControlRequest {
            path_len: 100_000,
            ..r
        };
        assert_eq!(lying.path(), None);
        let long = "é".repeat(CONTROL_MESSAGE_MAX);
        let m = ControlResponse::new(false, &long, StatsWire::default());
        assert!(m.message().len() <= CONTROL_MESSAGE_MAX && m.message().chars().all(|c| c == 'é'));
    }

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

/// What a [`ControlRequest`] asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum ControlKind {
    Stats = 1,
    /// Save the map to `path`.
    Save = 2,
    /// Replace the map with the one in `path` (unchanged if the file is bad).
    Load = 3,
    Clear = 4,
    /// Snapshot scope: `scope_kind` 0 whole map, 1 box of half extents `scope[0..3]`
    /// around the latest sensor pose, 2 fixed box `scope[0..3]`..`scope[3..6]`.
    SetScope = 5,
}

/// Longest path a control request carries, in bytes.
pub const CONTROL_PATH_MAX: usize = 512;
/// Longest message a control response carries, in bytes.
pub const CONTROL_MESSAGE_MAX: usize = 512;

/// A control request (request-response payload).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("voxmap::ControlRequest::v1")]
#[repr(C)]
pub struct ControlRequest {
    /// A [`ControlKind`] value; anything else is answered with an error.
    pub kind: u32,
    pub scope_kind: u32,
    pub path_len: u32,
    pub reserved: u32,
    pub scope: [f64; 6],
    pub path: [u8; CONTROL_PATH_MAX],
}

impl ControlRequest {
    pub fn new(kind: ControlKind) -> Self {
        Self {
            kind: kind as u32,
            scope_kind: 0,
            path_len: 0,
            reserved: 0,
            scope: [0.0; 6],
            path: [0; CONTROL_PATH_MAX],
        }
    }

    /// With a path (UTF-8); `None` if longer than [`CONTROL_PATH_MAX`].
    pub fn with_path(kind: ControlKind, path: &str) -> Option<Self> {
        let b = path.as_bytes();
        if b.len() > CONTROL_PATH_MAX {
            return None;
        }
        let mut r = Self::new(kind);
        r.path[..b.len()].copy_from_slice(b);
        r.path_len = b.len() as u32;
        Some(r)
    }

    /// The path, if `path_len` is in range and the bytes are UTF-8.
    pub fn path(&self) -> Option<&str> {
        let n = self.path_len as usize;
        std::str::from_utf8(self.path.get(..n)?).ok()
    }
}

/// Service counters, as reported by a `Stats` request.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("voxmap::StatsWire::v2")]
#[repr(C)]
pub struct StatsWire {
    pub frames_received: u64,
    pub frames_integrated: u64,
    pub frames_dropped: u64,
    pub frames_rejected: u64,
    pub points_integrated: u64,
    pub points_skipped: u64,
    pub map_leaves: u64,
    pub map_memory_bytes: u64,
    pub snapshot_bytes: u64,
    pub snapshot_sequence: u64,
    pub integrate_ms_p50: f64,
    pub integrate_ms_p99: f64,
    pub integrate_ms_max: f64,
    pub encode_ms_last: f64,
    /// Frame send (its time stamp) to receipt by the service, microseconds, over the
    /// last 1024 frames with a time stamp.
    pub intake_us_p50: f64,
    pub intake_us_p99: f64,
}

/// A control response: `ok` 1 or 0, a message, and the current stats.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("voxmap::ControlResponse::v2")]
#[repr(C)]
pub struct ControlResponse {
    pub ok: u32,
    pub message_len: u32,
    pub stats: StatsWire,
    pub message: [u8; CONTROL_MESSAGE_MAX],
}

impl ControlResponse {
    pub fn new(ok: bool, message: &str, stats: StatsWire) -> Self {
        let mut m = [0u8; CONTROL_MESSAGE_MAX];
        // Cut on a character boundary.
        let mut n = message.len().min(CONTROL_MESSAGE_MAX);
        while !message.is_char_boundary(n) {
            n -= 1;
        }
        m[..n].copy_from_slice(&message.as_bytes()[..n]);
        Self {
            ok: ok as u32,
            message_len: n as u32,
            stats,
            message: m,
        }
    }

    pub fn message(&self) -> &str {
        let n = (self.message_len as usize).min(CONTROL_MESSAGE_MAX);
        std::str::from_utf8(&self.message[..n]).unwrap_or("<invalid utf-8>")
    }
}
