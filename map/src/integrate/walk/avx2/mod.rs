//! The raycast walks on AVX2: four rays at once, one per 64-bit lane, set up four at a
//! time in queues ([`Queue`]; [`Axis::setup`], bit for bit `raycast::axis`), walked in
//! one of two ways: lane by lane ([`walk`]: every lane walks as many steps as the live
//! lane with the fewest left, then the lanes whose rays ended take their next) or in
//! groups ([`walk_groups`]: four rays walked together for as many steps as the longest,
//! a lane whose ray ended marking a sink, so the loop is left once per group). Marks:
//! - dense ([`walk_dense`], [`DenseMarks`]): a voxel is its bit index in the thread's
//!   [`DenseBits`], so a step is one add and a mark one OR into memory that stays in
//!   cache. Short rays walk in groups, long ones lane by lane ([`walks_grouped`]);
//! - sparse ([`walk_sparse`], lane by lane): a voxel is [`Packed`]; each lane stores its
//!   current plane's marks, and the voxel, to its current leaf's entry on every step,
//!   and moves to its next entry when it leaves the leaf, so a step has no branch
//!   ([`sparse::SparseMarks`]); after each burst of steps the leaves are OR-ed into the frame's
//!   tables.
//!
//! AVX2 has no mask registers, no unsigned 64-bit compares, no scatters, no compress and
//! no conversion from doubles to 64-bit integers, so this is not the AVX-512 walk
//! narrowed: the lane masks are vectors (all ones or all zeros per lane), a finished
//! axis's next crossing is `i64::MAX` so that signed compares order the crossings, and
//! dense marks are written lane by lane in scalar code, without being read first (see
//! [`walk_dense`]).
//! Its functions are compiled for the features `Kernel::Avx2` requires of the CPU (AVX2,
//! BMI1 and BMI2: the marks' shifts by a register then need no move of the count), and
//! "the CPU has AVX2" in its safety comments means all of them.
//! Per lane the walk is `Dda::step` exactly: the same crossings, ties (x, y, z) and end
//! voxel as `super::dense::walk_rays` and `super::sparse::walk_rays`. The dense walk stays
//! inside the box because the origin's voxel and every end voxel are checked to be in it:
//! a walk moves along each axis monotonically from the one to the other.

use super::covered::Covered;
use super::dense::{or_bit, set_bit, DenseBits, DenseBox};
use super::{Packed, Spill};
use crate::coord::VoxelCoord;
use crate::integrate::marks::{LeafCache, Slot};
use crate::integrate::ray::avx2::{load_ray, transpose4};
use crate::integrate::ray::Ray;
use crate::mask::BitIter;
use crate::raycast::T_ONE;
use std::arch::x86_64::*;
use std::ops::Range;

mod sparse;
#[cfg(test)]
mod tests;

pub(crate) use sparse::walk_sparse;

/// A finished axis's next crossing: above every real one, so never first again.
const NEVER: i64 = i64::MAX;

/// Cap on `t` between crossings, as in the AVX-512 walk: an axis with a larger one
/// crosses once, and the cap keeps `t + between` below [`NEVER`].
const T_CAP: u64 = 1 << 62;

/// Per-axis constants of the rays' set-up: all rays start at the same origin.
struct Axis {
    /// The origin, its voxel's lower face, and the distances from the origin to the
    /// faces above and below it, as `raycast::axis` computes them.
    o: __m256d,
    s: __m256d,
    up: __m256d,
    down: __m256d,
    /// Index increment of one step up the axis.
    stride: __m256i,
    /// The box's voxels along the axis, `lo..hi`, as floats.
    lo: __m256d,
    hi: __m256d,
}

/// `v` truncated to an integer, for `0 <= v <= 2^62` (AVX2 has no conversion from
/// doubles to 64-bit integers): the significand with its implicit bit, shifted by the
/// exponent. Shifts of 64 or more give 0, so one of the two shifts is the answer.
#[inline]
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn trunc_u64(v: __m256d) -> __m256i {
    let bits = _mm256_castpd_si256(v);
    let exp = _mm256_srli_epi64::<52>(bits);
    let mant = _mm256_or_si256(
        _mm256_and_si256(bits, _mm256_set1_epi64x((1 << 52) - 1)),
        _mm256_set1_epi64x(1 << 52),
    );
    let bias = _mm256_set1_epi64x(1075);
    _mm256_or_si256(
        _mm256_sllv_epi64(mant, _mm256_sub_epi64(exp, bias)),
        _mm256_srlv_epi64(mant, _mm256_sub_epi64(bias, exp)),
    )
}

impl Axis {
    #[target_feature(enable = "avx2,bmi1,bmi2")]
    fn new(o: f64, stride: i64, lo: i32, len: u64) -> Self {
        let s = o.floor();
        Axis {
            o: _mm256_set1_pd(o),
            s: _mm256_set1_pd(s),
            up: _mm256_set1_pd(s + 1.0 - o),
            down: _mm256_set1_pd(o - s),
            stride: _mm256_set1_epi64x(stride),
            lo: _mm256_set1_pd(f64::from(lo)),
            hi: _mm256_set1_pd(f64::from(lo) + len as f64),
        }
    }

    /// One axis of four rays' set-up, ending at `e`: lane by lane the arithmetic of
    /// `raycast::axis` in the same order, so bit for bit `Dda::new`'s, with `t`, `d` and
    /// `last` capped at [`T_CAP`]. Returns (t, d, last, inc, n, inside): `inside` all ones
    /// where the end voxel lies in the box.
    #[inline]
    #[target_feature(enable = "avx2,bmi1,bmi2")]
    fn setup(&self, e: __m256d) -> [__m256i; 6] {
        let t = _mm256_floor_pd(e);
        let inside = _mm256_and_pd(
            _mm256_cmp_pd::<_CMP_GE_OQ>(t, self.lo),
            _mm256_cmp_pd::<_CMP_LT_OQ>(t, self.hi),
        );
        // Floors of coordinates inside the box: their difference is exact, and below 2^31.
        let diff = _mm256_sub_pd(t, self.s);
        let abs = |v: __m256d| _mm256_andnot_pd(_mm256_set1_pd(-0.0), v);
        let n = _mm256_cvtepi32_epi64(_mm256_cvttpd_epi32(abs(diff)));
        let none = _mm256_cmpeq_epi64(n, _mm256_setzero_si256());
        let up = _mm256_cmp_pd::<_CMP_GT_OQ>(t, self.s);
        let inv = _mm256_div_pd(_mm256_set1_pd(1.0), abs(_mm256_sub_pd(e, self.o)));
        let face = _mm256_blendv_pd(self.down, self.up, up);
        let cap = _mm256_set1_pd(T_CAP as f64);
        let one = _mm256_set1_pd(T_ONE);
        let t0 = trunc_u64(_mm256_min_pd(
            _mm256_mul_pd(_mm256_mul_pd(face, inv), one),
            cap,
        ));
        // `d` reaches the cap only where `n` is 1, where `last` does not use it; where
        // `n` is 2 or more the ray is longer than a voxel, so t0, d (n - 1) and their sum
        // stay below 2^61 and `d` below 2^60: the 32 x 32-bit products below are exact.
        let d = trunc_u64(_mm256_min_pd(_mm256_mul_pd(inv, one), cap));
        let k = _mm256_sub_epi64(n, _mm256_set1_epi64x(1));
        let last = _mm256_add_epi64(t0, mul_small(d, k));
        let inc = _mm256_blendv_epi8(
            _mm256_sub_epi64(_mm256_setzero_si256(), self.stride),
            self.stride,
            _mm256_castpd_si256(up),
        );
        [
            _mm256_blendv_epi8(t0, _mm256_set1_epi64x(NEVER), none),
            _mm256_andnot_si256(none, d),
            _mm256_andnot_si256(none, last),
            _mm256_andnot_si256(none, inc),
            n,
            _mm256_castpd_si256(inside),
        ]
    }
}

/// The rays to walk: ranges of `rays`, taken in order.
struct Feed<'r> {
    rays: &'r [Ray],
    ranges: [Range<usize>; 8],
    at: usize,
}

impl<'r> Feed<'r> {
    fn new(rays: &'r [Ray], ranges: [Range<usize>; 8]) -> Self {
        Feed {
            rays,
            ranges,
            at: 0,
        }
    }

    /// All of `rays`, in order.
    fn all(rays: &'r [Ray]) -> Self {
        let mut ranges: [Range<usize>; 8] = Default::default();
        ranges[0] = 0..rays.len();
        Self::new(rays, ranges)
    }

    /// The next rays, at most `max`, as they lie in `rays`: empty when none are left.
    fn run(&mut self, max: usize) -> &'r [Ray] {
        while let Some(r) = self.ranges.get_mut(self.at) {
            if r.start >= r.end {
                self.at += 1;
                continue;
            }
            let end = r.end.min(r.start + max);
            let run = &self.rays[r.start..end];
            r.start = end;
            return run;
        }
        &[]
    }

    /// Ask for the cache lines of the next `4 * GROUPS` rays.
    fn prefetch(&self) {
        if let Some(r) = self.ranges.get(self.at) {
            for i in (r.start..r.end.min(r.start + 4 * GROUPS)).step_by(2) {
                crate::prefetch::prefetch(self.rays, i);
            }
        }
    }
}

#[inline(always)]
fn to_array(v: __m256i) -> [i64; 4] {
    // SAFETY: __m256i and [i64; 4] are both 32 plain bytes; every bit pattern is valid.
    unsafe { std::mem::transmute(v) }
}

#[inline(always)]
fn from_array(a: [i64; 4]) -> __m256i {
    // SAFETY: as in `to_array`.
    unsafe { std::mem::transmute(a) }
}

/// Bit `l` set for each lane `l` whose 64 bits are all ones in `m`.
#[inline]
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn lanes(m: __m256i) -> u32 {
    _mm256_movemask_pd(_mm256_castsi256_pd(m)) as u32
}

/// Groups of four rays set up at once in a lane's queue.
const GROUPS: usize = 4;

/// Up to `4 * GROUPS` rays, set up together, in the order the feed gave them: per group
/// and axis, vectors of next crossing (`NEVER` for an axis without any), between, last
/// and index increment, entry `4 g + j` in lane `j` of group `g`; each ray's steps, first
/// and end voxels and whether it hits. One per lane in [`walk`], one in [`walk_groups`].
/// (Four groups give the set-up's long chains more to overlap than two; eight measured
/// no better.)
struct Queue {
    t: [[__m256i; 3]; GROUPS],
    d: [[__m256i; 3]; GROUPS],
    last: [[__m256i; 3]; GROUPS],
    inc: [[__m256i; 3]; GROUPS],
    n: [i64; 4 * GROUPS],
    /// Bit `j` set where entry `j`'s ray hits.
    hits: u32,
    /// Each ray's first voxel: the walk's start, or where it leaves the covered box.
    p0: [i64; 4 * GROUPS],
    /// Each ray's end voxel.
    end: [i64; 4 * GROUPS],
    len: usize,
    next: usize,
    /// Steps of the rays set up so far that their walks skip in the covered box.
    skipped: u64,
}

impl Queue {
    #[target_feature(enable = "avx2,bmi1,bmi2")]
    fn new() -> Self {
        let zero = [_mm256_setzero_si256(); 3];
        Queue {
            t: [[_mm256_set1_epi64x(NEVER); 3]; GROUPS],
            d: [zero; GROUPS],
            last: [zero; GROUPS],
            inc: [zero; GROUPS],
            n: [0; 4 * GROUPS],
            hits: 0,
            p0: [0; 4 * GROUPS],
            end: [0; 4 * GROUPS],
            len: 0,
            next: 0,
            skipped: 0,
        }
    }

    /// The next ray: its entry in the queue; `None` when the feed has no rays left.
    #[inline(always)]
    fn pop(&mut self, feed: &mut Feed<'_>, from: &Start<'_>) -> Option<usize> {
        // SAFETY: the CPU has AVX2: `Queue::new`, the only way to make a queue, needs it.
        if self.next == self.len && !unsafe { self.fill(feed, from) } {
            return None;
        }
        self.next += 1;
        Some(self.next - 1)
    }

    /// Set up the next rays from `feed`; false if it has none left.
    #[inline(never)]
    #[target_feature(enable = "avx2,bmi1,bmi2")]
    fn fill(&mut self, feed: &mut Feed<'_>, from: &Start<'_>) -> bool {
        let Start {
            axes,
            origin,
            start,
            covered,
        } = *from;
        // Each ray whole in a vector (end, then the word of key and hit flag); entries
        // without a ray end at the origin: no steps.
        let mut rows = [_mm256_setr_pd(origin[0], origin[1], origin[2], 0.0); 4 * GROUPS];
        self.len = 0;
        loop {
            let run = feed.run(4 * GROUPS - self.len);
            if run.is_empty() {
                break;
            }
            for r in run {
                rows[self.len] = load_ray(r);
                self.len += 1;
            }
        }
        // The next rays are read at the next fill: ask for them now, so that their misses
        // overlap this fill's set-up and the walk.
        feed.prefetch();
        self.next = 0;
        let mut inside = _mm256_set1_epi64x(-1);
        let groups = self.len.div_ceil(4);
        let mut n = [[_mm256_setzero_si256(); 3]; GROUPS];
        let mut span = [[_mm256_setzero_pd(); 3]; GROUPS];
        self.hits = 0;
        for (g, rows) in rows.chunks_exact(4).enumerate().take(groups) {
            let [x, y, z, w] = transpose4(rows.try_into().expect("four rays"));
            // The hit flag is bit 32 of the word: to the sign bit.
            let hit = _mm256_movemask_pd(_mm256_castsi256_pd(_mm256_slli_epi64::<31>(
                _mm256_castpd_si256(w),
            )));
            self.hits |= (hit as u32) << (4 * g);
            for (a, (axis, e)) in axes.iter().zip([x, y, z]).enumerate() {
                let [t, d, last, inc, na, ins] = axis.setup(e);
                (self.t[g][a], self.d[g][a], self.last[g][a], self.inc[g][a]) = (t, d, last, inc);
                n[g][a] = na;
                span[g][a] = _mm256_andnot_pd(_mm256_set1_pd(-0.0), _mm256_sub_pd(e, axis.o));
                inside = _mm256_and_si256(inside, ins);
            }
        }
        // The walk's reads and writes stay in the box only if every end voxel does.
        if lanes(inside) != 0b1111 {
            outside_the_box();
        }
        let start_v = _mm256_set1_epi64x(start as i64);
        for (g, n) in n.iter().enumerate().take(groups) {
            // Increments are a stride, under 2^31, with its sign: signed 32-bit products.
            let inc = &self.inc[g];
            let end = (0..3).fold(start_v, |e, a| {
                _mm256_add_epi64(e, _mm256_mul_epi32(n[a], inc[a]))
            });
            self.end[4 * g..4 * g + 4].copy_from_slice(&to_array(end));
            let (left, p0) = match covered {
                Some(c) => self.skip_covered(g, c, start_v, n, &span[g]),
                None => (add3(n), start_v),
            };
            self.n[4 * g..4 * g + 4].copy_from_slice(&to_array(left));
            self.p0[4 * g..4 * g + 4].copy_from_slice(&to_array(p0));
        }
        self.len > 0
    }

    /// Start group `g`'s rays, whose crossings per axis are `n` and extents from the origin
    /// `span`, where they first leave the covered box `c`: the crossings before that made
    /// at once (those before its time, [`Covered::skip`], bit for bit), their walk from
    /// `start` skipped. Returns their steps left and the voxels they start from. The
    /// crossings made are estimated in doubles and then checked against the exact
    /// crossing times.
    #[target_feature(enable = "avx2,bmi1,bmi2")]
    fn skip_covered(
        &mut self,
        g: usize,
        c: &Covered,
        start: __m256i,
        n: &[__m256i; 3],
        span: &[__m256d; 3],
    ) -> (__m256i, __m256i) {
        let (zero, one, never) = (
            _mm256_setzero_si256(),
            _mm256_set1_epi64x(1),
            _mm256_set1_epi64x(NEVER),
        );
        let (t, d, inc) = (self.t[g], self.d[g], self.inc[g]);
        let min = |a: __m256i, b: __m256i| _mm256_blendv_epi8(a, b, _mm256_cmpgt_epi64(a, b));
        // The first crossing out of the box: per axis the one `leave` crossings on, where
        // the axis has that many (its `n` at least `leave`, so none for an axis without).
        let mut first = never;
        for a in 0..3 {
            let [down, up] = c.leave[a].map(|k| _mm256_set1_epi64x(k as i64));
            let before = _mm256_sub_epi64(
                _mm256_blendv_epi8(down, up, _mm256_cmpgt_epi64(inc[a], zero)),
                one,
            );
            let at = _mm256_add_epi64(t[a], mul_small(d[a], before));
            first = min(
                first,
                _mm256_blendv_epi8(never, at, _mm256_cmpgt_epi64(n[a], before)),
            );
        }
        // A ray that never leaves makes all its crossings.
        let ends_inside = _mm256_cmpeq_epi64(first, never);
        let (mut p, mut left) = (start, zero);
        let mut made_all = zero;
        for a in 0..3 {
            // Crossings before `first`: t[a] + j d[a] < first for j < k, about
            // (first - t[a]) / d[a] rounded up, then checked one each way (the estimate
            // is off by far less than one crossing, so only rounding at a tie can miss).
            // `d` is `T_ONE / span` truncated (bit for bit `raycast::axis`), so the
            // quotient is about (first - t) span / T_ONE: a product, not a division.
            let due = _mm256_cmpgt_epi64(first, t[a]);
            let per = _mm256_mul_pd(span[a], _mm256_set1_pd(1024.0 / T_ONE));
            let q = _mm256_mul_pd(approx_pd(_mm256_sub_epi64(first, t[a])), per);
            let est = _mm256_cvtepi32_epi64(_mm256_cvttpd_epi32(_mm256_ceil_pd(q)));
            let k = min(
                _mm256_andnot_si256(_mm256_cmpgt_epi64(zero, est), est),
                n[a],
            );
            let next = _mm256_add_epi64(t[a], mul_small(d[a], k));
            let more =
                _mm256_and_si256(_mm256_cmpgt_epi64(n[a], k), _mm256_cmpgt_epi64(first, next));
            let fewer = _mm256_andnot_si256(
                _mm256_cmpgt_epi64(first, _mm256_sub_epi64(next, d[a])),
                _mm256_cmpgt_epi64(k, zero),
            );
            // Masks are -1 where set: `more` adds one, `fewer` takes one.
            let k = _mm256_add_epi64(_mm256_sub_epi64(k, more), fewer);
            let k = _mm256_blendv_epi8(_mm256_and_si256(k, due), n[a], ends_inside);
            let next = _mm256_add_epi64(t[a], mul_small(d[a], k));
            let done =
                _mm256_andnot_si256(_mm256_cmpeq_epi64(n[a], zero), _mm256_cmpeq_epi64(k, n[a]));
            self.t[g][a] = _mm256_blendv_epi8(next, never, done);
            // Increments are a stride, under 2^31, with its sign: a signed 32-bit product.
            p = _mm256_add_epi64(p, _mm256_mul_epi32(k, inc[a]));
            left = _mm256_add_epi64(left, _mm256_sub_epi64(n[a], k));
            made_all = _mm256_add_epi64(made_all, k);
        }
        self.skipped += to_array(made_all).iter().sum::<i64>() as u64;
        (left, p)
    }
}

/// The sum of three vectors.
#[inline]
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn add3(v: &[__m256i; 3]) -> __m256i {
    _mm256_add_epi64(_mm256_add_epi64(v[0], v[1]), v[2])
}

/// `a * k` lane by lane, for `k < 2^32` and products below 2^63.
#[inline]
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn mul_small(a: __m256i, k: __m256i) -> __m256i {
    _mm256_add_epi64(
        _mm256_mul_epu32(a, k),
        _mm256_slli_epi64::<32>(_mm256_mul_epu32(_mm256_srli_epi64::<32>(a), k)),
    )
}

/// `v` as a double, its low 10 bits dropped, for `0 <= v <= 2^62`: an estimate.
#[inline]
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn approx_pd(v: __m256i) -> __m256d {
    // 2^52 as a double: OR-ed with an integer below 2^52 it is 2^52 plus that integer.
    let magic = _mm256_set1_epi64x(0x4330_0000_0000_0000);
    let bits = _mm256_or_si256(_mm256_srli_epi64::<10>(v), magic);
    _mm256_sub_pd(_mm256_castsi256_pd(bits), _mm256_castsi256_pd(magic))
}

/// Where a lane walk's rays start: the axes' set-up from the origin, the origin's voxel
/// index, and the covered box whose voxels the rays skip, if any.
#[derive(Clone, Copy)]
struct Start<'a> {
    axes: &'a [Axis; 3],
    origin: [f64; 3],
    start: u64,
    covered: Option<&'a Covered>,
}

/// Whether a dense walk whose rays walk `walked` steps each, on average, walks them in
/// groups ([`walk_groups`]) rather than refilling each lane as its ray ends ([`walk`]):
/// a group walks as long as its longest ray, so the steps its shorter rays idle grow
/// with the rays' length, while the refills cost the same per ray. Short rays, as a
/// small frame's are outside its covered box, walk grouped (docs/design.md, "The AVX2
/// kernel").
pub(super) fn walks_grouped(walked: f64) -> bool {
    walked <= 48.0
}

/// Walk the rays `rays[ranges[..]]` from `origin`, four at a time, in groups or not
/// ([`walks_grouped`]), setting their free and hit bits in `bits`, outside `covered`;
/// returns voxels on the rays and, of those, the ones skipped in `covered`. The same marks and counts as
/// `super::dense::walk_rays`. Marks are written without being read first (unlike
/// `avx512::test_first`'s frames): lane by lane in scalar code, the test's mispredicted
/// branches cost more than the writes (random 500k 6 m 28.3 -> 23.5-24.5 ms, structured
/// 21.9 -> 20.1, on AMD Zen 5).
#[target_feature(enable = "avx2,bmi1,bmi2")]
pub(crate) fn walk_dense(
    bits: &mut DenseBits,
    dbox: &DenseBox,
    origin: [f64; 3],
    rays: &[Ray],
    ranges: [Range<usize>; 8],
    covered: Option<&Covered>,
    grouped: bool,
) -> (u64, u64) {
    let strides = dbox.strides();
    let origin_voxel = crate::coord::units_to_voxel(origin).expect("origin checked");
    let (lo, d) = (dbox.lo, origin_voxel - dbox.lo);
    if [d.x, d.y, d.z]
        .iter()
        .zip(dbox.n)
        .any(|(&d, n)| d < 0 || d as u64 >= n)
    {
        outside_the_box();
    }
    let axes = [
        Axis::new(origin[0], strides[0], lo.x, dbox.n[0]),
        Axis::new(origin[1], strides[1], lo.y, dbox.n[1]),
        Axis::new(origin[2], strides[2], lo.z, dbox.n[2]),
    ];
    let start = dbox.index(origin_voxel);
    let sink = dbox.sink();
    let (free, hits) = bits.words_mut();
    let feed = Feed::new(rays, ranges);
    let from = Start {
        axes: &axes,
        origin,
        start,
        covered,
    };
    let marks = &mut DenseMarks { free, hits, sink };
    if grouped {
        walk_groups(marks, &from, feed)
    } else {
        walk(marks, &from, feed)
    }
}

/// Where a lane walk keeps the marks of the voxels its lanes visit. Voxels are `u64`
/// indices with fixed strides per axis (see [`Axis::new`]): bit indices into a dense box,
/// or [`Packed`] voxels.
trait Marks {
    /// Most steps walked between two [`Marks::burst_done`].
    const BURST: i64;
    /// The voxel index lanes without a ray sit on (their increments are 0).
    fn idle(&self) -> u64;
    /// Walk every lane `k` steps from its next crossings `t` and voxel `p`, marking each
    /// voxel before the step; `live` all ones in the lanes that walk a ray.
    ///
    /// # Safety
    /// Every live lane's `k` steps stay on its ray (`k` is at most its steps left), and
    /// the CPU has AVX2.
    unsafe fn steps(
        &mut self,
        k: i64,
        t: &mut [__m256i; 3],
        p: &mut __m256i,
        fixed: &Fixed,
        live: __m256i,
    );
    /// After a burst of steps: the lanes in `ended` (bit `l` for lane `l`) ended their
    /// rays at voxels `p`; those in `hit` hit there.
    ///
    /// # Safety
    /// The CPU has AVX2.
    unsafe fn burst_done(&mut self, p: [i64; 4], ended: u32, hit: u32);
    /// A ray ended in the voxel its walk starts from, `p`, which it hit.
    fn hit_at(&mut self, p: u64);
}

/// The dense walk's marks: bits of the thread's grid over the frame's box. Aligned to a
/// cache line so that the walk's frame is (see `avx512::SparseLanes`).
#[repr(align(64))]
struct DenseMarks<'a> {
    free: &'a mut [u64],
    hits: &'a mut [u64],
    sink: u64,
}

impl Marks for DenseMarks<'_> {
    const BURST: i64 = i64::MAX;

    fn idle(&self) -> u64 {
        self.sink
    }

    #[inline(never)]
    unsafe fn steps(
        &mut self,
        k: i64,
        t: &mut [__m256i; 3],
        p: &mut __m256i,
        fixed: &Fixed,
        _: __m256i,
    ) {
        // SAFETY: every lane's voxels are in the box: the origin's voxel and each ray's
        // end voxel were checked to be (`Queue::fill`), a lane stops at its ray's end (the
        // caller's promise), and a walk moves along each axis monotonically from the one
        // to the other. Lanes without a ray sit on the sink, increments 0.
        unsafe { walk_steps(k, t, p, fixed, self.free) };
    }

    unsafe fn burst_done(&mut self, p: [i64; 4], _: u32, hit: u32) {
        for l in BitIter(u64::from(hit)) {
            set_bit(self.hits, p[l] as u64);
        }
    }

    fn hit_at(&mut self, p: u64) {
        set_bit(self.hits, p);
    }
}

/// The lane-by-lane walk (the sparse walk's, and the dense walk's for long rays): the
/// lanes' rays from `feed`, telling `marks` the voxels each lane visits, each lane taking
/// its next ray as soon as its ray ends; returns
/// voxels on the rays and, of those, the ones skipped in `from.covered`. Voxel indices
/// start at `from.start` (the origin's voxel), or where a ray leaves the covered box, and
/// change by the axes' strides per step.
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn walk<M: Marks>(marks: &mut M, from: &Start<'_>, mut feed: Feed<'_>) -> (u64, u64) {
    let mut queues = [Queue::new(), Queue::new(), Queue::new(), Queue::new()];
    let never = _mm256_set1_epi64x(NEVER);
    let iota = _mm256_setr_epi64x(0, 1, 2, 3);
    let idle = _mm256_set1_epi64x(marks.idle() as i64);
    // Lane state: per axis next crossing, and the ray's constants; the voxel. A lane
    // without a ray sits on the idle voxel and does not move (no increments): the loop
    // needs no lane mask.
    let zero = _mm256_setzero_si256();
    let mut t = [never; 3];
    let mut fixed = Fixed {
        d: [zero; 3],
        last: [zero; 3],
        inc: [zero; 3],
    };
    let mut p = idle;
    let mut rem = [i64::MAX; 4];
    // Lane l's ray hits: bit l.
    let mut hit = 0u32;
    let mut live = 0u32;
    let mut need = 0b1111u32;
    let mut steps = 0u64;
    loop {
        // Give each lane in `need` its next ray that takes a step; rays that end in their
        // start voxel are done here (a hit at most).
        for l in BitIter(u64::from(need)) {
            let q = &mut queues[l];
            while let Some(j) = q.pop(&mut feed, from) {
                let n = q.n[j];
                steps += n as u64 + 1;
                if n == 0 {
                    if q.hits >> j & 1 != 0 {
                        marks.hit_at(q.p0[j] as u64);
                    }
                    continue;
                }
                // Entry j of the queue's vectors into lane l of the state's.
                let lane = _mm256_cmpeq_epi64(iota, _mm256_set1_epi64x(l as i64));
                let (g, i) = (j / 4, 2 * (j % 4) as i32);
                let pick = _mm256_setr_epi32(i, i + 1, i, i + 1, i, i + 1, i, i + 1);
                let put = |v: &mut [__m256i; 3], from: &[__m256i; 3]| {
                    for (v, &f) in v.iter_mut().zip(from) {
                        *v = _mm256_blendv_epi8(*v, _mm256_permutevar8x32_epi32(f, pick), lane);
                    }
                };
                put(&mut t, &q.t[g]);
                put(&mut fixed.d, &q.d[g]);
                put(&mut fixed.last, &q.last[g]);
                put(&mut fixed.inc, &q.inc[g]);
                p = _mm256_blendv_epi8(p, _mm256_set1_epi64x(q.p0[j]), lane);
                rem[l] = n;
                hit = hit & !(1 << l) | (q.hits >> j & 1) << l;
                live |= 1 << l;
                break;
            }
        }
        if live == 0 {
            break;
        }
        let done = need & !live;
        if done != 0 {
            // Lanes whose rays ran out: to the idle voxel, still.
            let m = lane_mask(done);
            let axes = t.iter_mut().zip(&mut fixed.d).zip(&mut fixed.inc);
            for ((t, d), inc) in axes {
                *t = _mm256_blendv_epi8(*t, never, m);
                *d = _mm256_andnot_si256(m, *d);
                *inc = _mm256_andnot_si256(m, *inc);
            }
            p = _mm256_blendv_epi8(p, idle, m);
            for l in BitIter(u64::from(done)) {
                rem[l] = i64::MAX;
            }
        }
        // Every lane walks as many steps as the live lane with the fewest left, so the
        // loop tests no lane for its end.
        let k = rem.iter().copied().min().unwrap_or(0).min(M::BURST);
        // SAFETY: k is at most every live lane's steps left; the CPU has AVX2, which
        // this function requires.
        unsafe { marks.steps(k, &mut t, &mut p, &fixed, lane_mask(live)) };
        // Which lanes ended, without a branch per lane: which one is a coin toss.
        let mut ended = 0;
        for (l, rem) in rem.iter_mut().enumerate() {
            *rem -= k;
            ended |= u32::from(*rem == 0) << l;
        }
        // SAFETY: this function requires AVX2.
        unsafe { marks.burst_done(to_array(p), ended, ended & hit) };
        live &= !ended;
        need = ended;
    }
    let skipped: u64 = queues.iter().map(|q| q.skipped).sum();
    (steps + skipped, skipped)
}

/// The dense walk: the rays from `feed`, set up sixteen at a time in one queue, walked a
/// group of four at a time, one ray per lane, for as many steps as the group's longest;
/// a lane whose ray has ended marks a sink word of its own. Returns voxels on the rays
/// and, of those, the ones skipped in `from.covered`. Refilling a lane as soon as its ray
/// ends (as [`walk`] does) leaves the loop every few steps on rays as short as a frame's
/// outside its covered box, and that bookkeeping cost more than the steps the shorter
/// rays of a group walk idle (see docs/design.md, "The AVX2 kernel"). Hits are marked from the end
/// voxels the set-up computed.
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn walk_groups(marks: &mut DenseMarks<'_>, from: &Start<'_>, mut feed: Feed<'_>) -> (u64, u64) {
    let mut q = Queue::new();
    let sinks = _mm256_add_epi64(
        _mm256_set1_epi64x(marks.sink as i64),
        _mm256_setr_epi64x(0, 64, 128, 192),
    );
    let mut steps = 0u64;
    while q.fill(&mut feed, from) {
        for g in 0..q.len.div_ceil(4) {
            let mut most = 0;
            for j in 4 * g..(4 * g + 4).min(q.len) {
                steps += q.n[j] as u64 + 1;
                most = most.max(q.n[j]);
                // Without a branch: whether a ray hits is a coin toss to the predictor
                // (a third of a 6 m frame's rays are cut), and its misses cost more
                // than a write of nothing.
                or_bit(marks.hits, q.end[j] as u64, q.hits >> j & 1 != 0);
            }
            if most == 0 {
                continue;
            }
            let load = |v: &[i64]| from_array(v.try_into().expect("four lanes"));
            let (n, p0) = (load(&q.n[4 * g..4 * g + 4]), load(&q.p0[4 * g..4 * g + 4]));
            let fixed = Fixed {
                d: q.d[g],
                last: q.last[g],
                inc: q.inc[g],
            };
            // SAFETY: the CPU has AVX2 (this function requires it). Every lane walks its
            // ray's steps left (entries past the queue's rays have none), and those stay
            // in the box: the origin's voxel and each ray's end voxel were checked to be
            // in it (`walk_dense`, `Queue::fill`), and a walk moves along each axis
            // monotonically from the one to the other. Then it marks its sink, one of
            // the four words past the box (`DenseBits::begin`).
            unsafe { group_steps(most, q.t[g], (p0, n), &fixed, sinks, marks.free) };
        }
    }
    (steps + q.skipped, q.skipped)
}

/// Walk a group's lanes `k` steps from crossings `t`, voxels `p` and steps left `n`
/// (`at`), marking each voxel before the step in `free`; a lane with no steps left marks
/// its word of `sinks` instead. A function of its own, not inlined: inside its caller the
/// register allocator kept the crossings on the stack, a store and a load on every step,
/// which once made the walk take twice as long.
///
/// # Safety
/// Every lane's first `n` voxels must lie in the box of `free`, and `sinks` be words of
/// `free` outside it. The CPU must have AVX2.
#[inline(never)]
#[target_feature(enable = "avx2,bmi1,bmi2")]
unsafe fn group_steps(
    k: i64,
    t: [__m256i; 3],
    (p, n): (__m256i, __m256i),
    fixed: &Fixed,
    sinks: __m256i,
    free: &mut [u64],
) {
    let one = _mm256_set1_epi64x(1);
    let (mut tv, mut left) = (t, n);
    let mut pv = _mm256_blendv_epi8(p, sinks, _mm256_cmpgt_epi64(one, left));
    for _ in 0..k {
        // SAFETY: every lane's voxel is a bit of `free`, as the caller guarantees.
        unsafe { mark(free, pv) };
        let (next, inc) = step(tv, fixed);
        tv = next;
        left = _mm256_sub_epi64(left, one);
        pv = _mm256_blendv_epi8(
            _mm256_add_epi64(pv, inc),
            sinks,
            _mm256_cmpgt_epi64(one, left),
        );
    }
}

/// All ones in lane `l` for each bit `l` of `lanes`.
#[inline]
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn lane_mask(lanes: u32) -> __m256i {
    _mm256_cmpgt_epi64(
        _mm256_and_si256(
            _mm256_set1_epi64x(i64::from(lanes)),
            _mm256_setr_epi64x(1, 2, 4, 8),
        ),
        _mm256_setzero_si256(),
    )
}

/// Each lane's per-ray constants: per axis, between crossings, last crossing, index
/// increment.
struct Fixed {
    d: [__m256i; 3],
    last: [__m256i; 3],
    inc: [__m256i; 3],
}

/// One step of every lane from next crossings `t` (ties x, y, z): the new crossings and
/// the index increment. Each axis's next crossing (never after its last) is computed off
/// the compare chain, as `Dda::step` does.
#[inline]
#[target_feature(enable = "avx2,bmi1,bmi2")]
fn step(t: [__m256i; 3], fixed: &Fixed) -> ([__m256i; 3], __m256i) {
    let never = _mm256_set1_epi64x(NEVER);
    let [tx, ty, tz] = t;
    let [dx, dy, dz] = fixed.d;
    let [lx, ly, lz] = fixed.last;
    let [mx, my, mz] = fixed.inc;
    let gxy = _mm256_cmpgt_epi64(tx, ty);
    let gxz = _mm256_cmpgt_epi64(tx, tz);
    let gyz = _mm256_cmpgt_epi64(ty, tz);
    let nx = _mm256_blendv_epi8(_mm256_add_epi64(tx, dx), never, _mm256_cmpeq_epi64(tx, lx));
    let ny = _mm256_blendv_epi8(_mm256_add_epi64(ty, dy), never, _mm256_cmpeq_epi64(ty, ly));
    let nz = _mm256_blendv_epi8(_mm256_add_epi64(tz, dz), never, _mm256_cmpeq_epi64(tz, lz));
    // Not x: y where its crossing is not after z's, else z.
    let not_x = _mm256_or_si256(gxy, gxz);
    (
        [
            _mm256_blendv_epi8(nx, tx, not_x),
            _mm256_blendv_epi8(ty, ny, _mm256_andnot_si256(gyz, not_x)),
            _mm256_blendv_epi8(tz, nz, _mm256_and_si256(gyz, not_x)),
        ],
        _mm256_blendv_epi8(mx, _mm256_blendv_epi8(my, mz, gyz), not_x),
    )
}

/// Walk every lane `k` steps from its next crossings `t` and voxel `p`, marking each voxel
/// before the step in `free`. A function of its own, not inlined: inside `walk_dense` the
/// register allocator kept the crossings on the stack, a store and a load on every step
/// (random 500k 6 m 28 -> 36 ms; structured 500k 6 m 14 -> 28 ms when an unrelated change
/// made the compiler inline it through `DenseMarks::steps` despite this attribute, which
/// is why that method is not inlined either).
///
/// # Safety
/// Every voxel of every lane's `k` steps must lie in the box of `free`, or be the sink
/// (its last word), which a lane without increments never leaves.
#[inline(never)]
#[target_feature(enable = "avx2,bmi1,bmi2")]
unsafe fn walk_steps(
    k: i64,
    t: &mut [__m256i; 3],
    p: &mut __m256i,
    fixed: &Fixed,
    free: &mut [u64],
) {
    let mut tv = *t;
    let mut pv = *p;
    for _ in 0..k {
        // SAFETY: every lane's voxel is a bit of `free`, as the caller guarantees.
        unsafe { mark(free, pv) };
        let (next, inc) = step(tv, fixed);
        tv = next;
        pv = _mm256_add_epi64(pv, inc);
    }
    (*t, *p) = (tv, pv);
}

/// Set the bit of each lane's voxel `p` in `free`, lane by lane, without testing them
/// first (see [`walk_dense`]).
///
/// # Safety
/// Every lane's voxel must be a bit of `free`.
#[inline(always)]
unsafe fn mark(free: &mut [u64], p: __m256i) {
    let mut lanes = Spill::<4>::new();
    // SAFETY: the spill is 32 bytes aligned to 64, all `_mm256_store_si256` writes.
    unsafe { _mm256_store_si256(lanes.ptr().cast(), p) };
    for q in lanes.lanes() {
        let (word, bit) = ((q >> 6) as usize, 1u64 << (q & 63));
        // SAFETY: `word < free.len()`, as the caller guarantees.
        let w = unsafe { free.get_unchecked_mut(word) };
        *w |= bit;
    }
}

/// A walk stepped outside its box: a bug, stopped before any read outside the marks.
#[cold]
#[inline(never)]
fn outside_the_box() -> ! {
    panic!("dense walk left its box");
}
