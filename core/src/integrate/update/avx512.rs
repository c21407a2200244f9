//! The update's observation on AVX-512BW: a leaf word's 64 voxels at once.

use crate::model::QuantizedModel;
use std::arch::x86_64::*;

/// `super::observe` in one masked saturating add, clamp, store and compare: the 64 values
/// of a leaf word take their observation at once instead of one set bit at a time. The
/// same values and marks:
/// an i8 add saturates only beyond the clamps, which are within i8. Random 500k 60 m, 2
/// threads, update phase: see `docs/design.md` ("One byte per voxel").
#[cfg(target_feature = "avx512bw")]
#[inline]
pub(in crate::integrate) fn observe<const FRESH: bool>(
    values: &mut [i8; 64],
    any: u64,
    hit: u64,
    q: &QuantizedModel,
) -> u64 {
    // SAFETY: this module is only compiled where the build enables AVX-512F (and DQ) for
    // the whole crate, and this function where it enables BW too.
    unsafe { observe_impl::<FRESH>(values, any, hit, q) }
}

#[cfg(target_feature = "avx512bw")]
#[target_feature(enable = "avx512f,avx512bw")]
fn observe_impl<const FRESH: bool>(
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
