//! The Moravec–Elfes log-odds sensor model and its fixed-point form stored in the map.
//!
//! Leaves store log-odds as `i8` in steps of `2^-k` nats, `k` chosen as the finest step for
//! which the clamping range fits (k = 5, 1/32 nat, for OctoMap's defaults). All updates are
//! then integer additions with saturation at the clamps: exact, deterministic and compact
//! (one byte per voxel). The rounding of the increments is below 0.5 % for the defaults.

use crate::coord::ConfigError;
use serde::{Deserialize, Serialize};

/// What the map knows about a voxel. The discriminants are the C and Python APIs' codes
/// (`VOXMAP_UNKNOWN` 0, `VOXMAP_FREE` 1, `VOXMAP_OCCUPIED` 2): `state as u8` is the code.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum VoxelState {
    Unknown = 0,
    Free = 1,
    Occupied = 2,
}

/// Probabilities of the inverse sensor model.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorModel {
    /// P(occupied | the voxel holds a ray's end point).
    pub p_hit: f64,
    /// P(occupied | a ray passed through the voxel).
    pub p_miss: f64,
    /// Lower clamping probability.
    pub clamp_min: f64,
    /// Upper clamping probability.
    pub clamp_max: f64,
    /// A known voxel with probability >= this is occupied, otherwise free.
    pub occupancy_threshold: f64,
}

impl Default for SensorModel {
    /// OctoMap's defaults.
    fn default() -> Self {
        Self {
            p_hit: 0.7,
            p_miss: 0.4,
            clamp_min: 0.1192,
            clamp_max: 0.971,
            occupancy_threshold: 0.5,
        }
    }
}

/// log(p / (1 - p)).
pub fn logodds(p: f64) -> f64 {
    (p / (1.0 - p)).ln()
}

/// Inverse of [`logodds`].
pub fn probability(l: f64) -> f64 {
    1.0 / (1.0 + (-l).exp())
}

/// A [`SensorModel`] in the map's fixed-point units.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct QuantizedModel {
    /// log2 of the number of fixed-point steps per nat.
    pub frac_bits: u8,
    pub hit: i8,
    pub miss: i8,
    pub min: i8,
    pub max: i8,
    pub threshold: i8,
}

impl SensorModel {
    pub fn validate(&self) -> Result<(), ConfigError> {
        let open01 = |name, v: f64| {
            if v.is_finite() && v > 0.0 && v < 1.0 {
                Ok(())
            } else {
                Err(ConfigError::Invalid {
                    name,
                    value: v,
                    why: "must be a probability strictly between 0 and 1",
                })
            }
        };
        open01("p_hit", self.p_hit)?;
        open01("p_miss", self.p_miss)?;
        open01("clamp_min", self.clamp_min)?;
        open01("clamp_max", self.clamp_max)?;
        open01("occupancy_threshold", self.occupancy_threshold)?;
        if self.p_hit <= 0.5 {
            return Err(ConfigError::Invalid {
                name: "p_hit",
                value: self.p_hit,
                why: "must be above 0.5",
            });
        }
        if self.p_miss >= 0.5 {
            return Err(ConfigError::Invalid {
                name: "p_miss",
                value: self.p_miss,
                why: "must be below 0.5",
            });
        }
        if !(self.clamp_min < self.occupancy_threshold && self.occupancy_threshold < self.clamp_max)
        {
            return Err(ConfigError::Invalid {
                name: "occupancy_threshold",
                value: self.occupancy_threshold,
                why: "must lie strictly between clamp_min and clamp_max",
            });
        }
        let span = logodds(self.clamp_min)
            .abs()
            .max(logodds(self.clamp_max).abs());
        if span > 127.0 {
            return Err(ConfigError::Invalid {
                name: "clamp",
                value: span,
                why: "log-odds clamps beyond +-127 nats",
            });
        }
        let q = self.quantize_unchecked();
        if q.hit <= 0 || q.miss >= 0 {
            return Err(ConfigError::Invalid {
                name: "p_hit/p_miss",
                value: self.p_hit,
                why: "too close to 0.5 to be represented at the clamping range's precision",
            });
        }
        Ok(())
    }

    /// The fixed-point form. Call [`Self::validate`] first.
    pub fn quantize(&self) -> Result<QuantizedModel, ConfigError> {
        self.validate()?;
        Ok(self.quantize_unchecked())
    }

    fn quantize_unchecked(&self) -> QuantizedModel {
        let span = logodds(self.clamp_min)
            .abs()
            .max(logodds(self.clamp_max).abs());
        let mut frac_bits = 0u8;
        while frac_bits < 12 && span * f64::from(1u32 << (frac_bits + 1)) <= 127.0 {
            frac_bits += 1;
        }
        let scale = f64::from(1u32 << frac_bits);
        let q = |p: f64| (logodds(p) * scale).round().clamp(-127.0, 127.0) as i8;
        QuantizedModel {
            frac_bits,
            hit: q(self.p_hit),
            miss: q(self.p_miss),
            min: q(self.clamp_min),
            max: q(self.clamp_max),
            threshold: q(self.occupancy_threshold),
        }
    }
}

impl QuantizedModel {
    /// Log-odds in nats of a stored value.
    #[inline]
    pub fn to_logodds(&self, v: i8) -> f64 {
        f64::from(v) / f64::from(1u32 << self.frac_bits)
    }

    /// The state of a known voxel with stored value `v`. Like OctoMap, a value at the
    /// threshold is occupied.
    #[inline]
    pub fn state(&self, v: i8) -> VoxelState {
        if v >= self.threshold {
            VoxelState::Occupied
        } else {
            VoxelState::Free
        }
    }

    /// One observation: saturating at the clamps.
    #[inline]
    pub fn update(&self, v: i8, hit: bool) -> i8 {
        let d = if hit { self.hit } else { self.miss };
        (i16::from(v) + i16::from(d)).clamp(i16::from(self.min), i16::from(self.max)) as i8
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn octomap_defaults_quantize_closely() {
        let m = SensorModel::default();
        let q = m.quantize().unwrap();
        assert_eq!(q.frac_bits, 5);
        for (p, v) in [
            (m.p_hit, q.hit),
            (m.p_miss, q.miss),
            (m.clamp_min, q.min),
            (m.clamp_max, q.max),
        ] {
            let err = (q.to_logodds(v) - logodds(p)).abs();
            assert!(err <= 0.5 / 32.0 + 1e-12, "p={p}: {err}");
        }
        assert_eq!(q.threshold, 0);
    }

    #[test]
    fn updates_saturate_at_the_clamps() {
        let q = SensorModel::default().quantize().unwrap();
        let mut v = 0i8;
        for _ in 0..100 {
            v = q.update(v, true);
        }
        assert_eq!(v, q.max);
        for _ in 0..100 {
            v = q.update(v, false);
        }
        assert_eq!(v, q.min);
        assert_eq!(q.state(q.max), VoxelState::Occupied);
        assert_eq!(q.state(q.min), VoxelState::Free);
        assert_eq!(q.state(q.update(0, true)), VoxelState::Occupied);
        assert_eq!(q.state(q.update(0, false)), VoxelState::Free);
    }

    #[test]
    fn rejects_bad_models() {
        let bad = [
            SensorModel {
                p_hit: 0.4,
                ..Default::default()
            },
            SensorModel {
                p_miss: 0.6,
                ..Default::default()
            },
            SensorModel {
                p_hit: f64::NAN,
                ..Default::default()
            },
            SensorModel {
                clamp_min: 0.6,
                ..Default::default()
            },
            SensorModel {
                occupancy_threshold: 0.99,
                ..Default::default()
            },
            SensorModel {
                clamp_max: 1.0,
                ..Default::default()
            },
        ];
        for m in bad {
            assert!(m.quantize().is_err(), "{m:?}");
        }
    }
}
