//! Coordinates: integer voxel coordinates, world points, and [`GridTransform`], the one
//! place that converts between them.

use nalgebra::Point3;
use std::ops::{Add, Sub};

/// A point in the map frame, in metres.
pub type WorldPoint = Point3<f64>;

/// Integer voxel coordinates in the signed 32-bit index space of a grid.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VoxelCoord {
    pub x: i32,
    pub y: i32,
    pub z: i32,
}

impl VoxelCoord {
    pub const fn new(x: i32, y: i32, z: i32) -> Self {
        Self { x, y, z }
    }

    pub const fn to_array(self) -> [i32; 3] {
        [self.x, self.y, self.z]
    }

    pub const fn from_array(a: [i32; 3]) -> Self {
        Self::new(a[0], a[1], a[2])
    }

    /// Arithmetic shift of every component (floor division by `2^s`).
    #[inline]
    pub const fn shr(self, s: u32) -> Self {
        Self::new(self.x >> s, self.y >> s, self.z >> s)
    }

    #[inline]
    pub const fn shl(self, s: u32) -> Self {
        Self::new(self.x << s, self.y << s, self.z << s)
    }

    /// Component-wise minimum.
    pub fn min(self, o: Self) -> Self {
        Self::new(self.x.min(o.x), self.y.min(o.y), self.z.min(o.z))
    }

    /// Component-wise maximum.
    pub fn max(self, o: Self) -> Self {
        Self::new(self.x.max(o.x), self.y.max(o.y), self.z.max(o.z))
    }
}

impl Add for VoxelCoord {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}

impl Sub for VoxelCoord {
    type Output = Self;
    fn sub(self, o: Self) -> Self {
        Self::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}

/// Largest |voxel index| a world point may map to. Leaves a margin below `i32::MAX`
/// so that leaf/brick arithmetic and ray steps can never overflow.
pub const MAX_VOXEL_INDEX: f64 = (1u32 << 30) as f64;

/// Points closer than this (in voxel units) to a voxel face count as lying on it. This
/// absorbs the decimal rounding of `x / resolution` (2.3 / 0.1 = 22.999999999999996)
/// without affecting any physically meaningful position.
#[doc(hidden)]
pub const FACE_SNAP: f64 = 1e-9;

/// Errors in grid or sensor-model parameters.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum ConfigError {
    /// Resolution must be finite and within [1e-4, 1e3] m.
    Resolution(f64),
    /// A parameter is out of its valid range.
    Invalid {
        name: &'static str,
        value: f64,
        why: &'static str,
    },
}

impl std::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ConfigError::Resolution(r) => {
                write!(
                    f,
                    "resolution {r} m is invalid: must be finite and within [1e-4, 1000] m"
                )
            }
            ConfigError::Invalid { name, value, why } => {
                write!(f, "{name} = {value} is invalid: {why}")
            }
        }
    }
}

impl std::error::Error for ConfigError {}

/// Conversion between world metres and voxel indices at one resolution.
///
/// Voxel `v` covers `[v * res, (v + 1) * res)` on each axis: conversion is by floor, so
/// negative coordinates work and a point on a face belongs to the voxel above it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridTransform {
    resolution: f64,
    inv: f64,
}

impl GridTransform {
    pub fn new(resolution: f64) -> Result<Self, ConfigError> {
        if !(resolution.is_finite() && (1e-4..=1e3).contains(&resolution)) {
            return Err(ConfigError::Resolution(resolution));
        }
        Ok(Self {
            resolution,
            inv: 1.0 / resolution,
        })
    }

    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// A world coordinate in continuous voxel units, snapped onto a face when within
    /// [`FACE_SNAP`] of one. `floor` of the result is the voxel index.
    #[inline]
    pub fn to_units(&self, w: f64) -> f64 {
        let k = w / self.resolution;
        let r = k.round_ties_even();
        if (k - r).abs() <= FACE_SNAP {
            r
        } else {
            k
        }
    }

    /// Continuous voxel units of a world point (see [`Self::to_units`]).
    #[inline]
    pub fn point_to_units(&self, p: &WorldPoint) -> [f64; 3] {
        [self.to_units(p.x), self.to_units(p.y), self.to_units(p.z)]
    }

    /// The voxel holding `p`, or `None` if `p` is not finite or outside the index space.
    pub fn voxel_of(&self, p: &WorldPoint) -> Option<VoxelCoord> {
        units_to_voxel(self.point_to_units(p))
    }

    /// World position of a voxel's centre.
    pub fn voxel_center(&self, v: VoxelCoord) -> WorldPoint {
        WorldPoint::new(
            (v.x as f64 + 0.5) * self.resolution,
            (v.y as f64 + 0.5) * self.resolution,
            (v.z as f64 + 0.5) * self.resolution,
        )
    }

    /// Inclusive bounds of the voxels whose centres lie in the box `[min, max]` (a centre
    /// within [`FACE_SNAP`] of a face counts as on it), or `None` if a corner is not
    /// finite or lies outside the index space. No voxel is inside when some `lo > hi`.
    pub fn voxels_centred_in(
        &self,
        min: &WorldPoint,
        max: &WorldPoint,
    ) -> Option<(VoxelCoord, VoxelCoord)> {
        // Voxel v's centre is (v + 0.5) res: inside iff min/res - 0.5 <= v <= max/res - 0.5.
        let half = self.resolution * 0.5;
        let lo = self.point_to_units(&WorldPoint::new(min.x - half, min.y - half, min.z - half));
        let hi = self.point_to_units(&WorldPoint::new(max.x - half, max.y - half, max.z - half));
        // ceil(u) = -floor(-u), with the same range check as floor.
        let lo = units_to_voxel(lo.map(|c| -c))?;
        Some((VoxelCoord::new(-lo.x, -lo.y, -lo.z), units_to_voxel(hi)?))
    }

    /// World position of a voxel's minimum corner.
    pub fn voxel_min_corner(&self, v: VoxelCoord) -> WorldPoint {
        WorldPoint::new(
            v.x as f64 * self.resolution,
            v.y as f64 * self.resolution,
            v.z as f64 * self.resolution,
        )
    }
}

/// Floor of continuous voxel units, `None` when non-finite or out of the index space.
#[inline]
pub fn units_to_voxel(u: [f64; 3]) -> Option<VoxelCoord> {
    let ok = u.iter().all(|c| c.is_finite() && c.abs() < MAX_VOXEL_INDEX);
    ok.then(|| {
        VoxelCoord::new(
            u[0].floor() as i32,
            u[1].floor() as i32,
            u[2].floor() as i32,
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_conversion_handles_negative_coordinates() {
        let t = GridTransform::new(0.1).unwrap();
        let v = |x, y, z| t.voxel_of(&WorldPoint::new(x, y, z)).unwrap();
        assert_eq!(v(0.05, -0.05, -0.15), VoxelCoord::new(0, -1, -2));
        assert_eq!(
            v(-1e-12, 0.0, 0.0).x,
            0,
            "within snap distance of the face at 0"
        );
        assert_eq!(v(-1e-6, 0.0, 0.0).x, -1);
    }

    #[test]
    fn points_on_faces_belong_to_the_voxel_above() {
        let t = GridTransform::new(0.1).unwrap();
        for (w, want) in [
            (0.3, 3),
            (2.3, 23),
            (-0.3, -3),
            (-2.3, -23),
            (0.7, 7),
            (0.0, 0),
            (-0.1, -1),
        ] {
            assert_eq!(
                t.voxel_of(&WorldPoint::new(w, w, w)).unwrap(),
                VoxelCoord::new(want, want, want),
                "{w}"
            );
        }
        // Exactly representable resolution: exact arithmetic, faces on multiples.
        let t = GridTransform::new(0.125).unwrap();
        assert_eq!(
            t.voxel_of(&WorldPoint::new(0.25, -0.25, 0.125)).unwrap(),
            VoxelCoord::new(2, -2, 1)
        );
        assert_eq!(
            t.voxel_of(&WorldPoint::new(0.2499999, -0.2500001, 0.0))
                .unwrap(),
            VoxelCoord::new(1, -3, 0)
        );
    }

    #[test]
    fn rejects_non_finite_and_out_of_range() {
        let t = GridTransform::new(0.1).unwrap();
        assert!(t.voxel_of(&WorldPoint::new(f64::NAN, 0.0, 0.0)).is_none());
        assert!(t
            .voxel_of(&WorldPoint::new(0.0, f64::INFINITY, 0.0))
            .is_none());
        assert!(t.voxel_of(&WorldPoint::new(0.0, 0.0, 1e9)).is_none());
        assert!(GridTransform::new(0.0).is_err());
        assert!(GridTransform::new(f64::NAN).is_err());
    }

    #[test]
    fn box_of_voxel_centres_is_closed() {
        let t = GridTransform::new(0.1).unwrap();
        let (v, w) = (VoxelCoord::new(-3, 2, 0), VoxelCoord::new(4, 5, 0));
        // Faces through centres: both voxels inside.
        assert_eq!(
            t.voxels_centred_in(&t.voxel_center(v), &t.voxel_center(w)),
            Some((v, w))
        );
        // Faces just inside those centres: both outside.
        let e = WorldPoint::new(1e-6, 1e-6, 1e-6).coords;
        let (lo, hi) = t
            .voxels_centred_in(&(t.voxel_center(v) + e), &(t.voxel_center(w) - e))
            .unwrap();
        assert_eq!(
            (lo, hi),
            (v + VoxelCoord::new(1, 1, 1), w - VoxelCoord::new(1, 1, 1))
        );
        // A box between two centres holds none.
        let (lo, hi) = t
            .voxels_centred_in(
                &WorldPoint::new(0.06, 0.06, 0.06),
                &WorldPoint::new(0.14, 0.14, 0.14),
            )
            .unwrap();
        assert!(lo.x > hi.x);
        assert!(t
            .voxels_centred_in(&WorldPoint::new(f64::NAN, 0.0, 0.0), &WorldPoint::origin())
            .is_none());
    }

    #[test]
    fn voxel_center_round_trips() {
        let t = GridTransform::new(0.05).unwrap();
        for v in [
            VoxelCoord::new(0, 0, 0),
            VoxelCoord::new(-7, 13, -1000),
            VoxelCoord::new(123456, -654321, 1),
        ] {
            assert_eq!(t.voxel_of(&t.voxel_center(v)).unwrap(), v);
        }
    }
}
