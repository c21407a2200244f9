//! Ray selection: the ray modes ([`RayMode`]) choose which of a frame's rays are cast.
//! `exact` casts every ray; `subsample` and `unique_end` are the speed modes (fewer rays,
//! a coarser map), `bundle` the quality mode (fewer rays than exact, a map nearer exact's
//! than unique_end's, and more time than exact: grouping the points costs more than the
//! rays it saves). Each keeps the first ray of a kind in scan order, so its result does not
//! depend on the thread count. This stage only reads rays (`ray`) and says which it keeps
//! ([`Kept`]); it never calls back into the prepare phase that drives it.
//!
//! Unless chosen as they are made (below), the rays are made and laid out by sides as in
//! exact mode, and the same pass notes each ray's cell key ([`CellKeys`]) in scan order
//! and where the layout put it ([`ChunkOrder`]). The modes choose from the keys alone (8
//! bytes a ray, not the ray's 32), and the layout then drops what they drop
//! (`prepare::compact`). A ray's cell is written three ways: its **cell key** (the cell's
//! coordinates from the frame's base and whether the ray hits, 64 bits), its **cell
//! index** in a [`CellBox`]'s bit set (32 bits), and its **note**: the index with
//! [`BEHIND`] set for a ray behind the sides' plane.
//!
//! Subsample and unique-end keep the first ray per cell (a sub-cell or the end voxel, and
//! whether the ray hits), on the first of three paths that fits:
//! - where the box of cells within max range of the sensor fits [`DENSE_CELL_BITS`], the
//!   rays are chosen as they are made, in a bit set per thread over that box, and the rays
//!   dropped are never laid out ([`choose_as_made`], `as_made.rs`): the 6 m frames of the
//!   paper;
//! - where the frame's own box fits, each thread marks the cells of its own run of rays in
//!   a bit set over it, then drops the rays whose cell an earlier run saw
//!   (`first::first_per_cell_dense`): long range, small scenes;
//! - otherwise hash sets in scan order, by partition (`first::first_per_cell_hashed`).
//!
//! Bundle groups the rays by end voxel (`bundle.rs`).

use super::ray::{direction_key, CellKeys, ChunkOrder, Extent, Ray, Sides, NO_CELL, RAY_CHUNK};
use crate::kernel::Kernels;
use crate::mask::BitIter;
use hashbrown::{HashMap, HashSet};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

mod as_made;
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2;
mod bundle;
mod first;
#[cfg(test)]
mod tests;

pub(crate) use as_made::{choose_as_made, Chooser};
use bundle::{bundle_dense, bundle_hashed, set_means};
use first::{first_per_cell_dense, first_per_cell_hashed};

/// Which of a frame's rays are cast: every one (`Exact`), fewer for speed (`Subsample`,
/// `UniqueEnd`), or fewer with a map nearer exact's (`Bundle`; see the module's doc).
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

/// Most cells (times two, hit or not) a frame's box may have for the bit-set path: 2^25
/// bits, 4 MiB per thread (and bit indices below 2^31).
pub(super) const DENSE_CELL_BITS: u64 = 1 << 25;

/// The buffers the ray modes reuse from frame to frame: in fresh memory a frame's
/// would cost a page fault every 4 KiB, every frame.
#[derive(Default)]
pub(crate) struct Buffers {
    /// Each ray's cell key in scan order ([`CellKeys`]), written as the rays are made.
    keys: Vec<u64>,
    /// Per chunk, where the layout put each ray of its scan.
    orders: Vec<ChunkOrder>,
    /// Each ray's cell bit ([`CellBox::bit`]).
    bits: Vec<u32>,
    /// [`bundle_dense`]'s (cell bit, ray) in cell order.
    sorted: Vec<AtomicU64>,
    /// Whether each ray is kept.
    keep: Vec<AtomicBool>,
    /// Bundle's [`Layout`].
    places: Vec<u16>,
    /// [`first_per_cell_dense`]'s bit sets, one per run: all zeros, but for the bits of the runs
    /// `marked` names (runs, rays per run, rays), which `bits` still notes.
    sets: Vec<Vec<u64>>,
    marked: Option<(usize, usize, usize)>,
    /// [`choose_as_made`]'s sets and notes.
    pub(crate) as_made: as_made::AsMade,
}

impl Buffers {
    /// Bytes of the buffers, as allocated.
    pub(crate) fn memory_bytes(&self) -> usize {
        self.keys.capacity() * 8
            + self.orders.capacity() * std::mem::size_of::<ChunkOrder>()
            + self.bits.capacity() * 4
            + self.sorted.capacity() * 8
            + self.keep.capacity()
            + self.places.capacity() * 2
            + self.sets.iter().map(|s| s.capacity() * 8).sum::<usize>()
            + self.as_made.memory_bytes()
    }

    /// Room for the notes of a frame of `n` points: a key per ray and an order per chunk.
    pub(crate) fn notes(&mut self, n: usize) -> (&mut [u64], &mut [ChunkOrder]) {
        sized(&mut self.keys, n, || NO_CELL);
        sized(&mut self.orders, n.div_ceil(RAY_CHUNK), ChunkOrder::default);
        (&mut self.keys, &mut self.orders)
    }

    /// Zero the bit sets the last frame marked, before `bits` is written again: by the bits
    /// its rays marked where they are few for the set, so that a small frame in a large
    /// box does not clear the whole box. Done just before the sets are used, not after
    /// the last use: zeroing brings a set into the cache (random 500k 6 m subsample took
    /// 2-3 ms longer with the sets zeroed a walk earlier).
    fn clean(&mut self) {
        let Some((runs, per, _)) = self.marked.take() else {
            return;
        };
        (self.sets[..runs].par_iter_mut())
            .zip(self.bits.par_chunks(per))
            .for_each(|(set, noted)| zero(set, noted));
    }
}

/// Zero what the bits `noted` marked in `set` (all of it where they are many).
fn zero(set: &mut [u64], noted: &[u32]) {
    if noted.len() * 8 >= set.len() {
        set.fill(0);
    } else {
        noted
            .iter()
            .for_each(|&n| set[(n & !FIRST) as usize / 64] = 0);
    }
}

/// `v` as long as `n`, writing only what it did not hold.
fn sized<T>(v: &mut Vec<T>, n: usize, new: impl FnMut() -> T) {
    v.truncate(n);
    v.resize_with(n, new);
}

/// The factor of a mode's cells: subsample's, one for the others (the end voxel).
pub(super) fn cell_factor(mode: RayMode) -> u32 {
    match mode {
        RayMode::Subsample { factor } => factor,
        _ => 1,
    }
}

/// Which rays a ray mode keeps (by place in the scan), and as what.
pub(crate) struct Kept<'a> {
    keep: Keep<'a>,
    /// Unique-end: each ray kept goes to the centre of its end voxel.
    centre: bool,
}

impl Kept<'_> {
    /// Which rays of a chunk (the `len` rays of the scan from `at`, laid out as `order`
    /// says) are kept, by place: per side (front, back), bit `p` for the ray at the side's
    /// place `p` (back places counted from the chunk's end); and how many rays kept are
    /// cut at max range.
    #[inline]
    pub(crate) fn by_place(
        &self,
        at: usize,
        len: usize,
        order: &ChunkOrder,
    ) -> ([[u64; RAY_CHUNK / 64]; 2], u64) {
        match self.keep {
            Keep::Flags(keep) => by_place(order, len, |j, _| keep[at + j].load(Ordering::Relaxed)),
            Keep::Placed(keep) => by_place(order, len, |_, p| keep[at + p].load(Ordering::Relaxed)),
            Keep::FirstPerCell { noted, seen, per } => {
                let noted = &noted[at..at + len];
                // A chunk lies in one run; the first run has no runs before it.
                match &seen[..at / per] {
                    [] => by_place(order, len, |j, _| noted[j] & FIRST != 0),
                    earlier => by_place(order, len, |j, _| {
                        let (n, b) = (noted[j], (noted[j] & !FIRST) as usize);
                        let unseen = |s: &Vec<u64>| s[b / 64] >> (b % 64) & 1 == 0;
                        n & FIRST != 0 && earlier.iter().all(unseen)
                    }),
                }
            }
        }
    }

    /// Whether [`Self::finish`] changes rays.
    pub(crate) fn centres(&self) -> bool {
        self.centre
    }

    /// A ray kept, as the mode casts it.
    #[inline]
    pub(crate) fn finish(&self, r: &Ray) -> Ray {
        if self.centre {
            to_centre(r)
        } else {
            *r
        }
    }
}

/// [`Kept::by_place`], given whether the ray `j` of the scan, at place `p` in the chunk,
/// is kept.
#[inline]
fn by_place(
    order: &ChunkOrder,
    len: usize,
    kept: impl Fn(usize, usize) -> bool,
) -> ([[u64; RAY_CHUNK / 64]; 2], u64) {
    let mut m = [[0u64; RAY_CHUNK / 64]; 2];
    let mut cut = 0;
    // Each side's rays in scan order take its places in turn, front from the chunk's
    // start, back from its end.
    for (s, side) in [&order.front, &order.back].into_iter().enumerate() {
        let mut p = 0;
        for (w, &bits) in side.iter().enumerate() {
            for b in BitIter(bits) {
                let j = w * 64 + b;
                let k = kept(j, if s == 0 { p } else { len - 1 - p });
                m[s][p / 64] |= u64::from(k) << (p % 64);
                cut += u64::from(k) & order.cut[w] >> b & 1;
                p += 1;
            }
        }
    }
    (m, cut)
}

/// Where a [`Kept`] finds whether a ray is kept.
enum Keep<'a> {
    /// A flag per ray of the scan.
    Flags(&'a [AtomicBool]),
    /// A flag per place of the layout (bundle's).
    Placed(&'a [AtomicBool]),
    /// [`first_per_cell_dense`]'s notes: each ray's cell bit, [`FIRST`] if it is the first of its
    /// run (of `per` rays) to see it, and per run the cells it saw; a ray is kept if first
    /// in its run and not seen by the runs before.
    FirstPerCell {
        noted: &'a [u32],
        seen: &'a [Vec<u64>],
        per: usize,
    },
}

/// Marks a cell's bit in [`CellBox::note_of`] as that of a ray behind the sides' plane.
pub(crate) const BEHIND: u64 = 1 << 33;

/// Marks a noted cell bit first in its run ([`Keep::FirstPerCell`]).
const FIRST: u32 = 1 << 31;

/// Choose (or merge) the rays that `mode` trades for speed, from the notes the making of
/// `rays` left in `bufs` ([`Buffers::notes`]); `extent` bounds the rays' ends. A bundle's
/// mean is written into its first ray's place; the rays dropped are those the returned
/// [`Kept`] does not keep. `mode` is not `Exact`.
pub(super) fn choose<'b>(
    rays: &mut [Ray],
    origin: [f64; 3],
    mode: RayMode,
    extent: &Extent,
    bufs: &'b mut Buffers,
) -> (Kept<'b>, &'b [ChunkOrder]) {
    sized(&mut bufs.keep, rays.len(), || AtomicBool::new(false));
    let cells = CellKeys::new(origin, cell_factor(mode));
    let boxed = CellBox::new(extent, &cells);
    match mode {
        RayMode::Bundle { threshold } => {
            let means = match boxed {
                Some(b) => {
                    // Out of `bufs` while the others are written.
                    let orders = std::mem::take(&mut bufs.orders);
                    let means = bundle_dense(rays, &orders, threshold, &b, bufs);
                    bufs.orders = orders;
                    means
                }
                None => {
                    sized(&mut bufs.places, rays.len(), || 0);
                    (bufs.places.par_chunks_mut(RAY_CHUNK))
                        .zip(bufs.orders.par_iter())
                        .for_each(|(p, o)| o.places(p));
                    let layout = Layout {
                        places: &bufs.places,
                    };
                    bundle_hashed(rays, &layout, threshold, &bufs.keys, &bufs.keep)
                }
            };
            set_means(rays, origin, means);
            let kept = Kept {
                keep: Keep::Placed(&bufs.keep),
                centre: false,
            };
            return (kept, &bufs.orders);
        }
        RayMode::Subsample { .. } | RayMode::UniqueEnd => {
            if let Some(b) = boxed {
                let (runs, per) = first_per_cell_dense(&b, bufs);
                let keep = Keep::FirstPerCell {
                    noted: &bufs.bits,
                    seen: &bufs.sets[..runs],
                    per,
                };
                let kept = Kept {
                    keep,
                    centre: mode == RayMode::UniqueEnd,
                };
                return (kept, &bufs.orders);
            }
            first_per_cell_hashed(&bufs.keys, &bufs.keep);
        }
        RayMode::Exact => unreachable!("exact rays are not thinned"),
    }
    let kept = Kept {
        keep: Keep::Flags(&bufs.keep),
        centre: mode == RayMode::UniqueEnd,
    };
    (kept, &bufs.orders)
}

/// Where the layout put each ray of the scan: its place within its chunk.
struct Layout<'a> {
    places: &'a [u16],
}

impl Layout<'_> {
    /// The place of ray `i` of the scan (not a skipped point's) in the laid-out rays.
    #[inline]
    fn place(&self, i: usize) -> usize {
        i / RAY_CHUNK * RAY_CHUNK + usize::from(self.places[i])
    }
}

/// A unique-end ray: to the centre of its end voxel.
fn to_centre(r: &Ray) -> Ray {
    Ray {
        end: r.end.map(|c| c.floor() + 0.5),
        ..*r
    }
}

/// Keys per run of [`partitioned`]'s pass: fixed, so that the partitions see the rays in
/// scan order whatever the thread count.
const HASH_RUN: usize = 16 * 1024;
/// Partitions of [`first_per_cell_hashed`]'s cells (a power of two).
const PARTITIONS: usize = 64;

/// Per fixed run of rays and per partition of the cell keys, `item(index, key)` of each
/// ray (skipped points' left out) in scan order: a partition's items, run after run, are
/// in scan order whatever the thread count. The items carry what a partition needs, so
/// that it reads them one after another instead of all over memory.
fn partitioned<T: Send>(keys: &[u64], item: impl Fn(u32, u64) -> T + Sync) -> Vec<Vec<Vec<T>>> {
    let part = |k: u64| (k.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 58) as usize;
    keys.par_chunks(HASH_RUN)
        .enumerate()
        .map(|(j, ks)| {
            let mut lists: Vec<Vec<T>> = (0..PARTITIONS).map(|_| Vec::new()).collect();
            for (i, &k) in ks.iter().enumerate().filter(|&(_, &k)| k != NO_CELL) {
                lists[part(k)].push(item((j * HASH_RUN + i) as u32, k));
            }
            lists
        })
        .collect()
}

/// Partition `p`'s items in scan order.
fn in_partition<T>(runs: &[Vec<Vec<T>>], p: usize) -> impl Iterator<Item = &T> + '_ {
    runs.iter().flat_map(move |r| r[p].iter())
}

/// The runs of rays in scan order that [`first_per_cell_dense`] and [`bundle_dense`] cut a
/// frame's `n` rays into, one per thread (fewer for few rays), of whole chunks: how many
/// and how long.
fn scan_runs(n: usize) -> (usize, usize) {
    let runs = rayon::current_num_threads().min(n / 4096).max(1);
    let per = n.div_ceil(runs).next_multiple_of(RAY_CHUNK).max(RAY_CHUNK);
    (n.div_ceil(per).max(1), per)
}

/// The cells ([`CellKeys`]) over a box of voxels (a frame's, or all a sensor's rays can
/// reach), indexed densely, each as two bits (hit or not), or one where every ray hits.
pub(crate) struct CellBox {
    /// The key field of the box's first cell on each axis (below 2^30 either way). In 32
    /// bits, as the dims: a box has at most [`DENSE_CELL_BITS`] (2^25) bits, so the bit
    /// of a cell fits too.
    lo: [i32; 3],
    dims: [u32; 3],
    /// 1 where a cell has two bits, else 0.
    hit_bit: u32,
}

impl CellBox {
    /// The box of a frame's `extent`; `None` when its cells need more than
    /// [`DENSE_CELL_BITS`] bits.
    pub(crate) fn new(extent: &Extent, cells: &CellKeys) -> Option<Self> {
        let (lo, hi) = (extent.lo.to_array(), extent.hi.to_array());
        let hit_bit = u32::from(extent.cut_rays > 0);
        Self::of_voxels(lo.map(i64::from), hi.map(i64::from), hit_bit, cells)
    }

    /// The box of every end a ray from `origin` (voxel units) can have, within `range`
    /// voxels, with a voxel to spare each way for rounding; `None` when it needs more
    /// than [`DENSE_CELL_BITS`] bits.
    pub(crate) fn around(origin: [f64; 3], range: f64, cells: &CellKeys) -> Option<Self> {
        let lo = origin.map(|c| (c - range).floor() as i64 - 1);
        let hi = origin.map(|c| (c + range).floor() as i64 + 1);
        Self::of_voxels(lo, hi, 1, cells)
    }

    /// The box of voxels `lo..=hi`.
    fn of_voxels(lo: [i64; 3], hi: [i64; 3], hit_bit: u32, cells: &CellKeys) -> Option<Self> {
        let f = cells.f as i64;
        let lo = [0, 1, 2].map(|a| lo[a] * f - cells.base[a] as i64);
        let dims = [0, 1, 2].map(|a| ((hi[a] + 1) * f - cells.base[a] as i64 - lo[a]) as u64);
        let n = dims[0]
            .checked_mul(dims[1])
            .and_then(|c| c.checked_mul(dims[2]))?;
        if n.checked_mul(1 << hit_bit)? > DENSE_CELL_BITS {
            return None;
        }
        // Below 2^30 either way, so that a key field (below 2^21) minus it fits an i32.
        let [l0, l1, l2] = lo.map(|l| (l.unsigned_abs() < 1 << 30).then_some(l as i32));
        Some(CellBox {
            lo: [l0?, l1?, l2?],
            // Each below 2^25, as their product is.
            dims: dims.map(|d| d as u32),
            hit_bit,
        })
    }

    fn bits(&self) -> usize {
        (self.dims.iter().product::<u32>() << self.hit_bit) as usize
    }

    /// The bit of `r`'s cell, with [`BEHIND`] if `r` lies behind the plane of `sides`;
    /// [`NO_CELL`] for a skipped point's ray.
    #[inline]
    pub(crate) fn note_of(&self, cells: &CellKeys, sides: &Sides, r: &Ray) -> u64 {
        match cells.key(r) {
            NO_CELL => NO_CELL,
            k => self.bit(k) as u64 | if sides.behind(r.end) { BEHIND } else { 0 },
        }
    }

    /// `out[i] = self.note_of(cells, sides, &rays[i])`, four at a time with the vector
    /// kernels.
    pub(crate) fn notes_of(
        &self,
        cells: &CellKeys,
        sides: &Sides,
        kernels: &Kernels,
        rays: &[Ray],
        out: &mut [u64],
    ) {
        let done = (kernels.notes)(self, cells, sides, rays, out);
        for (b, r) in out.iter_mut().zip(rays).skip(done) {
            *b = self.note_of(cells, sides, r);
        }
    }

    /// `bits[i]` the bit of `keys[i]` ([`Self::bit`]), `u32::MAX` for [`NO_CELL`]; the
    /// compiler vectorises the loop, `bit` being 32-bit arithmetic.
    fn bits_of(&self, keys: &[u64], bits: &mut [u32]) {
        for (b, &k) in bits.iter_mut().zip(keys) {
            // Computed for `NO_CELL` too, then dropped: a select, where a branch around the
            // call was not vectorised.
            let bit = self.bit(k);
            *b = if k == NO_CELL { u32::MAX } else { bit };
        }
    }

    /// The bit of a cell key (not [`NO_CELL`]). Ends lie in the box, whose voxel bounds the
    /// extent gives; a float end on the box's upper face is clamped into its last cell.
    #[inline]
    fn bit(&self, key: u64) -> u32 {
        // Spelled out per axis: as `[0, 1, 2].map` it was an out-of-line call per ray.
        let axis = |a: usize| {
            let k = (key >> (21 * a) & CellKeys::FIELD) as i32 - self.lo[a];
            k.clamp(0, self.dims[a] as i32 - 1) as u32
        };
        let cell = (axis(2) * self.dims[1] + axis(1)) * self.dims[0] + axis(0);
        cell << self.hit_bit | (key >> 63) as u32 & self.hit_bit
    }
}

/// The ray modes in one pass in scan order over a hash set (bundle: a sort): the
/// reference the faster paths are tested against.
#[cfg(test)]
pub(crate) fn choose_hashed(rays: &mut Vec<Ray>, origin: [f64; 3], mode: RayMode) {
    use super::prepare::set_direction_keys;
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
