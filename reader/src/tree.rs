//! The tree's fixed shape, shared by the map and the snapshots: leaf and internal-node
//! sizes, the snapshot's blocks of leaves, and the voxel <-> offset conversions. Nothing
//! here allocates or runs in parallel, so planners that only read snapshots link it alone.

use crate::coord::VoxelCoord;
use crate::mask::Mask512;

/// log2 of a leaf's edge in voxels.
pub const LEAF_LOG2: u32 = 3;
/// Voxels per leaf.
pub const LEAF_VOXELS: usize = 1 << (3 * LEAF_LOG2);
/// log2 of an internal node's edge in leaves.
pub const INTERNAL_LOG2: u32 = 4;
/// log2 of an internal node's edge in voxels.
pub const INTERNAL_TOTAL_LOG2: u32 = LEAF_LOG2 + INTERNAL_LOG2;
/// Children (leaves) per internal node.
pub const INTERNAL_CHILDREN: usize = 1 << (3 * INTERNAL_LOG2);
/// Leaves per block: the 8x8x8 leaves (64^3 voxels) that snapshots index together, eight
/// to an internal node.
pub const BLOCK_LEAVES: usize = 512;

/// `MORTON[i]`: the Morton (Z-order) place of in-leaf offset `i = x | y << 3 | z << 6`,
/// bits interleaved x, y, z from the lowest: the eight voxels of an aligned 2x2x2 cube are
/// consecutive. The distance field section stores a leaf's voxels in this order, so that
/// the eight voxels an interpolation reads share cache lines.
pub static MORTON: [u16; LEAF_VOXELS] = {
    let mut t = [0u16; LEAF_VOXELS];
    let mut i = 0;
    while i < LEAF_VOXELS {
        let (x, y, z) = (i & 7, i >> 3 & 7, i >> 6 & 7);
        let mut m = 0;
        let mut b = 0;
        while b < 3 {
            m |= ((x >> b & 1) | (y >> b & 1) << 1 | (z >> b & 1) << 2) << (3 * b);
            b += 1;
        }
        t[i] = m as u16;
        i += 1;
    }
    t
};

/// The inverse of [`MORTON`]: the in-leaf offset at each Morton place.
pub static UNMORTON: [u16; LEAF_VOXELS] = {
    let mut t = [0u16; LEAF_VOXELS];
    let mut i = 0;
    while i < LEAF_VOXELS {
        t[MORTON[i] as usize] = i as u16;
        i += 1;
    }
    t
};

/// Origin (minimum corner) of the block holding `v`.
#[inline]
pub fn block_origin(v: VoxelCoord) -> VoxelCoord {
    VoxelCoord::new(v.x & !63, v.y & !63, v.z & !63)
}

/// In-block index of the leaf holding `v`: its leaf coordinates mod 8, x | y << 3 | z << 6.
#[inline]
pub fn leaf_in_block(v: VoxelCoord) -> usize {
    ((v.x >> 3 & 7) | (v.y >> 3 & 7) << 3 | (v.z >> 3 & 7) << 6) as usize
}

/// Origin of the leaf with in-block index `j` of the block with origin `b` (the inverse of
/// [`leaf_in_block`]).
#[inline]
pub fn leaf_of_block(b: VoxelCoord, j: usize) -> VoxelCoord {
    voxel_at(VoxelCoord::default(), j).shl(LEAF_LOG2) + b
}
/// In-leaf offset of a voxel.
#[inline]
pub fn leaf_offset(v: VoxelCoord) -> usize {
    ((v.x & 7) | (v.y & 7) << 3 | (v.z & 7) << 6) as usize
}

/// Origin (minimum corner) of the leaf holding `v`.
#[inline]
pub fn leaf_origin(v: VoxelCoord) -> VoxelCoord {
    VoxelCoord::new(v.x & !7, v.y & !7, v.z & !7)
}

/// The voxels of the leaf with origin `o` that lie in the inclusive voxel box [lo, hi].
pub fn leaf_box_mask(o: VoxelCoord, lo: VoxelCoord, hi: VoxelCoord) -> Mask512 {
    // Per axis, the in-leaf coordinates inside the box as 8 bits.
    let axis = |o: i32, lo: i32, hi: i32| -> u64 {
        let a = (i64::from(lo) - i64::from(o)).clamp(0, 8);
        let b = (i64::from(hi) - i64::from(o) + 1).clamp(0, 8);
        if a >= b {
            0
        } else {
            (1 << b) - (1 << a)
        }
    };
    let (mx, my, mz) = (
        axis(o.x, lo.x, hi.x),
        axis(o.y, lo.y, hi.y),
        axis(o.z, lo.z, hi.z),
    );
    // Word z holds the slice at that z, bit x | y << 3.
    let slice = (0..8)
        .filter(|y| my >> y & 1 != 0)
        .fold(0u64, |s, y| s | mx << (8 * y));
    Mask512 {
        words: std::array::from_fn(|z| if mz >> z & 1 != 0 { slice } else { 0 }),
    }
}

/// Voxel at in-leaf offset `i` of the leaf with origin `o`.
#[inline]
pub fn voxel_at(o: VoxelCoord, i: usize) -> VoxelCoord {
    let i = i as i32;
    VoxelCoord::new(o.x + (i & 7), o.y + (i >> 3 & 7), o.z + (i >> 6))
}

/// The occupancy of one 8x8x8 leaf as two masks: which voxels are known, and which of
/// those are occupied. What exporters and renderers read, from a map or a snapshot alike.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LeafOccupancy {
    pub origin: VoxelCoord,
    pub known: Mask512,
    /// A subset of `known`.
    pub occupied: Mask512,
}

/// An 8x8x8 block of voxels: a value per voxel, which of them are active, and which of
/// those the grid's owner marks.
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Zeroable)]
#[repr(C)]
pub struct Leaf<V> {
    pub active: Mask512,
    /// A subset of `active` that the grid's owner keeps in step with the values; the grid
    /// itself never writes it. An occupancy map marks its occupied voxels
    /// (the map crate's `OccupancyMap`), so that readers of occupancy (snapshots, counts)
    /// read two masks per leaf, not its 512 values.
    pub marked: Mask512,
    pub values: [V; LEAF_VOXELS],
}

impl<V: Copy> Leaf<V> {
    /// Ask the CPU to start loading the leaf's two masks into cache, for a loop that reads
    /// them a few iterations later, so that the leaves' cache misses overlap rather than
    /// come one after another (see the snapshot encoder's `PREFETCH_AHEAD`). Only speed
    /// changes.
    #[inline]
    pub fn prefetch_masks(&self) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let base = std::ptr::from_ref(self).cast::<i8>();
            // The last byte too: a leaf from the allocator (a small map's first chunk) may
            // start inside a cache line, and its masks then span three.
            const MASKS: usize = 2 * std::mem::size_of::<Mask512>();
            for at in (0..MASKS).step_by(64).chain([MASKS - 1]) {
                // SAFETY: `_mm_prefetch` needs SSE, which every x86_64 CPU has; a prefetch
                // reads nothing into the program and cannot fault, and `at` is inside the
                // leaf (the masks come first, `repr(C)`).
                unsafe { _mm_prefetch::<_MM_HINT_T0>(base.add(at)) };
            }
        }
    }

    #[inline]
    pub fn get(&self, i: usize) -> Option<V> {
        self.active.get(i).then(|| self.values[i])
    }
}
