//! Phase 1, prepare: a frame's points become rays in voxel units (pose, face snap,
//! max-range cut), laid out by the sides of the sensor ([`Sides`]) as they are made, with
//! the frame's extent summed up in the same pass ([`ExtentSum`]); the trade-off modes thin
//! them ([`super::thin`]); the sparse walk gets them sorted by direction
//! ([`order_by_direction`]).

use super::thin::{thin_out, Buffers};
use super::{Frame, RayMode};
use crate::coord::{units_to_voxel, VoxelCoord};
use crate::kernel::Kernel;
use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
mod avx2;
#[cfg(target_arch = "x86_64")]
mod avx512;

/// Rays per parallel task of the walk, and per chunk of the layout by sides.
pub(super) const RAY_CHUNK: usize = 512;

/// A ray from the frame's sensor origin. `repr(C)` with explicit padding, so that every
/// byte is initialised and the dense walk can gather whole fields from a slice of rays:
/// `end` at offset 0, `key` at 24, `hit` at 28, 32 bytes in all.
#[derive(Clone, Copy, Debug)]
#[repr(C)]
pub(in crate::integrate) struct Ray {
    pub(in crate::integrate) end: [f64; 3],
    pub(in crate::integrate) key: u32,
    pub(in crate::integrate) hit: bool,
    pub(in crate::integrate) pad: [u8; 3],
}

const _: () = assert!(std::mem::size_of::<Ray>() == 32);

impl Ray {
    pub(in crate::integrate) fn new(end: [f64; 3], key: u32, hit: bool) -> Self {
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
pub(in crate::integrate) fn spread16(x: u32) -> u32 {
    let mut x = x & 0xffff;
    x = (x | x << 8) & 0x00ff_00ff;
    x = (x | x << 4) & 0x0f0f_0f0f;
    x = (x | x << 2) & 0x3333_3333;
    (x | x << 1) & 0x5555_5555
}

/// Put the rays in the sparse walk's order: gaps of skipped points dropped, sorted by
/// direction, so that neighbouring rays walk neighbouring memory.
pub(super) fn order_by_direction(rays: &mut Vec<Ray>, ray_count: u64, origin: [f64; 3]) {
    if ray_count < rays.len() as u64 {
        rays.retain(|r| r.key != SKIPPED);
    }
    set_direction_keys(rays, origin);
    rays.par_sort_unstable_by_key(|r| r.key);
}

/// Fill `rays` from the frame, laid out by `halves` with the counts per chunk in `sides`;
/// returns the number of non-finite points skipped and the rays' extent.
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
    kernel: Kernel,
    thin: &mut Buffers,
) -> (u64, Extent) {
    let maker = RayMaker::new(frame, tf, origin, range_units, kernel);
    // One pass writes the rays and sums up their extent: a frame's rays (16 MB for 500k
    // points) outgrow the cache, and passes of their own to count the skipped points and
    // take the bounds cost a third of the prepare phase (structured 500k 6 m: 7.8 ms, of
    // which 1.4 ms bounds and 0.5 ms counting, 2 threads). For the same reason the rays
    // are laid out as they are made. `rays` keeps its length from frame to frame, so
    // `resize` writes only where this frame has more points than the last.
    let n = frame.points.len();
    rays.truncate(n);
    rays.resize(n, Ray::new([0.0; 3], SKIPPED, false));
    sides.clear();
    sides.resize(n.div_ceil(RAY_CHUNK), [0; 2]);
    // The trade-off modes keep the first ray of a kind in scan order, so they see the rays
    // in scan order (one thread's layout) and lay them out after.
    let made_by = match mode {
        RayMode::Exact => halves,
        _ => Sides {
            axis: None,
            ..halves
        },
    };
    let sums = rays
        .par_chunks_mut(RAY_CHUNK)
        .zip(frame.points.par_chunks(RAY_CHUNK))
        .zip(sides.par_iter_mut())
        .map_init(Vec::new, |made, ((out, pts), side)| {
            let (counts, sum) = made_by.make(&maker, pts, out, made);
            *side = counts;
            sum
        })
        .reduce(|| ExtentSum::new(origin), ExtentSum::join);
    let skipped = sums.skipped;
    if mode == RayMode::Exact {
        return (skipped, sums.extent());
    }
    if skipped > 0 {
        rays.retain(|r| r.key != SKIPPED);
    }
    let kept = thin_out(rays, origin, mode, &sums.extent(), thin);
    let sum = halves.lay_out_kept(rays, sides, |i, r| kept.ray(i, r));
    (skipped, sum.extent())
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
pub(in crate::integrate) struct Sides {
    pub(in crate::integrate) origin: [f64; 3],
    /// The plane's normal in the world frame, a sensor axis; none for a one-thread pool,
    /// where all rays count as in front. One thread has no second grid to share first marks
    /// with, and in halves its lanes walk rays nearer in direction: laid out, its frames
    /// took 3-9% longer (500k 6 m workloads, three alternated rounds).
    pub(in crate::integrate) axis: Option<[f64; 3]>,
}

impl Sides {
    /// Points sampled to choose the axis.
    pub(in crate::integrate) const SAMPLES: usize = 1024;

    /// The sides for `frame` on a pool of `threads`: across the sensor axis whose plane
    /// halves the rays' lengths best, in a sample of the points (a sensor looking along one
    /// of its axes, as a camera along z or a forward lidar along x, has no ray behind it).
    pub(in crate::integrate) fn new(frame: &Frame<'_>, origin: [f64; 3], threads: usize) -> Self {
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
    /// and behind, and their extent. `made` is scratch.
    pub(in crate::integrate) fn make(
        &self,
        maker: &RayMaker,
        pts: &[[f32; 3]],
        out: &mut [Ray],
        made: &mut Vec<Ray>,
    ) -> ([u32; 2], ExtentSum) {
        if self.axis.is_some() {
            made.resize(out.len(), Ray::new([0.0; 3], SKIPPED, false));
            maker.make_all(made, pts);
            return (self.lay_out(made, out), ExtentSum::of(self.origin, made));
        }
        // All in front: in place, unless points were skipped.
        maker.make_all(out, pts);
        let sum = ExtentSum::of(self.origin, out);
        if sum.skipped == 0 {
            return ([out.len() as u32, 0], sum);
        }
        (self.lay_out_in_place(out, made), sum)
    }

    /// Lay the rays `made` out into `out`, as long; returns how many lie in front and
    /// behind. The rays of skipped points leave gaps.
    pub(in crate::integrate) fn lay_out(&self, made: &[Ray], out: &mut [Ray]) -> [u32; 2] {
        let (o, x) = (self.origin, self.axis.unwrap_or([0.0; 3]));
        let (mut front, mut back) = (0, out.len());
        for r in made.iter().filter(|r| r.key != SKIPPED) {
            let d = [0, 1, 2].map(|a| r.end[a] - o[a]);
            let behind = d[0] * x[0] + d[1] * x[1] + d[2] * x[2] < 0.0;
            // A select, not a branch: the side is a coin flip in many scans. A ray is left
            // to place, so `front < back`.
            out[if behind { back - 1 } else { front }] = *r;
            front += usize::from(!behind);
            back -= usize::from(behind);
        }
        out[front..back].fill(Ray::new([0.0; 3], SKIPPED, false));
        [front as u32, (out.len() - back) as u32]
    }

    /// Lay out in place, chunk by chunk, the rays `kept` keeps (given each ray's index
    /// and the ray, it returns the ray as kept, or `None`); the others leave gaps. `sides`
    /// gets each chunk's counts; returns the extent of the rays kept.
    pub(in crate::integrate) fn lay_out_kept(
        &self,
        rays: &mut [Ray],
        sides: &mut Vec<[u32; 2]>,
        kept: impl Fn(usize, &Ray) -> Option<Ray> + Sync,
    ) -> ExtentSum {
        sides.clear();
        sides.resize(rays.len().div_ceil(RAY_CHUNK), [0; 2]);
        rays.par_chunks_mut(RAY_CHUNK)
            .zip(sides.par_iter_mut())
            .enumerate()
            .map_init(Vec::new, |scratch, (c, (chunk, side))| {
                scratch.clear();
                let at = c * RAY_CHUNK;
                scratch.extend(
                    chunk
                        .iter()
                        .enumerate()
                        .filter_map(|(i, r)| kept(at + i, r)),
                );
                *side = self.lay_out(scratch, chunk);
                ExtentSum::of(self.origin, scratch)
            })
            .reduce(|| ExtentSum::new(self.origin), ExtentSum::join)
    }

    /// [`Sides::lay_out`] of `chunk` into itself, through `scratch`.
    pub(in crate::integrate) fn lay_out_in_place(
        &self,
        chunk: &mut [Ray],
        scratch: &mut Vec<Ray>,
    ) -> [u32; 2] {
        scratch.clear();
        scratch.extend_from_slice(chunk);
        self.lay_out(scratch, chunk)
    }
}

/// Rays in chunks laid out with counts `sides` (not their length: gaps are not rays).
pub(in crate::integrate) fn ray_count(sides: &[[u32; 2]]) -> u64 {
    sides.iter().map(|&[f, b]| u64::from(f + b)).sum()
}

/// Makes a frame's rays from its points: sensor frame to world by the pose, to voxel units
/// (snapped onto faces, see `GridTransform::to_units`), cut at max range.
#[derive(Clone, Copy, Debug)]
pub(in crate::integrate) struct RayMaker {
    /// Rotation rows and translation of the pose.
    pub(in crate::integrate) rot: [[f64; 3]; 3],
    pub(in crate::integrate) t: [f64; 3],
    pub(in crate::integrate) tf: crate::coord::GridTransform,
    pub(in crate::integrate) origin: [f64; 3],
    pub(in crate::integrate) range_units: f64,
    /// Below this squared length a ray surely ends within range; above it, the same
    /// comparison as the reference, `sqrt(len2) <= range_units`, decides.
    pub(in crate::integrate) surely_in: f64,
    /// Which kernel `make_all` runs.
    pub(in crate::integrate) kernel: Kernel,
}

impl RayMaker {
    pub(in crate::integrate) fn new(
        frame: &Frame<'_>,
        tf: &crate::coord::GridTransform,
        origin: [f64; 3],
        range_units: f64,
        kernel: Kernel,
    ) -> Self {
        let r = frame.pose.rotation.to_rotation_matrix().into_inner();
        RayMaker {
            rot: [0, 1, 2].map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]),
            t: frame.pose.translation.vector.into(),
            tf: *tf,
            origin,
            range_units,
            surely_in: range_units * range_units * (1.0 - 1e-9),
            kernel,
        }
    }

    /// The ray to `p`; a non-finite point gives a ray keyed `SKIPPED`. The arithmetic is
    /// spelled out (no library product) so that `avx512::make_rays` can repeat it
    /// operation for operation.
    #[inline]
    pub(in crate::integrate) fn make(&self, p: &[f32; 3]) -> Ray {
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
    pub(in crate::integrate) fn make_all(&self, out: &mut [Ray], pts: &[[f32; 3]]) {
        let done = match self.kernel {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: a `Kernel::Avx512` exists only where the CPU has AVX-512F, DQ and BW
            // (`Kernel::supported`); `make_rays` needs F and DQ.
            Kernel::Avx512 => unsafe { avx512::make_rays(self, out, pts) },
            #[cfg(target_arch = "x86_64")]
            // SAFETY: a `Kernel::Avx2` exists only where the CPU has AVX2 (`Kernel::supported`).
            Kernel::Avx2 => unsafe { avx2::make_rays(self, out, pts) },
            _ => 0,
        };
        for (r, p) in out.iter_mut().zip(pts).skip(done) {
            *r = self.make(p);
        }
    }
}

/// [`Extent`] of `rays`, in one pass (the layout of thinned rays sums it on the way).
#[cfg(test)]
pub(in crate::integrate) fn bounds(rays: &[Ray], origin: [f64; 3]) -> Extent {
    rays.par_chunks(RAY_CHUNK)
        .map(|c| ExtentSum::of(origin, c))
        .reduce(|| ExtentSum::new(origin), ExtentSum::join)
        .extent()
}

/// [`Extent`] being summed up over rays; skipped rays (non-finite points) are counted
/// apart. Bounds are taken on the ends in voxel units and floored once: floor is monotone,
/// so that is the bounds of the ends' voxels.
#[derive(Clone, Copy)]
pub(in crate::integrate) struct ExtentSum {
    pub(in crate::integrate) origin: [f64; 3],
    pub(in crate::integrate) lo: [f64; 3],
    pub(in crate::integrate) hi: [f64; 3],
    pub(in crate::integrate) cut: u64,
    pub(in crate::integrate) length: f64,
    pub(in crate::integrate) skipped: u64,
}

impl ExtentSum {
    pub(in crate::integrate) fn new(origin: [f64; 3]) -> Self {
        ExtentSum {
            origin,
            lo: origin,
            hi: origin,
            cut: 0,
            length: 0.0,
            skipped: 0,
        }
    }

    /// The sum over `rays`.
    pub(in crate::integrate) fn of(origin: [f64; 3], rays: &[Ray]) -> Self {
        let mut sum = ExtentSum::new(origin);
        rays.iter().for_each(|r| sum.add(r));
        sum
    }

    #[inline]
    pub(in crate::integrate) fn add(&mut self, r: &Ray) {
        if r.key == SKIPPED {
            self.skipped += 1;
            return;
        }
        for a in 0..3 {
            self.lo[a] = self.lo[a].min(r.end[a]);
            self.hi[a] = self.hi[a].max(r.end[a]);
            self.length += (r.end[a] - self.origin[a]).abs();
        }
        self.cut += u64::from(!r.hit);
    }

    pub(in crate::integrate) fn join(a: Self, b: Self) -> Self {
        ExtentSum {
            origin: a.origin,
            lo: [0, 1, 2].map(|i| a.lo[i].min(b.lo[i])),
            hi: [0, 1, 2].map(|i| a.hi[i].max(b.hi[i])),
            cut: a.cut + b.cut,
            length: a.length + b.length,
            skipped: a.skipped + b.skipped,
        }
    }

    pub(in crate::integrate) fn extent(&self) -> Extent {
        let voxel =
            |u| units_to_voxel(u).expect("ray ends lie within max range of a checked origin");
        Extent {
            lo: voxel(self.lo),
            hi: voxel(self.hi),
            cut_rays: self.cut,
            steps: self.length,
        }
    }
}

/// What [`ExtentSum`] finds out about a frame's rays.
pub(in crate::integrate) struct Extent {
    /// Voxel bounds (inclusive) of the origin and all ray ends.
    pub(in crate::integrate) lo: VoxelCoord,
    pub(in crate::integrate) hi: VoxelCoord,
    pub(in crate::integrate) cut_rays: u64,
    /// About the voxel steps of the walk: the rays' lengths in voxels along each axis.
    pub(in crate::integrate) steps: f64,
}
