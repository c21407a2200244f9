//! Phase 4, update: one log-odds observation per touched voxel from its final marks, hit
//! beating free, leaf by leaf in parallel ([`observe_leaf`]); 64 voxels at once with AVX-512BW, 32
//! with AVX2.

use super::marks::Slot;
use crate::grid::Leaf;
use crate::mask::BitIter;
use crate::model::QuantizedModel;

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2;
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512;

/// One observation for each of the 64 voxels of `values` whose bit is set in `any`, a hit
/// where set in `hit` too; returns those of them now at or above the occupancy threshold.
/// `FRESH`: the values are all zero, and are not read (see [`observe_leaf`]).
pub(crate) trait Observe {
    fn observe<const FRESH: bool>(
        values: &mut [i8; 64],
        any: u64,
        hit: u64,
        q: &QuantizedModel,
    ) -> u64;
}

/// [`Observe`] one set bit at a time.
pub(crate) struct Scalar;

impl Observe for Scalar {
    #[inline(always)]
    fn observe<const FRESH: bool>(
        values: &mut [i8; 64],
        any: u64,
        hit: u64,
        q: &QuantizedModel,
    ) -> u64 {
        observe_scalar::<FRESH>(values, any, hit, q)
    }
}

/// Observe one leaf's marks (its slot) into the map's leaf, leaving the slot zero ([`Slot::take`]), with
/// observations by `O`; returns the voxels updated. Each kernel's entry in the
/// [`crate::kernel::Kernels`] table is this function compiled for its features, so that
/// the kernel's observation inlines into the loop.
///
/// `fresh`: the leaf was created by this frame's merge, so it is all zero and may sit on a
/// page never touched. Such a leaf is only written, never read: a page first touched by a
/// read is mapped to the shared zero page, and the first write then copies it with a TLB
/// flush that interrupts every other core running the process (a fifth of a 60 m frame's
/// time with 2 threads). Written first, it gets a private page at once.
#[inline(always)]
pub(crate) fn observe_leaf<O: Observe>(
    leaf: &mut Leaf<i8>,
    slot: &Slot,
    q: &QuantizedModel,
    fresh: bool,
) -> u64 {
    let mut n = 0;
    for w in 0..8 {
        let (free, hit) = slot.take(w);
        let any = free | hit;
        if any == 0 {
            continue;
        }
        n += u64::from(any.count_ones());
        let values: &mut [i8; 64] = (&mut leaf.values[w * 64..][..64])
            .try_into()
            .expect("64 values");
        // Separate calls, not a select on `fresh`: the compiler may load both sides of a
        // select, and that load is the read this avoids.
        if fresh {
            leaf.active.words[w] = any;
            leaf.marked.words[w] = O::observe::<true>(values, any, hit, q);
        } else {
            leaf.active.words[w] |= any;
            let occupied = O::observe::<false>(values, any, hit, q);
            leaf.marked.words[w] = leaf.marked.words[w] & !any | occupied;
        }
    }
    n
}

/// One observation for each of the 64 voxels of `values` whose bit is set in `any`, a hit
/// where set in `hit` too; returns those of them now at or above the occupancy threshold.
/// `FRESH`: the values are all zero, and are not read (see [`observe_leaf`]). `avx512::observe`
/// does the same in one masked add.
#[inline]
pub(super) fn observe_scalar<const FRESH: bool>(
    values: &mut [i8; 64],
    any: u64,
    hit: u64,
    q: &QuantizedModel,
) -> u64 {
    let mut occupied = 0;
    for b in BitIter(any) {
        let old = if FRESH { 0 } else { values[b] };
        values[b] = q.update(old, hit >> b & 1 != 0);
        occupied |= u64::from(values[b] >= q.threshold) << b;
    }
    occupied
}
