//! Phase 2, walk: every ray from the sensor origin through the voxels it crosses, with the
//! exact DDA ([`crate::raycast::Dda`]), its marks set in per-frame memory. Two walks with
//! the same result, each scalar, on AVX2 and on AVX-512, chosen in one place ([`plan`],
//! [`run`]):
//!
//! | walk | marks kept in | file |
//! |---|---|---|
//! | dense, one ray at a time | the thread's bit grid over the frame's box ([`dense::DenseBits`]) | `dense.rs` ([`dense::walk_rays`]) |
//! | dense, four / eight rays at a time | the same | `avx2/mod.rs` (`avx2::walk_dense`) / `avx512.rs` (`avx512::walk_dense`) |
//! | sparse, one ray at a time | the frame's mark tables ([`FrameMarks`]) | `sparse.rs` ([`sparse::walk_rays`]) |
//! | sparse, four / eight rays at a time | the same | `avx2/sparse.rs` (`avx2::walk_sparse`) / `avx512.rs` (`avx512::walk_sparse`) |
//!
//! `integrate::tests::walks::dense_and_sparse_walks_agree` checks every walk of every kernel
//! the CPU has against the others, map and counts. Each walk is an entry of the
//! [`crate::kernel::Kernels`] table the integrator holds.

use super::marks::FrameMarks;
use super::ray::{Ray, RAY_CHUNK};
use super::MAX_RANGE_VOXELS;
use crate::coord::VoxelCoord;
use crate::kernel::{DenseWalk, Kernels};
use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2;
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512;
pub(crate) mod covered;
pub(crate) mod dense;
pub(crate) mod sparse;

/// The dense box to walk a frame with `lo..=hi` and about `steps` voxel steps in, or `None`
/// for the sparse walk.
pub(super) fn plan(
    walk: Walk,
    lo: VoxelCoord,
    hi: VoxelCoord,
    steps: f64,
) -> Option<dense::DenseBox> {
    match walk {
        Walk::Sparse => None,
        // Zeroing and merging the dense grids cost about 15 ns per word, and a dense
        // step saved 4-8 ns against a one-ray sparse one (1.5-2.5 against 4-10 ns):
        // walk dense when the grid has at most a quarter as many words as the walk
        // has steps. A few rays in a big box walk sparse. (Not re-tuned for the
        // AVX-512 sparse walk, 2.5-4 ns a step at 60 m with its memory traffic.)
        Walk::Auto => dense::DenseBox::new(lo, hi).filter(|b| b.words() as f64 * 4.0 <= steps),
        Walk::Dense | Walk::DenseTestFirst | Walk::DenseGrouped => dense::DenseBox::new(lo, hi),
    }
}

/// Everything one walk needs of the frame and the integrator.
pub(super) struct WalkInput<'a> {
    pub origin: [f64; 3],
    pub rays: &'a [Ray],
    /// Per chunk of `rays`: how many lie on either side of the sensor (dense walk only).
    pub counts: &'a [[u32; 2]],
    /// About the voxel steps of the walk.
    pub steps: f64,
    /// Voxel bounds (inclusive) of the origin and every ray's end.
    pub bounds: (VoxelCoord, VoxelCoord),
    /// The rays' longest length, voxel units.
    pub range: f64,
    pub walk: Walk,
    pub kernels: &'static Kernels,
}

/// Walk all rays into `marks` (sparse) or the pool threads' dense grids for frame
/// `frame_no` (when `dense_box` is set); returns the voxels on the rays and, of those, the
/// ones the dense walk skipped in its covered box ([`covered`]).
pub(super) fn run(
    input: &WalkInput<'_>,
    marks: &FrameMarks,
    dense: &[std::sync::Mutex<dense::DenseBits>],
    dense_box: Option<&dense::DenseBox>,
    frame_no: u64,
) -> (u64, u64) {
    match dense_box {
        None => (run_sparse(marks, input), 0),
        Some(b) => run_dense(dense, b, frame_no, input),
    }
}

/// Where a dense walk finds its covered box: its tasks walk in stages, the first whole
/// rays, and before each later stage the box is found again in the marks of all the rays
/// walked so far, which may hold a bigger one (docs/design.md, "The covered box"). Stage
/// `i` ends after `1 / STAGES[i]` of the tasks; the tasks' rays come from all of the scan
/// (see `run_dense`).
const STAGES: [usize; 3] = [32, 8, 2];

/// The dense walk: rays laid out by `Sides` with counts `input.counts`, into the pool
/// threads' grids for frame `frame_no`; returns the voxels on the rays and, of those, the
/// ones skipped in the covered box. The first tasks walk whole rays; the box is then found
/// in their marks, and the other tasks' rays skip it (see [`STAGES`]).
fn run_dense(
    dense: &[std::sync::Mutex<dense::DenseBits>],
    dbox: &dense::DenseBox,
    frame_no: u64,
    input: &WalkInput<'_>,
) -> (u64, u64) {
    let &WalkInput {
        origin,
        rays,
        counts,
        steps,
        bounds,
        range,
        walk,
        kernels,
    } = input;
    // Tasks walk the front sides of the chunks first, then the back sides: rayon hands the
    // first half of the tasks to one thread and the second half to another, so each
    // thread's rays mostly stay in its half of the box (work stealing evens out uneven
    // sides). Lane l of a task walks a chunk of the l-th eighth: in a sensor's scan order
    // (or sorted) these are far apart in direction (see `avx512::walk_dense`).
    let per_lane = counts.len().div_ceil(8);
    let part = |back: bool, l: usize, c: usize| {
        let k = l * per_lane + c;
        let Some(&[n_front, n_back]) = counts.get(k) else {
            return 0..0;
        };
        let start = k * RAY_CHUNK;
        let end = (start + RAY_CHUNK).min(rays.len());
        if back {
            end - n_back as usize..end
        } else {
            start..start + n_front as usize
        }
    };
    // Only the AVX-512 walk has this choice.
    #[cfg(not(target_arch = "x86_64"))]
    let test_first = {
        let _ = steps;
        false
    };
    #[cfg(target_arch = "x86_64")]
    let test_first = avx512::test_first(steps / (dbox.words() as f64 * 64.0));
    // The rays' mean steps, as estimated before the walk.
    let per_ray = steps / rays.len().max(1) as f64;
    let tasks =
        |stage: std::ops::Range<usize>, covered: Option<&covered::Covered>, test_first: bool| {
            // Steps a ray walks outside the covered box, on average (its sample's savings).
            let walked = per_ray - covered.map_or(0.0, |c| c.saves as f64);
            #[cfg(target_arch = "x86_64")]
            let grouped = match walk {
                Walk::DenseGrouped => true,
                Walk::Auto => avx2::walks_grouped(walked),
                _ => false,
            };
            // Only the AVX2 walk has this choice.
            #[cfg(not(target_arch = "x86_64"))]
            let grouped = {
                let _ = walked;
                false
            };
            (0..2 * per_lane)
                .into_par_iter()
                .filter(move |t| stage.contains(&(t % per_lane)))
                .map(|t| {
                    // Each pool thread has its own grids, so the lock is never contended.
                    let mut bits =
                        lock(&dense[rayon::current_thread_index().unwrap_or(0) % dense.len()]);
                    bits.begin(frame_no, dbox.words());
                    let ranges = std::array::from_fn(|l| part(t >= per_lane, l, t % per_lane));
                    let how = DenseWalk {
                        dbox,
                        origin,
                        covered,
                        test_first,
                        grouped,
                    };
                    (kernels.walk_dense)(&mut bits, rays, ranges, &how)
                })
                .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
        };
    let find = || {
        dense::with_live(dense, frame_no, |live| {
            covered::Covered::find(live, dbox, origin, range, bounds, rays)
        })
    };
    let (mut steps, mut skipped, mut from, mut covered) = (0, 0, 0, None);
    for k in STAGES
        .into_iter()
        .map(|k| per_lane.div_ceil(k))
        .chain([per_lane])
    {
        // A stage of one task a side would leave a thread idle at its end.
        if k < (from + 2).min(per_lane) || k == from {
            continue;
        }
        if from > 0 {
            covered = find().or(covered);
        }
        // Testing marks first pays where most repeat: not in the covered box, which the
        // rays skip, nor early in the frame, when the grids are still mostly empty.
        let test = walk == Walk::DenseTestFirst
            || test_first && covered.is_none() && from >= per_lane.div_ceil(8);
        let (s, c) = tasks(from..k, covered.as_ref(), test);
        (steps, skipped, from) = (steps + s, skipped + c, k);
    }
    (steps, skipped)
}

/// The sparse walk: all rays, sorted by direction, into `marks` in parallel chunks;
/// returns voxels visited.
fn run_sparse(marks: &FrameMarks, input: &WalkInput<'_>) -> u64 {
    let &WalkInput {
        origin,
        rays,
        kernels,
        ..
    } = input;
    rays.par_chunks(RAY_CHUNK)
        .map(|chunk| (kernels.walk_sparse)(marks, origin, chunk))
        .sum()
}

/// A vector's lanes stored once and loaded back one by one, for the vector walks' marks:
/// fewer instructions than moving each lane to a general register (`vpextrq` is two
/// micro-ops, and the moves hold the vector ports a step needs).
#[cfg(target_arch = "x86_64")]
#[repr(align(64))]
struct Spill<const N: usize>([u64; N]);

#[cfg(target_arch = "x86_64")]
impl<const N: usize> Spill<N> {
    #[inline(always)]
    fn new() -> Self {
        Spill([0; N])
    }

    /// Where a vector store puts the lanes: `8 * N` bytes, aligned to 64.
    #[inline(always)]
    fn ptr(&mut self) -> *mut u64 {
        self.0.as_mut_ptr()
    }

    /// The lanes, each loaded from memory. The loads are volatile because the compiler
    /// otherwise turns them back into lane moves.
    #[inline(always)]
    fn lanes(&self) -> impl Iterator<Item = u64> + '_ {
        // SAFETY: each `q` is a valid, aligned, initialised u64 of `self`.
        self.0.iter().map(|q| unsafe { std::ptr::read_volatile(q) })
    }
}

/// A voxel of a sparse walk packed in one `u64`, 21 bits per axis, relative to an origin
/// near the rays' start: a step is one add of a stride, a field's low 3 bits are the
/// voxel's offset in its leaf, and a change above them is a new leaf.
#[derive(Clone, Copy)]
pub(super) struct Packed {
    /// The voxel that packs to 0: leaf-aligned, `BIAS` below the start on every axis.
    o: VoxelCoord,
}

impl Packed {
    const F: u32 = 21;
    const BIAS: i32 = 1 << 19;
    /// Index change of one voxel step along x, y and z.
    const STRIDES: [i64; 3] = [1, 1 << Self::F, 1 << (2 * Self::F)];
    /// Bits of a field above its low 3.
    const LEAF: u64 = !(7 | 7 << Self::F | 7 << (2 * Self::F));
    /// Bits of the z field (for the vector walks).
    #[cfg(target_arch = "x86_64")]
    const Z_FIELD: u64 = !0 << (2 * Self::F);

    /// Packing for rays that start at `v`. Rays end within max range of their start, so
    /// no field under- or overflows.
    fn around(v: VoxelCoord) -> Self {
        const _: () = assert!(MAX_RANGE_VOXELS as i32 + 16 < Packed::BIAS);
        let b = Self::BIAS;
        Packed {
            o: v.shr(3).shl(3) - VoxelCoord::new(b, b, b),
        }
    }

    #[inline]
    fn pack(&self, v: VoxelCoord) -> u64 {
        let d = v - self.o;
        u64::from(d.x as u32)
            | u64::from(d.y as u32) << Self::F
            | u64::from(d.z as u32) << (2 * Self::F)
    }

    #[inline]
    fn unpack(&self, p: u64) -> VoxelCoord {
        let m = (1u64 << Self::F) - 1;
        let (f, f2) = (Self::F, 2 * Self::F);
        self.o + VoxelCoord::new((p & m) as i32, (p >> f & m) as i32, (p >> f2) as i32)
    }
}

/// The walks an integrator can take; tests force each in turn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(not(test), allow(dead_code))]
pub(crate) enum Walk {
    /// Dense when the frame's box fits the budget and its rays are many enough to pay for
    /// the grids, sparse otherwise.
    Auto,
    /// Sparse.
    Sparse,
    /// Dense whenever the box fits the budget; the AVX2 kernel refills each lane as its
    /// ray ends, whatever the rays' length (see `walk::avx2::walks_grouped`).
    Dense,
    /// Dense, testing each mark before writing it on every frame (see
    /// `walk::avx512::walk_dense`; the other kernels walk `Dense`).
    DenseTestFirst,
    /// Dense, the AVX2 kernel walking its rays in groups on every frame (the other kernels
    /// walk `Dense`).
    DenseGrouped,
}

fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}
