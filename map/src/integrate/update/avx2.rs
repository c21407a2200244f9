//! The update on AVX2: a leaf word's 64 voxels observed 32 at a time.

use super::{observe_leaf as observe_leaf_with, Observe};
use crate::grid::Leaf;
use crate::integrate::marks::Slot;
use crate::model::QuantizedModel;
use std::arch::x86_64::*;

/// [`super::observe_leaf`] with [`Avx2`] observations.
#[target_feature(enable = "avx2")]
pub(crate) fn observe_leaf(
    leaf: &mut Leaf<i8>,
    slot: &Slot,
    q: &QuantizedModel,
    fresh: bool,
) -> u64 {
    observe_leaf_with::<Avx2>(leaf, slot, q, fresh)
}

/// [`Observe`] with byte vectors: AVX2 has no byte-masked store, so each half of the word
/// is blended (the observed bytes new, the others as they were, or zero when `FRESH`, which
/// they are) and stored whole, both sides whatever their bits: which half of a plane a
/// ray crosses is a coin toss to the branch predictor. The same values and marks as one
/// at a time: an i8 add saturates only beyond the clamps, which are within i8.
pub(crate) struct Avx2;

impl Observe for Avx2 {
    #[inline(always)]
    fn observe<const FRESH: bool>(
        values: &mut [i8; 64],
        any: u64,
        hit: u64,
        q: &QuantizedModel,
    ) -> u64 {
        // SAFETY: these observations are only made inside `observe_leaf` above (which
        // enables AVX2, and is only called from the AVX2 table, given only where the CPU has
        // them: `Kernel::table`) and by the tests, after checking `Kernel::supported`.
        unsafe { observe::<FRESH>(values, any, hit, q) }
    }
}

/// Byte `i` all ones where bit `i` of `bits` is set.
#[inline]
#[target_feature(enable = "avx2")]
fn bytes_of(bits: u32) -> __m256i {
    let v = _mm256_set1_epi32(bits as i32);
    // Bytes 0-7 take byte 0 of `bits`, 8-15 byte 1, and so on (per 128-bit half).
    let spread = _mm256_setr_epi8(
        0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2, 2, 2, 3, 3, 3, 3, 3, 3,
        3, 3,
    );
    let bit = _mm256_set1_epi64x(0x8040_2010_0804_0201_u64 as i64);
    let b = _mm256_and_si256(_mm256_shuffle_epi8(v, spread), bit);
    _mm256_cmpeq_epi8(b, bit)
}

/// # Safety
/// The CPU must have AVX2.
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn observe<const FRESH: bool>(
    values: &mut [i8; 64],
    any: u64,
    hit: u64,
    q: &QuantizedModel,
) -> u64 {
    let (miss_d, hit_d) = (_mm256_set1_epi8(q.miss), _mm256_set1_epi8(q.hit));
    let (lo, hi) = (_mm256_set1_epi8(q.min), _mm256_set1_epi8(q.max));
    let threshold = _mm256_set1_epi8(q.threshold);
    let mut occupied = 0u64;
    for half in 0..2 {
        let at = values[32 * half..].as_mut_ptr();
        let shift = 32 * half as u32;
        let (any_h, hit_h) = ((any >> shift) as u32, (hit >> shift) as u32);
        let delta = _mm256_blendv_epi8(miss_d, hit_d, bytes_of(hit_h));
        let old = if FRESH {
            _mm256_setzero_si256()
        } else {
            // SAFETY: reads 32 bytes of `values` from `32 * half`.
            unsafe { _mm256_loadu_si256(at.cast()) }
        };
        let new = _mm256_max_epi8(_mm256_min_epi8(_mm256_adds_epi8(old, delta), hi), lo);
        let new = _mm256_blendv_epi8(old, new, bytes_of(any_h));
        // SAFETY: writes 32 bytes of `values` from `32 * half`.
        unsafe { _mm256_storeu_si256(at.cast(), new) };
        // new >= threshold, as not threshold > new.
        let below = _mm256_movemask_epi8(_mm256_cmpgt_epi8(threshold, new)) as u32;
        occupied |= u64::from(!below & any_h) << shift;
    }
    occupied
}
