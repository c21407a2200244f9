//! The distance field beside a map: [`DistanceField`] builds and maintains, for each voxel
//! within `max_distance` of an obstacle, the exact offset to the nearest one (`esdf.rs`),
//! patch by patch with an exact separable transform (`patch.rs`). What the field means and
//! how snapshots carry it is in `voxmap-reader`'s `field` and `snapshot::field`,
//! re-exported here.

pub use voxmap_reader::field::*;

mod esdf;
pub(crate) mod patch;

#[cfg(test)]
mod tests;

pub use esdf::{DistanceField, FieldReport, LeafBand};
