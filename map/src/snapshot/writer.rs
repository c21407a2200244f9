//! The snapshot of a map: [`Plan`] gathers the map's leaves in block order (all of them,
//! or those a box scope reaches) and has `voxmap-reader`'s [`Encoder`] lay them out and
//! write them, its pieces of work on the current rayon pool (the caller's, via `install`,
//! or the global one) and its records encoded by the process's kernel.

use super::{EncodeError, Encoder, FieldBands, MapInfo, Meta, Pieces, PlannedLeaf, Scope};
use crate::coord::{VoxelCoord, WorldPoint};
use crate::field::{DistanceField, FieldConfig};
use crate::grid::leaf_box_mask;
use crate::mask::Mask512;
use crate::occupancy::OccupancyMap;
use rayon::prelude::*;
use voxmap_reader::snapshot::encode::EncodePiece;

/// The encoder's pieces on the current rayon pool, records by the process's kernel.
#[derive(Clone, Copy, Debug, Default)]
pub struct OnPool;

impl Pieces for OnPool {
    fn map<J: Send, R: Send>(&self, jobs: Vec<J>, f: impl Fn(J) -> R + Sync + Send) -> Vec<R> {
        jobs.into_par_iter().map(f).collect()
    }

    fn encode_piece(&self) -> EncodePiece {
        crate::kernel::Kernels::process_or_scalar().encode_piece
    }

    fn sizes(&self) -> (usize, usize) {
        // Small in tests, so that their maps span many pieces.
        if cfg!(test) {
            (64, 4096)
        } else {
            (4096, 4 << 20)
        }
    }
}

/// A snapshot of a map laid out but not yet written: size it with [`Plan::encoded_len`],
/// then [`Plan::write`] it into a buffer of at least that many bytes.
pub struct Plan<'a>(Encoder<'a, OnPool>);

impl<'a> Plan<'a> {
    pub fn new(map: &'a OccupancyMap, scope: Scope, meta: Meta) -> Self {
        let mut keeps = Vec::new();
        let scope_box = match scope {
            Scope::Whole => None,
            Scope::Box { min, max } => Some(
                map.transform()
                    .voxels_centred_in(&WorldPoint::from(min), &WorldPoint::from(max))
                    .unwrap_or((VoxelCoord::new(1, 1, 1), VoxelCoord::new(0, 0, 0))),
            ),
        };
        let leaves: Vec<PlannedLeaf<'a>> = match scope {
            // Leaves are not read here; the encoder reads each one once.
            Scope::Whole => {
                let grid = map.grid();
                (grid.leaf_indices_in_block_order().par_iter())
                    .map(|&(origin, i)| PlannedLeaf::new(origin, grid.leaf(i), None))
                    .collect()
            }
            Scope::Box { min, max } => {
                let bounds = map
                    .transform()
                    .voxels_centred_in(&WorldPoint::from(min), &WorldPoint::from(max));
                // Only the leaves overlapping the box are read (a box around the sensor
                // in a large map is a small part of it).
                let planned = bounds.map_or(Vec::new(), |(lo, hi)| {
                    map.grid().filter_map_leaves_in_box(lo, hi, |origin, leaf| {
                        let inside = leaf_box_mask(origin, lo, hi);
                        let keep = leaf.active.and(&inside);
                        (!keep.is_empty()).then_some((origin, leaf, keep))
                    })
                });
                keeps.reserve(planned.len());
                planned
                    .into_iter()
                    .map(|(origin, leaf, keep)| {
                        keeps.push(keep);
                        PlannedLeaf::new(origin, leaf, Some(keeps.len() as u32 - 1))
                    })
                    .collect()
            }
        };
        let info = MapInfo {
            resolution: map.resolution(),
            quantized: *map.quantized(),
        };
        Plan(Encoder::new(info, leaves, keeps, scope_box, meta, OnPool))
    }

    /// Carry `field` (kept beside the planned map) in the snapshot, for the leaves planned.
    pub fn with_field(self, field: &'a DistanceField) -> Self {
        Plan(self.0.with_field(field))
    }

    pub fn leaf_count(&self) -> usize {
        self.0.leaf_count()
    }

    /// Bytes [`Plan::write`] needs.
    pub fn encoded_len(&self) -> usize {
        self.0.encoded_len()
    }

    /// Write the snapshot into `buf[..encoded_len()]`; returns the length written.
    pub fn write(&self, buf: &mut [u8]) -> Result<usize, EncodeError> {
        self.0.write(buf)
    }

    /// Encode into a new vector.
    pub fn to_vec(&self) -> Vec<u8> {
        self.0.to_vec()
    }
}

impl FieldBands for DistanceField {
    fn config(&self) -> FieldConfig {
        *DistanceField::config(self)
    }

    fn radius(&self) -> u32 {
        DistanceField::radius(self)
    }

    fn max_distance(&self) -> f64 {
        DistanceField::max_distance(self)
    }

    fn window(&self) -> Option<(VoxelCoord, VoxelCoord)> {
        DistanceField::window(self)
    }

    fn band(&self, origin: VoxelCoord) -> Option<(&Mask512, &[[i8; 3]])> {
        self.leaf(origin).map(|b| (b.mask(), b.offsets()))
    }
}
