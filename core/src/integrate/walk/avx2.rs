//! The dense raycast walk on AVX2: four rays at once, one per 64-bit lane. (The sparse
//! walk stays scalar under this kernel: a four-lane version, its brick words kept per
//! lane, walked the random 500k 60 m frame's rays 35-50% slower than one ray at a time;
//! see `docs/design.md`.)
//!
//! AVX2 has no mask registers, no unsigned 64-bit compares, no scatters and no compress,
//! so this is not the AVX-512 walk narrowed: the lane masks are vectors (all ones or all
//! zeros per lane), a finished axis's next crossing is `i64::MAX` so that signed compares
//! order the crossings, a new ray is set up in scalar code ([`raycast::axis`], exactly as
//! [`crate::raycast::Dda::new`] does) for the lanes that need one, and marks are written
//! lane by lane. Per lane the walk is `Dda::step` exactly: the same crossings, ties (x, y,
//! z) and end voxel as `super::dense::walk_rays`.

use super::dense::{set_bit, DenseBits, DenseBox};
use crate::integrate::prepare::Ray;
use crate::mask::BitIter;
use crate::raycast;
use std::arch::x86_64::*;
use std::ops::Range;

/// A finished axis's next crossing: above every real one, so never first again.
const NEVER: i64 = i64::MAX;

/// Cap on `t` between crossings, as in the AVX-512 walk: an axis with a larger one
/// crosses once, and the cap keeps `t + between` below [`NEVER`].
const T_CAP: u64 = 1 << 62;

/// One ray's per-axis set-up in lane form: next crossing, between, last, index increment,
/// and the ray's steps.
struct Setup {
    t: [i64; 3],
    d: [i64; 3],
    last: [i64; 3],
    inc: [i64; 3],
    n: i64,
}

fn setup(origin: [f64; 3], end: [f64; 3], strides: [i64; 3]) -> Setup {
    let mut s = Setup {
        t: [NEVER; 3],
        d: [0; 3],
        last: [0; 3],
        inc: [0; 3],
        n: 0,
    };
    for a in 0..3 {
        let (_, dir, t0, d, last, n) = raycast::axis(origin[a], end[a]);
        if n > 0 {
            // t0 and last are at most about 2^60 (t = 1); `d` above the cap only when
            // n = 1, where `last` does not use it.
            s.t[a] = t0.min(T_CAP) as i64;
            s.d[a] = d.min(T_CAP) as i64;
            s.last[a] = last.min(T_CAP) as i64;
            s.inc[a] = i64::from(dir) * strides[a];
        }
        s.n += i64::from(n);
    }
    s
}

/// Each lane's rays: its current range, then the ones left to hand out.
struct Feed<'r> {
    rays: &'r [Ray],
    cur: [usize; 4],
    lim: [usize; 4],
    spare: [Range<usize>; 4],
    spare_left: usize,
}

impl Feed<'_> {
    /// Lane `l`'s next ray: from its range, else a spare range, else half of what the
    /// lane with the most left has (as the AVX-512 walk shares).
    fn next(&mut self, l: usize) -> Option<&Ray> {
        if self.cur[l] >= self.lim[l] {
            if self.spare_left > 0 {
                self.spare_left -= 1;
                let r = self.spare[self.spare_left].clone();
                (self.cur[l], self.lim[l]) = (r.start, r.end);
            } else {
                let (j, left) = (0..4)
                    .map(|j| (j, self.lim[j].saturating_sub(self.cur[j])))
                    .max_by_key(|&(_, left)| left)?;
                if left < 2 {
                    return None;
                }
                let mid = self.cur[j] + left / 2;
                (self.cur[l], self.lim[l]) = (mid, self.lim[j]);
                self.lim[j] = mid;
            }
            if self.cur[l] >= self.lim[l] {
                return self.next(l);
            }
        }
        let r = &self.rays[self.cur[l]];
        self.cur[l] += 1;
        Some(r)
    }
}

/// Walk the rays `rays[ranges[..]]` from `origin`, four lanes over the eight ranges,
/// setting their free and hit bits in `bits`; returns voxels visited. The same marks and
/// count as `super::dense::walk_rays`. `test_first`: marks are read before they are
/// written (see `avx512::test_first`).
#[target_feature(enable = "avx2")]
pub(super) fn walk_dense(
    bits: &mut DenseBits,
    dbox: &DenseBox,
    origin: [f64; 3],
    rays: &[Ray],
    ranges: [Range<usize>; 8],
    test_first: bool,
) -> u64 {
    if test_first {
        walk::<true>(bits, dbox, origin, rays, ranges)
    } else {
        walk::<false>(bits, dbox, origin, rays, ranges)
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
#[target_feature(enable = "avx2")]
fn lanes(m: __m256i) -> u32 {
    _mm256_movemask_pd(_mm256_castsi256_pd(m)) as u32
}

#[target_feature(enable = "avx2")]
fn walk<const TEST_FIRST: bool>(
    bits: &mut DenseBits,
    dbox: &DenseBox,
    origin: [f64; 3],
    rays: &[Ray],
    ranges: [Range<usize>; 8],
) -> u64 {
    let strides = dbox.strides();
    let start = dbox.index(crate::coord::units_to_voxel(origin).expect("origin checked"));
    let sink = dbox.sink() as i64;
    let (free, hits) = bits.words_mut();
    let [r0, r1, r2, r3, r4, r5, r6, r7] = ranges;
    let mut feed = Feed {
        rays,
        cur: [r0.start, r1.start, r2.start, r3.start],
        lim: [r0.end, r1.end, r2.end, r3.end],
        spare: [r7, r6, r5, r4],
        spare_left: 4,
    };
    let zero = _mm256_setzero_si256();
    let ones = _mm256_set1_epi64x(-1);
    let one = _mm256_set1_epi64x(1);
    let never = _mm256_set1_epi64x(NEVER);
    let words = _mm256_set1_epi64x(free.len() as i64);
    // Lane state, kept in arrays between refills and in registers while walking.
    let mut st = [[NEVER; 4]; 3];
    let mut dt = [[0i64; 4]; 3];
    let mut lt = [[0i64; 4]; 3];
    let mut mt = [[0i64; 4]; 3];
    let mut pos = [0i64; 4];
    let mut rem = [0i64; 4];
    let mut hit = [false; 4];
    let mut live = 0u32;
    let mut need = 0b1111u32;
    let mut steps = 0u64;
    loop {
        // Give each lane in `need` its next ray that takes a step; rays that end in their
        // start voxel are done here (a hit at most).
        for l in BitIter(u64::from(need)) {
            while let Some(r) = feed.next(l) {
                let s = setup(origin, r.end, strides);
                steps += s.n as u64 + 1;
                if s.n == 0 {
                    if r.hit {
                        set_bit(hits, start);
                    }
                    continue;
                }
                for a in 0..3 {
                    st[a][l] = s.t[a];
                    dt[a][l] = s.d[a];
                    lt[a][l] = s.last[a];
                    mt[a][l] = s.inc[a];
                }
                pos[l] = start as i64;
                rem[l] = s.n;
                hit[l] = r.hit;
                live |= 1 << l;
                break;
            }
        }
        if live == 0 {
            break;
        }
        // A lane without a ray sits on the sink bit and does not move (no increments),
        // its count never reaches 0: the loop needs no lane mask.
        for l in 0..4 {
            if live >> l & 1 == 0 {
                for a in 0..3 {
                    (st[a][l], dt[a][l], lt[a][l], mt[a][l]) = (NEVER, 0, 0, 0);
                }
                (pos[l], rem[l]) = (sink, -1);
            }
        }
        let (mut tx, mut ty, mut tz) = (from_array(st[0]), from_array(st[1]), from_array(st[2]));
        let (dx, dy, dz) = (from_array(dt[0]), from_array(dt[1]), from_array(dt[2]));
        let (lx, ly, lz) = (from_array(lt[0]), from_array(lt[1]), from_array(lt[2]));
        let (mx, my, mz) = (from_array(mt[0]), from_array(mt[1]), from_array(mt[2]));
        let mut p = from_array(pos);
        let mut left = from_array(rem);
        // Walk until a lane ends its ray.
        let ended = loop {
            if TEST_FIRST {
                // Most marks are set already: read the words with one gather and write
                // only the lanes whose bit is not yet set.
                let word = _mm256_srli_epi64::<6>(p);
                let bit = _mm256_sllv_epi64(one, _mm256_and_si256(p, _mm256_set1_epi64x(63)));
                if lanes(_mm256_cmpgt_epi64(words, word)) != 0b1111 {
                    outside_the_box();
                }
                // SAFETY: every lane's `word < free.len()` (checked just above; lanes
                // without a ray read the sink's word), so every read is inside `free`.
                let w = unsafe { _mm256_i64gather_epi64::<8>(free.as_ptr().cast(), word) };
                let unset = lanes(_mm256_cmpeq_epi64(_mm256_and_si256(w, bit), zero));
                if unset != 0 {
                    let (word, bit) = (to_array(word), to_array(bit));
                    for l in BitIter(u64::from(unset)) {
                        free[word[l] as usize] |= bit[l] as u64;
                    }
                }
            } else {
                for q in to_array(p) {
                    set_bit(free, q as u64);
                }
            }
            // Step: the axis whose crossing comes first (ties x, y, z). Each axis's next
            // crossing (never after its last) is computed off the compare chain, as
            // `Dda::step` does.
            let gxy = _mm256_cmpgt_epi64(tx, ty);
            let gxz = _mm256_cmpgt_epi64(tx, tz);
            let gyz = _mm256_cmpgt_epi64(ty, tz);
            let nx =
                _mm256_blendv_epi8(_mm256_add_epi64(tx, dx), never, _mm256_cmpeq_epi64(tx, lx));
            let ny =
                _mm256_blendv_epi8(_mm256_add_epi64(ty, dy), never, _mm256_cmpeq_epi64(ty, ly));
            let nz =
                _mm256_blendv_epi8(_mm256_add_epi64(tz, dz), never, _mm256_cmpeq_epi64(tz, lz));
            let cx = _mm256_andnot_si256(_mm256_or_si256(gxy, gxz), ones);
            let cy = _mm256_andnot_si256(_mm256_or_si256(cx, gyz), ones);
            let cz = _mm256_andnot_si256(cx, gyz);
            tx = _mm256_blendv_epi8(tx, nx, cx);
            ty = _mm256_blendv_epi8(ty, ny, cy);
            tz = _mm256_blendv_epi8(tz, nz, cz);
            let inc = _mm256_or_si256(
                _mm256_or_si256(_mm256_and_si256(cx, mx), _mm256_and_si256(cy, my)),
                _mm256_and_si256(cz, mz),
            );
            p = _mm256_add_epi64(p, inc);
            left = _mm256_sub_epi64(left, one);
            let end = lanes(_mm256_cmpeq_epi64(left, zero));
            if end != 0 {
                break end;
            }
        };
        (st, pos, rem) = (
            [to_array(tx), to_array(ty), to_array(tz)],
            to_array(p),
            to_array(left),
        );
        for l in BitIter(u64::from(ended)) {
            if hit[l] {
                set_bit(hits, pos[l] as u64);
            }
        }
        live &= !ended;
        need = ended;
    }
    steps
}

/// A walk stepped outside its box: a bug, stopped before any read outside the marks.
#[cold]
#[inline(never)]
fn outside_the_box() -> ! {
    panic!("dense walk left its box");
}
