//! Euclidean distance fields: for each voxel near an obstacle, the nearest obstacle voxel.
//!
//! The field is exact: a voxel's distance is the Euclidean distance between its centre and
//! the centre of the nearest obstacle voxel (in voxels: `sqrt(dx² + dy² + dz²)` over whole
//! offsets), as dynamicEDT3D and FIESTA define it, not a chamfer or quasi-Euclidean sum.
//! It is kept only in a band: voxels closer than `radius` voxels (`max_distance`) to an
//! obstacle. Each stores its offset to the nearest obstacle, three `i8`s, from which both
//! the distance and the obstacle follow with no quantisation. Among obstacles at the same
//! distance the one with the smallest dx, then dy, then the lower one is kept, so the
//! field is a function of the obstacles alone, whatever computed it.
//!
//! This module holds what the map's writer and a planner's reader share ([`FieldConfig`],
//! [`UnknownPolicy`]); the map crate's `DistanceField` builds and maintains a field beside
//! a map. Snapshots carry it ([`crate::snapshot::field`]), where planners query it in place.

use crate::coord::{ConfigError, VoxelCoord};
use crate::mask::Mask512;
use hashbrown::HashMap;

/// Largest band radius in voxels: offsets are stored as `i8`, and the transform's keys
/// hold a squared distance below `2 * 63²` in 13 bits.
pub const MAX_RADIUS: u32 = 63;

/// What unknown (never observed) voxels count as: dynamicEDT3D's `treatUnknownAsOccupied`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UnknownPolicy {
    /// Only occupied voxels are obstacles (optimistic planning through unknown space).
    #[default]
    Free,
    /// Unknown voxels are obstacles too: distances shrink toward unexplored space.
    Occupied,
}

impl UnknownPolicy {
    pub fn name(self) -> &'static str {
        match self {
            Self::Free => "free",
            Self::Occupied => "occupied",
        }
    }

    /// The code snapshots store: 0 free, 1 occupied.
    pub fn code(self) -> u8 {
        self as u8
    }

    pub fn from_code(c: u8) -> Option<Self> {
        match c {
            0 => Some(Self::Free),
            1 => Some(Self::Occupied),
            _ => None,
        }
    }
}

impl std::str::FromStr for UnknownPolicy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "free" => Ok(Self::Free),
            "occupied" => Ok(Self::Occupied),
            _ => Err(format!("unknown policy {s:?}: free or occupied")),
        }
    }
}

/// What a distance field covers.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldConfig {
    /// Distances are kept below this (metres); rounded to whole voxels, 1 to
    /// [`MAX_RADIUS`] of them.
    pub max_distance: f64,
    /// What unknown voxels count as.
    #[serde(default)]
    pub unknown: UnknownPolicy,
    /// Half-extents (metres) of a box around the sensor that the field covers, moving with
    /// it; `None`: the whole map.
    #[serde(default)]
    pub window: Option<[f64; 3]>,
}

impl Default for FieldConfig {
    fn default() -> Self {
        Self {
            max_distance: 2.0,
            unknown: UnknownPolicy::Free,
            window: None,
        }
    }
}

impl FieldConfig {
    /// The band radius in voxels at `resolution`, or why this configuration is invalid.
    pub fn radius(&self, resolution: f64) -> Result<u32, ConfigError> {
        let r = self.max_distance / resolution;
        if !(r.is_finite() && r.round() >= 1.0 && r.round() <= f64::from(MAX_RADIUS)) {
            return Err(ConfigError::Invalid {
                name: "esdf max_distance",
                value: self.max_distance,
                why: "must be 1 to 63 voxels at the map's resolution",
            });
        }
        if let Some(w) = self.window {
            if !w
                .iter()
                .all(|h| h.is_finite() && *h > 0.0 && h / resolution < 1e6)
            {
                return Err(ConfigError::Invalid {
                    name: "esdf window",
                    value: w.iter().cloned().fold(f64::NAN, f64::min),
                    why: "half-extents must be finite, positive and under 10^6 voxels",
                });
            }
        }
        Ok(r.round() as u32)
    }
}

/// Squared length of an offset, in voxels².
#[inline]
pub fn offset_len2(o: [i8; 3]) -> i32 {
    o.iter().map(|&c| i32::from(c) * i32::from(c)).sum()
}

/// The obstacles of a map leaf under a policy: its occupied voxels, and its unknown ones
/// too where unknown counts as occupied.
pub fn obstacles(active: &Mask512, marked: &Mask512, policy: UnknownPolicy) -> Mask512 {
    match policy {
        UnknownPolicy::Free => *marked,
        UnknownPolicy::Occupied => Mask512 {
            words: std::array::from_fn(|w| marked.words[w] | !active.words[w]),
        },
    }
}

/// Whether the leaf at `origin` reaches into `window` (or there is none).
pub fn leaf_in_window(window: Option<(VoxelCoord, VoxelCoord)>, origin: VoxelCoord) -> bool {
    window.is_none_or(|(lo, hi)| {
        let e = origin + VoxelCoord::new(7, 7, 7);
        origin.x <= hi.x
            && lo.x <= e.x
            && origin.y <= hi.y
            && lo.y <= e.y
            && origin.z <= hi.z
            && lo.z <= e.z
    })
}

/// One leaf's band: which of its voxels are in the band, and their offsets to the nearest
/// obstacle, in the mask's order.
pub trait Band {
    fn mask(&self) -> &Mask512;
    fn offsets(&self) -> &[[i8; 3]];

    /// The band's obstacles: its voxels at offset zero.
    fn obstacles(&self) -> Mask512 {
        let mut at_zero = Mask512::EMPTY;
        for (i, d) in self.mask().iter_ones().zip(self.offsets()) {
            if *d == [0; 3] {
                at_zero.set(i);
            }
        }
        at_zero
    }
}

impl Band for (Mask512, Vec<[i8; 3]>) {
    fn mask(&self) -> &Mask512 {
        &self.0
    }

    fn offsets(&self) -> &[[i8; 3]] {
        &self.1
    }
}

/// Check a field's bands read from a file against the map they were saved with: each band
/// leaf-aligned, a leaf of the map (`is_leaf`), inside the window, stored once, its offsets
/// within `radius`; and in every map leaf inside the window (`leaves`: origin and
/// obstacles) the band's voxels at offset zero exactly its obstacles. So a field of another
/// map is refused.
pub fn check_bands<B: Band>(
    bands: &HashMap<VoxelCoord, B>,
    duplicates: bool,
    radius: u32,
    window: Option<(VoxelCoord, VoxelCoord)>,
    is_leaf: impl Fn(VoxelCoord) -> bool,
    leaves: impl Iterator<Item = (VoxelCoord, Mask512)>,
) -> Result<(), String> {
    if duplicates {
        return Err("a leaf stored twice".into());
    }
    let r2 = (radius * radius) as i32;
    for (&o, band) in bands {
        if o.to_array()
            .iter()
            .any(|c| c & 7 != 0 || c.unsigned_abs() >= 1 << 30)
        {
            return Err(format!(
                "leaf origin {o:?} not leaf-aligned or out of range"
            ));
        }
        if !is_leaf(o) {
            return Err(format!("leaf {o:?} is not a leaf of the map"));
        }
        if !leaf_in_window(window, o) {
            return Err(format!("leaf {o:?} lies outside the field's window"));
        }
        if band.offsets().iter().any(|&d| offset_len2(d) >= r2) {
            return Err(format!("an offset of leaf {o:?} reaches beyond the radius"));
        }
    }
    for (o, obstacles) in leaves {
        if !leaf_in_window(window, o) {
            continue;
        }
        let stored = bands.get(&o).map_or(Mask512::EMPTY, |b| b.obstacles());
        if stored != obstacles {
            return Err(format!("leaf {o:?} disagrees with the map's obstacles"));
        }
    }
    Ok(())
}
