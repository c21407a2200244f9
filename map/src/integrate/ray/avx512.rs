//! Ray making on AVX-512: eight points at a time, bit for bit as [`RayMaker::make`].

use super::{Ray, RayMaker, SKIPPED};
use std::arch::x86_64::*;

/// `out[i] = m.make(&pts[i])` for eight points at a time, with `make`'s f64 operations in
/// its order (so bit for bit the same rays); returns how many it made, a multiple of eight.
/// The rest is left to the caller. Making a ray is about 50 cycles of scalar code, three
/// divisions among them, and was most of the prepare phase.
#[target_feature(enable = "avx512f,avx512dq")]
pub(crate) fn make_rays(m: &RayMaker, out: &mut [Ray], pts: &[[f32; 3]]) -> usize {
    let n = out.len().min(pts.len()) / 8 * 8;
    let zero = _mm512_setzero_pd();
    let res = _mm512_set1_pd(m.tf.resolution());
    let snap = _mm512_set1_pd(crate::coord::FACE_SNAP);
    let range = _mm512_set1_pd(m.range_units);
    let surely_in = _mm512_set1_pd(m.surely_in);
    let origin = m.origin.map(|c| _mm512_set1_pd(c));
    let rot = m.rot.map(|r| r.map(|c| _mm512_set1_pd(c)));
    let t = m.t.map(|c| _mm512_set1_pd(c));
    // Coordinate `a` of point `j` of eight is f32 number `3 j + a`.
    let idx = _mm256_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21);
    for (o8, p8) in out[..n].chunks_exact_mut(8).zip(pts[..n].chunks_exact(8)) {
        let [x, y, z] = [0, 1, 2].map(|a| {
            // SAFETY: `p8` is eight points, 24 f32s; the indices are 3 j + a < 24.
            let f = unsafe { _mm256_i32gather_ps::<4>(p8.as_ptr().cast::<f32>().add(a), idx) };
            _mm512_cvtps_pd(f)
        });
        // Finite iff c - c is 0 (NaN otherwise).
        let finite = [x, y, z]
            .map(|c| _mm512_cmp_pd_mask::<_CMP_EQ_OQ>(_mm512_sub_pd(c, c), zero))
            .into_iter()
            .fold(0xff, |a, b| a & b);
        let mut e = [0, 1, 2].map(|i| {
            let r = rot[i];
            let w = _mm512_add_pd(
                _mm512_add_pd(
                    _mm512_add_pd(_mm512_mul_pd(r[0], x), _mm512_mul_pd(r[1], y)),
                    _mm512_mul_pd(r[2], z),
                ),
                t[i],
            );
            // `GridTransform::to_units`.
            let k = _mm512_div_pd(w, res);
            let near = _mm512_roundscale_pd::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(k);
            let off = _mm512_abs_pd(_mm512_sub_pd(k, near));
            _mm512_mask_blend_pd(_mm512_cmp_pd_mask::<_CMP_LE_OQ>(off, snap), k, near)
        });
        let d = [0, 1, 2].map(|a| _mm512_sub_pd(e[a], origin[a]));
        let len2 = _mm512_add_pd(
            _mm512_add_pd(_mm512_mul_pd(d[0], d[0]), _mm512_mul_pd(d[1], d[1])),
            _mm512_mul_pd(d[2], d[2]),
        );
        let len = _mm512_sqrt_pd(len2);
        let hit = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(len2, surely_in)
            | _mm512_cmp_pd_mask::<_CMP_LE_OQ>(len, range);
        let cut = finite & !hit;
        if cut != 0 {
            let s = _mm512_div_pd(range, len);
            for a in 0..3 {
                let c = _mm512_add_pd(origin[a], _mm512_mul_pd(d[a], s));
                e[a] = _mm512_mask_blend_pd(cut, e[a], c);
            }
        }
        let e = e.map(|v| {
            let mut a = [0.0f64; 8];
            // SAFETY: `a` is 64 writable bytes; the store has no alignment requirement.
            unsafe { _mm512_storeu_pd(a.as_mut_ptr(), v) };
            a
        });
        for (j, r) in o8.iter_mut().enumerate() {
            *r = if finite >> j & 1 == 0 {
                Ray::new([0.0; 3], SKIPPED, false)
            } else {
                Ray::new([e[0][j], e[1][j], e[2][j]], 0, hit >> j & 1 != 0)
            };
        }
    }
    n
}
