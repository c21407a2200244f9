//! Rays and their layout: a [`Ray`] from the sensor to a point's end in voxel units, made
//! by [`RayMaker`] (eight at a time on AVX-512, four on AVX2: `avx512.rs`, `avx2.rs`); a
//! frame's rays in chunks of [`RAY_CHUNK`], each laid out by the [`Sides`] of a plane
//! through the sensor (where the layout put each ray: [`ChunkOrder`]); their extent summed
//! as they are made ([`ExtentSum`] into [`Extent`]). The prepare phase makes them, the ray
//! modes choose among them (`select`), the walks cast them.

use crate::coord::{units_to_voxel, VoxelCoord};
use crate::kernel::Kernels;
use crate::mask::BitIter;
use nalgebra::Isometry3;
#[cfg(test)]
use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2;
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512;

/// One frame: points in the sensor frame and the sensor's pose in the map frame.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    pub pose: Isometry3<f64>,
    pub points: &'a [[f32; 3]],
}

/// Rays per parallel task of the walk, and per chunk of the layout by sides.
pub(crate) const RAY_CHUNK: usize = 512;

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
pub(crate) fn direction_key(d: [f64; 3]) -> u32 {
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

/// The key of a ray from a non-finite point, never a direction's key.
pub(crate) const SKIPPED: u32 = u32::MAX;

#[inline]
pub(crate) fn spread16(x: u32) -> u32 {
    let mut x = x & 0xffff;
    x = (x | x << 8) & 0x00ff_00ff;
    x = (x | x << 4) & 0x0f0f_0f0f;
    x = (x | x << 2) & 0x3333_3333;
    (x | x << 1) & 0x5555_5555
}

/// Word `w` of a chunk's mask of its first `n` places.
pub(crate) fn first_bits(n: usize, w: usize) -> u64 {
    match n.saturating_sub(w * 64) {
        0 => 0,
        bits @ 1..64 => (1u64 << bits) - 1,
        _ => !0,
    }
}

/// Which rays of a chunk, by their place in the scan, a layout by [`Sides`] put in front
/// and which behind (bit `j` of word `j / 64`); the rays of skipped points in neither.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct ChunkOrder {
    pub(crate) front: [u64; RAY_CHUNK / 64],
    pub(crate) back: [u64; RAY_CHUNK / 64],
    /// The rays cut at max range (noted for the ray modes only).
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
            for b in BitIter(m) {
                out[w * 64 + b] = k;
                k += 1;
            }
        }
        let mut k = len as u16;
        for (w, &m) in self.back.iter().enumerate() {
            for b in BitIter(m) {
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
    /// with, and in sides its lanes walk rays nearer in direction: laid out, its frames
    /// took 3-9% longer (500k 6 m workloads, three alternated rounds).
    pub(crate) axis: Option<[f64; 3]>,
}

impl Sides {
    /// Points sampled to choose the axis.
    pub(crate) const SAMPLES: usize = 1024;

    /// The sides for `frame` on a pool of `threads`: across the sensor axis whose plane
    /// sides the rays' lengths best, in a sample of the points (a sensor looking along one
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

/// Rays in chunks laid out with counts `counts` (not their length: gaps are not rays).
pub(crate) fn ray_count(counts: &[[u32; 2]]) -> u64 {
    counts.iter().map(|&[f, b]| u64::from(f + b)).sum()
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

/// The key of a skipped point's ray: no cell's ([`CellKeys`] fields never are all ones).
pub(crate) const NO_CELL: u64 = u64::MAX;

/// A ray's cell (`factor` per voxel edge, `floor(end * factor)` on each axis) and hit flag
/// in one `u64`: 21 bits an axis, relative to the origin's cell and biased by 2^20, and
/// the hit flag on top. Rays end within max range (8192 voxels) of the origin and the
/// factor is at most 64, so a field lies within 2^20 ± (2^19 + 1): never all ones.
pub(crate) struct CellKeys {
    pub(crate) f: f64,
    /// The cell that keys to 0 on each axis, as a float (an integer).
    pub(crate) base: [f64; 3],
}

impl CellKeys {
    pub(crate) const BIAS: f64 = (1 << 20) as f64;
    pub(crate) const FIELD: u64 = (1 << 21) - 1;

    pub(crate) fn new(origin: [f64; 3], factor: u32) -> Self {
        let f = f64::from(factor);
        CellKeys {
            f,
            base: origin.map(|c| (c * f).floor() - Self::BIAS),
        }
    }

    /// The key of `r`, [`NO_CELL`] for a skipped point's.
    #[inline]
    pub(crate) fn key(&self, r: &Ray) -> u64 {
        if r.key == SKIPPED {
            return NO_CELL;
        }
        let c =
            [0, 1, 2].map(|a| ((r.end[a] * self.f).floor() - self.base[a]) as u64 & Self::FIELD);
        c[0] | c[1] << 21 | c[2] << 42 | u64::from(r.hit) << 63
    }

    /// `out[i] = self.key(&rays[i])`, four at a time with the vector kernels.
    pub(crate) fn keys(&self, kernels: &Kernels, rays: &[Ray], out: &mut [u64]) {
        let done = (kernels.cell_keys)(self, rays, out);
        for (k, r) in out.iter_mut().zip(rays).skip(done) {
            *k = self.key(r);
        }
    }
}
