//! Phase 3, merge: the dense walk's per-thread grids are folded into the frame's mark
//! tables (`walk::dense::fold_into`), then every touched brick gets its map leaf, created
//! if new ([`attach_leaves`]): the tables list their bricks by coarse cell in parallel,
//! and each cell's bricks get their leaves in parallel, one cell per internal node.

use super::marks::{FrameMarks, CELL_LOG2};
use crate::occupancy::OccupancyMap;
use rayon::prelude::*;

/// Give every touched brick its map leaf; returns (leaf index, (slot, leaf is new)) sorted
/// by leaf index.
pub(super) fn attach_leaves(marks: &FrameMarks, map: &mut OccupancyMap) -> Vec<(u32, (u32, bool))> {
    // A coarse cell is one internal node of the map (both 128 voxels a side, aligned), so
    // the cells' bricks get their leaves in parallel, numbered as one by one in cell
    // order: new leaves are laid out in space order.
    const _: () = assert!(CELL_LOG2 == crate::tree::INTERNAL_LOG2);
    let before = map.grid().leaf_count();
    let mut items = map
        .grid_mut()
        .leaf_indices_or_insert(&marks.bricks_in_order());
    // All of them new, the leaves are numbered in the order listed: no need to check.
    let all_new = map.grid().leaf_count() - before == items.len();
    if !all_new && !items.par_windows(2).all(|w| w[0].0 < w[1].0) {
        items.par_sort_unstable_by_key(|&(l, _)| l);
    }
    items
}
