//! voxmap-reader: what a planner reads of a voxmap map, with no thread pool and no
//! integrator.
//!
//! - [`snapshot::SnapshotView`]: a snapshot read in place (in shared memory, a file, any
//!   bytes), validated once, then queried: state at a point, batched states, first hit
//!   along a segment, whether a box is free, occupied voxels; [`snapshot::FieldView`] for
//!   the distance field a snapshot may carry.
//! - [`coord::GridTransform`] / [`VoxelCoord`] / [`WorldPoint`]: the one world <-> voxel
//!   conversion.
//! - [`model::SensorModel`]: the log-odds sensor model and its fixed-point form, and
//!   [`VoxelState`].
//! - [`tree`]: the tree's fixed shape (leaves of 8³ voxels, blocks of 8³ leaves), [`mask`]
//!   the leaves' 512-bit masks, [`raycast`] the exact DDA.
//! - [`mapfile::read_as_snapshot`]: a map file (`.vxm`) or snapshot file opened as
//!   snapshot bytes, on the calling thread.
//!
//! The map itself, its integrator and the snapshot writer are in `voxmap-map`, which
//! builds on this crate.
//!
//! ```
//! use voxmap_reader::snapshot::SnapshotView;
//!
//! // Bytes that are not a snapshot are refused with a reason, never a panic.
//! let err = SnapshotView::open(&[0u8; 16]).unwrap_err();
//! println!("{err}");
//! ```

pub mod coord;
pub mod field;
pub mod mapfile;
pub mod mask;
pub mod model;
pub mod prefetch;
pub mod raycast;
pub mod snapshot;
#[doc(hidden)]
pub mod test_rng;
pub mod tree;

pub use coord::{GridTransform, VoxelCoord, WorldPoint};
pub use model::{SensorModel, VoxelState};
pub use tree::LeafOccupancy;
