//! Frame integration: the paper's two-step update, made merge-free.
//!
//! 1. **Prepare** (parallel): transform points into the map frame, skip non-finite ones,
//!    cut rays at `max_range`, apply the optional trade-off mode; lay the rays out by the
//!    side of the sensor they lie on (`Sides`), so that each thread of the dense walk
//!    keeps mostly to its half of the box; for the sparse walk, sort the rays by direction
//!    (an octahedral Morton key) so that neighbouring rays walk neighbouring memory.
//! 2. **Raycast** (parallel over chunks of rays), one of two walks with the same result:
//!    - *sparse*: each ray is walked with the exact DDA, eight at a time where the build
//!      has AVX-512 (`avx512::cast_sparse`), one at a time otherwise; its marks are
//!      gathered per 8x8x8 brick and OR-ed into the per-frame [`FrameMarks`], sparse
//!      tables of touched bricks only, one per thread. Threads walk rays of different
//!      directions, so their tables share bricks only near the sensor, and there is no
//!      grid to merge: this is what keeps 2 threads ahead of 1 at 60 m, where the paper's
//!      per-thread dense grids made the merge dominate.
//!    - *dense*, when the frame's box is small (about 30 m of range at 0.1 m): each thread
//!      walks into its own bit grid over the whole box (`dense`), eight rays at a time, one
//!      per vector lane, where the build has AVX-512 (`avx512`), one at a time otherwise.
//!      The grids are OR-ed into the [`FrameMarks`] afterwards; a frame walks dense only
//!      when its rays are many enough to pay for zeroing and merging them. The walk is 2-4x
//!      faster than the sparse one with AVX-512, 1.3-2x without.
//! 3. **Merge**: the touched bricks, sorted spatially, get their map leaves (created if
//!    new) in one sequential pass.
//! 4. **Update** (parallel over leaf chunks): one log-odds update per touched voxel, hit
//!    beating free within the frame.
//!
//! Marks are OR-ed and each voxel is updated once from its final marks, so the map after a
//! frame does not depend on the thread count or scheduling.

use crate::coord::{units_to_voxel, ConfigError, VoxelCoord, MAX_VOXEL_INDEX};
use crate::grid::{leaf_offset, Leaf};
use crate::map::OccupancyMap;
use crate::mask::BitIter;
use crate::model::QuantizedModel;
use crate::pages::{Zeroed, HUGE_PAGE};
use crate::raycast::Dda;
use hashbrown::HashSet;
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering::*};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

#[cfg(all(
    target_arch = "x86_64",
    target_feature = "avx512f",
    target_feature = "avx512dq"
))]
mod avx512;
mod dense;

/// Longest allowed ray, in voxels; bounds the per-frame mark table.
pub const MAX_RANGE_VOXELS: f64 = 8192.0;

/// How rays are chosen from a frame's points. Every mode but `Exact` trades map quality
/// for speed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case", tag = "mode")]
pub enum RayMode {
    /// One ray per point.
    #[default]
    Exact,
    /// Skip a point whose end falls in a sub-cell (`factor` times finer than the map)
    /// already seen in this frame.
    Subsample { factor: u32 },
    /// Points whose end voxels coincide form a bundle; a bundle of more than `threshold`
    /// points casts one ray to their mean end point.
    Bundle { threshold: u32 },
    /// One ray per distinct end voxel, to its centre (OctoMap's discretized insert).
    UniqueEnd,
}

impl RayMode {
    /// Short name used in reports: `exact`, `subsample`, `bundle`, `unique_end`.
    pub fn name(&self) -> &'static str {
        match self {
            RayMode::Exact => "exact",
            RayMode::Subsample { .. } => "subsample",
            RayMode::Bundle { .. } => "bundle",
            RayMode::UniqueEnd => "unique_end",
        }
    }
}

/// Integration parameters.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct IntegratorConfig {
    /// Worker threads (>= 1). One thread runs the same walk, merge and update (its rays
    /// are not laid out by sides, see `Sides`).
    pub threads: usize,
    /// Rays longer than this (metres) are cut here and mark free space only.
    pub max_range: f64,
    pub mode: RayMode,
    /// Pin worker i to the i-th CPU (wrapping) that the thread creating the integrator may
    /// run on (Linux), so that workers never share a CPU while another idles (see `cpus`).
    /// Off where CPU-heavy processes share those CPUs, or several integrators share a
    /// machine's few CPUs (each pins to the same first ones); a process's CPU set
    /// (`taskset`, cgroup cpusets) limits where workers go either way.
    #[serde(default = "pin_by_default")]
    pub pin_threads: bool,
}

fn pin_by_default() -> bool {
    IntegratorConfig::default().pin_threads
}

impl Default for IntegratorConfig {
    fn default() -> Self {
        Self {
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            max_range: 30.0,
            mode: RayMode::Exact,
            pin_threads: true,
        }
    }
}

/// One frame: points in the sensor frame and the sensor's pose in the map frame.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    pub pose: Isometry3<f64>,
    pub points: &'a [[f32; 3]],
}

/// Why a whole frame was rejected. Nothing reached the map.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum IntegrateError {
    /// The pose has a non-finite component.
    NonFinitePose,
    /// The sensor origin (plus max range) lies outside the map's index space.
    OriginOutOfRange { origin: [f64; 3] },
    /// The integrator's max range spans more than [`MAX_RANGE_VOXELS`] voxels at the
    /// map's resolution (e.g. after loading a finer map).
    RangeTooLong { max_range: f64, resolution: f64 },
}

impl std::fmt::Display for IntegrateError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            IntegrateError::NonFinitePose => write!(f, "frame rejected: sensor pose is not finite"),
            IntegrateError::OriginOutOfRange { origin } => {
                write!(
                    f,
                    "frame rejected: sensor origin {origin:?} m is outside the map's index space"
                )
            }
            IntegrateError::RangeTooLong {
                max_range,
                resolution,
            } => write!(
                f,
                "frame rejected: max range {max_range} m is more than {MAX_RANGE_VOXELS} voxels at {resolution} m"
            ),
        }
    }
}

impl std::error::Error for IntegrateError {}

/// Time per phase of one integration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PhaseTimes {
    pub prepare: Duration,
    pub raycast: Duration,
    pub merge: Duration,
    pub update: Duration,
}

impl PhaseTimes {
    pub fn total(&self) -> Duration {
        self.prepare + self.raycast + self.merge + self.update
    }
}

/// What one integration did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct IntegrateReport {
    /// Points in the frame.
    pub points: u64,
    /// Points skipped for a non-finite coordinate.
    pub skipped_nonfinite: u64,
    /// Rays cast (after the trade-off mode).
    pub rays: u64,
    /// Rays cut at max range (free space only).
    pub cut_rays: u64,
    /// Voxels visited by all rays, end voxels included.
    pub voxel_steps: u64,
    /// Leaves (8x8x8 bricks) and voxels updated.
    pub touched_leaves: u64,
    pub touched_voxels: u64,
    /// The frame's box was small enough for the dense walk (see `integrate::dense`).
    pub dense: bool,
    pub times: PhaseTimes,
}

/// A ray from the frame's sensor origin. `repr(C)` with explicit padding, so that every
/// byte is initialised and the dense walk can gather whole fields from a slice of rays:
/// `end` at offset 0, `key` at 24, `hit` at 28, 32 bytes in all.
#[derive(Clone, Copy, Debug)]
#[repr(C)]
struct Ray {
    end: [f64; 3],
    key: u32,
    hit: bool,
    pad: [u8; 3],
}

const _: () = assert!(std::mem::size_of::<Ray>() == 32);

impl Ray {
    fn new(end: [f64; 3], key: u32, hit: bool) -> Self {
        Ray {
            end,
            key,
            hit,
            pad: [0; 3],
        }
    }
}

/// Integrates frames into maps. Holds a thread pool and scratch memory that is reused
/// from frame to frame; one per map writer.
pub struct Integrator {
    cfg: IntegratorConfig,
    pool: rayon::ThreadPool,
    marks: FrameMarks,
    rays: Vec<Ray>,
    /// Per chunk of `rays`: how many lie on either side of the sensor (see [`Sides`]).
    sides: Vec<[u32; 2]>,
    /// Per pool thread: dense marks for frames with a small box.
    dense: Vec<std::sync::Mutex<dense::DenseBits>>,
    /// Frames integrated, to tell this frame's dense marks from stale ones.
    frames: u64,
    /// Which walk to take (tests compare them).
    walk: Walk,
}

impl Integrator {
    pub fn new(cfg: IntegratorConfig) -> Result<Self, ConfigError> {
        if cfg.threads == 0 || cfg.threads > 1024 {
            return Err(ConfigError::Invalid {
                name: "threads",
                value: cfg.threads as f64,
                why: "must be 1..=1024",
            });
        }
        if !(cfg.max_range.is_finite() && cfg.max_range > 0.0) {
            return Err(ConfigError::Invalid {
                name: "max_range",
                value: cfg.max_range,
                why: "must be finite and > 0",
            });
        }
        match cfg.mode {
            RayMode::Subsample { factor } if !(1..=64).contains(&factor) => {
                return Err(ConfigError::Invalid {
                    name: "subsample_factor",
                    value: factor as f64,
                    why: "must be 1..=64",
                })
            }
            RayMode::Bundle { threshold: 0 } => {
                return Err(ConfigError::Invalid {
                    name: "bundle_threshold",
                    value: 0.0,
                    why: "must be >= 1",
                })
            }
            _ => {}
        }
        let cpus = if cfg.pin_threads {
            crate::cpus::allowed()
        } else {
            Vec::new()
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(cfg.threads)
            .thread_name(|i| format!("voxmap-int-{i}"))
            .start_handler(move |i| {
                if let Some(&cpu) = cpus.get(i % cpus.len().max(1)) {
                    crate::cpus::pin_to(cpu);
                }
            })
            .build()
            .map_err(|_| ConfigError::Invalid {
                name: "threads",
                value: cfg.threads as f64,
                why: "thread pool failed",
            })?;
        Ok(Self {
            dense: (0..cfg.threads).map(|_| Default::default()).collect(),
            cfg,
            pool,
            marks: FrameMarks::default(),
            rays: Vec::new(),
            sides: Vec::new(),
            frames: 0,
            walk: Walk::Auto,
        })
    }

    /// Run `f` on this integrator's thread pool, so that parallel work around integration
    /// (snapshot encoding) keeps to the configured thread count.
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.pool.install(f)
    }

    pub fn config(&self) -> &IntegratorConfig {
        &self.cfg
    }

    /// Whether this integrator can work on a map of `resolution`: its max range spans at
    /// most [`MAX_RANGE_VOXELS`] voxels there.
    pub fn fits_resolution(&self, resolution: f64) -> bool {
        self.check_range(resolution).is_ok()
    }

    /// Check that `max_range` is representable at `resolution` (see [`MAX_RANGE_VOXELS`]).
    fn check_range(&self, resolution: f64) -> Result<f64, ConfigError> {
        let r = self.cfg.max_range / resolution;
        if r > MAX_RANGE_VOXELS {
            return Err(ConfigError::Invalid {
                name: "max_range",
                value: self.cfg.max_range,
                why: "longer than 8192 voxels at this resolution",
            });
        }
        Ok(r)
    }

    /// Integrate one frame. On error nothing has changed in the map.
    pub fn integrate(
        &mut self,
        map: &mut OccupancyMap,
        frame: &Frame<'_>,
    ) -> Result<IntegrateReport, IntegrateError> {
        let range_units =
            self.check_range(map.resolution())
                .map_err(|_| IntegrateError::RangeTooLong {
                    max_range: self.cfg.max_range,
                    resolution: map.resolution(),
                })?;
        let pose = frame.pose;
        if !(pose.translation.vector.iter().all(|c| c.is_finite())
            && pose.rotation.coords.iter().all(|c| c.is_finite()))
        {
            return Err(IntegrateError::NonFinitePose);
        }
        let tf = *map.transform();
        let origin = tf.point_to_units(&Point3::from(pose.translation.vector));
        if origin
            .iter()
            .any(|c| c.abs() + range_units + 16.0 >= MAX_VOXEL_INDEX)
        {
            return Err(IntegrateError::OriginOutOfRange {
                origin: pose.translation.vector.into(),
            });
        }
        let q = *map.quantized();
        let mode = self.cfg.mode;
        self.frames += 1;
        let frame_no = self.frames;
        let (pool, marks, rays, sides, dense) = (
            &self.pool,
            &mut self.marks,
            &mut self.rays,
            &mut self.sides,
            &self.dense,
        );
        let walk = self.walk;
        let mut report = IntegrateReport {
            points: frame.points.len() as u64,
            ..Default::default()
        };
        pool.install(|| {
            let t0 = Instant::now();
            let halves = Sides::new(frame, origin, rayon::current_num_threads());
            let (skipped, extent) =
                prepare_rays(rays, sides, halves, frame, &tf, origin, range_units, mode);
            report.skipped_nonfinite = skipped;
            // Not `rays.len()`: skipped points leave gaps (see `Sides`).
            report.rays = ray_count(sides);
            let Extent {
                lo,
                hi,
                cut_rays,
                steps,
            } = extent;
            report.cut_rays = cut_rays;
            let dense_box = match walk {
                Walk::Sparse | Walk::SparseScalar => None,
                // Zeroing and merging the dense grids cost about 15 ns per word, and a dense
                // step saved 4-8 ns against a one-ray sparse one (1.5-2.5 against 4-10 ns):
                // walk dense when the grid has at most a quarter as many words as the walk
                // has steps. A few rays in a big box walk sparse. (Not re-tuned for the
                // AVX-512 sparse walk, 2.5-4 ns a step at 60 m with its memory traffic.)
                Walk::Auto => {
                    dense::DenseBox::new(lo, hi).filter(|b| b.words() as f64 * 4.0 <= steps)
                }
                Walk::Dense | Walk::DenseScalar | Walk::DenseTestFirst => {
                    dense::DenseBox::new(lo, hi)
                }
            };
            report.dense = dense_box.is_some();
            // The dense walk needs no order but the sides: its grids stay in cache whatever
            // the rays' directions, and its lanes only need to be far apart in direction,
            // which chunks from the eight eighths of a sensor's scan are (sorting took half
            // of its prepare time). The sparse walk needs them sorted by direction, without
            // gaps.
            if !report.dense {
                if report.rays < rays.len() as u64 {
                    rays.retain(|r| r.key != SKIPPED);
                }
                set_direction_keys(rays, origin);
                rays.par_sort_unstable_by_key(|r| r.key);
            }
            let chunks = rays.len().div_ceil(RAY_CHUNK);
            marks.reset(
                lo,
                hi,
                chunks + dense_box.map_or(0, |b| b.brick_rows()),
                rayon::current_num_threads(),
            );
            let t1 = Instant::now();
            report.voxel_steps = match &dense_box {
                None => cast_sparse(marks, origin, rays, steps, walk),
                Some(b) => cast_dense(dense, b, frame_no, origin, rays, sides, steps, walk),
            };
            let t2 = Instant::now();
            if let Some(b) = &dense_box {
                // The threads that walked this frame have its marks; the others' are stale.
                let guards: Vec<_> = dense.iter().map(|m| lock(m)).collect();
                let live: Vec<&dense::DenseBits> = guards
                    .iter()
                    .map(|g| &**g)
                    .filter(|g| g.frame() == frame_no)
                    .collect();
                dense::merge(marks, b, &live);
            }
            let items = merge(marks, map);
            let t3 = Instant::now();
            report.touched_leaves = items.len() as u64;
            report.touched_voxels = map
                .grid_mut()
                .leaf_pool_mut()
                .par_update(&items, |leaf, &(slot, fresh)| {
                    apply(leaf, marks.slot(slot), &q, fresh)
                });
            marks.clear_used();
            let t4 = Instant::now();
            report.times = PhaseTimes {
                prepare: t1 - t0,
                raycast: t2 - t1,
                merge: t3 - t2,
                update: t4 - t3,
            };
        });
        Ok(report)
    }
}

/// Octahedral direction key, Morton-interleaved: rays with close directions get close keys.
#[inline]
fn direction_key(d: [f64; 3]) -> u32 {
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

fn set_direction_keys(rays: &mut [Ray], origin: [f64; 3]) {
    rays.par_iter_mut()
        .for_each(|r| r.key = direction_key([0, 1, 2].map(|a| r.end[a] - origin[a])));
}

/// The key of a ray from a non-finite point, never a direction's key.
const SKIPPED: u32 = u32::MAX;

#[inline]
fn spread16(x: u32) -> u32 {
    let mut x = x & 0xffff;
    x = (x | x << 8) & 0x00ff_00ff;
    x = (x | x << 4) & 0x0f0f_0f0f;
    x = (x | x << 2) & 0x3333_3333;
    (x | x << 1) & 0x5555_5555
}

/// Fill `rays` from the frame, laid out by `halves` with the counts per chunk in `sides`;
/// returns the number of non-finite points skipped and the rays' extent.
#[allow(clippy::too_many_arguments)]
fn prepare_rays(
    rays: &mut Vec<Ray>,
    sides: &mut Vec<[u32; 2]>,
    halves: Sides,
    frame: &Frame<'_>,
    tf: &crate::coord::GridTransform,
    origin: [f64; 3],
    range_units: f64,
    mode: RayMode,
) -> (u64, Extent) {
    let maker = RayMaker::new(frame, tf, origin, range_units);
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
        .reduce(|| ExtentSum::new(origin), ExtentSum::merge);
    let skipped = sums.skipped;
    if mode == RayMode::Exact {
        return (skipped, sums.extent());
    }
    if skipped > 0 {
        rays.retain(|r| r.key != SKIPPED);
    }
    thin_out(rays, origin, mode);
    halves.lay_out_all(rays, sides);
    (skipped, bounds(rays, origin))
}

/// Drop (or merge) the rays that `mode` trades for speed.
fn thin_out(rays: &mut Vec<Ray>, origin: [f64; 3], mode: RayMode) {
    match mode {
        RayMode::Exact => {}
        RayMode::Subsample { factor } => {
            let f = f64::from(factor);
            let mut seen = HashSet::with_capacity(rays.len());
            rays.retain(|r| {
                let c = r.end.map(|c| (c * f).floor() as i64);
                seen.insert((c, r.hit))
            });
        }
        RayMode::UniqueEnd => {
            let mut seen = HashSet::with_capacity(rays.len());
            rays.retain_mut(|r| {
                let v = r.end.map(f64::floor);
                r.end = v.map(|c| c + 0.5);
                seen.insert((v.map(|c| c as i64), r.hit))
            });
        }
        RayMode::Bundle { threshold } => {
            let vox = |r: &Ray| (r.end.map(|c| c.floor() as i64), r.hit);
            set_direction_keys(rays, origin);
            rays.par_sort_unstable_by_key(|r| (vox(r), r.key));
            let mut out = Vec::with_capacity(rays.len());
            let mut i = 0;
            while i < rays.len() {
                let k = vox(&rays[i]);
                let n = rays[i..].iter().take_while(|r| vox(r) == k).count();
                let group = &rays[i..i + n];
                if n > threshold as usize {
                    let mut m = [0.0; 3];
                    for r in group {
                        (0..3).for_each(|a| m[a] += r.end[a]);
                    }
                    let end = m.map(|c| c / n as f64);
                    let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
                    out.push(Ray::new(end, direction_key(d), group[0].hit));
                } else {
                    out.extend_from_slice(group);
                }
                i += n;
            }
            *rays = out;
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
struct Sides {
    origin: [f64; 3],
    /// The plane's normal in the world frame, a sensor axis; none for a one-thread pool,
    /// where all rays count as in front. One thread has no second grid to share first marks
    /// with, and in halves its lanes walk rays nearer in direction: laid out, its frames
    /// took 3-9% longer (500k 6 m workloads, three alternated rounds).
    axis: Option<[f64; 3]>,
}

impl Sides {
    /// Points sampled to choose the axis.
    const SAMPLES: usize = 1024;

    /// The sides for `frame` on a pool of `threads`: across the sensor axis whose plane
    /// halves the rays' lengths best, in a sample of the points (a sensor looking along one
    /// of its axes, as a camera along z or a forward lidar along x, has no ray behind it).
    fn new(frame: &Frame<'_>, origin: [f64; 3], threads: usize) -> Self {
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
    fn make(
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
    fn lay_out(&self, made: &[Ray], out: &mut [Ray]) -> [u32; 2] {
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

    /// Lay out rays without gaps in place; `sides` gets each chunk's counts.
    fn lay_out_all(&self, rays: &mut [Ray], sides: &mut Vec<[u32; 2]>) {
        sides.clear();
        if self.axis.is_none() {
            // All in front, in place.
            sides.extend(rays.chunks(RAY_CHUNK).map(|c| [c.len() as u32, 0]));
            return;
        }
        sides.resize(rays.len().div_ceil(RAY_CHUNK), [0; 2]);
        rays.par_chunks_mut(RAY_CHUNK)
            .zip(sides.par_iter_mut())
            .for_each_init(Vec::new, |made, (chunk, side)| {
                *side = self.lay_out_in_place(chunk, made);
            });
    }

    /// [`Sides::lay_out`] of `chunk` into itself, through `scratch`.
    fn lay_out_in_place(&self, chunk: &mut [Ray], scratch: &mut Vec<Ray>) -> [u32; 2] {
        scratch.clear();
        scratch.extend_from_slice(chunk);
        self.lay_out(scratch, chunk)
    }
}

/// Rays in chunks laid out with counts `sides` (not their length: gaps are not rays).
fn ray_count(sides: &[[u32; 2]]) -> u64 {
    sides.iter().map(|&[f, b]| u64::from(f + b)).sum()
}

/// Makes a frame's rays from its points: sensor frame to world by the pose, to voxel units
/// (snapped onto faces, see `GridTransform::to_units`), cut at max range.
#[derive(Clone, Copy, Debug)]
struct RayMaker {
    /// Rotation rows and translation of the pose.
    rot: [[f64; 3]; 3],
    t: [f64; 3],
    tf: crate::coord::GridTransform,
    origin: [f64; 3],
    range_units: f64,
    /// Below this squared length a ray surely ends within range; above it, the same
    /// comparison as the reference, `sqrt(len2) <= range_units`, decides.
    surely_in: f64,
}

impl RayMaker {
    fn new(
        frame: &Frame<'_>,
        tf: &crate::coord::GridTransform,
        origin: [f64; 3],
        range_units: f64,
    ) -> Self {
        let r = frame.pose.rotation.to_rotation_matrix().into_inner();
        RayMaker {
            rot: [0, 1, 2].map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]),
            t: frame.pose.translation.vector.into(),
            tf: *tf,
            origin,
            range_units,
            surely_in: range_units * range_units * (1.0 - 1e-9),
        }
    }

    /// The ray to `p`; a non-finite point gives a ray keyed `SKIPPED`. The arithmetic is
    /// spelled out (no library product) so that `avx512::make_rays` can repeat it
    /// operation for operation.
    #[inline]
    fn make(&self, p: &[f32; 3]) -> Ray {
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

    /// `out[i] = self.make(&pts[i])`, eight at a time where the build has AVX-512.
    fn make_all(&self, out: &mut [Ray], pts: &[[f32; 3]]) {
        #[cfg(all(
            target_arch = "x86_64",
            target_feature = "avx512f",
            target_feature = "avx512dq"
        ))]
        // SAFETY: only compiled when the build enables AVX-512F and DQ for the whole crate
        // (the cfg above), so every CPU that runs this code has them.
        let done = unsafe { avx512::make_rays(self, out, pts) };
        #[cfg(not(all(
            target_arch = "x86_64",
            target_feature = "avx512f",
            target_feature = "avx512dq"
        )))]
        let done = 0;
        for (r, p) in out.iter_mut().zip(pts).skip(done) {
            *r = self.make(p);
        }
    }
}

/// [`Extent`] of `rays`, in one pass.
fn bounds(rays: &[Ray], origin: [f64; 3]) -> Extent {
    rays.par_chunks(RAY_CHUNK)
        .map(|c| ExtentSum::of(origin, c))
        .reduce(|| ExtentSum::new(origin), ExtentSum::merge)
        .extent()
}

/// [`Extent`] being summed up over rays; skipped rays (non-finite points) are counted
/// apart. Bounds are taken on the ends in voxel units and floored once: floor is monotone,
/// so that is the bounds of the ends' voxels.
#[derive(Clone, Copy)]
struct ExtentSum {
    origin: [f64; 3],
    lo: [f64; 3],
    hi: [f64; 3],
    cut: u64,
    length: f64,
    skipped: u64,
}

impl ExtentSum {
    fn new(origin: [f64; 3]) -> Self {
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
    fn of(origin: [f64; 3], rays: &[Ray]) -> Self {
        let mut sum = ExtentSum::new(origin);
        rays.iter().for_each(|r| sum.add(r));
        sum
    }

    #[inline]
    fn add(&mut self, r: &Ray) {
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

    fn merge(a: Self, b: Self) -> Self {
        ExtentSum {
            origin: a.origin,
            lo: [0, 1, 2].map(|i| a.lo[i].min(b.lo[i])),
            hi: [0, 1, 2].map(|i| a.hi[i].max(b.hi[i])),
            cut: a.cut + b.cut,
            length: a.length + b.length,
            skipped: a.skipped + b.skipped,
        }
    }

    fn extent(&self) -> Extent {
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
struct Extent {
    /// Voxel bounds (inclusive) of the origin and all ray ends.
    lo: VoxelCoord,
    hi: VoxelCoord,
    cut_rays: u64,
    /// About the voxel steps of the walk: the rays' lengths in voxels along each axis.
    steps: f64,
}

/// The walks an integrator can take; tests force each in turn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(not(test), allow(dead_code))]
enum Walk {
    /// Dense when the frame's box fits the budget and its rays are many enough to pay for
    /// the grids (eight rays at a time where the build has AVX-512, one at a time
    /// otherwise), sparse otherwise.
    Auto,
    /// Sparse, eight rays at a time where the build has AVX-512.
    Sparse,
    /// Sparse one ray at a time, even where the build has AVX-512.
    SparseScalar,
    /// Dense whenever the box fits the budget.
    Dense,
    /// Dense one ray at a time, even where the build has AVX-512.
    DenseScalar,
    /// Dense, testing each mark before writing it on every frame (see
    /// `avx512::cast_chunk`), where the build has AVX-512.
    DenseTestFirst,
}

/// Walk all rays, laid out by [`Sides`] with counts `sides`, into the pool threads' dense
/// marks for frame `frame_no`; returns voxels visited.
#[allow(clippy::too_many_arguments)]
fn cast_dense(
    dense: &[std::sync::Mutex<dense::DenseBits>],
    dbox: &dense::DenseBox,
    frame_no: u64,
    origin: [f64; 3],
    rays: &[Ray],
    sides: &[[u32; 2]],
    steps: f64,
    walk: Walk,
) -> u64 {
    // Tasks walk the front sides of the chunks first, then the back sides: rayon hands the
    // first half of the tasks to one thread and the second half to another, so each
    // thread's rays mostly stay in its half of the box (work stealing evens out uneven
    // sides). Lane l of a task walks a chunk of the l-th eighth: in a sensor's scan order
    // (or sorted) these are far apart in direction (see `avx512::cast_chunk`).
    let per_lane = sides.len().div_ceil(8);
    let part = |back: bool, l: usize, c: usize| {
        let k = l * per_lane + c;
        let Some(&[n_front, n_back]) = sides.get(k) else {
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
    #[cfg(all(
        target_arch = "x86_64",
        target_feature = "avx512f",
        target_feature = "avx512dq"
    ))]
    let (refill_at, test_first) = (
        avx512::refill_at(steps / ray_count(sides).max(1) as f64),
        walk == Walk::DenseTestFirst || avx512::test_first(steps / (dbox.words() as f64 * 64.0)),
    );
    (0..2 * per_lane)
        .into_par_iter()
        .map(|t| {
            // Each pool thread has its own marks, so the lock is never contended.
            let mut bits = lock(&dense[rayon::current_thread_index().unwrap_or(0) % dense.len()]);
            bits.begin(frame_no, dbox.words());
            let ranges = std::array::from_fn(|l| part(t >= per_lane, l, t % per_lane));
            #[cfg(all(
                target_arch = "x86_64",
                target_feature = "avx512f",
                target_feature = "avx512dq"
            ))]
            if walk != Walk::DenseScalar {
                // SAFETY: only compiled when the build enables AVX-512F and DQ for the whole
                // crate (the cfg above), so every CPU that runs this code has them.
                return unsafe {
                    avx512::cast_chunk(&mut bits, dbox, origin, rays, ranges, refill_at, test_first)
                };
            }
            let _ = (walk, steps);
            dense::cast_chunk(&mut bits, dbox, origin, rays, ranges)
        })
        .sum()
}

/// Walk all rays into `marks` in parallel chunks; returns voxels visited.
fn cast_sparse(marks: &FrameMarks, origin: [f64; 3], rays: &[Ray], steps: f64, walk: Walk) -> u64 {
    #[cfg(all(
        target_arch = "x86_64",
        target_feature = "avx512f",
        target_feature = "avx512dq"
    ))]
    if walk != Walk::SparseScalar {
        let refill_at = avx512::refill_at(steps / rays.len().max(1) as f64);
        return rays
            .par_chunks(RAY_CHUNK)
            // SAFETY: only compiled when the build enables AVX-512F and DQ for the whole
            // crate (the cfg above), so every CPU that runs this code has them.
            .map(|chunk| unsafe {
                avx512::cast_sparse(&mut marks.cache(), origin, chunk, refill_at)
            })
            .sum();
    }
    let _ = (walk, steps);
    rays.par_chunks(RAY_CHUNK)
        .map(|chunk| cast_chunk(marks, origin, chunk))
        .sum()
}

fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A voxel of a sparse walk packed in one `u64`, 21 bits per axis, relative to an origin
/// near the rays' start: a step is one add of a stride, a field's low 3 bits are the
/// voxel's offset in its brick, and a change above them is a new brick.
#[derive(Clone, Copy)]
struct Packed {
    /// The voxel that packs to 0: brick-aligned, `BIAS` below the start on every axis.
    o: VoxelCoord,
}

impl Packed {
    const F: u32 = 21;
    const BIAS: i32 = 1 << 19;
    /// Index change of one voxel step along x, y and z.
    const STRIDES: [i64; 3] = [1, 1 << Self::F, 1 << (2 * Self::F)];
    /// Bits of a field above its low 3.
    const BRICK: u64 = !(7 | 7 << Self::F | 7 << (2 * Self::F));

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

/// Walk a chunk of rays one at a time, OR-ing their marks into `marks`; returns voxels
/// visited. Not inlined, and with the DDA set-up inlined into it, so that its code does not depend
/// on inlining choices made for its callers (which changed its speed by 40%).
#[inline(never)]
fn cast_chunk(marks: &FrameMarks, origin: [f64; 3], rays: &[Ray]) -> u64 {
    let mut steps = 0u64;
    let mut cache = marks.cache();
    for r in rays {
        let mut dda = Dda::new(origin, r.end);
        let n = dda.steps();
        steps += u64::from(n) + 1;
        let mut local = [0u64; 8];
        // The marks of the current z plane of the brick. A ray visits each plane of a brick
        // in one run, so the plane's word is only stored, never read back: a read-modify-
        // write of `local` would chain every step through store-to-load forwarding.
        let mut plane = 0u64;
        let mut brick = dda.voxel().shr(3);
        if n > 2 {
            // All steps but the last two: mark the current voxel, step, flush the brick's
            // marks on leaving it. The voxel is [`Packed`]: a step is one add and "left the
            // brick" one test, and the loop keeps more in registers. About 5% faster: 46
            // of 57 interleaved paired runs (6 m workloads, 1 and 2 threads) on a noisy VM.
            let start = dda.voxel();
            let packed = Packed::around(start);
            let [mx, my, mz] = Packed::STRIDES.map(|s| s as u64);
            let [sx, sy, sz] = dda.direction().map(|s| s as u64);
            let (mx, my, mz) = (
                mx.wrapping_mul(sx),
                my.wrapping_mul(sy),
                mz.wrapping_mul(sz),
            );
            let mut p = packed.pack(start);
            const F: u32 = Packed::F;
            for _ in 2..n {
                let was = p;
                plane |= 1u64 << ((p & 7) | (p >> (F - 3) & 0x38));
                local[(p >> (2 * F) & 7) as usize] = plane;
                let (cx, cy, _) = dda.step_far_crossing();
                p = p.wrapping_add(if cx {
                    mx
                } else if cy {
                    my
                } else {
                    mz
                });
                let moved = p ^ was;
                plane &= ((moved >> (2 * F) != 0) as u64).wrapping_sub(1);
                if moved & Packed::BRICK != 0 {
                    cache.or_free(brick, &local);
                    local = [0; 8];
                    plane = 0;
                    brick = packed.unpack(p).shr(3);
                }
            }
            let v = packed.unpack(p);
            (dda.x, dda.y, dda.z) = (v.x, v.y, v.z);
        }
        dda.settle();
        for _ in 0..n.min(2) {
            let (x, y, z) = (dda.x, dda.y, dda.z);
            plane |= 1u64 << ((x & 7) | (y & 7) << 3);
            local[(z & 7) as usize] = plane;
            dda.step();
            plane &= ((dda.z != z) as u64).wrapping_sub(1);
            if ((dda.x ^ x) | (dda.y ^ y) | (dda.z ^ z)) & !7 != 0 {
                cache.or_free(brick, &local);
                local = [0; 8];
                plane = 0;
                brick = dda.voxel().shr(3);
            }
        }
        // A ray's last step may enter a brick only to end there: nothing free to mark, and
        // a slot would give the map an empty leaf.
        if local != [0; 8] {
            cache.or_free(brick, &local);
        }
        if r.hit {
            cache.set_hit(dda.voxel());
        }
    }
    steps
}

/// Apply one brick's marks to its leaf; returns the voxels updated. `fresh`: the leaf was
/// created by this frame's merge, so it is all zero and may sit on a page never touched.
/// Such a leaf is only written, never read: a page first touched by a read is mapped to
/// the shared zero page, and the first write then copies it with a TLB flush that
/// interrupts every other core running the process (a fifth of a 60 m frame's time with
/// 2 threads). Written first, it gets a private page at once.
fn apply(leaf: &mut Leaf<i8>, slot: &Slot, q: &QuantizedModel, fresh: bool) -> u64 {
    let mut n = 0;
    for w in 0..8 {
        let free = slot.free[w].load(Relaxed);
        let hit = slot.hit[w].load(Relaxed);
        let any = free | hit;
        if any == 0 {
            continue;
        }
        n += u64::from(any.count_ones());
        let values: &mut [i8; 64] = (&mut leaf.values[w * 64..][..64])
            .try_into()
            .expect("64 values");
        // Separate calls, not a select on `fresh`: the compiler may load both sides of a
        // select, and that load is the read this avoids.
        if fresh {
            leaf.active.words[w] = any;
            leaf.marked.words[w] = observe::<true>(values, any, hit, q);
        } else {
            leaf.active.words[w] |= any;
            let occupied = observe::<false>(values, any, hit, q);
            leaf.marked.words[w] = leaf.marked.words[w] & !any | occupied;
        }
    }
    n
}

// `observe` is `avx512::observe` where the build has AVX-512BW, `observe_scalar` elsewhere.
#[cfg(all(
    target_arch = "x86_64",
    target_feature = "avx512f",
    target_feature = "avx512dq",
    target_feature = "avx512bw"
))]
use avx512::observe;

/// One observation for each of the 64 voxels of `values` whose bit is set in `any`, a hit
/// where set in `hit` too; returns those of them now at or above the occupancy threshold.
/// `FRESH`: the values are all zero, and are not read (see [`apply`]). `avx512::observe`
/// does the same in one masked add.
#[cfg_attr(
    all(
        target_arch = "x86_64",
        target_feature = "avx512f",
        target_feature = "avx512dq",
        target_feature = "avx512bw"
    ),
    allow(dead_code)
)]
#[inline]
fn observe_scalar<const FRESH: bool>(
    values: &mut [i8; 64],
    any: u64,
    hit: u64,
    q: &QuantizedModel,
) -> u64 {
    let mut occupied = 0;
    for b in BitIter(any) {
        let old = if FRESH { 0 } else { values[b] };
        values[b] = q.update(old, hit >> b & 1 != 0);
        occupied |= u64::from(values[b] >= q.threshold) << b;
    }
    occupied
}

#[cfg(not(all(
    target_arch = "x86_64",
    target_feature = "avx512f",
    target_feature = "avx512dq",
    target_feature = "avx512bw"
)))]
use observe_scalar as observe;

/// Give every touched brick its map leaf; returns (leaf index, (slot, leaf is new)) sorted
/// by leaf index.
fn merge(marks: &FrameMarks, map: &mut OccupancyMap) -> Vec<(u32, (u32, bool))> {
    let grid = map.grid_mut();
    let mut hint = (VoxelCoord::new(i32::MIN, 0, 0), u32::MAX);
    let first_new = grid.leaf_count() as u32;
    let mut items = Vec::with_capacity(marks.used_slots() as usize);
    // Internal-node-major order, so consecutive bricks share the cached internal node and
    // new leaves are laid out in space order.
    items.extend(marks.bricks_in_order().map(|(o, s)| {
        let l = grid.leaf_index_or_insert(o, Some(&mut hint));
        (l, (s, l >= first_new))
    }));
    if !items.windows(2).all(|w| w[0].0 < w[1].0) {
        items.par_sort_unstable_by_key(|&(l, _)| l);
    }
    items
}

// ---------------------------------------------------------------------------------------
// Per-frame marks

/// Bricks per coarse-cell edge (a coarse cell is 16^3 bricks, 128^3 voxels).
const CELL_LOG2: u32 = 4;
const CELL_ENTRIES: usize = 1 << (3 * CELL_LOG2);
/// Pool chunks of one huge page each (see [`Zeroed`]).
const SLOT_CHUNK: usize = HUGE_PAGE / std::mem::size_of::<Slot>();
const BLOCK_CHUNK: usize = HUGE_PAGE / std::mem::size_of::<Block>();

/// Free and hit marks of one 8x8x8 brick, bit `x | y << 3 | z << 6` as in a leaf.
#[derive(bytemuck::Zeroable)]
struct Slot {
    free: [AtomicU64; 8],
    hit: [AtomicU64; 8],
}

impl Slot {
    /// OR free marks in: plain loads and stores, no test first, as only the task holding
    /// the slot's lane writes it, and the line is about to be read anyway.
    #[inline]
    fn or_free(&self, bits: &[u64; 8]) {
        for (w, &b) in self.free.iter().zip(bits) {
            w.store(w.load(Relaxed) | b, Relaxed);
        }
    }

    /// OR `other`'s marks into this one's. Only between phases, when no walk writes.
    fn absorb(&self, other: &Slot) {
        let pairs = self.free.iter().zip(&other.free);
        for (w, o) in pairs.chain(self.hit.iter().zip(&other.hit)) {
            w.store(w.load(Relaxed) | o.load(Relaxed), Relaxed);
        }
    }
}

// A coarse cell covers exactly one grid internal node, and both number their 16^3
// children x | y << 4 | z << 8: walking cells and their entries in order is walking the
// grid's internal nodes and their children in order.
const _: () = assert!(3 + CELL_LOG2 == crate::grid::INTERNAL_TOTAL_LOG2);

/// The brick entries of one coarse cell: slot id + 1, or 0.
#[derive(bytemuck::Zeroable)]
struct Block([AtomicU32; CELL_ENTRIES]);

impl Zero for Block {
    fn zero(&self) {
        self.0.iter().for_each(|e| e.store(0, Relaxed));
    }
}

/// Pool items: valid all-zero, and zeroed in place.
trait Zero: bytemuck::Zeroable + Send + Sync {
    fn zero(&self);
}

impl Zero for Slot {
    fn zero(&self) {
        self.free
            .iter()
            .chain(&self.hit)
            .for_each(|w| w.store(0, Relaxed));
    }
}

/// A growable pool of zero-initialised `T`, handed out by id from any thread. Ids and
/// storage persist across frames; `clear` re-zeroes what was used.
struct Pool<T, const CHUNK: usize> {
    chunks: Vec<OnceLock<Zeroed<T>>>,
    next: AtomicU32,
}

impl<T, const CHUNK: usize> Default for Pool<T, CHUNK> {
    fn default() -> Self {
        Self {
            chunks: Vec::new(),
            next: AtomicU32::new(0),
        }
    }
}

impl<T: Zero, const CHUNK: usize> Pool<T, CHUNK> {
    fn reserve(&mut self, n: usize) {
        let want = n.div_ceil(CHUNK);
        while self.chunks.len() < want {
            self.chunks.push(OnceLock::new());
        }
    }

    fn alloc(&self) -> u32 {
        let id = self.next.fetch_add(1, Relaxed);
        self.get_or_init(id);
        id
    }

    /// Reserve `n` consecutive ids at once; each must be initialised with `get_or_init`
    /// before use. Ids reserved but never used stay zero, and are cleared like used ones.
    fn reserve_ids(&self, n: u32) -> Range<u32> {
        let first = self.next.fetch_add(n, Relaxed);
        first..first + n
    }

    #[inline]
    fn get_or_init(&self, id: u32) -> &T {
        let id = id as usize;
        let new_chunk = || {
            let items = Zeroed::<T>::new(CHUNK);
            // The zeroes come as untouched pages, which map to the shared zero page on
            // their first read; the first write then copies it and flushes the TLBs of
            // every core running the process. Writing them now gets private pages at once.
            items.iter().for_each(T::zero);
            items
        };
        &self.chunks[id / CHUNK].get_or_init(new_chunk)[id % CHUNK]
    }

    #[inline]
    fn get(&self, id: u32) -> &T {
        let id = id as usize;
        &self.chunks[id / CHUNK].get().expect("allocated id")[id % CHUNK]
    }

    fn used(&self) -> u32 {
        self.next.load(Relaxed)
    }

    fn clear(&mut self) {
        let n = self.used() as usize;
        self.chunks[..n.div_ceil(CHUNK)]
            .par_iter()
            .enumerate()
            .for_each(|(c, chunk)| {
                if let Some(items) = chunk.get() {
                    let end = (n - c * CHUNK).min(CHUNK);
                    items[..end].iter().for_each(T::zero);
                }
            });
        self.next.store(0, Relaxed);
    }
}

/// The id stored in a lane's `entry` (as id + 1), allocated on first use. No other task
/// writes the lane meanwhile, so a plain load and store suffice.
#[inline]
fn claim(entry: &AtomicU32, alloc: impl FnOnce() -> u32) -> u32 {
    match entry.load(Relaxed) {
        0 => {
            let id = alloc();
            entry.store(id + 1, Relaxed);
            id
        }
        e => e - 1,
    }
}

/// The per-frame mark tables, one per *lane*: a dense array of coarse cells over the
/// frame's bounding box, each pointing to a block of brick entries, each pointing to a
/// [`Slot`]. Only touched bricks get a slot; slots are contiguous, so the merge pass walks
/// a compact list.
///
/// A lane is written by one task at a time: [`FrameMarks::cache`] takes one, and dropping
/// the cache gives it back. So marks are plain read-modify-writes, not locked ones. A
/// locked OR holds back every later load until its cache line arrives; at 60 m, where most
/// marks miss cache, that was a quarter of the walk. A brick walked from several lanes
/// has a slot in each, and [`FrameMarks::bricks_in_order`] ORs them into one. The lanes
/// cost little: rayon gives each thread long runs of neighbouring chunks, and rays sorted
/// by direction, so the lanes share bricks only near the sensor.
#[derive(Default)]
struct FrameMarks {
    lo: VoxelCoord,
    cells_dim: [usize; 3],
    /// Coarse cells of the box.
    ncells: usize,
    /// Lane l's cells are `cells[l * ncells..][..ncells]`: block id + 1, or 0.
    cells: Vec<AtomicU32>,
    /// Whether each lane is held by a live [`BrickCache`].
    taken: Vec<AtomicBool>,
    blocks: Pool<Block, BLOCK_CHUNK>,
    slots: Pool<Slot, SLOT_CHUNK>,
}

/// A task's hold on one lane of the [`FrameMarks`], with its recent lookups: the last
/// block, and a direct-mapped cache of bricks (by the low bits of their coordinates) to
/// slots. Sorted rays revisit the same bricks near the sensor over and over; a hit here
/// skips the table walk.
struct BrickCache<'a> {
    marks: &'a FrameMarks,
    lane: usize,
    cell: usize,
    block: Option<u32>,
    bricks: [Option<(VoxelCoord, &'a Slot)>; BRICK_CACHE],
    /// Slot ids this task has reserved and not yet used: one shared counter increment
    /// per SLOT_BATCH new bricks instead of one per brick, which at 60 m (a new slot every
    /// few steps) made the two threads fight over the counter's cache line.
    spare_slots: Range<u32>,
}

const SLOT_BATCH: u32 = 16;
/// Rays per parallel task of the raycast.
const RAY_CHUNK: usize = 512;

/// Bricks in a [`BrickCache`], 16 per axis (96 KiB, in L2). A chunk's rays cross about
/// 170 bricks each at 60 m, in a cone wider than 8 bricks: with 512 (8 per axis), the
/// AVX-512 sparse walk's ray phase took 1539-1805 ms against 1267-1367 ms (random 500k
/// 60 m, one thread, three alternated runs).
const BRICK_CACHE: usize = 4096;

#[inline]
fn brick_cache_index(b: VoxelCoord) -> usize {
    ((b.x & 15) | (b.y & 15) << 4 | (b.z & 15) << 8) as usize
}

impl FrameMarks {
    /// Prepare for a frame whose voxels lie in `[lo, hi]`, cast in `chunks` tasks (each may
    /// leave up to a batch of reserved slot ids unused) on `lanes` threads.
    fn reset(&mut self, lo: VoxelCoord, hi: VoxelCoord, chunks: usize, lanes: usize) {
        let lanes = lanes.max(1);
        self.lo = lo.shr(3 + CELL_LOG2).shl(3 + CELL_LOG2);
        let d = hi.shr(3 + CELL_LOG2) - lo.shr(3 + CELL_LOG2);
        self.cells_dim = [d.x as usize + 1, d.y as usize + 1, d.z as usize + 1];
        self.ncells = self.cells_dim.iter().product::<usize>();
        self.cells.clear();
        self.cells
            .resize_with(self.ncells * lanes, || AtomicU32::new(0));
        self.taken.clear();
        self.taken.resize_with(lanes, || AtomicBool::new(false));
        self.blocks.reserve(self.ncells * lanes);
        self.slots
            .reserve(self.ncells * lanes * CELL_ENTRIES + chunks * SLOT_BATCH as usize);
    }

    /// Take a free lane for one task. Each thread holds at most one cache at a time and
    /// there are as many lanes as threads, so one is free; the thread's own index is tried
    /// first, so that a thread keeps finding its own blocks.
    fn cache(&self) -> BrickCache<'_> {
        let n = self.taken.len();
        let first = rayon::current_thread_index().unwrap_or(0);
        let mut i = 0;
        let lane = loop {
            let l = (first + i) % n;
            if self.taken[l]
                .compare_exchange(false, true, Acquire, Relaxed)
                .is_ok()
            {
                break l;
            }
            i += 1;
            if i % n == 0 {
                std::thread::yield_now();
            }
        };
        BrickCache {
            marks: self,
            lane,
            cell: 0,
            block: None,
            bricks: [None; BRICK_CACHE],
            spare_slots: 0..0,
        }
    }

    fn used_slots(&self) -> u32 {
        self.slots.used()
    }

    fn slot(&self, s: u32) -> &Slot {
        self.slots.get(s)
    }

    /// Every touched brick as (origin voxel, slot), in (z, y, x) order of cells and, within
    /// a cell, of bricks; a brick with slots in several lanes gets the others' marks ORed
    /// into the first. Call between a frame's phases, when no cache is live.
    fn bricks_in_order(&self) -> impl Iterator<Item = (VoxelCoord, u32)> + '_ {
        let [dx, dy, _] = self.cells_dim;
        let (n, lanes) = (self.ncells, self.taken.len());
        let m = (1 << CELL_LOG2) - 1;
        (0..n)
            .filter_map(move |c| {
                let blocks: Vec<&Block> = (0..lanes)
                    .filter_map(|l| match self.cells[l * n + c].load(Relaxed) {
                        0 => None,
                        b => Some(self.blocks.get(b - 1)),
                    })
                    .collect();
                (!blocks.is_empty()).then_some((c, blocks))
            })
            .flat_map(move |(c, blocks)| {
                let cell = VoxelCoord::new(
                    (c % dx) as i32,
                    (c / dx % dy) as i32,
                    (c / (dx * dy)) as i32,
                );
                let base = self.lo + cell.shl(3 + CELL_LOG2);
                (0..CELL_ENTRIES).filter_map(move |e| {
                    let mut ids = blocks
                        .iter()
                        .map(|b| b.0[e].load(Relaxed))
                        .filter(|&s| s != 0);
                    let first = ids.next()? - 1;
                    let slot = self.slots.get(first);
                    ids.for_each(|s| slot.absorb(self.slots.get(s - 1)));
                    let at = VoxelCoord::new(
                        (e & m) as i32,
                        (e >> CELL_LOG2 & m) as i32,
                        (e >> (2 * CELL_LOG2)) as i32,
                    );
                    Some((base + at.shl(3), first))
                })
            })
    }

    /// Zero everything this frame used, keeping the memory for the next.
    fn clear_used(&mut self) {
        self.slots.clear();
        self.blocks.clear();
    }
}

impl<'a> BrickCache<'a> {
    #[inline]
    fn slot_for(&mut self, brick: VoxelCoord) -> &'a Slot {
        let ci = brick_cache_index(brick);
        if let Some((b, slot)) = self.bricks[ci] {
            if b == brick {
                return slot;
            }
        }
        let slot = self.slot_lookup(brick);
        self.bricks[ci] = Some((brick, slot));
        slot
    }

    #[inline(never)]
    fn slot_lookup(&mut self, brick: VoxelCoord) -> &'a Slot {
        let marks = self.marks;
        let r = brick - marks.lo.shr(3);
        let (x, y, z) = (r.x as usize, r.y as usize, r.z as usize);
        let cell = (x >> CELL_LOG2)
            + marks.cells_dim[0] * ((y >> CELL_LOG2) + marks.cells_dim[1] * (z >> CELL_LOG2));
        let block = match self.block {
            Some(b) if self.cell == cell => b,
            _ => {
                let b = claim(&marks.cells[self.lane * marks.ncells + cell], || {
                    marks.blocks.alloc()
                });
                self.cell = cell;
                self.block = Some(b);
                b
            }
        };
        let m = (1 << CELL_LOG2) - 1;
        let e = (x & m) | (y & m) << CELL_LOG2 | (z & m) << (2 * CELL_LOG2);
        let entry = &marks.blocks.get(block).0[e];
        let spare = &mut self.spare_slots;
        let s = claim(entry, || {
            if Range::is_empty(spare) {
                *spare = marks.slots.reserve_ids(SLOT_BATCH);
            }
            let id = spare.next().expect("refilled above");
            marks.slots.get_or_init(id);
            id
        });
        marks.slots.get(s)
    }

    /// OR a brick's free marks into its slot ([`Slot::or_free`]).
    #[inline]
    fn or_free(&mut self, brick: VoxelCoord, bits: &[u64; 8]) {
        self.slot_for(brick).or_free(bits);
    }

    #[inline]
    fn set_hit(&mut self, v: VoxelCoord) {
        let slot = self.slot_for(v.shr(3));
        let i = leaf_offset(v);
        let w = &slot.hit[i >> 6];
        w.store(w.load(Relaxed) | 1u64 << (i & 63), Relaxed);
    }
}

impl Drop for BrickCache<'_> {
    fn drop(&mut self) {
        // Release: the next task to take this lane, on any thread, sees these marks.
        self.marks.taken[self.lane].store(false, Release);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{SensorModel, VoxelState};
    use crate::raycast::for_each_voxel;
    use crate::test_rng::Rng;
    use hashbrown::HashMap;
    use nalgebra::{Translation3, UnitQuaternion};

    /// Integrate `pts` seen from the origin, exact mode, 2 threads.
    fn at_origin(map: &mut OccupancyMap, max_range: f64, pts: &[[f32; 3]]) -> IntegrateReport {
        let frame = Frame {
            pose: Isometry3::identity(),
            points: pts,
        };
        integrator(2, max_range, RayMode::Exact)
            .integrate(map, &frame)
            .unwrap()
    }

    fn integrator(threads: usize, max_range: f64, mode: RayMode) -> Integrator {
        Integrator::new(IntegratorConfig {
            threads,
            max_range,
            mode,
            ..Default::default()
        })
        .unwrap()
    }

    fn snapshot(map: &OccupancyMap) -> Vec<(VoxelCoord, i8)> {
        map.assert_marks_in_step();
        let mut v: Vec<_> = map.grid().active_voxels().collect();
        v.sort();
        v
    }

    /// The update rule written the slow, obvious way: per ray a list of voxels, hit beats
    /// free within a frame, then one update per voxel.
    fn reference_integrate(map: &mut OccupancyMap, frame: &Frame<'_>, max_range: f64) {
        let tf = *map.transform();
        let o = tf.point_to_units(&Point3::from(frame.pose.translation.vector));
        let range = max_range / tf.resolution();
        let mut marks: HashMap<VoxelCoord, bool> = HashMap::new();
        for p in frame.points {
            if !p.iter().all(|c| c.is_finite()) {
                continue;
            }
            let w = frame.pose * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            let mut e = tf.point_to_units(&w);
            let d: Vec<f64> = (0..3).map(|a| e[a] - o[a]).collect();
            let len = d.iter().map(|c| c * c).sum::<f64>().sqrt();
            let hit = len <= range;
            if !hit {
                e = [0, 1, 2].map(|a| o[a] + d[a] * range / len);
            }
            let mut path = Vec::new();
            for_each_voxel(o, e, |v| path.push(v));
            let end = path.pop().unwrap();
            for v in path {
                marks.entry(v).or_insert(false);
            }
            if hit {
                marks.insert(end, true);
            }
        }
        let q = *map.quantized();
        for (v, hit) in marks {
            let old = map.value(v).unwrap_or(0);
            map.set_value(v, q.update(old, hit));
        }
    }

    fn random_frame(rng: &mut Rng, n: usize, radius: f64) -> (Isometry3<f64>, Vec<[f32; 3]>) {
        let pose = Isometry3::from_parts(
            Translation3::new(rng.f() * 4.0 - 2.0, rng.f() * 4.0 - 2.0, rng.f() - 0.5),
            UnitQuaternion::from_euler_angles(rng.f() * 6.0, rng.f() - 0.5, rng.f() * 6.0),
        );
        (pose, (0..n).map(|_| rng.ball(radius)).collect())
    }

    #[test]
    fn matches_the_reference_update_over_several_frames() {
        let mut rng = Rng(3);
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let mut want = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let mut integ = integrator(2, 3.0, RayMode::Exact);
        for _ in 0..4 {
            let (pose, pts) = random_frame(&mut rng, 3000, 4.0);
            let frame = Frame { pose, points: &pts };
            let r = integ.integrate(&mut map, &frame).unwrap();
            assert!(
                r.cut_rays > 0 && r.cut_rays < r.rays,
                "both kinds of rays: {r:?}"
            );
            reference_integrate(&mut want, &frame, 3.0);
        }
        assert_eq!(snapshot(&map), snapshot(&want));
    }

    #[test]
    fn result_is_identical_for_any_thread_count() {
        let mut rng = Rng(11);
        // Non-finite points leave gaps among the rays, laid out by sides from 2 threads
        // and in scan order on 1 (see `Sides`); the trade-off modes keep the first ray of a
        // kind, which must not depend on that layout.
        let frames: Vec<_> = (0..3)
            .map(|_| {
                let (pose, mut pts) = random_frame(&mut rng, 20000, 12.0);
                pts.iter_mut().step_by(11).for_each(|p| p[0] = f32::NAN);
                (pose, pts)
            })
            .collect();
        let run = |threads, mode| {
            let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
            let mut integ = integrator(threads, 10.0, mode);
            let mut steps = 0;
            for (pose, pts) in &frames {
                steps += integ
                    .integrate(
                        &mut map,
                        &Frame {
                            pose: *pose,
                            points: pts,
                        },
                    )
                    .unwrap()
                    .voxel_steps;
            }
            (snapshot(&map), steps, map.grid().leaf_count())
        };
        for mode in [
            RayMode::Exact,
            RayMode::Subsample { factor: 2 },
            RayMode::Bundle { threshold: 2 },
            RayMode::UniqueEnd,
        ] {
            let one = run(1, mode);
            assert!(one.0.len() > 100_000);
            for t in [2, 3, 4] {
                assert!(run(t, mode) == one, "{mode:?}: {t} threads differ from 1");
            }
        }
    }

    /// The dense walk's halves cut across the sensor axis that halves a frame best, found
    /// from a sample of its points, and only on more than one thread.
    #[test]
    fn sides_cut_across_the_axis_that_halves_the_frame() {
        let mut rng = Rng(5);
        let (pose, pts) = random_frame(&mut rng, 30000, 6.0);
        let origin = [1.0, 2.0, 3.0];
        // Keep the points with x and z in front (a sensor looking along x and z): only y
        // halves them.
        let front: Vec<_> = pts.iter().map(|p| [p[0].abs(), p[1], p[2].abs()]).collect();
        let frame = Frame {
            pose,
            points: &front,
        };
        assert!(Sides::new(&frame, origin, 1).axis.is_none());
        let axis = Sides::new(&frame, origin, 2).axis.unwrap();
        let y = pose.rotation * nalgebra::Vector3::y();
        assert!(
            (nalgebra::Vector3::from(axis) - y).norm() < 1e-12,
            "{axis:?}"
        );
        // Laid out by it: in front of the plane first, behind last, the gaps between.
        let s = Sides::new(&frame, origin, 2);
        let rays: Vec<_> = (0..RAY_CHUNK)
            .map(|i| match i % 5 {
                0 => Ray::new([0.0; 3], SKIPPED, false),
                _ => {
                    let d = [0, 1, 2].map(|_| rng.f() - 0.5);
                    Ray::new([0, 1, 2].map(|a| origin[a] + d[a]), 0, i % 3 == 0)
                }
            })
            .collect();
        let mut out = vec![Ray::new([9.0; 3], 1, true); RAY_CHUNK];
        let [front, back] = s.lay_out(&rays, &mut out).map(|c| c as usize);
        let ahead = |r: &Ray| {
            (0..3)
                .map(|a| (r.end[a] - origin[a]) * axis[a])
                .sum::<f64>()
                >= 0.0
        };
        assert_eq!(front + back, RAY_CHUNK - RAY_CHUNK.div_ceil(5));
        assert!(out[..front].iter().all(|r| r.key != SKIPPED && ahead(r)));
        assert!(out[front..RAY_CHUNK - back]
            .iter()
            .all(|r| r.key == SKIPPED));
        assert!(out[RAY_CHUNK - back..]
            .iter()
            .all(|r| r.key != SKIPPED && !ahead(r)));
        let key = |r: &Ray| (r.end.map(f64::to_bits), r.hit);
        let mut laid: Vec<_> = out.iter().filter(|r| r.key != SKIPPED).map(key).collect();
        let mut made: Vec<_> = rays.iter().filter(|r| r.key != SKIPPED).map(key).collect();
        laid.sort_unstable();
        made.sort_unstable();
        assert_eq!(laid, made);
    }

    /// The dense walks (eight rays at a time or one, into per-thread bit grids) and the
    /// sparse walk (one ray at a time into shared bricks) give the same map, steps and report,
    /// on frames with fewer rays than lanes, rays ending in their start voxel, rays cut at
    /// max range, negative coordinates, and a frame too big for the dense box.
    /// The vectorised observation of a leaf word gives the values the scalar one does:
    /// random words and marks, under the default model and models that clamp at the ends
    /// of i8 (where the vector add saturates) and inside them.
    #[cfg(all(
        target_arch = "x86_64",
        target_feature = "avx512f",
        target_feature = "avx512dq",
        target_feature = "avx512bw"
    ))]
    #[test]
    fn observing_a_word_at_once_equals_bit_by_bit() {
        let default = SensorModel::default().quantize().unwrap();
        let wide = QuantizedModel {
            hit: 127,
            miss: -128,
            min: -128,
            max: 127,
            ..default
        };
        let narrow = QuantizedModel {
            hit: 90,
            miss: -70,
            min: -50,
            max: 60,
            ..default
        };
        let mut rng = Rng(7);
        let word = |rng: &mut Rng| {
            (rng.f() * 2f64.powi(32)) as u64 | ((rng.f() * 2f64.powi(32)) as u64) << 32
        };
        for q in [default, wide, narrow] {
            for _ in 0..2000 {
                let (free, hit) = (word(&mut rng), word(&mut rng) & word(&mut rng));
                let any = free | hit;
                let old: [i8; 64] = std::array::from_fn(|_| rng.i(-128, 127) as i8);
                let (mut a, mut b) = (old, old);
                let marks = observe::<false>(&mut a, any, hit, &q);
                assert_eq!(marks, observe_scalar::<false>(&mut b, any, hit, &q));
                assert_eq!(a, b);
                let (mut a, mut b) = ([0i8; 64], [0i8; 64]);
                let marks = observe::<true>(&mut a, any, hit, &q);
                assert_eq!(marks, observe_scalar::<true>(&mut b, any, hit, &q));
                assert_eq!(a, b);
            }
        }
    }

    #[test]
    fn lanes_are_held_one_cache_each_and_merge_their_marks() {
        let mut marks = FrameMarks::default();
        let lo = VoxelCoord::new(-300, 0, 0);
        marks.reset(lo, VoxelCoord::new(300, 15, 15), 4, 2);
        // Bricks (voxel coordinates >> 3) at both ends of the box and one in between.
        let shared = VoxelCoord::new(-1, 1, 0);
        let (only_a, only_b) = (VoxelCoord::new(-37, 0, 0), VoxelCoord::new(37, 1, 1));
        let mut a = marks.cache();
        let mut b = marks.cache();
        assert_ne!(a.lane, b.lane);
        let a_lane = a.lane;
        a.or_free(shared, &[1, 0, 0, 0, 0, 0, 0, 1 << 63]);
        a.or_free(only_a, &[0, 2, 0, 0, 0, 0, 0, 0]);
        b.or_free(shared, &[4, 0, 0, 0, 0, 0, 0, 0]);
        b.set_hit(shared.shl(3) + VoxelCoord::new(7, 7, 7));
        b.or_free(only_b, &[0, 0, 8, 0, 0, 0, 0, 0]);
        drop(a);
        assert_eq!(marks.cache().lane, a_lane, "a dropped cache frees its lane");
        drop(b);
        let bricks: Vec<_> = marks.bricks_in_order().collect();
        let origins: Vec<_> = bricks.iter().map(|&(o, _)| o).collect();
        assert_eq!(origins, [only_a.shl(3), shared.shl(3), only_b.shl(3)]);
        let words = |s: u32| {
            let slot = marks.slot(s);
            let load = |w: &[AtomicU64; 8]| w.each_ref().map(|x| x.load(Relaxed));
            (load(&slot.free), load(&slot.hit))
        };
        let (free, hit) = words(bricks[1].1);
        assert_eq!(free, [5, 0, 0, 0, 0, 0, 0, 1 << 63]);
        assert_eq!(hit, [0, 0, 0, 0, 0, 0, 0, 1 << 63]);
        assert_eq!(words(bricks[0].1).0, [0, 2, 0, 0, 0, 0, 0, 0]);
        assert_eq!(words(bricks[2].1).0, [0, 0, 8, 0, 0, 0, 0, 0]);
    }

    #[test]
    fn dense_and_sparse_walks_agree() {
        let mut rng = Rng(29);
        // Short rays and long (lanes refill three at a time or one, see
        // `avx512::refill_at`), many rays in a small box (most marks repeat, see
        // `avx512::cast_chunk`), and a box too big for the dense grid.
        let mut frames: Vec<_> = [
            (5, 2.0),
            (3000, 4.0),
            (20000, 9.0),
            (3000, 25.0),
            (40000, 0.5),
            (4000, 45.0),
        ]
        .into_iter()
        .map(|(n, radius)| random_frame(&mut rng, n, radius))
        .collect();
        // Rays that end in the sensor's voxel, or along an axis.
        let (pose, _) = random_frame(&mut rng, 0, 1.0);
        let inv = pose.inverse();
        let at = |w: [f64; 3]| {
            let p = inv * Point3::new(w[0], w[1], w[2]);
            [p.x as f32, p.y as f32, p.z as f32]
        };
        let t = pose.translation.vector;
        let mut pts = vec![at([t.x, t.y, t.z]), at([t.x + 0.01, t.y, t.z])];
        pts.extend((0..20).map(|i| at([t.x + 0.1 * f64::from(i), t.y, t.z])));
        frames.push((pose, pts));
        // Long rays in the first eighth only: lanes done early take over others' rays.
        let (pose, mut pts) = random_frame(&mut rng, 16000, 0.5);
        pts[..2000]
            .iter_mut()
            .for_each(|p| *p = p.map(|c| c * 12.0));
        frames.push((pose, pts));
        // Non-finite points leave gaps in the rays' chunks (see `Sides`): scattered, and
        // filling a whole chunk. Then scans with every ray on one side of every sensor
        // axis, so on one side of the plane: one half of the walk's tasks has all the rays.
        let (pose, mut pts) = random_frame(&mut rng, 6000, 3.0);
        pts.iter_mut().step_by(7).for_each(|p| p[1] = f32::NAN);
        pts[1500..2600]
            .iter_mut()
            .for_each(|p| p[2] = f32::INFINITY);
        frames.push((pose, pts));
        for sign in [1.0f32, -1.0] {
            let (pose, mut pts) = random_frame(&mut rng, 5000, 3.0);
            pts.iter_mut().for_each(|p| *p = p.map(|c| sign * c.abs()));
            frames.push((pose, pts));
        }
        // Exact diagonals in 2 and 3 axes from a voxel centre, on a grid whose
        // coordinates are exact in binary: every corner and edge crossing is a tie.
        let q = 0.125;
        let sensor = Isometry3::translation(q / 2.0, q / 2.0, q / 2.0);
        let mut diag = Vec::new();
        for k in 1..40 {
            let d = (f64::from(k) * q) as f32;
            for s in [
                [1., 1., 1.],
                [-1., 1., -1.],
                [1., -1., 0.],
                [0., -1., -1.],
                [-1., 0., 1.],
            ] {
                diag.push([s[0] * d, s[1] * d, s[2] * d]);
            }
            // Ends on voxel corners and edges, in directions that are not diagonals.
            let c = |i: i32| (f64::from(i) * q - q / 2.0) as f32;
            diag.push([c(k), c(k / 2), c(-k / 3)]);
            diag.push([c(-k), c(k / 3), c(0)]);
        }
        let grids = [(0.1, frames), (q, vec![(sensor, diag)])];
        let run = |walk: Walk| {
            let mut out = Vec::new();
            for (resolution, frames) in &grids {
                let mut map = OccupancyMap::new(*resolution, SensorModel::default()).unwrap();
                let mut integ = integrator(2, 40.0, RayMode::Exact);
                integ.walk = walk;
                let mut reports = Vec::new();
                for (pose, pts) in frames {
                    let frame = Frame {
                        pose: *pose,
                        points: pts,
                    };
                    let r = integ.integrate(&mut map, &frame).unwrap();
                    reports.push((
                        r.rays,
                        r.cut_rays,
                        r.voxel_steps,
                        r.touched_leaves,
                        r.touched_voxels,
                        r.dense,
                    ));
                }
                out.push((snapshot(&map), map.grid().leaf_count(), reports));
            }
            out
        };
        let sparse = run(Walk::SparseScalar);
        assert!(sparse.iter().flat_map(|g| &g.2).all(|r| !r.5));
        for walk in [
            Walk::Sparse,
            Walk::Dense,
            Walk::DenseScalar,
            Walk::DenseTestFirst,
            Walk::Auto,
        ] {
            let dense = run(walk);
            let took_dense: Vec<bool> = dense.iter().flat_map(|g| &g.2).map(|r| r.5).collect();
            if walk == Walk::Sparse {
                assert!(!took_dense.contains(&true));
            } else if walk != Walk::Auto {
                assert_eq!(
                    took_dense,
                    [true, true, true, true, true, false, true, true, true, true, true, true]
                );
            }
            for (d, s) in dense.iter().zip(&sparse) {
                let strip = |r: &(u64, u64, u64, u64, u64, bool)| (r.0, r.1, r.2, r.3, r.4);
                assert_eq!(
                    d.2.iter().map(strip).collect::<Vec<_>>(),
                    s.2.iter().map(strip).collect::<Vec<_>>(),
                    "{walk:?}"
                );
                assert_eq!(d.1, s.1, "{walk:?}");
                assert!(d.0 == s.0, "{walk:?}: maps differ");
            }
        }
    }

    /// Sensor inside a closed box room: every wall voxel hit is occupied, the interior the
    /// rays crossed is free, and nothing outside the walls is known.
    #[test]
    fn closed_box_room() {
        let (hx, hy, hz) = (2.0f64, 1.5f64, 1.2f64); // half extents, metres; walls at +-h
        let sensor = [0.33f64, -0.21, 0.1];
        let mut pts = Vec::new();
        let n = 200_000;
        for i in 0..n {
            // Fibonacci sphere directions.
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * 2.399963229728653;
            let d = [r * phi.cos(), r * phi.sin(), z];
            let t = (0..3)
                .map(|a| {
                    let h = [hx, hy, hz][a];
                    if d[a] > 0.0 {
                        (h - 0.01 - sensor[a]) / d[a]
                    } else if d[a] < 0.0 {
                        (-h + 0.01 - sensor[a]) / d[a]
                    } else {
                        f64::INFINITY
                    }
                })
                .fold(f64::INFINITY, f64::min);
            pts.push([0, 1, 2].map(|a| (d[a] * t) as f32));
        }
        let pose = Isometry3::translation(sensor[0], sensor[1], sensor[2]);
        let mut map = OccupancyMap::new(0.05, SensorModel::default()).unwrap();
        let r = integrator(2, 10.0, RayMode::Exact)
            .integrate(&mut map, &Frame { pose, points: &pts })
            .unwrap();
        assert_eq!(r.cut_rays, 0);
        let tf = *map.transform();
        let state = |x: f64, y: f64, z: f64| map.state_at(&WorldPointT::new(x, y, z));
        // The wall voxel of every point is occupied.
        for p in pts.iter().step_by(97) {
            let w = pose * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            assert_eq!(map.state_at(&w), VoxelState::Occupied, "{w:?}");
        }
        // The interior, at least two voxels from the walls, is free wherever rays crossed it;
        // with 200k rays from one point that is every voxel (checked on a lattice).
        let res = tf.resolution();
        let mut checked = 0;
        let steps = |h: f64| (-((h - 2.0 * res) / 0.1) as i32)..=(((h - 2.0 * res) / 0.1) as i32);
        for ix in steps(hx) {
            for iy in steps(hy) {
                for iz in steps(hz) {
                    let (x, y, z) = (
                        ix as f64 * 0.1 + 0.013,
                        iy as f64 * 0.1 + 0.013,
                        iz as f64 * 0.1 + 0.013,
                    );
                    assert_eq!(state(x, y, z), VoxelState::Free, "interior ({x}, {y}, {z})");
                    checked += 1;
                }
            }
        }
        assert!(checked > 5000);
        // Outside the walls: unknown, and no known voxel lies beyond them.
        assert_eq!(state(hx + 0.3, 0.0, 0.0), VoxelState::Unknown);
        assert_eq!(state(0.0, -hy - 0.3, 0.0), VoxelState::Unknown);
        assert_eq!(state(0.0, 0.0, hz + 0.5), VoxelState::Unknown);
        for (v, _) in map.grid().active_voxels() {
            let c = tf.voxel_center(v);
            assert!(
                c.x.abs() < hx + res && c.y.abs() < hy + res && c.z.abs() < hz + res,
                "known outside: {c:?}"
            );
        }
        let counts = map.counts();
        assert!(
            counts.occupied > 1000 && counts.free > 100_000,
            "{counts:?}"
        );
    }

    type WorldPointT = crate::coord::WorldPoint;

    #[test]
    fn max_range_rays_mark_free_only() {
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let pts = [[5.0f32, 0.05, 0.05], [1.0, 0.05, 0.05]];
        let r = at_origin(&mut map, 2.0, &pts[..1]);
        assert_eq!((r.rays, r.cut_rays), (1, 1));
        assert_eq!(map.counts().occupied, 0);
        // Cut at 2 m along the ray: x = 1.9998, voxel 19 is the cut end.
        assert_eq!(map.state(VoxelCoord::new(18, 0, 0)), VoxelState::Free);
        assert_eq!(
            map.state(VoxelCoord::new(19, 0, 0)),
            VoxelState::Unknown,
            "the cut end itself is not marked"
        );
        at_origin(&mut map, 2.0, &pts[1..]);
        assert_eq!(map.state(VoxelCoord::new(10, 0, 0)), VoxelState::Occupied);

        // Cut at x = 16.5: the end voxel opens leaf 2 but is not marked, so no leaf 2.
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        at_origin(&mut map, 1.65, &pts[..1]);
        assert_eq!(map.state(VoxelCoord::new(15, 0, 0)), VoxelState::Free);
        let leaves: Vec<_> = map
            .grid()
            .leaves()
            .map(|(o, l)| (o.x, l.active.count()))
            .collect();
        assert_eq!(leaves.len(), 2, "{leaves:?}");
        assert!(leaves.iter().all(|&(x, n)| x < 16 && n == 8), "{leaves:?}");
    }

    /// Leaves mark their voxels at or above the threshold, also exactly at it (here one
    /// hit's value), on every walk, in new leaves and in leaves seen before.
    #[test]
    fn leaves_mark_voxels_at_the_threshold() {
        let model = SensorModel {
            occupancy_threshold: SensorModel::default().p_hit,
            ..Default::default()
        };
        for walk in [
            Walk::Sparse,
            Walk::SparseScalar,
            Walk::Dense,
            Walk::DenseScalar,
        ] {
            let mut map = OccupancyMap::new(0.1, model).unwrap();
            let q = *map.quantized();
            assert_eq!(q.threshold, q.hit);
            let mut integ = integrator(2, 5.0, RayMode::Exact);
            integ.walk = walk;
            let mut rng = Rng(5);
            for _ in 0..3 {
                let (pose, pts) = random_frame(&mut rng, 2000, 4.0);
                integ
                    .integrate(&mut map, &Frame { pose, points: &pts })
                    .unwrap();
                map.assert_marks_in_step();
            }
            let at = map
                .grid()
                .active_voxels()
                .filter(|&(_, v)| v == q.threshold);
            assert!(at.count() > 100, "{walk:?}: few voxels at the threshold");
        }
    }

    #[test]
    fn hit_beats_free_within_a_frame_and_degenerate_rays() {
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        // The second point's ray passes through the first point's voxel.
        let pts = [
            [0.55f32, 0.05, 0.05],
            [1.55, 0.05, 0.05],
            [0.0, 0.0, 0.0],
            [0.01, 0.02, 0.03],
        ];
        at_origin(&mut map, 10.0, &pts);
        let q = *map.quantized();
        assert_eq!(map.value(VoxelCoord::new(5, 0, 0)), Some(q.hit));
        assert_eq!(map.value(VoxelCoord::new(15, 0, 0)), Some(q.hit));
        assert_eq!(map.value(VoxelCoord::new(10, 0, 0)), Some(q.miss));
        // Zero-length rays: the sensor's own voxel is a hit, once.
        assert_eq!(map.value(VoxelCoord::new(0, 0, 0)), Some(q.hit));
    }

    /// `make_all` (eight at a time on AVX-512 builds) makes exactly `make`'s rays: on
    /// random points, non-finite ones, points on voxel faces and at max range, under
    /// rotated poses.
    #[test]
    fn rays_made_in_bulk_equal_rays_made_one_by_one() {
        let mut rng = Rng(77);
        let tf = crate::coord::GridTransform::new(0.1).unwrap();
        for round in 0..20 {
            let (pose, mut pts) = random_frame(&mut rng, 1003, 8.0);
            let o = tf.point_to_units(&Point3::from(pose.translation.vector));
            let range = 5.0 / tf.resolution();
            // Some points on multiples of the resolution (faces under the identity pose),
            // exactly at max range, non-finite, or beyond max range.
            let pose = if round % 4 == 0 {
                Isometry3::identity()
            } else {
                pose
            };
            let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
            for (i, p) in pts.iter_mut().enumerate().step_by(3) {
                match i % 4 {
                    0 => *p = p.map(|c| (c * 10.0).round() / 10.0),
                    1 => *p = [5.0, 0.0, 0.0],
                    2 => p[i % 3] = bad[i / 4 % 3],
                    _ => *p = p.map(|c| c * 3.0),
                }
            }
            let frame = Frame { pose, points: &pts };
            let maker = RayMaker::new(&frame, &tf, o, range);
            let mut bulk = vec![Ray::new([0.0; 3], 0, false); pts.len()];
            maker.make_all(&mut bulk, &pts);
            for (p, b) in pts.iter().zip(&bulk) {
                let one = maker.make(p);
                assert_eq!(
                    (one.end.map(f64::to_bits), one.key, one.hit),
                    (b.end.map(f64::to_bits), b.key, b.hit),
                    "point {p:?}"
                );
            }
        }
    }

    #[test]
    fn non_finite_points_are_skipped_and_counted() {
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let pts = [
            [1.0f32, 0.0, 0.0],
            [f32::NAN, 0.0, 0.0],
            [0.0, f32::INFINITY, 0.0],
            [0.0, 1.0, 0.0],
        ];
        let r = at_origin(&mut map, 10.0, &pts);
        assert_eq!((r.points, r.skipped_nonfinite, r.rays), (4, 2, 2));
        assert_eq!(map.counts().occupied, 2);
    }

    #[test]
    fn bad_frames_are_rejected_and_change_nothing() {
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let mut integ = integrator(2, 10.0, RayMode::Exact);
        integ
            .integrate(
                &mut map,
                &Frame {
                    pose: Isometry3::identity(),
                    points: &[[1.0, 1.0, 1.0]],
                },
            )
            .unwrap();
        let before = snapshot(&map);
        let far = Isometry3::translation(1e9, 0.0, 0.0);
        assert!(matches!(
            integ.integrate(
                &mut map,
                &Frame {
                    pose: far,
                    points: &[[1.0, 0.0, 0.0]]
                }
            ),
            Err(IntegrateError::OriginOutOfRange { .. })
        ));
        let nan = Isometry3::translation(f64::NAN, 0.0, 0.0);
        assert_eq!(
            integ.integrate(
                &mut map,
                &Frame {
                    pose: nan,
                    points: &[[1.0, 0.0, 0.0]]
                }
            ),
            Err(IntegrateError::NonFinitePose)
        );
        assert_eq!(snapshot(&map), before);
        assert!(Integrator::new(IntegratorConfig {
            threads: 0,
            ..Default::default()
        })
        .is_err());
        assert!(Integrator::new(IntegratorConfig {
            max_range: f64::NAN,
            ..Default::default()
        })
        .is_err());
        let long = IntegratorConfig {
            max_range: 2000.0,
            threads: 1,
            ..Default::default()
        };
        assert_eq!(
            Integrator::new(long).unwrap().integrate(
                &mut map,
                &Frame {
                    pose: Isometry3::identity(),
                    points: &[]
                }
            ),
            Err(IntegrateError::RangeTooLong {
                max_range: 2000.0,
                resolution: 0.1
            })
        );
        assert_eq!(snapshot(&map), before);
    }

    #[test]
    fn trade_off_modes_cast_fewer_rays_and_stay_close() {
        let mut rng = Rng(5);
        // Dense: 50k points in a 1 m ball (~4200 voxels) at 0.1 m: many share end voxels.
        let pts: Vec<_> = (0..50_000).map(|_| rng.ball(1.0)).collect();
        let frame = Frame {
            pose: Isometry3::identity(),
            points: &pts,
        };
        let run = |mode| {
            let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
            let r = integrator(2, 10.0, mode)
                .integrate(&mut map, &frame)
                .unwrap();
            (r, map.counts(), snapshot(&map))
        };
        let (exact, ce, se) = run(RayMode::Exact);
        for mode in [
            RayMode::UniqueEnd,
            RayMode::Subsample { factor: 1 },
            RayMode::Bundle { threshold: 2 },
        ] {
            let (r, c, _) = run(mode);
            assert!(
                r.rays < exact.rays / 2,
                "{mode:?}: {} of {} rays",
                r.rays,
                exact.rays
            );
            // Same end voxels: the occupied set is nearly unchanged.
            let d = (c.occupied as f64 - ce.occupied as f64).abs() / ce.occupied as f64;
            assert!(
                d < 0.05,
                "{mode:?}: occupied {} vs {}",
                c.occupied,
                ce.occupied
            );
        }
        // Unique-end keeps exactly one ray per end voxel: the occupied set is the same.
        assert_eq!(run(RayMode::UniqueEnd).1.occupied, ce.occupied);
        // A bundle threshold above every group size changes nothing.
        assert_eq!(
            run(RayMode::Bundle {
                threshold: 1_000_000
            })
            .2,
            se
        );
        // A very fine subsample grid (1.6 mm) keeps nearly every ray.
        assert!(run(RayMode::Subsample { factor: 64 }).0.rays * 1000 > exact.rays * 999);
    }
}
