//! Phase 3, merge: the dense walk's per-thread grids are folded into the frame's mark
//! tables (`walk::dense::fold_into`), then every touched brick gets its map leaf, created
//! if new, in one sequential pass in space order ([`attach_leaves`]) over the bricks the
//! tables list in parallel.

use super::marks::FrameMarks;
use crate::coord::VoxelCoord;
use crate::map::OccupancyMap;
use rayon::prelude::*;

/// Give every touched brick its map leaf; returns (leaf index, (slot, leaf is new)) sorted
/// by leaf index.
pub(super) fn attach_leaves(marks: &FrameMarks, map: &mut OccupancyMap) -> Vec<(u32, (u32, bool))> {
    let grid = map.grid_mut();
    let mut hint = (VoxelCoord::new(i32::MIN, 0, 0), u32::MAX);
    let first_new = grid.leaf_count() as u32;
    let mut items = Vec::with_capacity(marks.used_slots() as usize);
    // Internal-node-major order, so consecutive bricks share the cached internal node and
    // new leaves are laid out in space order.
    for cell in marks.bricks_in_order() {
        items.extend(cell.into_iter().map(|(o, s)| {
            let l = grid.leaf_index_or_insert(o, Some(&mut hint));
            (l, (s, l >= first_new))
        }));
    }
    if !items.windows(2).all(|w| w[0].0 < w[1].0) {
        items.par_sort_unstable_by_key(|&(l, _)| l);
    }
    items
}
