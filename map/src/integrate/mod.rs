//! Frame integration: the paper's two-step update (mark every voxel a frame touches, then
//! update each once), made merge-free and independent of the thread count.
//!
//! [`Integrator::integrate`] runs four phases, each one call into its module:
//!
//! | phase | what it does | file | test that pins it down |
//! |---|---|---|---|
//! | prepare | points → rays in voxel units (pose, max-range cut, ray modes), laid out by the sensor's sides; sorted by direction for the sparse walk | `prepare.rs`, `ray/` (`select/` for the modes) | `rays_made_in_bulk_equal_rays_made_one_by_one`, `sides_cut_across_the_axis_that_halves_the_frame`, `ray_modes_cast_fewer_rays_and_stay_close` |
//! | walk | exact DDA through every ray's voxels, marks into per-thread grids (dense) or per-frame leaf tables (sparse) | `walk/` (one dispatch point, `walk::run`) | `dense_and_sparse_walks_agree` |
//! | merge | dense grids folded into the mark tables; every touched leaf's marks paired with its map leaf | `merge.rs`, `walk/dense.rs` (`fold_into`) | `tables_are_held_one_cache_each_and_merge_their_marks` |
//! | update | one log-odds observation per touched voxel, hit beating free | `update/` | `matches_the_reference_update_over_several_frames`, `observing_a_word_at_once_equals_bit_by_bit` |
//!
//! The per-frame marks live in `marks.rs` ([`marks::FrameMarks`]). Marks are OR-ed and each
//! voxel is updated once from its final marks, so the map after a frame does not depend on
//! the thread count or scheduling (`result_is_identical_for_any_thread_count`).
//!
//! The words (the glossary of `docs/architecture.md` has them all):
//! - **leaf**: 8³ voxels: the map's leaf holds their values ([`crate::grid::Leaf`]); a
//!   frame's marks of a leaf (its free and hit bits) are a **slot** ([`marks::Slot`]),
//!   which the merge pairs with the map's leaf.
//! - **node**: 16³ leaves, one internal node of the map; the mark tables list a node's
//!   touched leaves in a [`marks::NodeEntries`]. (A snapshot's **block** is 8³ leaves.)
//! - **table**: one thread's share of the mark tables; **lane**: one ray of a vector walk.
//! - **chunk**: [`ray::RAY_CHUNK`] rays, the unit of parallel work and of the layout.
//!
//! Each phase with a vector form calls its entry in the process's [`Kernels`] table (the
//! kernel chosen once per process, `VOXMAP_KERNEL` forcing one); every kernel gives the
//! same map.
//!
//! The walks are 2-4x faster dense than sparse with AVX-512, 1.3-2x without. The sparse walk
//! is what keeps 2 threads ahead of 1 at 60 m, where the paper's per-thread dense grids made
//! the merge dominate: threads walk rays of different directions, so their tables share
//! leaves only near the sensor.

use crate::coord::{ConfigError, MAX_VOXEL_INDEX};
use crate::kernel::{Kernel, KernelError, Kernels};
use crate::occupancy::OccupancyMap;
use marks::FrameMarks;
use nalgebra::Point3;
use ray::{Extent, Ray, Sides};
use std::time::{Duration, Instant};

pub(crate) mod marks;
mod merge;
pub(crate) mod prepare;
pub(crate) mod ray;
pub(crate) mod select;
pub(crate) mod update;
pub(crate) mod walk;

pub use ray::Frame;
pub use select::RayMode;
use walk::Walk;

#[cfg(test)]
mod tests;

/// Longest allowed ray, in voxels; bounds the per-frame mark table.
pub const MAX_RANGE_VOXELS: f64 = 8192.0;

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

/// Why an integrator (or a [`crate::Mapper`]) could not be set up.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum SetupError {
    /// A setting is out of its range.
    Config(ConfigError),
    /// `VOXMAP_KERNEL` names a kernel this build or CPU lacks.
    Kernel(KernelError),
}

impl std::fmt::Display for SetupError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Config(e) => write!(f, "{e}"),
            Self::Kernel(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for SetupError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::Config(e) => Some(e),
            Self::Kernel(e) => Some(e),
        }
    }
}

impl From<ConfigError> for SetupError {
    fn from(e: ConfigError) -> Self {
        Self::Config(e)
    }
}

impl IntegrateError {
    /// A short name of the reason, for counting.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::NonFinitePose => "pose not finite",
            Self::OriginOutOfRange { .. } => "origin out of range",
            Self::RangeTooLong { .. } => "range too long",
        }
    }
}

/// Time per phase of one integration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PhaseTimes {
    pub prepare: Duration,
    /// Of `prepare`: a ray mode choosing its rays and dropping the others from the
    /// layout (zero in exact mode), what the mode costs before its walk saves anything.
    /// Where rays are chosen as they are made, it counts their layout too, which the
    /// exact mode also does: an upper bound.
    pub select: Duration,
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
    /// Rays cast (after the ray mode).
    pub rays: u64,
    /// Rays cut at max range (free space only).
    pub cut_rays: u64,
    /// Voxels on all rays, end voxels included.
    pub voxel_steps: u64,
    /// Of `voxel_steps`, those the dense walk did not walk: inside a box around the sensor
    /// whose voxels the frame's first rays had all marked already (`walk::covered`).
    pub covered_steps: u64,
    /// Leaves (8x8x8 leaves) and voxels updated.
    pub touched_leaves: u64,
    pub touched_voxels: u64,
    /// Inclusive voxel bounds of the sensor origin and every ray's end: no voxel outside
    /// changed (a [`crate::field::DistanceField`] update looks only there).
    pub bounds: Option<(crate::VoxelCoord, crate::VoxelCoord)>,
    /// The frame's box was small enough for the dense walk (see `integrate::walk::dense`).
    pub dense: bool,
    pub times: PhaseTimes,
}

/// Integrates frames into maps. Holds a thread pool and scratch memory that is reused
/// from frame to frame; one per map writer.
pub struct Integrator {
    cfg: IntegratorConfig,
    pool: rayon::ThreadPool,
    marks: FrameMarks,
    rays: Vec<Ray>,
    /// Per chunk of `rays`: how many lie on either side of the sensor (see [`Sides`]).
    counts: Vec<[u32; 2]>,
    /// What the ray modes reuse from frame to frame.
    select: select::Buffers,
    /// Per pool thread: dense marks for frames with a small box.
    dense: Vec<std::sync::Mutex<walk::dense::DenseBits>>,
    /// Frames integrated, to tell this frame's dense marks from stale ones.
    frames: u64,
    /// Which walk to take (tests compare them).
    walk: Walk,
    /// The kernel's entry points (tests compare kernels).
    kernels: &'static Kernels,
}

impl Integrator {
    pub fn new(cfg: IntegratorConfig) -> Result<Self, SetupError> {
        if cfg.threads == 0 || cfg.threads > 1024 {
            return Err(ConfigError::Invalid {
                name: "threads",
                value: cfg.threads as f64,
                why: "must be 1..=1024",
            }
            .into());
        }
        if !(cfg.max_range.is_finite() && cfg.max_range > 0.0) {
            return Err(ConfigError::Invalid {
                name: "max_range",
                value: cfg.max_range,
                why: "must be finite and > 0",
            }
            .into());
        }
        match cfg.mode {
            RayMode::Subsample { factor } if !(1..=64).contains(&factor) => {
                return Err(ConfigError::Invalid {
                    name: "subsample_factor",
                    value: factor as f64,
                    why: "must be 1..=64",
                }
                .into())
            }
            RayMode::Bundle { threshold: 0 } => {
                return Err(ConfigError::Invalid {
                    name: "bundle_threshold",
                    value: 0.0,
                    why: "must be >= 1",
                }
                .into())
            }
            _ => {}
        }
        let kernels = Kernels::process().map_err(SetupError::Kernel)?;
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
            counts: Vec::new(),
            select: Default::default(),
            frames: 0,
            walk: Walk::Auto,
            kernels,
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

    /// Bytes of the buffers the integrator keeps from frame to frame (rays, marks, the ray
    /// modes' and the dense walk's buffers), as allocated: what a memory budget leaves
    /// out of the map's share.
    pub fn memory_bytes(&self) -> usize {
        use std::mem::size_of_val;
        let dense: usize = (self.dense.iter())
            .map(|d| {
                let d = d.lock().unwrap_or_else(|e| e.into_inner());
                (d.free.capacity() + d.hit.capacity()) * 8
            })
            .sum();
        self.rays.capacity() * std::mem::size_of::<Ray>()
            + size_of_val(self.counts.as_slice())
            + self.marks.memory_bytes()
            + self.select.memory_bytes()
            + dense
    }

    /// The kernel this integrator runs: the CPU's best, or `VOXMAP_KERNEL`'s.
    pub fn kernel(&self) -> Kernel {
        self.kernels.kernel()
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
        let (range_units, origin) = self.check_frame(map, frame)?;
        let tf = *map.transform();
        let q = *map.quantized();
        let mode = self.cfg.mode;
        self.frames += 1;
        let frame_no = self.frames;
        let (pool, marks, rays, counts, select, dense, walk, kernels) = (
            &self.pool,
            &mut self.marks,
            &mut self.rays,
            &mut self.counts,
            &mut self.select,
            &self.dense,
            self.walk,
            self.kernels,
        );
        let mut report = IntegrateReport {
            points: frame.points.len() as u64,
            ..Default::default()
        };
        pool.install(|| {
            let t0 = Instant::now();
            // Prepare.
            let sides = Sides::new(frame, origin, rayon::current_num_threads());
            let (skipped, extent, select_time) = prepare::prepare_rays(
                rays,
                counts,
                sides,
                frame,
                &tf,
                origin,
                range_units,
                mode,
                kernels,
                select,
            );
            let Extent {
                lo,
                hi,
                cut_rays,
                steps,
            } = extent;
            report.skipped_nonfinite = skipped;
            // Not `rays.len()`: skipped points leave gaps (see `Sides`).
            report.rays = ray::ray_count(counts);
            report.cut_rays = cut_rays;
            report.bounds = Some((lo, hi));
            let dense_box = walk::plan(walk, lo, hi, steps);
            report.dense = dense_box.is_some();
            // The dense walk needs no order but the sides: its grids stay in cache whatever
            // the rays' directions, and its lanes only need to be far apart in direction,
            // which chunks from the eight eighths of a sensor's scan are (sorting took half
            // of its prepare time). The sparse walk needs them sorted by direction, without
            // gaps.
            if !report.dense {
                prepare::order_by_direction(rays, counts, origin);
            }
            marks.reset(lo, hi, rayon::current_num_threads());
            let t1 = Instant::now();
            // Walk.
            let input = walk::WalkInput {
                origin,
                rays,
                counts,
                steps,
                bounds: (lo, hi),
                range: range_units,
                walk,
                kernels,
            };
            (report.voxel_steps, report.covered_steps) =
                walk::run(&input, marks, dense, dense_box.as_ref(), frame_no);
            let t2 = Instant::now();
            // Merge.
            if let Some(b) = &dense_box {
                walk::dense::with_live(dense, frame_no, |live| {
                    walk::dense::fold_into(marks, b, live)
                });
            }
            let items = merge::attach_leaves(marks, map);
            let t3 = Instant::now();
            // Update.
            report.touched_leaves = items.len() as u64;
            report.touched_voxels = map.grid_mut().leaf_pool_mut().par_update(
                &items,
                |&(slot, _)| marks.slot(slot).prefetch(),
                |leaf, &(slot, fresh)| (kernels.observe_leaf)(leaf, marks.slot(slot), &q, fresh),
            );
            marks.clear_used();
            let t4 = Instant::now();
            report.times = PhaseTimes {
                prepare: t1 - t0,
                select: select_time,
                raycast: t2 - t1,
                merge: t3 - t2,
                update: t4 - t3,
            };
        });
        Ok(report)
    }

    /// The frame's range in voxel units and sensor origin in voxel units, or why the frame
    /// is rejected.
    fn check_frame(
        &self,
        map: &OccupancyMap,
        frame: &Frame<'_>,
    ) -> Result<(f64, [f64; 3]), IntegrateError> {
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
        let origin = map
            .transform()
            .point_to_units(&Point3::from(pose.translation.vector));
        if origin
            .iter()
            .any(|c| c.abs() + range_units + 16.0 >= MAX_VOXEL_INDEX)
        {
            return Err(IntegrateError::OriginOutOfRange {
                origin: pose.translation.vector.into(),
            });
        }
        Ok((range_units, origin))
    }
}
