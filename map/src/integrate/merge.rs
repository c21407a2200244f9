//! Phase 3, merge: the dense walk's per-thread grids are folded into the frame's mark
//! tables (`walk::dense::fold_into`), then the marks of every touched leaf are paired with
//! the map's leaf, created if new ([`attach_leaves`]): the tables list their touched leaves
//! by node in parallel, and each node's leaves are found or made in parallel, one node per
//! internal node of the map.

use super::marks::{FrameMarks, CELL_LOG2};
use crate::occupancy::OccupancyMap;
use rayon::prelude::*;

/// Pair every touched leaf's marks with its map leaf; returns (leaf index, (slot, leaf is new)) sorted
/// by leaf index.
pub(super) fn attach_leaves(marks: &FrameMarks, map: &mut OccupancyMap) -> Vec<(u32, (u32, bool))> {
    // A node is one internal node of the map (both 128 voxels a side, aligned), so
    // the nodes' touched leaves get their map leaves in parallel, numbered as one by one in node
    // order: new leaves are laid out in space order.
    const _: () = assert!(CELL_LOG2 == crate::tree::INTERNAL_LOG2);
    let before = map.grid().leaf_count();
    let mut items = map
        .grid_mut()
        .leaf_indices_or_insert(&marks.leaves_in_order());
    // All of them new, the leaves are numbered in the order listed: no need to check.
    let all_new = map.grid().leaf_count() - before == items.len();
    if !all_new && !items.par_windows(2).all(|w| w[0].0 < w[1].0) {
        items.par_sort_unstable_by_key(|&(l, _)| l);
    }
    items
}
