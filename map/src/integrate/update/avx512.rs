//! The update on AVX-512BW: a leaf word's 64 voxels observed at once.

use super::{observe_leaf as observe_leaf_with, Observe};
use crate::grid::Leaf;
use crate::integrate::marks::Slot;
use crate::model::QuantizedModel;
use std::arch::x86_64::*;

/// [`super::observe_leaf`] with [`Avx512`] observations.
#[target_feature(enable = "avx512f,avx512dq,avx512bw")]
pub(crate) fn observe_leaf(
    leaf: &mut Leaf<i8>,
    slot: &Slot,
    q: &QuantizedModel,
    fresh: bool,
) -> u64 {
    observe_leaf_with::<Avx512>(leaf, slot, q, fresh)
}

/// [`Observe`] in one masked saturating add, clamp, store and compare: the 64 values of a
/// leaf word take their observation at once instead of one set bit at a time. The same
/// values and marks: an i8 add saturates only beyond the clamps, which are within i8.
/// Random 500k 60 m, 2 threads, update phase: see `docs/design.md` ("One byte per voxel").
pub(crate) struct Avx512;

impl Observe for Avx512 {
    #[inline(always)]
    fn observe<const FRESH: bool>(
        values: &mut [i8; 64],
        any: u64,
        hit: u64,
        q: &QuantizedModel,
    ) -> u64 {
        // SAFETY: these observations are only made inside `observe_leaf` above (which
        // enables AVX-512F and BW, and is only called from the AVX-512 table, given only
        // where the CPU has them: `Kernel::table`) and by the tests, after checking
        // `Kernel::supported`.
        unsafe { observe::<FRESH>(values, any, hit, q) }
    }
}

/// # Safety
/// The CPU must have AVX-512F and BW.
#[target_feature(enable = "avx512f,avx512bw")]
pub(crate) unsafe fn observe<const FRESH: bool>(
    values: &mut [i8; 64],
    any: u64,
    hit: u64,
    q: &QuantizedModel,
) -> u64 {
    let delta = _mm512_mask_blend_epi8(hit, _mm512_set1_epi8(q.miss), _mm512_set1_epi8(q.hit));
    let old = if FRESH {
        _mm512_setzero_si512()
    } else {
        // SAFETY: reads the 64 bytes of `values`.
        unsafe { _mm512_loadu_si512(values.as_ptr().cast()) }
    };
    let new = _mm512_max_epi8(
        _mm512_min_epi8(_mm512_adds_epi8(old, delta), _mm512_set1_epi8(q.max)),
        _mm512_set1_epi8(q.min),
    );
    // SAFETY: writes bytes of `values` only, those whose bit is set in `any`.
    unsafe { _mm512_mask_storeu_epi8(values.as_mut_ptr(), any, new) };
    _mm512_mask_cmpge_epi8_mask(any, new, _mm512_set1_epi8(q.threshold))
}
