//! Snapshots of a map: [`writer::Plan`] sizes a snapshot of the map (whole or a box, with
//! or without values and the distance field) and writes it straight into a caller's buffer,
//! through `voxmap-reader`'s [`Encoder`]. The layout, the records, the encoder and the views
//! are `voxmap-reader`'s `snapshot`, re-exported here.
//!
//! A map written into a snapshot and read back in place:
//!
//! ```
//! use voxmap_map::{OccupancyMap, SensorModel, VoxelCoord, VoxelState};
//! use voxmap_map::snapshot::{Meta, Plan, Scope, SnapshotView};
//! let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
//! map.set_value(VoxelCoord::new(3, -2, 7), 100);
//! let bytes = Plan::new(&map, Scope::Whole, Meta::default()).to_vec();
//! let view = SnapshotView::open(&bytes).unwrap();
//! assert_eq!(view.state(VoxelCoord::new(3, -2, 7)), VoxelState::Occupied);
//! assert_eq!(view.state(VoxelCoord::new(0, 0, 0)), VoxelState::Unknown);
//! ```
//!
//! With the distance field, queried through the snapshot's [`FieldView`]:
//!
//! ```
//! use voxmap_map::{OccupancyMap, SensorModel, VoxelCoord};
//! use voxmap_map::field::{DistanceField, FieldConfig};
//! use voxmap_map::snapshot::{Meta, Plan, Scope, SnapshotView};
//! let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
//! for x in -10..10 { map.set_value(VoxelCoord::new(x, 0, 0), -10); }
//! map.set_value(VoxelCoord::new(0, 0, 0), 100);
//! let mut field = DistanceField::new(FieldConfig::default(), 0.1).unwrap();
//! field.rebuild(&map, None);
//! let bytes = Plan::new(&map, Scope::Whole, Meta::default()).with_field(&field).to_vec();
//! let view = SnapshotView::open(&bytes).unwrap();
//! let f = view.distance_field().unwrap();
//! assert!((f.distance(VoxelCoord::new(5, 0, 0)).unwrap() - 0.5).abs() < 1e-12);
//! assert_eq!(f.distance(VoxelCoord::new(0, 40, 0)), None); // nothing known there
//! ```

pub use voxmap_reader::snapshot::*;

pub mod writer;

pub use writer::{OnPool, Plan};

#[cfg(test)]
mod tests;
