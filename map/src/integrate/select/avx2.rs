//! Cell keys and notes on AVX2: four rays at a time, bit for bit as [`CellKeys::key`] and
//! [`CellBox::note_of`]; and the rays made and noted in one pass ([`make_noted`]).

use super::{CellBox, Chooser, BEHIND};
use crate::integrate::ray::avx2::{load_ray, store4, transpose4, ExtentSum4, RayMaker4, Sides4};
use crate::integrate::ray::ExtentSum;
use crate::integrate::ray::{CellKeys, Ray, Sides};
use std::arch::x86_64::*;

/// Four rays (`rays.len() == 4`) as lanes: their x, y and z, and the word of key (bits
/// 0-31) and hit flag (bit 32).
#[target_feature(enable = "avx2")]
#[inline]
fn load4(rays: &[Ray]) -> [__m256d; 4] {
    assert_eq!(rays.len(), 4);
    transpose4([0, 1, 2, 3].map(|j| load_ray(&rays[j])))
}

/// `out[i] = c.key(&rays[i])` for four rays at a time; returns how many it keyed, a
/// multiple of four. The rest is left to the caller.
#[target_feature(enable = "avx2")]
pub(crate) fn keys(c: &CellKeys, rays: &[Ray], out: &mut [u64]) -> usize {
    let n = rays.len().min(out.len()) / 4 * 4;
    let f = _mm256_set1_pd(c.f);
    let base = c.base.map(|b| _mm256_set1_pd(b));
    let field = _mm256_set1_epi64x(CellKeys::FIELD as i64);
    let low32 = _mm256_set1_epi64x(0xffff_ffff);
    let top = _mm256_set1_epi64x(i64::MIN);
    for (o4, r4) in out[..n].chunks_exact_mut(4).zip(rays[..n].chunks_exact(4)) {
        let [x, y, z, w] = load4(r4);
        let w = _mm256_castpd_si256(w);
        let [kx, ky, kz] = [(x, 0), (y, 1), (z, 2)].map(|(v, a)| {
            let cell = _mm256_sub_pd(_mm256_floor_pd(_mm256_mul_pd(v, f)), base[a]);
            // Fields of rays within max range fit 21 bits (see `CellKeys`): exact in i32.
            _mm256_and_si256(_mm256_cvtepi32_epi64(_mm256_cvtpd_epi32(cell)), field)
        });
        let hit = _mm256_and_si256(_mm256_slli_epi64::<31>(w), top);
        let skipped = _mm256_cmpeq_epi64(_mm256_and_si256(w, low32), low32);
        let key = _mm256_or_si256(
            _mm256_or_si256(kx, _mm256_slli_epi64::<21>(ky)),
            _mm256_or_si256(_mm256_slli_epi64::<42>(kz), _mm256_or_si256(hit, skipped)),
        );
        // SAFETY: `o4` is four writable u64s; the store has no alignment requirement.
        unsafe { _mm256_storeu_si256(o4.as_mut_ptr().cast(), key) };
    }
    n
}

/// The constants of [`CellBox::note_of`] in vectors, to note four rays at a time.
struct Noter {
    f: __m256d,
    off: [__m256d; 3],
    last: [__m256d; 3],
    dx: __m256d,
    dy: __m256d,
    side: Sides4,
    hit_bit: __m256i,
    shift: __m128i,
}

impl Noter {
    #[target_feature(enable = "avx2")]
    fn new(b: &CellBox, c: &CellKeys, sides: &Sides) -> Self {
        let [dx, dy] = [0, 1].map(|a| _mm256_set1_pd(b.dims[a] as f64));
        Noter {
            f: _mm256_set1_pd(c.f),
            off: [0, 1, 2].map(|a| _mm256_set1_pd(c.base[a] + b.lo[a] as f64)),
            last: b.dims.map(|d| _mm256_set1_pd((d - 1) as f64)),
            dx,
            dy,
            side: Sides4::new(sides),
            hit_bit: _mm256_set1_epi64x(b.hit_bit as i64),
            shift: _mm_set_epi64x(0, b.hit_bit as i64),
        }
    }

    /// The notes of four rays given as lanes (x, y, z and the word of key and hit). The
    /// cell in doubles: every value is an integer below 2^26, exact; the side with the
    /// scalar code's operations in its order.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn note4(&self, [x, y, z, w]: [__m256d; 4]) -> __m256i {
        let zero = _mm256_setzero_pd();
        let low32 = _mm256_set1_epi64x(0xffff_ffff);
        let w = _mm256_castpd_si256(w);
        let [cx, cy, cz] = [(x, 0), (y, 1), (z, 2)].map(|(v, a)| {
            let cell = _mm256_sub_pd(_mm256_floor_pd(_mm256_mul_pd(v, self.f)), self.off[a]);
            _mm256_min_pd(_mm256_max_pd(cell, zero), self.last[a])
        });
        let cell = _mm256_add_pd(
            _mm256_mul_pd(_mm256_add_pd(_mm256_mul_pd(cz, self.dy), cy), self.dx),
            cx,
        );
        let cell = _mm256_cvtepi32_epi64(_mm256_cvtpd_epi32(cell));
        let hit = _mm256_and_si256(_mm256_srli_epi64::<32>(w), self.hit_bit);
        let skipped = _mm256_cmpeq_epi64(_mm256_and_si256(w, low32), low32);
        let back = _mm256_and_si256(
            _mm256_castpd_si256(self.side.behind([x, y, z])),
            _mm256_set1_epi64x(BEHIND as i64),
        );
        _mm256_or_si256(
            _mm256_or_si256(_mm256_sll_epi64(cell, self.shift), back),
            _mm256_or_si256(hit, skipped),
        )
    }
}

/// `out[i] = b.note_of(c, sides, &rays[i])` for four rays at a time; returns how many it
/// did, a multiple of four.
#[target_feature(enable = "avx2")]
pub(crate) fn notes(
    b: &CellBox,
    c: &CellKeys,
    sides: &Sides,
    rays: &[Ray],
    out: &mut [u64],
) -> usize {
    let n = rays.len().min(out.len()) / 4 * 4;
    let noter = Noter::new(b, c, sides);
    for (o4, r4) in out[..n].chunks_exact_mut(4).zip(rays[..n].chunks_exact(4)) {
        let note = noter.note4(load4(r4));
        // SAFETY: `o4` is four writable u64s; the store has no alignment requirement.
        unsafe { _mm256_storeu_si256(o4.as_mut_ptr().cast(), note) };
    }
    n
}

/// `RayMaker::make_all`, `ExtentSum::of_scalar` and [`notes`] in one pass, bit for bit: four
/// rays made at a time, stored to `made`, summed and noted from the vectors they were
/// made in; and the word of `set` holding each note's bit asked for, which the marking
/// of the chunk reads next. `None`, with nothing written, unless `pts` is a whole number
/// of fours as long as `made` and `notes`.
#[target_feature(enable = "avx2")]
pub(crate) fn make_noted(
    how: Chooser<'_>,
    pts: &[[f32; 3]],
    made: &mut [Ray],
    notes: &mut [u64],
    set: &[u64],
) -> Option<ExtentSum> {
    if !pts.len().is_multiple_of(4) || pts.len() != made.len() || made.len() != notes.len() {
        return None;
    }
    let m = how.maker;
    let maker = RayMaker4::new(m);
    let noter = Noter::new(how.cells_box, how.cells, how.sides);
    let mut sums = [ExtentSum4::new(m.origin), ExtentSum4::new(m.origin)];
    let ahead = super::as_made::worth_prefetching(set);
    for ((p4, o4), n4) in (pts.chunks_exact(4))
        .zip(made.chunks_exact_mut(4))
        .zip(notes.chunks_exact_mut(4))
    {
        let m4 = maker.make(p4);
        let lanes = m4.lanes();
        let note = noter.note4(lanes);
        // SAFETY: `n4` is four writable u64s; the store has no alignment requirement.
        unsafe { _mm256_storeu_si256(n4.as_mut_ptr().cast(), note) };
        // The marking reads each cell's word of `set` after the chunk is made: ask for
        // them now.
        super::as_made::prefetch_set_words(ahead, n4);
        let rays = transpose4(lanes);
        store4(o4, rays);
        m4.sum_into(&mut sums, &rays);
    }
    let [even, odd] = sums.map(|s| s.sum());
    Some(ExtentSum::join(even, odd))
}
