//! Ray making on AVX2: four points at a time, bit for bit as [`RayMaker::make`].

use super::{Ray, RayMaker, SKIPPED};
use std::arch::x86_64::*;

/// `out[i] = m.make(&pts[i])` for four points at a time, with `make`'s f64 operations in
/// its order (so bit for bit the same rays; no FMA, which would round differently);
/// returns how many it made, a multiple of four. The rest is left to the caller.
#[target_feature(enable = "avx2")]
pub(super) fn make_rays(m: &RayMaker, out: &mut [Ray], pts: &[[f32; 3]]) -> usize {
    let n = out.len().min(pts.len()) / 4 * 4;
    let zero = _mm256_setzero_pd();
    let sign = _mm256_set1_pd(-0.0);
    let res = _mm256_set1_pd(m.tf.resolution());
    let snap = _mm256_set1_pd(crate::coord::FACE_SNAP);
    let range = _mm256_set1_pd(m.range_units);
    let surely_in = _mm256_set1_pd(m.surely_in);
    let origin = m.origin.map(|c| _mm256_set1_pd(c));
    let rot = m.rot.map(|r| r.map(|c| _mm256_set1_pd(c)));
    let t = m.t.map(|c| _mm256_set1_pd(c));
    // Coordinate `a` of point `j` of four is f32 number `3 j + a`.
    let idx = _mm_setr_epi32(0, 3, 6, 9);
    let mask = |v: __m256d| _mm256_movemask_pd(v) as u32;
    for (o4, p4) in out[..n].chunks_exact_mut(4).zip(pts[..n].chunks_exact(4)) {
        let [x, y, z] = [0, 1, 2].map(|a| {
            // SAFETY: `p4` is four points, 12 f32s; the indices are 3 j + a < 12.
            let f = unsafe { _mm_i32gather_ps::<4>(p4.as_ptr().cast::<f32>().add(a), idx) };
            _mm256_cvtps_pd(f)
        });
        // Finite iff c - c is 0 (NaN otherwise).
        let finite = [x, y, z]
            .map(|c| mask(_mm256_cmp_pd::<_CMP_EQ_OQ>(_mm256_sub_pd(c, c), zero)))
            .into_iter()
            .fold(0b1111, |a, b| a & b);
        let mut e = [0, 1, 2].map(|i| {
            let r = rot[i];
            let w = _mm256_add_pd(
                _mm256_add_pd(
                    _mm256_add_pd(_mm256_mul_pd(r[0], x), _mm256_mul_pd(r[1], y)),
                    _mm256_mul_pd(r[2], z),
                ),
                t[i],
            );
            // `GridTransform::to_units`.
            let k = _mm256_div_pd(w, res);
            let near = _mm256_round_pd::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(k);
            let off = _mm256_andnot_pd(sign, _mm256_sub_pd(k, near));
            _mm256_blendv_pd(k, near, _mm256_cmp_pd::<_CMP_LE_OQ>(off, snap))
        });
        let d = [0, 1, 2].map(|a| _mm256_sub_pd(e[a], origin[a]));
        let len2 = _mm256_add_pd(
            _mm256_add_pd(_mm256_mul_pd(d[0], d[0]), _mm256_mul_pd(d[1], d[1])),
            _mm256_mul_pd(d[2], d[2]),
        );
        let len = _mm256_sqrt_pd(len2);
        let hit = mask(_mm256_or_pd(
            _mm256_cmp_pd::<_CMP_LT_OQ>(len2, surely_in),
            _mm256_cmp_pd::<_CMP_LE_OQ>(len, range),
        ));
        let cut = finite & !hit;
        if cut != 0 {
            let s = _mm256_div_pd(range, len);
            let cut_v = _mm256_castsi256_pd(_mm256_setr_epi64x(
                -i64::from(cut & 1),
                -i64::from(cut >> 1 & 1),
                -i64::from(cut >> 2 & 1),
                -i64::from(cut >> 3 & 1),
            ));
            for a in 0..3 {
                let c = _mm256_add_pd(origin[a], _mm256_mul_pd(d[a], s));
                e[a] = _mm256_blendv_pd(e[a], c, cut_v);
            }
        }
        let e = e.map(|v| {
            let mut a = [0.0f64; 4];
            // SAFETY: `a` is 32 writable bytes; the store has no alignment requirement.
            unsafe { _mm256_storeu_pd(a.as_mut_ptr(), v) };
            a
        });
        for (j, r) in o4.iter_mut().enumerate() {
            *r = if finite >> j & 1 == 0 {
                Ray::new([0.0; 3], SKIPPED, false)
            } else {
                Ray::new([e[0][j], e[1][j], e[2][j]], 0, hit >> j & 1 != 0)
            };
        }
    }
    n
}
