//! Dense per-thread marks for frames whose box is small (short-range sensors).
//!
//! When a frame's voxel box fits [`DENSE_BUDGET_WORDS`], each raycast thread marks into
//! its own row-major bit grid over the whole box: a voxel is one bit index, a step one add,
//! a mark one OR, and the grid stays in the thread's cache. The merge then ORs the threads'
//! grids leaf by leaf into the frame's [`FrameMarks`] slots, which the update reads as
//! it would after the sparse walk. Marks are OR-ed, so the result does not depend on which
//! thread walked which ray.

use super::covered::Covered;
use crate::coord::VoxelCoord;
use crate::integrate::marks::{FrameMarks, LeafCache};
use crate::integrate::ray::Ray;
use crate::raycast::Dda;
use rayon::prelude::*;
use std::ops::Range;
use std::sync::atomic::Ordering::Relaxed;

/// Largest dense grid per thread, in 64-bit words of free marks (hit marks take as many
/// again): 32 MiB, a box of about 640^3 voxels (30 m of range at 0.1 m). Beyond this,
/// frames take the sparse walk. Each pool thread keeps its grids' memory between frames:
/// up to 64 MiB per thread.
pub(super) const DENSE_BUDGET_WORDS: u64 = 1 << 22;

/// A frame's voxel box as a row-major bit grid: x fastest, rows padded to whole words,
/// every edge a multiple of 8 from a leaf-aligned corner, so a leaf's row of 8 voxels is
/// one byte of one word.
#[derive(Clone, Copy, Debug)]
pub(crate) struct DenseBox {
    pub(crate) lo: VoxelCoord,
    /// Voxels per axis: x a multiple of 64, y and z of 8.
    pub(crate) n: [u64; 3],
}

impl DenseBox {
    /// The box over voxels `lo..=hi`, if its grid fits the budget.
    pub(crate) fn new(lo: VoxelCoord, hi: VoxelCoord) -> Option<Self> {
        let lo = lo.shr(3).shl(3);
        let len = |a: i32, b: i32| (i64::from(b) - i64::from(a) + 1) as u64;
        let n = [
            len(lo.x, hi.x).next_multiple_of(64),
            len(lo.y, hi.y).next_multiple_of(8),
            len(lo.z, hi.z).next_multiple_of(8),
        ];
        let words = (n[0] / 64).checked_mul(n[1])?.checked_mul(n[2])?;
        (words <= DENSE_BUDGET_WORDS).then_some(Self { lo, n })
    }

    pub(crate) fn words(&self) -> usize {
        (self.n[0] / 64 * self.n[1] * self.n[2]) as usize
    }

    /// A bit index outside the box whose marks are ignored, for walkers that must mark
    /// something in every lane.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    pub(crate) fn sink(&self) -> u64 {
        self.words() as u64 * 64
    }

    /// Bit index of a voxel inside the box.
    #[inline]
    pub(crate) fn index(&self, v: VoxelCoord) -> u64 {
        let d = v - self.lo;
        debug_assert!(d.x >= 0 && d.y >= 0 && d.z >= 0);
        d.x as u64 + self.n[0] * (d.y as u64 + self.n[1] * d.z as u64)
    }

    /// The voxel at a bit index inside the box.
    pub(crate) fn voxel(&self, index: u64) -> VoxelCoord {
        let (x, yz) = (index % self.n[0], index / self.n[0]);
        self.lo + VoxelCoord::new(x as i32, (yz % self.n[1]) as i32, (yz / self.n[1]) as i32)
    }

    /// Bit index change of one voxel step along x, y and z.
    #[inline]
    pub(crate) fn strides(&self) -> [i64; 3] {
        [1, self.n[0] as i64, (self.n[0] * self.n[1]) as i64]
    }

    /// Rows of leaves (one per leaf y and z), the merge's unit of parallel work.
    pub(crate) fn leaf_rows(&self) -> usize {
        (self.n[1] / 8 * self.n[2] / 8) as usize
    }
}

/// One thread's marks over a [`DenseBox`], for one frame.
#[derive(Default)]
pub(crate) struct DenseBits {
    pub(crate) free: Vec<u64>,
    pub(crate) hit: Vec<u64>,
    /// The frame these marks belong to; marks of an older frame are stale.
    pub(crate) frame: u64,
}

impl DenseBits {
    /// Start `frame`'s marks over `words` words, unless already started.
    pub(crate) fn begin(&mut self, frame: u64, words: usize) {
        if self.frame != frame {
            self.frame = frame;
            // Four words more than the box: sinks, one per lane of the AVX2 walk.
            for v in [&mut self.free, &mut self.hit] {
                v.clear();
                v.resize(words + 4, 0);
            }
        }
    }

    pub(crate) fn frame(&self) -> u64 {
        self.frame
    }

    /// The free and the hit words, which the walks mark with [`set_bit`].
    pub(crate) fn words_mut(&mut self) -> (&mut [u64], &mut [u64]) {
        (&mut self.free, &mut self.hit)
    }
}

/// `f` of the grids of the pool threads that walked frame `frame`: they hold its marks, the
/// others' are stale.
pub(crate) fn with_live<R>(
    dense: &[std::sync::Mutex<DenseBits>],
    frame: u64,
    f: impl FnOnce(&[&DenseBits]) -> R,
) -> R {
    let guards: Vec<_> = dense.iter().map(|m| super::lock(m)).collect();
    let live: Vec<&DenseBits> = (guards.iter().map(|g| &**g))
        .filter(|g| g.frame() == frame)
        .collect();
    f(&live)
}

/// Set bit `index` of `words`.
#[inline(always)]
pub(super) fn set_bit(words: &mut [u64], index: u64) {
    or_bit(words, index, true);
}

/// Set bit `index` of `words` if `on`, without a branch: a write of nothing otherwise.
#[inline(always)]
pub(super) fn or_bit(words: &mut [u64], index: u64, on: bool) {
    words[(index / 64) as usize] |= u64::from(on) << (index % 64);
}

/// Walk the rays `rays[ranges[l]]` from `origin` one at a time, setting their free and hit
/// bits in `bits`; returns voxels on the rays and, of those, the ones not walked inside
/// `covered`. The dense walk where the build has no AVX-512: the same voxels as
/// `avx512::walk_dense`. As in the sparse walk, all steps but the last two skip the check
/// for an axis past its last crossing (`Dda::step_far_crossing`).
pub(crate) fn walk_rays(
    bits: &mut DenseBits,
    dbox: &DenseBox,
    origin: [f64; 3],
    rays: &[Ray],
    ranges: [Range<usize>; 8],
    covered: Option<&Covered>,
) -> (u64, u64) {
    let (mut steps, mut skipped) = (0, 0);
    let [ix, iy, iz] = dbox.strides();
    let (free, hits) = bits.words_mut();
    for r in ranges.into_iter().flat_map(|g| &rays[g]) {
        let mut dda = Dda::new(origin, r.end);
        steps += u64::from(dda.steps()) + 1;
        if let Some(c) = covered {
            let (t, d, last, dir) = dda.axes();
            let made = c.skip(t, d, last, dir);
            skipped += made.iter().sum::<u64>();
            dda = dda.after(made);
        }
        let n = dda.steps();
        let mut p = dbox.index(dda.voxel());
        if n > 2 {
            let [sx, sy, sz] = dda.direction();
            let inc =
                [i64::from(sx) * ix, i64::from(sy) * iy, i64::from(sz) * iz].map(|v| v as u64);
            for _ in 2..n {
                set_bit(free, p);
                let (cx, cy, _) = dda.step_far_crossing();
                p = p.wrapping_add(if cx {
                    inc[0]
                } else if cy {
                    inc[1]
                } else {
                    inc[2]
                });
            }
            let v = dbox.voxel(p);
            (dda.x, dda.y, dda.z) = (v.x, v.y, v.z);
            dda.settle();
        }
        while dda.steps() > 0 {
            set_bit(free, p);
            dda.step();
            p = dbox.index(dda.voxel());
        }
        if r.hit {
            set_bit(hits, p);
        }
    }
    (steps, skipped)
}

/// OR the threads' marks of this frame into `marks`, leaf by leaf; only leaves with a
/// mark get a slot. `marks` must be reset for the frame's box.
pub(crate) fn fold_into(marks: &FrameMarks, dbox: &DenseBox, bits: &[&DenseBits]) {
    let row_words = (dbox.n[0] / 64) as usize;
    let (ny, nby) = (dbox.n[1] as usize, dbox.n[1] as usize / 8);
    // A leaf row's marks into `cache`'s table.
    let fold_row = |cache: &mut LeafCache<'_>, r: usize| {
        let (by, bz) = (r % nby, r / nby);
        for wx in 0..row_words {
            // Word (wx) of the 64 rows of this leaf row: [z][y].
            let mut free = [[0u64; 8]; 8];
            let mut hit = [[0u64; 8]; 8];
            let mut any = 0;
            for z in 0..8 {
                for y in 0..8 {
                    let i = wx + row_words * (by * 8 + y + ny * (bz * 8 + z));
                    for b in bits {
                        free[z][y] |= b.free[i];
                        hit[z][y] |= b.hit[i];
                    }
                    any |= free[z][y] | hit[z][y];
                }
            }
            if any == 0 {
                continue;
            }
            // Byte k of a row word is leaf k's row; a leaf's word z holds its rows y as
            // bytes y.
            for k in 0..8 {
                let leaf_word = |rows: &[u64; 8]| {
                    (0..8).fold(0u64, |w, y| w | (rows[y] >> (8 * k) & 0xff) << (8 * y))
                };
                let f: [u64; 8] = std::array::from_fn(|z| leaf_word(&free[z]));
                let h: [u64; 8] = std::array::from_fn(|z| leaf_word(&hit[z]));
                if f.iter().chain(&h).all(|&w| w == 0) {
                    continue;
                }
                let origin = dbox.lo
                    + VoxelCoord::new((wx * 64 + k * 8) as i32, (by * 8) as i32, (bz * 8) as i32);
                let slot = cache.slot_for(origin.shr(3));
                // Each leaf belongs to one row, and only this pass writes slots: plain
                // stores suffice.
                for (w, v) in slot.free.iter().zip(f) {
                    w.store(v, Relaxed);
                }
                for (w, v) in slot.hit.iter().zip(h) {
                    w.store(v, Relaxed);
                }
            }
        }
    };
    // Runs of rows, a few per thread, each with one cache: a cache starts with 96 KiB of
    // empty entries, which a cache per row (225 rows in a small frame's box) spent 10% of
    // the frame filling.
    let rows = dbox.leaf_rows();
    let per = rows.div_ceil(4 * rayon::current_num_threads()).max(1);
    (0..rows.div_ceil(per)).into_par_iter().for_each(|run| {
        marks.with_cache(|cache| {
            for r in run * per..(run * per + per).min(rows) {
                fold_row(cache, r);
            }
        })
    });
}
