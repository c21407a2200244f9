//! The control protocol (request-response on `<prefix>/<map>/control`): what a request
//! asks for ([`ControlKind`], [`MapScope`]), its fixed-size wire form
//! ([`ControlRequest`]), and the answer ([`ControlResponse`] with [`StatsWire`]).

use iceoryx2::prelude::ZeroCopySend;

/// What a [`ControlRequest`] asks for; on the wire its `u32` value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum ControlKind {
    Stats = 1,
    /// Save the map to `path`.
    Save = 2,
    /// Replace the map with the one in `path` (unchanged if the file is bad).
    Load = 3,
    Clear = 4,
    /// Set where snapshots cover the map ([`MapScope`]).
    SetScope = 5,
}

impl TryFrom<u32> for ControlKind {
    type Error = ControlError;

    fn try_from(v: u32) -> Result<Self, ControlError> {
        Ok(match v {
            1 => Self::Stats,
            2 => Self::Save,
            3 => Self::Load,
            4 => Self::Clear,
            5 => Self::SetScope,
            k => return Err(ControlError::UnknownKind(k)),
        })
    }
}

/// Where snapshots cover the map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MapScope {
    /// The whole map.
    Whole,
    /// A box of these half extents (metres, each > 0) around the latest sensor pose.
    AroundSensor { half_extents: [f64; 3] },
    /// A fixed box in the map frame, `min <= max` on every axis.
    Fixed { min: [f64; 3], max: [f64; 3] },
}

impl MapScope {
    /// Wire codes of `ControlRequest::scope_kind`.
    const WHOLE: u32 = 0;
    const AROUND_SENSOR: u32 = 1;
    const FIXED: u32 = 2;

    /// The box this scope covers with the sensor at `sensor`, or `None` for the whole map.
    pub fn bounds(&self, sensor: [f64; 3]) -> Option<([f64; 3], [f64; 3])> {
        match *self {
            Self::Whole => None,
            Self::AroundSensor { half_extents: h } => Some((
                [0, 1, 2].map(|k| sensor[k] - h[k]),
                [0, 1, 2].map(|k| sensor[k] + h[k]),
            )),
            Self::Fixed { min, max } => Some((min, max)),
        }
    }
}

/// Why a control request could not be decoded or built.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum ControlError {
    /// `kind` is no [`ControlKind`].
    UnknownKind(u32),
    /// `scope_kind` is no [`MapScope`].
    UnknownScope(u32),
    /// A scope value is NaN or infinite.
    NonFiniteScope,
    /// An `AroundSensor` half extent is not > 0.
    EmptyHalfExtents,
    /// A `Fixed` box's min exceeds its max on some axis.
    InvertedBox,
    /// The path is longer than [`CONTROL_PATH_MAX`] bytes.
    PathTooLong(usize),
    /// The path's length field is out of range or its bytes are not UTF-8.
    BadPath,
}

impl std::fmt::Display for ControlError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::UnknownKind(k) => write!(f, "unknown request kind {k}"),
            Self::UnknownScope(k) => write!(f, "unknown scope kind {k}"),
            Self::NonFiniteScope => write!(f, "scope values must be finite"),
            Self::EmptyHalfExtents => write!(f, "half extents must be > 0"),
            Self::InvertedBox => write!(f, "box min must not exceed max"),
            Self::PathTooLong(n) => {
                write!(f, "path of {n} bytes is longer than {CONTROL_PATH_MAX}")
            }
            Self::BadPath => write!(f, "the request's path is not valid UTF-8 within its length"),
        }
    }
}

impl std::error::Error for ControlError {}

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
    /// With `SetScope`: 0 whole map, 1 around the sensor (half extents in `scope[..3]`),
    /// 2 fixed box (`scope[..3]` to `scope[3..]`); see [`ControlRequest::scope`].
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

    /// With a path (UTF-8), for `Save` and `Load`.
    pub fn with_path(kind: ControlKind, path: &str) -> Result<Self, ControlError> {
        let b = path.as_bytes();
        if b.len() > CONTROL_PATH_MAX {
            return Err(ControlError::PathTooLong(b.len()));
        }
        let mut r = Self::new(kind);
        r.path[..b.len()].copy_from_slice(b);
        r.path_len = b.len() as u32;
        Ok(r)
    }

    /// A `SetScope` request.
    pub fn with_scope(scope: MapScope) -> Self {
        let mut r = Self::new(ControlKind::SetScope);
        match scope {
            MapScope::Whole => r.scope_kind = MapScope::WHOLE,
            MapScope::AroundSensor { half_extents } => {
                r.scope_kind = MapScope::AROUND_SENSOR;
                r.scope[..3].copy_from_slice(&half_extents);
            }
            MapScope::Fixed { min, max } => {
                r.scope_kind = MapScope::FIXED;
                r.scope[..3].copy_from_slice(&min);
                r.scope[3..].copy_from_slice(&max);
            }
        }
        r
    }

    /// What the request asks for.
    pub fn kind(&self) -> Result<ControlKind, ControlError> {
        ControlKind::try_from(self.kind)
    }

    /// The path, if `path_len` is in range and the bytes are UTF-8.
    pub fn path(&self) -> Option<&str> {
        let n = self.path_len as usize;
        std::str::from_utf8(self.path.get(..n)?).ok()
    }

    /// The scope of a `SetScope` request, checked.
    pub fn scope(&self) -> Result<MapScope, ControlError> {
        let s = self.scope;
        if !s.iter().all(|c| c.is_finite()) {
            return Err(ControlError::NonFiniteScope);
        }
        let (lo, hi) = ([s[0], s[1], s[2]], [s[3], s[4], s[5]]);
        match self.scope_kind {
            MapScope::WHOLE => Ok(MapScope::Whole),
            MapScope::AROUND_SENSOR if lo.iter().all(|&h| h > 0.0) => {
                Ok(MapScope::AroundSensor { half_extents: lo })
            }
            MapScope::AROUND_SENSOR => Err(ControlError::EmptyHalfExtents),
            MapScope::FIXED if (0..3).all(|k| lo[k] <= hi[k]) => {
                Ok(MapScope::Fixed { min: lo, max: hi })
            }
            MapScope::FIXED => Err(ControlError::InvertedBox),
            k => Err(ControlError::UnknownScope(k)),
        }
    }
}

/// Service counters, as reported by a `Stats` request.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("voxmap::StatsWire::v4")]
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
    /// The integrator's vector kernels (`scalar`, `avx2`, `avx512`), ASCII, zero-padded.
    pub kernel: [u8; 16],
    /// The memory budget (bytes; 0 = unlimited).
    pub memory_budget_bytes: u64,
    /// The map's resident bytes (with a tile store: leaves, nodes, records waiting to be written).
    pub resident_bytes: u64,
    /// Tiles (128^3 voxels) in memory, with a tile store.
    pub tiles_resident: u64,
    /// Tiles only in the tile store.
    pub tiles_stored: u64,
    /// Tiles evicted to the store and loaded back from it since the start.
    pub tile_evictions: u64,
    pub tile_loads: u64,
    /// Tiles whose store record was refused (damaged); their regions read as unknown.
    pub tiles_refused: u64,
    /// The longest a frame waited for its tiles to load, ms.
    pub tile_wait_ms_max: f64,
}

impl StatsWire {
    /// `kernel` as text (empty if not ASCII).
    pub fn kernel(&self) -> &str {
        let n = self.kernel.iter().position(|&b| b == 0).unwrap_or(16);
        std::str::from_utf8(&self.kernel[..n])
            .ok()
            .filter(|s| s.is_ascii())
            .unwrap_or("")
    }

    /// `name` (at most 16 bytes kept) as a `kernel` field.
    pub fn kernel_field(name: &str) -> [u8; 16] {
        let mut k = [0u8; 16];
        let n = name.len().min(16);
        k[..n].copy_from_slice(&name.as_bytes()[..n]);
        k
    }
}

/// A control response: `ok` 1 or 0, a message, and the current stats.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("voxmap::ControlResponse::v4")]
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_paths_and_messages_are_bounded() {
        let r = ControlRequest::with_path(ControlKind::Save, "/tmp/m.vxm").unwrap();
        assert_eq!(r.path(), Some("/tmp/m.vxm"));
        assert_eq!(
            ControlRequest::with_path(ControlKind::Save, &"x".repeat(CONTROL_PATH_MAX + 1)),
            Err(ControlError::PathTooLong(CONTROL_PATH_MAX + 1))
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
    fn kinds_and_scopes_round_trip_and_bad_ones_are_refused() {
        for k in [
            ControlKind::Stats,
            ControlKind::Save,
            ControlKind::Load,
            ControlKind::Clear,
            ControlKind::SetScope,
        ] {
            assert_eq!(ControlRequest::new(k).kind(), Ok(k));
        }
        for bad in [0, 6, u32::MAX] {
            let r = ControlRequest {
                kind: bad,
                ..ControlRequest::new(ControlKind::Stats)
            };
            assert_eq!(r.kind(), Err(ControlError::UnknownKind(bad)));
        }
        let scopes = [
            MapScope::Whole,
            MapScope::AroundSensor {
                half_extents: [1.0, 2.0, 3.0],
            },
            MapScope::Fixed {
                min: [-1.0, -2.0, -3.0],
                max: [1.0, 2.0, 3.0],
            },
        ];
        for s in scopes {
            assert_eq!(ControlRequest::with_scope(s).scope(), Ok(s));
        }
        let around = ControlRequest::with_scope(MapScope::AroundSensor {
            half_extents: [1.0, 0.0, 1.0],
        });
        assert_eq!(around.scope(), Err(ControlError::EmptyHalfExtents));
        let inverted = ControlRequest::with_scope(MapScope::Fixed {
            min: [0.0, 2.0, 0.0],
            max: [1.0, 1.0, 1.0],
        });
        assert_eq!(inverted.scope(), Err(ControlError::InvertedBox));
        let mut nan = ControlRequest::with_scope(MapScope::Whole);
        nan.scope[4] = f64::NAN;
        assert_eq!(nan.scope(), Err(ControlError::NonFiniteScope));
        let unknown = ControlRequest {
            scope_kind: 3,
            ..ControlRequest::with_scope(MapScope::Whole)
        };
        assert_eq!(unknown.scope(), Err(ControlError::UnknownScope(3)));
    }
}
