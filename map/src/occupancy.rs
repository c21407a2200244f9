//! [`OccupancyMap`]: a grid of fixed-point log-odds with its resolution and sensor model.

use crate::coord::{ConfigError, GridTransform, VoxelCoord, WorldPoint};
use crate::grid::{leaf_offset, Grid};
use crate::model::{QuantizedModel, SensorModel, VoxelState};
pub use crate::tree::LeafOccupancy;

/// Counts of known voxels by state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MapCounts {
    pub occupied: u64,
    pub free: u64,
    pub leaves: u64,
}

/// A 3D log-odds occupancy map. Voxels never observed are inactive (unknown); observed
/// voxels hold a fixed-point log-odds value (see [`crate::model`]). Each leaf marks its
/// occupied voxels ([`Leaf::marked`]): every write of a value keeps the mark in step.
pub struct OccupancyMap {
    grid: Grid<i8>,
    transform: GridTransform,
    model: SensorModel,
    q: QuantizedModel,
}

impl std::fmt::Debug for OccupancyMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OccupancyMap")
            .field("resolution", &self.resolution())
            .field("leaves", &self.grid.leaf_count())
            .field("model", &self.model)
            .finish()
    }
}

impl OccupancyMap {
    pub fn new(resolution: f64, model: SensorModel) -> Result<Self, ConfigError> {
        Ok(Self {
            grid: Grid::new(),
            transform: GridTransform::new(resolution)?,
            q: model.quantize()?,
            model,
        })
    }

    pub fn resolution(&self) -> f64 {
        self.transform.resolution()
    }

    pub fn transform(&self) -> &GridTransform {
        &self.transform
    }

    pub fn model(&self) -> &SensorModel {
        &self.model
    }

    pub fn quantized(&self) -> &QuantizedModel {
        &self.q
    }

    pub fn grid(&self) -> &Grid<i8> {
        &self.grid
    }

    pub(crate) fn grid_mut(&mut self) -> &mut Grid<i8> {
        &mut self.grid
    }

    /// Stored fixed-point log-odds of a voxel, if known.
    pub fn value(&self, v: VoxelCoord) -> Option<i8> {
        self.grid.get(v)
    }

    /// Set a voxel's stored value directly (clamped to the model's range).
    pub fn set_value(&mut self, v: VoxelCoord, value: i8) {
        let value = value.clamp(self.q.min, self.q.max);
        let leaf = self.grid.set(v, value);
        if value >= self.q.threshold {
            leaf.marked.set(leaf_offset(v));
        } else {
            leaf.marked.clear(leaf_offset(v));
        }
    }

    pub fn state(&self, v: VoxelCoord) -> VoxelState {
        match self.grid.get(v) {
            None => VoxelState::Unknown,
            Some(l) => self.q.state(l),
        }
    }

    /// State at a world point; points outside the index space are unknown.
    pub fn state_at(&self, p: &WorldPoint) -> VoxelState {
        self.transform
            .voxel_of(p)
            .map_or(VoxelState::Unknown, |v| self.state(v))
    }

    /// Occupancy probability of a known voxel.
    pub fn probability(&self, v: VoxelCoord) -> Option<f64> {
        self.grid
            .get(v)
            .map(|l| crate::model::probability(self.q.to_logodds(l)))
    }

    pub fn counts(&self) -> MapCounts {
        let mut c = MapCounts {
            leaves: self.grid.leaf_count() as u64,
            ..Default::default()
        };
        for (_, leaf) in self.grid.leaves() {
            let known = leaf.active.count() as u64;
            let occ = leaf.marked.count() as u64;
            c.occupied += occ;
            c.free += known - occ;
        }
        c
    }

    /// Every non-empty leaf's occupancy, in no particular order.
    pub fn leaf_occupancy(&self) -> impl Iterator<Item = LeafOccupancy> + '_ {
        (self.grid.leaves())
            .filter(|(_, leaf)| !leaf.active.is_empty())
            .map(|(origin, leaf)| LeafOccupancy {
                origin,
                known: leaf.active,
                occupied: leaf.marked,
            })
    }

    /// Panics unless every leaf marks exactly its known voxels at or above the threshold.
    #[cfg(test)]
    pub(crate) fn assert_marks_in_step(&self) {
        for (origin, leaf) in self.grid.leaves() {
            let mut want = crate::mask::Mask512::EMPTY;
            for i in leaf.active.iter_ones() {
                if leaf.values[i] >= self.q.threshold {
                    want.set(i);
                }
            }
            assert_eq!(leaf.marked, want, "leaf at {origin:?} marks other voxels");
        }
    }

    /// Heap bytes held by the map.
    pub fn memory_bytes(&self) -> usize {
        self.grid.memory_bytes()
    }

    /// Forget everything; keeps resolution and model.
    pub fn clear(&mut self) {
        self.grid = Grid::new();
    }
}
