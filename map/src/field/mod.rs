//! The distance field beside a map: [`DistanceField`] builds and maintains, for each voxel
//! within `max_distance` of an obstacle, the exact offset to the nearest one (`esdf.rs`),
//! tile by tile with an exact separable transform (`tile.rs`). What the field means and
//! how snapshots carry it is in `voxmap-reader`'s `field` and `snapshot::field`,
//! re-exported here.

pub use voxmap_reader::field::*;

mod esdf;
pub(crate) mod tile;

#[cfg(test)]
mod tests;

pub use esdf::{DistanceField, FieldReport, LeafBand};
