//! Ray making on AVX2: four points at a time, bit for bit as [`RayMaker::make`]; the
//! extent of rays, bit for bit as [`ExtentSum::of_scalar`]; and both with the layout by sides in
//! one pass, bit for bit as [`Sides::make`](super::Sides::make).

use super::{ChunkOrder, ExtentSum, Ray, RayMaker, Sides, RAY_CHUNK, SKIPPED};
use std::arch::x86_64::*;

/// The pose, grid and range of a [`RayMaker`] in vectors, to make four rays at a time.
pub(crate) struct RayMaker4 {
    res: __m256d,
    snap: __m256d,
    range: __m256d,
    surely_in: __m256d,
    origin: [__m256d; 3],
    rot: [[__m256d; 3]; 3],
    t: [__m256d; 3],
}

/// Four rays made: their ends per axis (lanes of a skipped point's are not ends), which
/// are finite points and which hit (bit `j` for lane `j`).
pub(crate) struct Rays4 {
    e: [__m256d; 3],
    finite: u32,
    hit: u32,
}

#[inline]
#[target_feature(enable = "avx2")]
fn mask(v: __m256d) -> u32 {
    _mm256_movemask_pd(v) as u32
}

impl RayMaker4 {
    #[target_feature(enable = "avx2")]
    pub(crate) fn new(m: &RayMaker) -> Self {
        RayMaker4 {
            res: _mm256_set1_pd(m.tf.resolution()),
            snap: _mm256_set1_pd(crate::coord::FACE_SNAP),
            range: _mm256_set1_pd(m.range_units),
            surely_in: _mm256_set1_pd(m.surely_in),
            origin: m.origin.map(|c| _mm256_set1_pd(c)),
            rot: m.rot.map(|r| r.map(|c| _mm256_set1_pd(c))),
            t: m.t.map(|c| _mm256_set1_pd(c)),
        }
    }

    /// The rays to four points, with `make`'s f64 operations in its order (so bit for bit
    /// the same rays; no FMA, which would round differently).
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) fn make(&self, p4: &[[f32; 3]]) -> Rays4 {
        let zero = _mm256_setzero_pd();
        let sign = _mm256_set1_pd(-0.0);
        let [x, y, z] = deinterleave(p4).map(|c| _mm256_cvtps_pd(c));
        // Finite iff c - c is 0 (NaN otherwise).
        let finite = [x, y, z]
            .map(|c| mask(_mm256_cmp_pd::<_CMP_EQ_OQ>(_mm256_sub_pd(c, c), zero)))
            .into_iter()
            .fold(0b1111, |a, b| a & b);
        let mut e = [0, 1, 2].map(|i| {
            let r = self.rot[i];
            let w = _mm256_add_pd(
                _mm256_add_pd(
                    _mm256_add_pd(_mm256_mul_pd(r[0], x), _mm256_mul_pd(r[1], y)),
                    _mm256_mul_pd(r[2], z),
                ),
                self.t[i],
            );
            // `GridTransform::to_units`.
            let k = _mm256_div_pd(w, self.res);
            let near = _mm256_round_pd::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(k);
            let off = _mm256_andnot_pd(sign, _mm256_sub_pd(k, near));
            _mm256_blendv_pd(k, near, _mm256_cmp_pd::<_CMP_LE_OQ>(off, self.snap))
        });
        let d = [0, 1, 2].map(|a| _mm256_sub_pd(e[a], self.origin[a]));
        let len2 = _mm256_add_pd(
            _mm256_add_pd(_mm256_mul_pd(d[0], d[0]), _mm256_mul_pd(d[1], d[1])),
            _mm256_mul_pd(d[2], d[2]),
        );
        let surely = mask(_mm256_cmp_pd::<_CMP_LT_OQ>(len2, self.surely_in));
        // The square root only where a lane may end beyond max range: in most frames
        // rarely, and it is the slowest instruction here.
        if surely == 0b1111 {
            return Rays4 {
                e,
                finite,
                hit: surely,
            };
        }
        let len = _mm256_sqrt_pd(len2);
        let hit = surely | mask(_mm256_cmp_pd::<_CMP_LE_OQ>(len, self.range));
        let cut = finite & !hit;
        if cut != 0 {
            let s = _mm256_div_pd(self.range, len);
            let cut_v = _mm256_castsi256_pd(lanes(cut));
            for a in 0..3 {
                let c = _mm256_add_pd(self.origin[a], _mm256_mul_pd(d[a], s));
                e[a] = _mm256_blendv_pd(e[a], c, cut_v);
            }
        }
        Rays4 { e, finite, hit }
    }
}

/// All ones in lane `j` where bit `j` of `bits` is set, else zeros.
#[inline]
#[target_feature(enable = "avx2")]
fn lanes(bits: u32) -> __m256i {
    let lane = |j: u32| -i64::from(bits >> j & 1);
    _mm256_setr_epi64x(lane(0), lane(1), lane(2), lane(3))
}

/// `out[i] = m.make(&pts[i])` for four points at a time; returns how many it made, a
/// multiple of four. The rest is left to the caller.
#[target_feature(enable = "avx2")]
pub(crate) fn make_rays(m: &RayMaker, out: &mut [Ray], pts: &[[f32; 3]]) -> usize {
    let n = out.len().min(pts.len()) / 4 * 4;
    let maker = RayMaker4::new(m);
    for (o4, p4) in out[..n].chunks_exact_mut(4).zip(pts[..n].chunks_exact(4)) {
        store4(o4, maker.make(p4).rays());
    }
    n
}

/// Four rays whole (as [`Rays4::rays`] gives them) into `o4`, one store each.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn store4(o4: &mut [Ray], rays: [__m256d; 4]) {
    assert_eq!(o4.len(), 4);
    let p = o4.as_mut_ptr().cast::<f64>();
    for (j, r) in rays.into_iter().enumerate() {
        // SAFETY: `o4` is four `repr(C)` rays of 32 bytes, end first: store `j` writes ray
        // `j` whole, all of its fields valid values (`Rays4::rays`).
        unsafe { _mm256_store_pd(p.add(4 * j), r) };
    }
}

impl Rays4 {
    /// The four rays whole, as `Ray::new` lays them out, a vector each: lane `j`'s end
    /// with key 0 and its hit flag, or a skipped point's ray (end 0, key `SKIPPED`, no
    /// hit).
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) fn rays(&self) -> [__m256d; 4] {
        transpose4(self.lanes())
    }

    /// [`Self::rays`] as lanes: their x, y and z, and the word after the end (key in the
    /// low 32 bits, hit flag in the next byte, padding 0).
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) fn lanes(&self) -> [__m256d; 4] {
        const _: () = assert!(std::mem::size_of::<Ray>() == 32 && SKIPPED == u32::MAX);
        let ok = _mm256_castsi256_pd(lanes(self.finite));
        let word = |j: u32| {
            if self.finite >> j & 1 == 0 {
                i64::from(SKIPPED)
            } else {
                i64::from(self.hit >> j & 1) << 32
            }
        };
        let w = _mm256_castsi256_pd(_mm256_setr_epi64x(word(0), word(1), word(2), word(3)));
        let [x, y, z] = self.e.map(|v| _mm256_and_pd(v, ok));
        [x, y, z, w]
    }

    /// Add the four rays (`rays`, as [`Self::rays`] gives them) to `sums`, ray `j` to sum
    /// `j % 2`, as [`extent_of`] adds rays in scan order to its two sums.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) fn sum_into(&self, sums: &mut [ExtentSum4; 2], rays: &[__m256d; 4]) {
        for (j, &r) in rays.iter().enumerate() {
            let sum = &mut sums[j % 2];
            if self.finite >> j & 1 == 0 {
                sum.skipped += 1;
            } else {
                sum.add(r, self.hit >> j & 1 != 0);
            }
        }
    }
}

/// The plane of a [`Sides`] in vectors, to tell for four ends at a time which lie behind
/// it.
pub(crate) struct Sides4 {
    o: [__m256d; 3],
    axis: [__m256d; 3],
}

impl Sides4 {
    #[target_feature(enable = "avx2")]
    pub(crate) fn new(sides: &Sides) -> Self {
        Sides4 {
            o: sides.origin.map(|c| _mm256_set1_pd(c)),
            axis: sides.axis.unwrap_or([0.0; 3]).map(|c| _mm256_set1_pd(c)),
        }
    }

    /// All ones in the lanes of the ends `e` behind the plane:
    /// (d0 * x0 + d1 * x1) + d2 * x2 < 0, as `Sides::behind` computes it.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) fn behind(&self, e: [__m256d; 3]) -> __m256d {
        let d = [0, 1, 2].map(|a| _mm256_sub_pd(e[a], self.o[a]));
        let dot = _mm256_add_pd(
            _mm256_add_pd(
                _mm256_mul_pd(d[0], self.axis[0]),
                _mm256_mul_pd(d[1], self.axis[1]),
            ),
            _mm256_mul_pd(d[2], self.axis[2]),
        );
        _mm256_cmp_pd::<_CMP_LT_OQ>(dot, _mm256_setzero_pd())
    }
}

/// A ray whole in one vector: its x, y and z, and the word of key (bits 0-31) and hit
/// flag (bit 32).
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn load_ray(r: &Ray) -> __m256d {
    const _: () = assert!(std::mem::size_of::<Ray>() == 32);
    // SAFETY: a `repr(C)` ray is 32 bytes, every byte initialised (explicit padding), the
    // end first.
    unsafe { _mm256_load_pd(std::ptr::from_ref(r).cast::<f64>()) }
}

/// The 4 x 4 doubles `rows` transposed: lane `j` of vector `i` becomes lane `i` of vector
/// `j`. Four rays loaded whole become their x, y, z and words, and back.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn transpose4(rows: [__m256d; 4]) -> [__m256d; 4] {
    let [a, b, c, d] = rows;
    let (t0, t1) = (_mm256_unpacklo_pd(a, b), _mm256_unpackhi_pd(a, b)); // a0 b0 a2 b2, a1 b1 a3 b3
    let (t2, t3) = (_mm256_unpacklo_pd(c, d), _mm256_unpackhi_pd(c, d)); // c0 d0 c2 d2, c1 d1 c3 d3
    [
        _mm256_permute2f128_pd::<0x20>(t0, t2),
        _mm256_permute2f128_pd::<0x20>(t1, t3),
        _mm256_permute2f128_pd::<0x31>(t0, t2),
        _mm256_permute2f128_pd::<0x31>(t1, t3),
    ]
}

/// [`Sides::make`] without notes, in one pass, bit for bit: four rays made at a time,
/// each written straight to its place in `out` by the side [`Sides::behind`] computes
/// (its operations in its order), and their extent summed as [`ExtentSum::of_scalar`] sums the
/// rays in scan order. `None`, with nothing written, unless `pts` is a whole number of
/// fours as long as `out`.
#[target_feature(enable = "avx2")]
pub(crate) fn make_laid_out(
    m: &RayMaker,
    sides: &Sides,
    pts: &[[f32; 3]],
    out: &mut [Ray],
) -> Option<([u32; 2], ChunkOrder, ExtentSum)> {
    if !pts.len().is_multiple_of(4) || pts.len() != out.len() || out.len() > RAY_CHUNK {
        return None;
    }
    let maker = RayMaker4::new(m);
    let side = Sides4::new(sides);
    let mut sums = [ExtentSum4::new(sides.origin), ExtentSum4::new(sides.origin)];
    let (mut front, mut back) = (0, out.len());
    let mut order = ChunkOrder::default();
    for (q, p4) in pts.chunks_exact(4).enumerate() {
        let made = maker.make(p4);
        let behind = mask(side.behind(made.e)) & made.finite;
        let ahead = made.finite & !behind;
        let (w, b) = (4 * q / 64, 4 * q % 64);
        order.front[w] |= u64::from(ahead) << b;
        order.back[w] |= u64::from(behind) << b;
        let rays = made.rays();
        made.sum_into(&mut sums, &rays);
        for (j, r) in rays.into_iter().enumerate() {
            if made.finite >> j & 1 == 0 {
                continue;
            }
            let behind = behind >> j & 1 != 0;
            let place = if behind { back - 1 } else { front };
            front += usize::from(!behind);
            back -= usize::from(behind);
            // SAFETY: `place` is below `out.len()` (each ray made takes one place between
            // `front` and `back`); a ray is 32 bytes, `repr(C)`, end first, and `r` holds
            // one whole with valid fields (`Rays4::rays`).
            unsafe { _mm256_store_pd(out.as_mut_ptr().add(place).cast::<f64>(), r) };
        }
    }
    out[front..back].fill(Ray::new([0.0; 3], SKIPPED, false));
    let [even, odd] = sums.map(|s| s.sum());
    let counts = [front as u32, (out.len() - back) as u32];
    Some((counts, order, ExtentSum::join(even, odd)))
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

/// [`ExtentSum::of_scalar`] on AVX2, bit for bit: the same two sums over alternate rays
/// ([`ExtentSum4`]).
#[target_feature(enable = "avx2")]
pub(crate) fn extent_of(origin: [f64; 3], rays: &[Ray]) -> ExtentSum {
    let (mut even, mut odd) = (ExtentSum4::new(origin), ExtentSum4::new(origin));
    let add = |s: &mut ExtentSum4, r: &Ray| {
        if r.key == SKIPPED {
            s.skipped += 1;
            return;
        }
        s.add(load_ray(r), r.hit);
    };
    let mut pairs = rays.chunks_exact(2);
    for p in &mut pairs {
        add(&mut even, &p[0]);
        add(&mut odd, &p[1]);
    }
    pairs.remainder().iter().for_each(|r| add(&mut even, r));
    ExtentSum::join(even.sum(), odd.sum())
}

/// An [`ExtentSum`] being summed with a ray's three axes in the lanes of one vector (the
/// fourth lane, the key and hit flag read as a float, is ignored).
pub(crate) struct ExtentSum4 {
    origin: [f64; 3],
    o: __m256d,
    lo: __m256d,
    hi: __m256d,
    len: __m256d,
    cut: u64,
    skipped: u64,
}

impl ExtentSum4 {
    #[target_feature(enable = "avx2")]
    pub(crate) fn new(origin: [f64; 3]) -> Self {
        let o = _mm256_setr_pd(origin[0], origin[1], origin[2], 0.0);
        ExtentSum4 {
            origin,
            o,
            lo: o,
            hi: o,
            len: _mm256_setzero_pd(),
            cut: 0,
            skipped: 0,
        }
    }

    /// A ray (not a skipped point's) whose first 32 bytes are `v`.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) fn add(&mut self, v: __m256d, hit: bool) {
        let sign = _mm256_set1_pd(-0.0);
        self.lo = _mm256_min_pd(self.lo, v);
        self.hi = _mm256_max_pd(self.hi, v);
        self.len = _mm256_add_pd(self.len, _mm256_andnot_pd(sign, _mm256_sub_pd(v, self.o)));
        self.cut += u64::from(!hit);
    }

    #[target_feature(enable = "avx2")]
    pub(crate) fn sum(self) -> ExtentSum {
        let lanes = |v: __m256d| {
            let mut a = [0.0f64; 4];
            // SAFETY: `a` is 32 writable bytes; the store has no alignment requirement.
            unsafe { _mm256_storeu_pd(a.as_mut_ptr(), v) };
            [a[0], a[1], a[2]]
        };
        ExtentSum {
            origin: self.origin,
            lo: lanes(self.lo),
            hi: lanes(self.hi),
            cut: self.cut,
            length: lanes(self.len),
            skipped: self.skipped,
        }
    }
}
