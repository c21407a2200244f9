//! Ray making on AVX2: four points at a time, bit for bit as [`RayMaker::make`]; and the
//! extent of rays, bit for bit as [`ExtentSum::of`].

use super::{ExtentSum, Ray, RayMaker, SKIPPED};
use std::arch::x86_64::*;

/// `out[i] = m.make(&pts[i])` for four points at a time, with `make`'s f64 operations in
/// its order (so bit for bit the same rays; no FMA, which would round differently);
/// returns how many it made, a multiple of four. The rest is left to the caller.
#[target_feature(enable = "avx2")]
pub(super) fn make_rays(m: &RayMaker, out: &mut [Ray], pts: &[[f32; 3]]) -> usize {
    let n = out.len().min(pts.len()) / 4 * 4;
    let zero = _mm256_setzero_pd();
    let mask = |v: __m256d| _mm256_movemask_pd(v) as u32;
    let sign = _mm256_set1_pd(-0.0);
    let res = _mm256_set1_pd(m.tf.resolution());
    let snap = _mm256_set1_pd(crate::coord::FACE_SNAP);
    let range = _mm256_set1_pd(m.range_units);
    let surely_in = _mm256_set1_pd(m.surely_in);
    let origin = m.origin.map(|c| _mm256_set1_pd(c));
    let rot = m.rot.map(|r| r.map(|c| _mm256_set1_pd(c)));
    let t = m.t.map(|c| _mm256_set1_pd(c));
    for (o4, p4) in out[..n].chunks_exact_mut(4).zip(pts[..n].chunks_exact(4)) {
        let [x, y, z] = deinterleave(p4).map(|c| _mm256_cvtps_pd(c));
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

/// Four points' x, y and z, each as four floats: three loads and nine shuffles (three
/// gathers were slower on AMD Zen 5).
#[inline]
#[target_feature(enable = "avx2")]
fn deinterleave(p4: &[[f32; 3]]) -> [__m128; 3] {
    assert_eq!(p4.len(), 4);
    let f = p4.as_ptr().cast::<f32>();
    // SAFETY: four points are 12 f32s: the loads read f32s 0-3, 4-7 and 8-11.
    let (a, b, c) = unsafe {
        (
            _mm_loadu_ps(f),
            _mm_loadu_ps(f.add(4)),
            _mm_loadu_ps(f.add(8)),
        )
    };
    // a = x0 y0 z0 x1, b = y1 z1 x2 y2, c = z2 x3 y3 z3.
    let x = _mm_blend_ps::<0b0010>(_mm_blend_ps::<0b0100>(a, b), c); // x0 x3 x2 x1
    let y = _mm_blend_ps::<0b0100>(_mm_blend_ps::<0b1001>(a, b), c); // y1 y0 y3 y2
    let z = _mm_blend_ps::<0b1001>(_mm_blend_ps::<0b0010>(a, b), c); // z2 z1 z0 z3
    [
        _mm_permute_ps::<0b01_10_11_00>(x),
        _mm_permute_ps::<0b10_11_00_01>(y),
        _mm_permute_ps::<0b11_00_01_10>(z),
    ]
}

/// [`ExtentSum::of`] on AVX2, bit for bit: the same two sums over alternate rays, with a
/// sum's three axes in the lanes of one vector (the fourth lane, the key and hit flag
/// read as a float, is ignored).
#[target_feature(enable = "avx2")]
pub(super) fn extent_of(origin: [f64; 3], rays: &[Ray]) -> ExtentSum {
    struct Acc {
        lo: __m256d,
        hi: __m256d,
        len: __m256d,
        cut: u64,
        skipped: u64,
    }
    let o = _mm256_setr_pd(origin[0], origin[1], origin[2], 0.0);
    let sign = _mm256_set1_pd(-0.0);
    let new = || Acc {
        lo: o,
        hi: o,
        len: _mm256_setzero_pd(),
        cut: 0,
        skipped: 0,
    };
    let add = |s: &mut Acc, r: &Ray| {
        if r.key == SKIPPED {
            s.skipped += 1;
            return;
        }
        // SAFETY: a `repr(C)` ray is 32 initialised bytes, the end first.
        let v = unsafe { _mm256_loadu_pd(std::ptr::from_ref(r).cast::<f64>()) };
        s.lo = _mm256_min_pd(s.lo, v);
        s.hi = _mm256_max_pd(s.hi, v);
        s.len = _mm256_add_pd(s.len, _mm256_andnot_pd(sign, _mm256_sub_pd(v, o)));
        s.cut += u64::from(!r.hit);
    };
    let (mut even, mut odd) = (new(), new());
    let mut pairs = rays.chunks_exact(2);
    for p in &mut pairs {
        add(&mut even, &p[0]);
        add(&mut odd, &p[1]);
    }
    pairs.remainder().iter().for_each(|r| add(&mut even, r));
    let out = |s: Acc| {
        let lanes = |v: __m256d| {
            let mut a = [0.0f64; 4];
            // SAFETY: `a` is 32 writable bytes; the store has no alignment requirement.
            unsafe { _mm256_storeu_pd(a.as_mut_ptr(), v) };
            [a[0], a[1], a[2]]
        };
        ExtentSum {
            origin,
            lo: lanes(s.lo),
            hi: lanes(s.hi),
            cut: s.cut,
            length: lanes(s.len),
            skipped: s.skipped,
        }
    };
    ExtentSum::join(out(even), out(odd))
}
