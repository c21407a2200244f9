//! voxmap-map: a sparse 3D log-odds occupancy map with a parallel raycasting core.
//!
//! The principal types:
//! - [`Mapper`]: one map with its integrator, its optional distance field and the
//!   bookkeeping of the frames it took: `insert(frame)`, then read the map, the field or a
//!   snapshot. What the service, `replay` and `bench` go through.
//! - [`OccupancyMap`]: the map (a VDB-style [`grid::Grid`] of fixed-point log-odds, its
//!   resolution and [`SensorModel`]).
//! - [`Integrator`]: integrates point-cloud [`Frame`]s into a map with exact DDA raycasting
//!   on a thread pool; the result does not depend on the thread count.
//! - [`snapshot::Plan`]: encodes a map (and its distance field) into a snapshot buffer,
//!   which planners read with `voxmap-reader`'s [`snapshot::SnapshotView`].
//! - [`field::DistanceField`]: the exact distance field kept beside a map.
//! - [`kernel::Kernels`]: the vector kernels' entry points, chosen once per process.
//!
//! What a planner reads (coordinates, masks, the sensor model, the DDA, the snapshot
//! layout and views) is the `voxmap-reader` crate, re-exported here module by module.
//!
//! ```
//! use voxmap_map::{Frame, Integrator, IntegratorConfig, OccupancyMap, SensorModel, VoxelState};
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

pub use voxmap_reader::{coord, mask, model, prefetch, raycast, tree};

mod cpus;
pub mod field;
pub mod grid;
pub mod integrate;
pub mod io;
pub mod kernel;
pub mod mapper;
pub mod occupancy;
mod pages;
pub mod snapshot;
pub mod store;

#[cfg(test)]
use voxmap_reader::test_rng;

pub use coord::{GridTransform, VoxelCoord, WorldPoint};
pub use integrate::{
    Frame, IntegrateError, IntegrateReport, Integrator, IntegratorConfig, RayMode, SetupError,
};
pub use kernel::{Kernel, Kernels};
pub use mapper::{FrameStamp, InsertReport, Mapper, MapperConfig};
pub use model::{SensorModel, VoxelState};
pub use occupancy::{MapCounts, OccupancyMap};
pub use tree::LeafOccupancy;
