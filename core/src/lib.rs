//! voxmap-core: a sparse 3D log-odds occupancy map with a parallel raycasting core.
//!
//! Feature `map` (default): the map, the integrator, file formats and the snapshot writer.
//! Without it: the snapshot reader ([`snapshot::SnapshotView`]) and what it needs
//! (coordinates, masks, the sensor model, the DDA), with no thread pool.
//!
//! The principal types:
//! - [`OccupancyMap`]: the map (a VDB-style [`grid::Grid`] of fixed-point log-odds, its
//!   resolution and [`SensorModel`]).
//! - [`Integrator`]: integrates point-cloud [`Frame`]s into a map with exact DDA raycasting
//!   on a thread pool; the result does not depend on the thread count.
//! - [`coord::GridTransform`] / [`VoxelCoord`]: the one world <-> voxel conversion.
//!
//! ```
//! use voxmap_core::{Frame, Integrator, IntegratorConfig, OccupancyMap, SensorModel, VoxelState};
//! use nalgebra::Isometry3;
//!
//! let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
//! let mut integrator = Integrator::new(IntegratorConfig { threads: 2, max_range: 10.0, ..Default::default() }).unwrap();
//! let points = [[2.0f32, 0.0, 0.0]];
//! integrator.integrate(&mut map, &Frame { pose: Isometry3::identity(), points: &points }).unwrap();
//! assert_eq!(map.state_at(&[2.05, 0.05, 0.05].into()), VoxelState::Occupied);
//! assert_eq!(map.state_at(&[1.0, 0.05, 0.05].into()), VoxelState::Free);
//! assert_eq!(map.state_at(&[3.0, 0.05, 0.05].into()), VoxelState::Unknown);
//! ```

pub mod coord;
pub mod field;
pub mod kernel;
pub mod mask;
pub mod model;
mod prefetch;
pub mod raycast;
pub mod snapshot;
pub mod tree;

// The map and what writes it: left out with `default-features = false`, so that a planner
// reading snapshots links no thread pool.
#[cfg(feature = "map")]
mod cpus;
#[cfg(feature = "map")]
pub mod grid;
#[cfg(feature = "map")]
pub mod integrate;
#[cfg(feature = "map")]
pub mod io;
#[cfg(feature = "map")]
pub mod map;
#[cfg(feature = "map")]
mod pages;

#[cfg(test)]
mod test_rng;

pub use coord::{GridTransform, VoxelCoord, WorldPoint};
#[cfg(feature = "map")]
pub use integrate::{
    Frame, IntegrateError, IntegrateReport, Integrator, IntegratorConfig, RayMode,
};
pub use kernel::Kernel;
#[cfg(feature = "map")]
pub use map::{MapCounts, OccupancyMap};
pub use model::{SensorModel, VoxelState};
pub use tree::LeafOccupancy;
