//! Phase 1, prepare: a frame's points become rays in voxel units (pose, face snap,
//! max-range cut), laid out by the sides of the sensor ([`Sides`]) as they are made, with
//! the frame's extent summed up in the same pass ([`ExtentSum`]); the trade-off modes
//! choose in the same pass (subsample and unique-end in a box about the sensor) or from
//! notes of it ([`super::thin`]) and drop the rest from the layout ([`compact`]); the
//! sparse walk gets them sorted by direction ([`order_by_direction`]).

use super::thin::{cell_factor, make_firsts, thin_out, Buffers, CellBox, CellKeys, Chooser, Kept};
use super::{Frame, RayMode};
use crate::coord::{units_to_voxel, VoxelCoord};
use crate::kernel::Kernels;
use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2;
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512;

/// Rays per parallel task of the walk, and per chunk of the layout by sides.
pub(super) const RAY_CHUNK: usize = 512;

/// A ray from the frame's sensor origin. `repr(C)` with explicit padding, so that every
/// byte is initialised and the dense walk can gather whole fields from a slice of rays:
/// `end` at offset 0, `key` at 24, `hit` at 28, 32 bytes in all. Aligned to its size, so
/// that the vector kernels load and store a ray whole in one aligned access (unaligned
/// 32-byte accesses are split in two by the compiler's generic x86-64 tuning).
#[derive(Clone, Copy, Debug, bytemuck::Zeroable)]
#[repr(C, align(32))]
pub(crate) struct Ray {
    pub(crate) end: [f64; 3],
    pub(crate) key: u32,
    pub(crate) hit: bool,
    pub(crate) pad: [u8; 3],
}

const _: () = assert!(std::mem::size_of::<Ray>() == 32);

impl Ray {
    pub(crate) fn new(end: [f64; 3], key: u32, hit: bool) -> Self {
        Ray {
            end,
            key,
            hit,
            pad: [0; 3],
        }
    }
}

/// Octahedral direction key, Morton-interleaved: rays with close directions get close keys.
#[inline]
pub(super) fn direction_key(d: [f64; 3]) -> u32 {
    let s = d[0].abs() + d[1].abs() + d[2].abs();
    if s == 0.0 {
        return 0;
    }
    let inv = 1.0 / s;
    let (mut u, mut v) = (d[0] * inv, d[1] * inv);
    if d[2] < 0.0 {
        let (au, av) = (u.abs(), v.abs());
        u = (1.0 - av).copysign(u);
        v = (1.0 - au).copysign(v);
    }
    let qu = ((u + 1.0) * 32767.5) as u32 & 0xffff;
    let qv = ((v + 1.0) * 32767.5) as u32 & 0xffff;
    (spread16(qu) | spread16(qv) << 1).min(SKIPPED - 1)
}

pub(super) fn set_direction_keys(rays: &mut [Ray], origin: [f64; 3]) {
    rays.par_iter_mut()
        .for_each(|r| r.key = direction_key([0, 1, 2].map(|a| r.end[a] - origin[a])));
}

/// The key of a ray from a non-finite point, never a direction's key.
pub(super) const SKIPPED: u32 = u32::MAX;

#[inline]
pub(crate) fn spread16(x: u32) -> u32 {
    let mut x = x & 0xffff;
    x = (x | x << 8) & 0x00ff_00ff;
    x = (x | x << 4) & 0x0f0f_0f0f;
    x = (x | x << 2) & 0x3333_3333;
    (x | x << 1) & 0x5555_5555
}

/// Put the rays in the sparse walk's order: gaps of skipped points and dropped rays
/// closed, sorted by direction, so that neighbouring rays walk neighbouring memory.
pub(super) fn order_by_direction(rays: &mut Vec<Ray>, sides: &[[u32; 2]], origin: [f64; 3]) {
    let mut to = 0;
    for (c, &[front, back]) in sides.iter().enumerate() {
        let at = c * RAY_CHUNK;
        let len = (rays.len() - at).min(RAY_CHUNK);
        let (front, back) = (front as usize, back as usize);
        rays.copy_within(at..at + front, to);
        rays.copy_within(at + len - back..at + len, to + front);
        to += front + back;
    }
    rays.truncate(to);
    set_direction_keys(rays, origin);
    rays.par_sort_unstable_by_key(|r| r.key);
}

/// Fill `rays` from the frame, laid out by `halves` with the counts per chunk in `sides`;
/// returns the number of non-finite points skipped, the rays' extent, and the time a
/// trade-off mode took to choose its rays and drop the others from the layout
/// ([`compact`]).
#[allow(clippy::too_many_arguments)]
pub(super) fn prepare_rays(
    rays: &mut Vec<Ray>,
    sides: &mut Vec<[u32; 2]>,
    halves: Sides,
    frame: &Frame<'_>,
    tf: &crate::coord::GridTransform,
    origin: [f64; 3],
    range_units: f64,
    mode: RayMode,
    kernels: &'static Kernels,
    thin: &mut Buffers,
) -> (u64, Extent, std::time::Duration) {
    let maker = RayMaker::new(frame, tf, origin, range_units, kernels);
    // One pass writes the rays, lays them out and sums up their extent: a frame's rays
    // (16 MB for 500k points) outgrow the cache, and passes of their own to count the
    // skipped points and take the bounds cost a third of the prepare phase (structured
    // 500k 6 m: 7.8 ms, of which 1.4 ms bounds and 0.5 ms counting, 2 threads). `rays`
    // keeps its length from frame to frame, so `resize` writes only where this frame has
    // more points than the last.
    let n = frame.points.len();
    rays.truncate(n);
    rays.resize(n, Ray::new([0.0; 3], SKIPPED, false));
    sides.clear();
    sides.resize(n.div_ceil(RAY_CHUNK), [0; 2]);
    let cells = CellKeys::new(origin, cell_factor(mode));
    let around = match mode {
        RayMode::Subsample { .. } | RayMode::UniqueEnd => {
            CellBox::around(origin, range_units, &cells)
        }
        RayMode::Exact | RayMode::Bundle { .. } => None,
    };
    if let Some(cells_box) = around {
        // Every end the frame can have fits a bit set: the rays are chosen as they are
        // made ([`make_firsts`]).
        let how = Chooser {
            maker: &maker,
            halves: &halves,
            cells: &cells,
            cells_box: &cells_box,
            centre: mode == RayMode::UniqueEnd,
        };
        let (sums, cut, took) = make_firsts(rays, sides, frame.points, how, &mut thin.firsts);
        return (sums.skipped, kept_extent(&sums, n, sides, cut), took);
    }
    let chunks = rays
        .par_chunks_mut(RAY_CHUNK)
        .zip(frame.points.par_chunks(RAY_CHUNK))
        .zip(sides.par_iter_mut());
    let sums = if mode == RayMode::Exact {
        chunks
            .map_init(Vec::new, |made, ((out, pts), side)| {
                let (counts, _, sum) = halves.make(&maker, pts, out, made, None);
                *side = counts;
                sum
            })
            .reduce(|| ExtentSum::new(origin), ExtentSum::join)
    } else {
        // The trade-off modes choose rays in scan order: the same pass notes each ray's
        // cell, in scan order, and where the layout put it, so that choosing reads 8 bytes
        // a ray instead of the ray, and dropping rays is a compaction of the layout.
        let (keys, orders) = thin.notes(n);
        chunks
            .zip(keys.par_chunks_mut(RAY_CHUNK))
            .zip(orders.par_iter_mut())
            .map_init(Vec::new, |made, ((((out, pts), side), keys), order)| {
                let note = Some((&cells, keys));
                let (counts, o, sum) = halves.make(&maker, pts, out, made, note);
                (*side, *order) = (counts, o);
                sum
            })
            .reduce(|| ExtentSum::new(origin), ExtentSum::join)
    };
    let skipped = sums.skipped;
    if mode == RayMode::Exact {
        return (skipped, sums.extent(), std::time::Duration::ZERO);
    }
    let t = std::time::Instant::now();
    let (kept, orders) = thin_out(rays, origin, mode, &sums.extent(), thin);
    let cut = compact(rays, sides, orders, &kept);
    let thinned = t.elapsed();
    (skipped, kept_extent(&sums, n, sides, cut), thinned)
}

/// The extent of the rays a trade-off mode kept of a frame's `points` (laid out with the
/// counts `sides`, `cut` of them cut at max range), from the sum over all rays made: the
/// box of all rays holds those kept (a kept ray moves only within its end voxel), and the
/// walk's length is taken as the share of rays kept.
fn kept_extent(sums: &ExtentSum, points: usize, sides: &[[u32; 2]], cut: u64) -> Extent {
    let mut extent = sums.extent();
    let made = (points as u64 - sums.skipped).max(1) as f64;
    extent.steps *= ray_count(sides) as f64 / made;
    extent.cut_rays = cut;
    extent
}

/// Drop from the layout of each chunk the rays `kept` does not keep (a bundle's mean is
/// already in its first ray's place); `orders` says which ray of the scan lies where
/// ([`ChunkOrder`]). `sides` gets the new counts (what lies between is left as it was,
/// not rays); returns how many rays kept are cut at max range.
pub(super) fn compact(
    rays: &mut [Ray],
    sides: &mut [[u32; 2]],
    orders: &[ChunkOrder],
    kept: &Kept<'_>,
) -> u64 {
    rays.par_chunks_mut(RAY_CHUNK)
        .zip(sides.par_iter_mut())
        .zip(orders.par_iter())
        .enumerate()
        .map(|(c, ((chunk, side), order))| {
            let (places, cut) = kept.by_place(c * RAY_CHUNK, chunk.len(), order);
            *side = places.map(|p| p.iter().map(|w| w.count_ones()).sum());
            let len = chunk.len();
            fill_holes(&places[0], |p| p, chunk);
            fill_holes(&places[1], |p| len - 1 - p, chunk);
            if kept.centres() {
                let [front, back] = side.map(|n| n as usize);
                let (ahead, behind) = chunk.split_at_mut(len - back);
                for r in ahead[..front].iter_mut().chain(behind) {
                    *r = kept.finish(r);
                }
            }
            cut
        })
        .sum()
}

/// The rays a side of a chunk keeps, to the side's first places: `keep` has bit `p` for
/// each ray kept at the side's place `p`, which is `at(p)` in the chunk. The kept rays
/// past the first places fill the holes there, in order: the walk's result does not
/// depend on the order of the rays, and a ray moves only if a hole is left for it.
fn fill_holes(keep: &[u64; RAY_CHUNK / 64], at: impl Fn(usize) -> usize, chunk: &mut [Ray]) {
    let n: usize = keep.iter().map(|w| w.count_ones() as usize).sum();
    let first = |w: usize| first_bits(n, w);
    let ones = |m: [u64; RAY_CHUNK / 64]| {
        (0..RAY_CHUNK / 64).flat_map(move |w| Ones(m[w]).map(move |b| w * 64 + b))
    };
    let holes = ones(std::array::from_fn(|w| !keep[w] & first(w)));
    let moved = ones(std::array::from_fn(|w| keep[w] & !first(w)));
    for (h, m) in holes.zip(moved) {
        chunk[at(h)] = chunk[at(m)];
    }
}

/// Word `w` of a chunk's mask of its first `n` places.
fn first_bits(n: usize, w: usize) -> u64 {
    match n.saturating_sub(w * 64) {
        0 => 0,
        bits @ 1..64 => (1u64 << bits) - 1,
        _ => !0,
    }
}

/// The places of a word's set bits, lowest first.
pub(crate) struct Ones(pub(crate) u64);

impl Iterator for Ones {
    type Item = usize;

    #[inline]
    fn next(&mut self) -> Option<usize> {
        let b = (self.0 != 0).then(|| self.0.trailing_zeros() as usize);
        self.0 &= self.0.wrapping_sub(1);
        b
    }
}

/// Which rays of a chunk, by their place in the scan, a layout by [`Sides`] put in front
/// and which behind (bit `j` of word `j / 64`); the rays of skipped points in neither.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct ChunkOrder {
    pub(crate) front: [u64; RAY_CHUNK / 64],
    pub(crate) back: [u64; RAY_CHUNK / 64],
    /// The rays cut at max range (noted for the trade-off modes only).
    pub(crate) cut: [u64; RAY_CHUNK / 64],
}

impl ChunkOrder {
    /// All of a chunk's `len` rays in front, in scan order.
    fn all_front(len: usize) -> Self {
        ChunkOrder {
            front: std::array::from_fn(|w| first_bits(len, w)),
            ..ChunkOrder::default()
        }
    }

    /// Where the layout put each ray of the chunk's scan (as long as the chunk): the
    /// place within the chunk of each but the skipped points' rays.
    pub(crate) fn places(&self, out: &mut [u16]) {
        let len = out.len();
        let mut k = 0;
        for (w, &m) in self.front.iter().enumerate() {
            for b in Ones(m) {
                out[w * 64 + b] = k;
                k += 1;
            }
        }
        let mut k = len as u16;
        for (w, &m) in self.back.iter().enumerate() {
            for b in Ones(m) {
                k -= 1;
                out[w * 64 + b] = k;
            }
        }
    }
}

/// The two sides of a plane through the sensor, across one of its axes: the one that
/// splits the frame's rays most evenly (sideways for a camera, front and back or sideways
/// for a lidar), by which the dense walk gives each thread its own half of the box.
///
/// Each chunk of [`RAY_CHUNK`] rays holds its rays in front of the plane first, those
/// behind it last, and the rays of skipped points (gaps) between.
///
/// Why: with test-first marks, a voxel's first mark in a thread's grid costs a write and a
/// mispredicted branch. Fed rays of every direction, each of two threads first-marked
/// nearly the whole box, twice the first marks of one thread, and a chunk of rays took 20%
/// longer at 2 threads than at 1 (random 500k 6 m). Laying out costs no pass over memory
/// of its own: the rays of a chunk are laid out as they are made.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Sides {
    pub(crate) origin: [f64; 3],
    /// The plane's normal in the world frame, a sensor axis; none for a one-thread pool,
    /// where all rays count as in front. One thread has no second grid to share first marks
    /// with, and in halves its lanes walk rays nearer in direction: laid out, its frames
    /// took 3-9% longer (500k 6 m workloads, three alternated rounds).
    pub(crate) axis: Option<[f64; 3]>,
}

impl Sides {
    /// Points sampled to choose the axis.
    pub(crate) const SAMPLES: usize = 1024;

    /// The sides for `frame` on a pool of `threads`: across the sensor axis whose plane
    /// halves the rays' lengths best, in a sample of the points (a sensor looking along one
    /// of its axes, as a camera along z or a forward lidar along x, has no ray behind it).
    pub(crate) fn new(frame: &Frame<'_>, origin: [f64; 3], threads: usize) -> Self {
        if threads < 2 {
            return Sides { origin, axis: None };
        }
        let pts = frame.points;
        let mut behind = [0.0f64; 3];
        let mut all = 0.0;
        for p in pts.iter().step_by((pts.len() / Self::SAMPLES).max(1)) {
            let p = p.map(f64::from);
            let len = p[0].abs() + p[1].abs() + p[2].abs();
            if len.is_finite() {
                all += len;
                (0..3).for_each(|a| behind[a] += if p[a] < 0.0 { len } else { 0.0 });
            }
        }
        let off = |a: usize| (2.0 * behind[a] - all).abs();
        let a = (0..3).fold(0, |best, a| if off(a) < off(best) { a } else { best });
        let axis = frame.pose.rotation * nalgebra::Vector3::ith(a, 1.0);
        Sides {
            origin,
            axis: Some(axis.into()),
        }
    }

    /// Make the rays to `pts` into `out`, as long, laid out; returns how many lie in front
    /// and behind, where the layout put each, and their extent. With `note`, each ray's
    /// cell key goes into its slice (as long as `pts`) and the cut rays into the order's
    /// `cut`. `made` is scratch.
    pub(crate) fn make(
        &self,
        maker: &RayMaker,
        pts: &[[f32; 3]],
        out: &mut [Ray],
        made: &mut Vec<Ray>,
        note: Option<(&CellKeys, &mut [u64])>,
    ) -> ([u32; 2], ChunkOrder, ExtentSum) {
        // With `note`: the cell keys, and which rays are cut, in scan order.
        let notes = |rays: &[Ray], note: Option<(&CellKeys, &mut [u64])>| {
            let mut cut = [0u64; RAY_CHUNK / 64];
            if let Some((cells, keys)) = note {
                cells.keys(maker.kernels, rays, keys);
                for (j, r) in rays.iter().enumerate() {
                    cut[j / 64] |= u64::from(r.key != SKIPPED && !r.hit) << (j % 64);
                }
            }
            cut
        };
        if self.axis.is_some() {
            if note.is_none() {
                if let Some(laid) = (maker.kernels.make_laid_out)(maker, self, pts, out) {
                    return laid;
                }
            }
            made.resize(out.len(), Ray::new([0.0; 3], SKIPPED, false));
            maker.make_all(made, pts);
            let cut = notes(made, note);
            let (counts, order) = self.lay_out(made, out);
            let sum = (maker.kernels.extent_of)(self.origin, made);
            return (counts, ChunkOrder { cut, ..order }, sum);
        }
        // All in front: in place, unless points were skipped.
        maker.make_all(out, pts);
        let cut = notes(out, note);
        let sum = (maker.kernels.extent_of)(self.origin, out);
        if sum.skipped == 0 {
            let order = ChunkOrder::all_front(out.len());
            return ([out.len() as u32, 0], ChunkOrder { cut, ..order }, sum);
        }
        let (counts, order) = self.lay_out_in_place(out, made);
        (counts, ChunkOrder { cut, ..order }, sum)
    }

    /// Lay the rays `made` out into `out`, as long; returns how many lie in front and
    /// behind, and where each went. The rays of skipped points leave gaps.
    pub(crate) fn lay_out(&self, made: &[Ray], out: &mut [Ray]) -> ([u32; 2], ChunkOrder) {
        let (mut front, mut back) = (0, out.len());
        let mut order = ChunkOrder::default();
        for (w, block) in made.chunks(64).enumerate() {
            // The words of `order` built in registers: or-ing into memory made a chain of
            // loads and stores through the whole loop.
            let (mut ahead, mut made) = (0u64, 0u64);
            for (b, r) in block.iter().enumerate().filter(|(_, r)| r.key != SKIPPED) {
                let behind = self.behind(r.end);
                // A select, not a branch: the side is a coin flip in many scans. A ray is
                // left to place, so `front < back`.
                out[if behind { back - 1 } else { front }] = *r;
                front += usize::from(!behind);
                back -= usize::from(behind);
                ahead |= u64::from(!behind) << b;
                made |= 1 << b;
            }
            order.front[w] = ahead;
            order.back[w] = made & !ahead;
        }
        out[front..back].fill(Ray::new([0.0; 3], SKIPPED, false));
        ([front as u32, (out.len() - back) as u32], order)
    }

    /// Whether a ray to `end` lies behind the plane (never, across no axis).
    #[inline]
    pub(crate) fn behind(&self, end: [f64; 3]) -> bool {
        let (o, x) = (self.origin, self.axis.unwrap_or([0.0; 3]));
        let d = [0, 1, 2].map(|a| end[a] - o[a]);
        d[0] * x[0] + d[1] * x[1] + d[2] * x[2] < 0.0
    }

    /// [`Sides::lay_out`] of `chunk` into itself, through `scratch`.
    pub(crate) fn lay_out_in_place(
        &self,
        chunk: &mut [Ray],
        scratch: &mut Vec<Ray>,
    ) -> ([u32; 2], ChunkOrder) {
        scratch.clear();
        scratch.extend_from_slice(chunk);
        self.lay_out(scratch, chunk)
    }
}

/// Rays in chunks laid out with counts `sides` (not their length: gaps are not rays).
pub(crate) fn ray_count(sides: &[[u32; 2]]) -> u64 {
    sides.iter().map(|&[f, b]| u64::from(f + b)).sum()
}

/// Makes a frame's rays from its points: sensor frame to world by the pose, to voxel units
/// (snapped onto faces, see `GridTransform::to_units`), cut at max range.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RayMaker {
    /// Rotation rows and translation of the pose.
    pub(crate) rot: [[f64; 3]; 3],
    pub(crate) t: [f64; 3],
    pub(crate) tf: crate::coord::GridTransform,
    pub(crate) origin: [f64; 3],
    pub(crate) range_units: f64,
    /// Below this squared length a ray surely ends within range; above it, the same
    /// comparison as the reference, `sqrt(len2) <= range_units`, decides.
    pub(crate) surely_in: f64,
    /// The kernel whose entries make and note the rays.
    pub(crate) kernels: &'static Kernels,
}

impl RayMaker {
    pub(crate) fn new(
        frame: &Frame<'_>,
        tf: &crate::coord::GridTransform,
        origin: [f64; 3],
        range_units: f64,
        kernels: &'static Kernels,
    ) -> Self {
        let r = frame.pose.rotation.to_rotation_matrix().into_inner();
        RayMaker {
            rot: [0, 1, 2].map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]),
            t: frame.pose.translation.vector.into(),
            tf: *tf,
            origin,
            range_units,
            surely_in: range_units * range_units * (1.0 - 1e-9),
            kernels,
        }
    }

    /// The ray to `p`; a non-finite point gives a ray keyed `SKIPPED`. The arithmetic is
    /// spelled out (no library product) so that `avx512::make_rays` can repeat it
    /// operation for operation.
    #[inline]
    pub(crate) fn make(&self, p: &[f32; 3]) -> Ray {
        if !p.iter().all(|c| c.is_finite()) {
            return Ray::new([0.0; 3], SKIPPED, false);
        }
        let [x, y, z] = p.map(f64::from);
        let mut e = [0, 1, 2].map(|i| {
            let r = self.rot[i];
            self.tf.to_units(r[0] * x + r[1] * y + r[2] * z + self.t[i])
        });
        let o = self.origin;
        let d = [e[0] - o[0], e[1] - o[1], e[2] - o[2]];
        let len2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        let hit = len2 < self.surely_in || len2.sqrt() <= self.range_units;
        if !hit {
            let s = self.range_units / len2.sqrt();
            e = [0, 1, 2].map(|a| o[a] + d[a] * s);
        }
        Ray::new(e, 0, hit)
    }

    /// `out[i] = self.make(&pts[i])`, eight at a time with the AVX-512 kernel, four with AVX2.
    pub(crate) fn make_all(&self, out: &mut [Ray], pts: &[[f32; 3]]) {
        let done = (self.kernels.make_rays)(self, out, pts);
        for (r, p) in out.iter_mut().zip(pts).skip(done) {
            *r = self.make(p);
        }
    }
}

/// [`Extent`] of `rays`, in one pass (the layout of thinned rays sums it on the way).
#[cfg(test)]
pub(crate) fn bounds(rays: &[Ray], origin: [f64; 3]) -> Extent {
    rays.par_chunks(RAY_CHUNK)
        .map(|c| ExtentSum::of_scalar(origin, c))
        .reduce(|| ExtentSum::new(origin), ExtentSum::join)
        .extent()
}

/// [`Extent`] being summed up over rays; skipped rays (non-finite points) are counted
/// apart. Bounds are taken on the ends in voxel units and floored once: floor is monotone,
/// so that is the bounds of the ends' voxels.
#[derive(Clone, Copy)]
pub(crate) struct ExtentSum {
    pub(crate) origin: [f64; 3],
    pub(crate) lo: [f64; 3],
    pub(crate) hi: [f64; 3],
    pub(crate) cut: u64,
    /// The rays' lengths along each axis (a sum per axis: one sum was a chain of adds
    /// that took most of the pass).
    pub(crate) length: [f64; 3],
    pub(crate) skipped: u64,
}

impl ExtentSum {
    pub(crate) fn new(origin: [f64; 3]) -> Self {
        ExtentSum {
            origin,
            lo: origin,
            hi: origin,
            cut: 0,
            length: [0.0; 3],
            skipped: 0,
        }
    }

    /// The sum over `rays`, portably (each kernel's `extent_of` in [`Kernels`]).
    pub(crate) fn of_scalar(origin: [f64; 3], rays: &[Ray]) -> Self {
        // Two sums over alternate rays, so that two chains of dependent operations overlap.
        let mut s = [ExtentSum::new(origin); 2];
        let mut pairs = rays.chunks_exact(2);
        for p in &mut pairs {
            s[0].add(&p[0]);
            s[1].add(&p[1]);
        }
        pairs.remainder().iter().for_each(|r| s[0].add(r));
        ExtentSum::join(s[0], s[1])
    }

    #[inline]
    pub(crate) fn add(&mut self, r: &Ray) {
        if r.key == SKIPPED {
            self.skipped += 1;
            return;
        }
        for a in 0..3 {
            self.lo[a] = self.lo[a].min(r.end[a]);
            self.hi[a] = self.hi[a].max(r.end[a]);
            self.length[a] += (r.end[a] - self.origin[a]).abs();
        }
        self.cut += u64::from(!r.hit);
    }

    pub(crate) fn join(a: Self, b: Self) -> Self {
        ExtentSum {
            origin: a.origin,
            lo: [0, 1, 2].map(|i| a.lo[i].min(b.lo[i])),
            hi: [0, 1, 2].map(|i| a.hi[i].max(b.hi[i])),
            cut: a.cut + b.cut,
            length: [0, 1, 2].map(|i| a.length[i] + b.length[i]),
            skipped: a.skipped + b.skipped,
        }
    }

    pub(crate) fn extent(&self) -> Extent {
        let voxel =
            |u| units_to_voxel(u).expect("ray ends lie within max range of a checked origin");
        Extent {
            lo: voxel(self.lo),
            hi: voxel(self.hi),
            cut_rays: self.cut,
            steps: self.length.iter().sum(),
        }
    }
}

/// What [`ExtentSum`] finds out about a frame's rays.
pub(crate) struct Extent {
    /// Voxel bounds (inclusive) of the origin and all ray ends.
    pub(crate) lo: VoxelCoord,
    pub(crate) hi: VoxelCoord,
    pub(crate) cut_rays: u64,
    /// About the voxel steps of the walk: the rays' lengths in voxels along each axis.
    pub(crate) steps: f64,
}
