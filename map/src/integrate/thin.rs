//! The paper's trade-off modes ([`RayMode`] other than `Exact`): fewer rays for a coarser
//! map. Each keeps the first ray of a kind in scan order, so its result does not depend on
//! the thread count.
//!
//! Unless chosen as they are made (below), the rays are made and laid out by sides as in
//! exact mode, and the same pass notes each ray's cell key ([`CellKeys`]) in scan order
//! and where the layout put it ([`ChunkOrder`]). The modes choose from the keys alone (8
//! bytes a ray, not the ray's 32), and the layout then drops what they drop
//! (`prepare::compact`).
//!
//! Subsample and unique-end keep the first ray per cell (a sub-cell or the end voxel, and
//! whether the ray hits), on the first of three paths that fits:
//! - where the box of cells within max range of the sensor fits [`DENSE_CELL_BITS`], the
//!   rays are chosen as they are made, in a bit set per thread over that box, and the rays
//!   dropped are never laid out ([`make_firsts`]): the 6 m frames of the paper;
//! - where the frame's own box fits, each thread marks the cells of its own run of rays in
//!   a bit set over it, then drops the rays whose cell an earlier run saw
//!   ([`firsts_dense`]): long range, small scenes;
//! - otherwise hash sets in scan order, by partition ([`firsts_hashed`]).
//!
//! Bundle groups the rays by end voxel: over a small frame's box with a counting sort by
//! cell ([`bundle_dense`]), over larger ones in hash tables by partition ([`bundle`]).
//! Both sum a group's ends in scan order, so the mean is the same on any thread count.

use super::prepare::{direction_key, ChunkOrder, Extent, Ones, Ray, Sides, RAY_CHUNK, SKIPPED};
use super::RayMode;
use crate::kernel::Kernels;
use hashbrown::{HashMap, HashSet};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2;
mod firsts;

pub(crate) use firsts::{make_firsts, Chooser};

/// Most cells (times two, hit or not) a frame's box may have for the bit-set path: 2^25
/// bits, 4 MiB per thread (and bit indices below 2^31).
pub(super) const DENSE_CELL_BITS: u64 = 1 << 25;

/// The key of a skipped point's ray: no cell's ([`CellKeys`] fields never are all ones).
const NONE: u64 = u64::MAX;

/// The buffers the trade-off modes reuse from frame to frame: in fresh memory a frame's
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
    /// [`firsts_dense`]'s bit sets, one per run: all zeros, but for the bits of the runs
    /// `marked` names (runs, rays per run, rays), which `bits` still notes.
    sets: Vec<Vec<u64>>,
    marked: Option<(usize, usize, usize)>,
    /// [`make_firsts`]'s sets and notes.
    pub(crate) firsts: firsts::Firsts,
}

impl Buffers {
    /// Room for the notes of a frame of `n` points: a key per ray and an order per chunk.
    pub(crate) fn notes(&mut self, n: usize) -> (&mut [u64], &mut [ChunkOrder]) {
        sized(&mut self.keys, n, || NONE);
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

/// A ray's cell (`factor` per voxel edge, `floor(end * factor)` on each axis) and hit flag
/// in one `u64`: 21 bits an axis, relative to the origin's cell and biased by 2^20, and
/// the hit flag on top. Rays end within max range (8192 voxels) of the origin and the
/// factor is at most 64, so a field lies within 2^20 ± (2^19 + 1): never all ones.
pub(crate) struct CellKeys {
    f: f64,
    /// The cell that keys to 0 on each axis, as a float (an integer).
    base: [f64; 3],
}

impl CellKeys {
    const BIAS: f64 = (1 << 20) as f64;
    const FIELD: u64 = (1 << 21) - 1;

    pub(crate) fn new(origin: [f64; 3], factor: u32) -> Self {
        let f = f64::from(factor);
        CellKeys {
            f,
            base: origin.map(|c| (c * f).floor() - Self::BIAS),
        }
    }

    /// The key of `r`, [`NONE`] for a skipped point's.
    #[inline]
    pub(crate) fn key(&self, r: &Ray) -> u64 {
        if r.key == SKIPPED {
            return NONE;
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

/// The factor of a mode's cells: subsample's, one for the others (the end voxel).
pub(super) fn cell_factor(mode: RayMode) -> u32 {
    match mode {
        RayMode::Subsample { factor } => factor,
        _ => 1,
    }
}

/// Which rays a trade-off mode keeps (by place in the scan), and as what.
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
            Keep::Firsts { noted, seen, per } => {
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
            for b in Ones(bits) {
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
    /// [`firsts_dense`]'s notes: each ray's cell bit, [`FIRST`] if it is the first of its
    /// run (of `per` rays) to see it, and per run the cells it saw; a ray is kept if first
    /// in its run and not seen by the runs before.
    Firsts {
        noted: &'a [u32],
        seen: &'a [Vec<u64>],
        per: usize,
    },
}

/// Marks a cell's bit in [`CellBox::note_of`] as that of a ray behind the sides' plane.
pub(crate) const BEHIND: u64 = 1 << 33;

/// Marks a noted cell bit first in its run ([`Keep::Firsts`]).
const FIRST: u32 = 1 << 31;

/// Choose (or merge) the rays that `mode` trades for speed, from the notes the making of
/// `rays` left in `bufs` ([`Buffers::notes`]); `extent` bounds the rays' ends. A bundle's
/// mean is written into its first ray's place; the rays dropped are those the returned
/// [`Kept`] does not keep. `mode` is not `Exact`.
pub(super) fn thin_out<'b>(
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
                    bundle(rays, &layout, threshold, &bufs.keys, &bufs.keep)
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
                let (runs, per) = firsts_dense(&b, bufs);
                let keep = Keep::Firsts {
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
            firsts_hashed(&bufs.keys, &bufs.keep);
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
/// Partitions of [`firsts_hashed`]'s cells (a power of two).
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
            for (i, &k) in ks.iter().enumerate().filter(|&(_, &k)| k != NONE) {
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

/// [`firsts_dense`] for boxes too large for bit sets: each cell goes to one of
/// [`PARTITIONS`] by a hash of its key; each partition, on a thread of its own, takes its
/// rays in scan order into a hash set of its own and keeps those it had not seen.
fn firsts_hashed(keys: &[u64], keep: &[AtomicBool]) {
    let runs = partitioned(keys, |i, k| (k, i));
    (0..PARTITIONS).into_par_iter().for_each(|p| {
        let mut seen = HashSet::with_capacity(runs.iter().map(|r| r[p].len()).sum());
        for &(k, i) in in_partition(&runs, p) {
            keep[i as usize].store(seen.insert(k), Ordering::Relaxed);
        }
    });
}

/// A bundled group: its first ray's place in the layout and the mean of its ends.
type Mean = (u32, [f64; 3]);

/// Bundle: the rays ending in one voxel (and alike in hitting) form a group; a group of
/// more than `threshold` becomes one ray to the mean of their ends, in the place of its
/// first ray; smaller groups keep their rays. Grouped by partition as [`firsts_hashed`]:
/// a group's ends are summed in scan order, so the mean is the same on any thread count.
/// Whether each ray is kept goes into `keep` by its place in the layout.
fn bundle(
    rays: &[Ray],
    layout: &Layout<'_>,
    threshold: u32,
    keys: &[u64],
    keep: &[AtomicBool],
) -> Vec<Vec<Mean>> {
    let runs = partitioned(keys, |i, k| (k, i, rays[layout.place(i as usize)].end));
    (0..PARTITIONS)
        .into_par_iter()
        .map(|p| {
            let n = runs.iter().map(|r| r[p].len()).sum();
            // Each group once in the table; its rays' group indices remembered, so the
            // second pass reads them in order rather than hashing again.
            let mut index: HashMap<u64, u32> = HashMap::with_capacity(n);
            let mut groups: Vec<(u32, u32, [f64; 3])> = Vec::new(); // first ray, count, sum
            let mut of_ray = Vec::with_capacity(n);
            for &(k, i, end) in in_partition(&runs, p) {
                let g = *index.entry(k).or_insert_with(|| {
                    groups.push((i, 0, [0.0; 3]));
                    groups.len() as u32 - 1
                });
                let group = &mut groups[g as usize];
                group.1 += 1;
                (0..3).for_each(|a| group.2[a] += end[a]);
                of_ray.push(g);
            }
            for (&(_, i, _), &g) in in_partition(&runs, p).zip(&of_ray) {
                let (first, n, _) = groups[g as usize];
                let place = layout.place(i as usize);
                keep[place].store(n <= threshold || i == first, Ordering::Relaxed);
            }
            (groups.into_iter())
                .filter(|&(_, n, _)| n > threshold)
                .map(|(first, n, sum)| {
                    let mean = sum.map(|c| c / f64::from(n));
                    (layout.place(first as usize) as u32, mean)
                })
                .collect()
        })
        .collect()
}

/// Low bits of a cell's bit that [`bundle_dense`] groups by within a bucket: a bucket's
/// tables (4096 cells' counts, first rays and sums, 128 KiB) stay in the L2 cache.
const BUCKET_BITS: u32 = 12;

/// [`bundle`] over a frame's box of cells ([`CellBox`], hit or not): the rays are sorted
/// by cell with one counting pass (buckets of the cells' high bits, stable, so a bucket
/// holds its rays in scan order), then each bucket groups its rays in a small table of
/// its own. A group's ends are summed in scan order, as [`bundle`] sums them.
fn bundle_dense(
    rays: &[Ray],
    orders: &[ChunkOrder],
    threshold: u32,
    cells: &CellBox,
    bufs: &mut Buffers,
) -> Vec<Vec<Mean>> {
    let n = rays.len();
    let (runs, per) = scan_runs(n);
    let buckets = cells.bits().div_ceil(1 << BUCKET_BITS);
    // `bits` is about to change: the sets it notes go first.
    bufs.clean();
    sized(&mut bufs.bits, n, || 0);
    // Each run's bucket counts, then where each run's part of each bucket starts.
    let mut counts: Vec<Vec<u32>> = (bufs.bits.par_chunks_mut(per))
        .zip(bufs.keys.par_chunks(per))
        .map(|(bits, keys)| {
            cells.bits_of(keys, bits);
            bucket_counts(bits, buckets)
        })
        .collect();
    let mut starts = Vec::with_capacity(buckets + 1);
    let mut at = 0u32;
    for b in 0..buckets {
        starts.push(at);
        for c in counts.iter_mut() {
            let k = c[b];
            c[b] = at;
            at += k;
        }
    }
    starts.push(at);
    let m = at as usize;
    // Stable scatter: (cell bit, ray's place in the layout) in bucket order, the rays of
    // a bucket in scan order; distinct runs write distinct places. A run is whole chunks,
    // and a chunk's rays take the places of their side in scan order.
    sized(&mut bufs.sorted, m, || AtomicU64::new(0));
    let sorted = &bufs.sorted;
    (bufs.bits.par_chunks(per))
        .zip(counts.par_iter_mut())
        .enumerate()
        .for_each(|(j, (bits, at))| {
            for (c, bits) in bits.chunks(RAY_CHUNK).enumerate() {
                let start = j * per + c * RAY_CHUNK;
                let order = &orders[start / RAY_CHUNK];
                let (mut front, mut back) = (0, bits.len());
                for (i, &b) in bits.iter().enumerate().filter(|&(_, &b)| b != u32::MAX) {
                    let ahead = order.front[i / 64] >> (i % 64) & 1 != 0;
                    let place = if ahead { front } else { back - 1 };
                    front += usize::from(ahead);
                    back -= usize::from(!ahead);
                    let slot = &mut at[(b >> BUCKET_BITS) as usize];
                    let item = u64::from(b) << 32 | (start + place) as u64;
                    sorted[*slot as usize].store(item, Ordering::Relaxed);
                    *slot += 1;
                }
            }
        });
    // Per task, the bundled groups as (first ray, mean end). The tasks' buckets hold
    // about as many rays each: a structured scene puts most rays in a few buckets.
    let tasks = (runs * 16).min(buckets);
    let bounds: Vec<usize> = (0..=tasks)
        .map(|t| {
            starts
                .partition_point(|&s| (s as usize) < t * m / tasks)
                .min(buckets)
        })
        .collect();
    // Every ray is kept unless a bundle drops it: the grouping writes only the drops, a
    // byte at a place the other thread's buckets may share a line with.
    let keep = &bufs.keep;
    keep.par_iter()
        .for_each(|k| k.store(true, Ordering::Relaxed));
    // Per cell of a bucket (its low bits): rays, the first, the sum of the ends; zeroed
    // once per worker (128 KiB), each bucket leaving them as it found them.
    let tables = || {
        let cells = 1 << BUCKET_BITS;
        (
            vec![0u32; cells],
            vec![0u32; cells],
            vec![[0.0f64; 3]; cells],
        )
    };
    (0..tasks)
        .into_par_iter()
        .map_init(tables, |(count, first, sum), t| {
            const LOW: u64 = (1 << BUCKET_BITS) - 1;
            let low = |x: u64| ((x >> 32) & LOW) as usize;
            let mut out = Vec::new();
            for b in bounds[t]..bounds[t + 1] {
                let items = &sorted[starts[b] as usize..starts[b + 1] as usize];
                for x in items.iter().map(|x| x.load(Ordering::Relaxed)) {
                    let c = &mut count[low(x)];
                    if *c == 0 {
                        first[low(x)] = x as u32;
                    }
                    *c += 1;
                    // The next pass reads the end of each ray it bundles.
                    crate::prefetch::prefetch(rays, x as u32 as usize);
                }
                for x in items.iter().map(|x| x.load(Ordering::Relaxed)) {
                    let (l, p) = (low(x), x as u32);
                    if count[l] > threshold {
                        if p != first[l] {
                            keep[p as usize].store(false, Ordering::Relaxed);
                        }
                        let e = rays[p as usize].end;
                        (0..3).for_each(|a| sum[l][a] += e[a]);
                    }
                }
                for x in items.iter().map(|x| x.load(Ordering::Relaxed)) {
                    let l = low(x);
                    if count[l] > threshold {
                        let k = f64::from(count[l]);
                        out.push((first[l], sum[l].map(|c| c / k)));
                        sum[l] = [0.0; 3];
                    }
                    count[l] = 0;
                }
            }
            out
        })
        .collect()
}

/// How many of `bits` (but `u32::MAX`) fall in each of the `buckets` of
/// [`BUCKET_BITS`] cells.
fn bucket_counts(bits: &[u32], buckets: usize) -> Vec<u32> {
    // Four tables in turn: a scene's rays in scan order often fall in one bucket, where a
    // single table would chain each count on the one before. Bucket `buckets` takes the
    // skipped points.
    let mut c = vec![[0u32; 4]; buckets + 1];
    let bucket = |b: u32| ((b >> BUCKET_BITS) as usize).min(buckets);
    let mut quads = bits.chunks_exact(4);
    for q in &mut quads {
        (0..4).for_each(|i| c[bucket(q[i])][i] += 1);
    }
    quads.remainder().iter().for_each(|&b| c[bucket(b)][0] += 1);
    c[..buckets].iter().map(|t| t.iter().sum()).collect()
}

/// The runs of rays in scan order that [`firsts_dense`] and [`bundle_dense`] cut a
/// frame's `n` rays into, one per thread (fewer for few rays), of whole chunks: how many
/// and how long.
fn scan_runs(n: usize) -> (usize, usize) {
    let runs = rayon::current_num_threads().min(n / 4096).max(1);
    let per = n.div_ceil(runs).next_multiple_of(RAY_CHUNK).max(RAY_CHUNK);
    (n.div_ceil(per).max(1), per)
}

/// A bundle's first ray becomes the ray to the mean.
fn set_means(rays: &mut [Ray], origin: [f64; 3], means: Vec<Vec<Mean>>) {
    for (first, end) in means.into_iter().flatten() {
        let r = &mut rays[first as usize];
        let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
        *r = Ray::new(end, direction_key(d), r.hit);
    }
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

    /// The bit of `r`'s cell, with [`BEHIND`] if `r` lies behind the plane of `halves`;
    /// [`NONE`] for a skipped point's ray.
    #[inline]
    pub(crate) fn note_of(&self, cells: &CellKeys, halves: &Sides, r: &Ray) -> u64 {
        match cells.key(r) {
            NONE => NONE,
            k => self.bit(k) as u64 | if halves.behind(r.end) { BEHIND } else { 0 },
        }
    }

    /// `out[i] = self.note_of(cells, halves, &rays[i])`, four at a time with the vector
    /// kernels.
    pub(crate) fn notes_of(
        &self,
        cells: &CellKeys,
        halves: &Sides,
        kernels: &Kernels,
        rays: &[Ray],
        out: &mut [u64],
    ) {
        let done = (kernels.notes)(self, cells, halves, rays, out);
        for (b, r) in out.iter_mut().zip(rays).skip(done) {
            *b = self.note_of(cells, halves, r);
        }
    }

    /// `bits[i]` the bit of `keys[i]` ([`Self::bit`]), `u32::MAX` for [`NONE`]; the
    /// compiler vectorises the loop, `bit` being 32-bit arithmetic.
    fn bits_of(&self, keys: &[u64], bits: &mut [u32]) {
        for (b, &k) in bits.iter_mut().zip(keys) {
            // Computed for `NONE` too, then dropped: a select, where a branch around the
            // call was not vectorised.
            let bit = self.bit(k);
            *b = if k == NONE { u32::MAX } else { bit };
        }
    }

    /// The bit of a cell key (not [`NONE`]). Ends lie in the box, whose voxel bounds the
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

/// Which rays are the first of their cell in scan order, as [`Keep::Firsts`] reads it;
/// returns the runs and their length. The rays are cut into one run per thread; each run
/// notes its own firsts, marking them in a bit set of its own, by which the runs after
/// the first then drop the rays an earlier run saw. The first pass notes each ray's bit,
/// so the second reads 4 bytes a ray instead of the key. The sets are left marked for
/// [`Buffers::clean`].
fn firsts_dense(cells: &CellBox, bufs: &mut Buffers) -> (usize, usize) {
    let n = bufs.keys.len();
    let (runs, per) = scan_runs(n);
    let words = cells.bits().div_ceil(64);
    bufs.sets.resize_with(runs.max(bufs.sets.len()), Vec::new);
    // Each run zeroes its own set where the last frame's runs were the same, on the thread
    // that then uses it; otherwise all are zeroed first (`bits` still holds their marks).
    let same = bufs.marked == Some((runs, per, n)) && bufs.bits.len() == n;
    if same {
        bufs.marked = None;
    } else {
        bufs.clean();
    }
    sized(&mut bufs.bits, n, || 0);
    (bufs.bits.par_chunks_mut(per))
        .zip(bufs.keys.par_chunks(per))
        .zip(bufs.sets[..runs].par_iter_mut())
        .for_each(|((noted, keys), set)| {
            if same {
                zero(set, noted);
            }
            // All zeros: only a longer set has new words to zero.
            set.resize(words, 0);
            for (n, &k) in noted.iter_mut().zip(keys) {
                if k == NONE {
                    *n = 0;
                    continue;
                }
                let b = cells.bit(k);
                let (w, m) = (b as usize / 64, 1u64 << (b % 64));
                *n = b | if set[w] & m == 0 { FIRST } else { 0 };
                set[w] |= m;
            }
        });
    bufs.marked = Some((runs, per, n));
    (runs, per)
}

/// The trade-off modes in one pass in scan order over a hash set (bundle: a sort): the
/// reference the faster paths are tested against.
#[cfg(test)]
pub(crate) fn thin_hashed(rays: &mut Vec<Ray>, origin: [f64; 3], mode: RayMode) {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrate::prepare::{bounds, compact, Sides};
    use crate::test_rng::Rng;

    /// What a trade-off mode casts of `rays` (made in scan order): keys noted, laid out by
    /// sides across `axis` as the prepare phase does it, chosen and compacted, with each
    /// supported kernel (all giving the same rays). Returned per chunk, the rays in front
    /// in scan order, then those behind in scan order; across no axis, the rays kept in
    /// scan order.
    fn thinned(
        rays: &[Ray],
        origin: [f64; 3],
        mode: RayMode,
        extent: &Extent,
        bufs: &mut Buffers,
        axis: Option<[f64; 3]>,
    ) -> Vec<Ray> {
        let mut got: Option<Vec<Ray>> = None;
        for kernel in crate::kernel::Kernel::available() {
            let kernels = kernel.table().expect("an available kernel");
            let cells = CellKeys::new(origin, cell_factor(mode));
            let halves = Sides { origin, axis };
            let mut laid = rays.to_vec();
            let mut sides = Vec::new();
            let (keys, orders) = bufs.notes(rays.len());
            cells.keys(kernels, rays, keys);
            for ((made, out), order) in (rays.chunks(RAY_CHUNK))
                .zip(laid.chunks_mut(RAY_CHUNK))
                .zip(orders.iter_mut())
            {
                let (counts, o) = halves.lay_out(made, out);
                sides.push(counts);
                let mut cut = [0u64; RAY_CHUNK / 64];
                for (j, r) in made.iter().enumerate() {
                    cut[j / 64] |= u64::from(r.key != SKIPPED && !r.hit) << (j % 64);
                }
                *order = ChunkOrder { cut, ..o };
            }
            let (kept, orders) = thin_out(&mut laid, origin, mode, extent, bufs);
            let cut = compact(&mut laid, &mut sides, orders, &kept);
            let cast: Vec<Ray> = (laid.chunks(RAY_CHUNK).zip(&sides))
                .flat_map(|(c, &[front, back])| {
                    let (f, b) = (front as usize, back as usize);
                    c[..f].iter().chain(c[c.len() - b..].iter().rev()).copied()
                })
                .collect();
            // The rays cast lie in the box of all rays; their cut ones are counted.
            let want = bounds(&cast, origin);
            assert!(extent
                .lo
                .to_array()
                .iter()
                .zip(want.lo.to_array())
                .all(|(a, b)| *a <= b));
            assert!(extent
                .hi
                .to_array()
                .iter()
                .zip(want.hi.to_array())
                .all(|(a, b)| *a >= b));
            assert_eq!(cut, want.cut_rays, "{mode:?} {kernel:?}");
            let fields = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit, r.key)).collect::<Vec<_>>();
            if let Some(g) = &got {
                assert!(fields(g) == fields(&cast), "{mode:?}: {kernel:?} differs");
            }
            got = Some(cast);
        }
        got.expect("the scalar kernel runs anywhere")
    }

    /// Rays as a sorted list of their fields' bits: the rays cast, whatever their order.
    fn as_set(v: &[Ray]) -> Vec<([u64; 3], bool, u32)> {
        let mut s: Vec<_> = v
            .iter()
            .map(|r| (r.end.map(f64::to_bits), r.hit, r.key))
            .collect();
        s.sort_unstable();
        s
    }

    /// A cell's bit in 64-bit arithmetic, from the box's definition: the reference for
    /// [`CellBox::bit`]'s 32 bits.
    fn bit_in_64_bits(b: &CellBox, key: u64) -> u64 {
        let c = [0, 1, 2].map(|a| {
            let k = (key >> (21 * a) & CellKeys::FIELD) as i64 - i64::from(b.lo[a]);
            k.clamp(0, i64::from(b.dims[a]) - 1) as u64
        });
        let d = b.dims.map(u64::from);
        let cell = (c[2] * d[1] + c[1]) * d[0] + c[0];
        cell << b.hit_bit | (key >> 63 & u64::from(b.hit_bit))
    }

    /// [`CellBox::bits_of`] (vectorised, 32 bits) agrees with the 64-bit reference key by
    /// key: ends inside the box, outside it (clamped to its faces), hit or not, and
    /// skipped points.
    #[test]
    fn bits_of_agrees_with_64_bit_reference() {
        let mut rng = Rng(7);
        let origin = [0.25, 0.5, -0.75];
        for factor in [1, 2] {
            let cells = CellKeys::new(origin, factor);
            let rays: Vec<Ray> = (0..20_000)
                .map(|i| {
                    let end = [0, 1, 2].map(|a| origin[a] + rng.f() * 12.0 - 6.0);
                    Ray::new(end, 0, i % 3 != 0)
                })
                .collect();
            // A box of the first few ends only: most keys lie outside it. And one of a
            // cell a bit (no ray cut at max range).
            let small = bounds(&rays[..50], origin);
            let mut one_bit = bounds(&rays, origin);
            one_bit.cut_rays = 0;
            let mut hit_bits = Vec::new();
            for extent in [bounds(&rays, origin), small, one_bit] {
                let b = CellBox::new(&extent, &cells).unwrap();
                hit_bits.push(b.hit_bit);
                let mut keys: Vec<u64> = rays.iter().map(|r| cells.key(r)).collect();
                keys.insert(7, NONE);
                let mut bits = vec![0; keys.len()];
                b.bits_of(&keys, &mut bits);
                for (&k, &got) in keys.iter().zip(&bits) {
                    let want = if k == NONE {
                        u32::MAX
                    } else {
                        bit_in_64_bits(&b, k) as u32
                    };
                    assert!(want < b.bits() as u32 || k == NONE);
                    assert_eq!(got, want, "key {k:#x}");
                }
            }
            assert_eq!(hit_bits, [1, 1, 0]);
        }
    }

    /// The bit-set path keeps exactly the rays, with the ends, that the
    /// hash set in scan order keeps, on any number of threads; rays on the box's faces,
    /// repeated cells and skipped points included; the hash partitions too.
    #[test]
    fn dense_firsts_keep_what_the_scan_order_hash_keeps() {
        let mut rng = Rng(11);
        let origin = [3.5, -2.25, 0.5];
        let mut rays: Vec<Ray> = (0..60_000)
            .map(|i| {
                if i % 97 == 0 {
                    return Ray::new([0.0; 3], SKIPPED, false);
                }
                // Ends on a coarse lattice (many repeats, some exactly on cell faces).
                let end = [0, 1, 2].map(|a| origin[a] + (rng.f() * 20.0 - 10.0).round() / 2.0);
                Ray::new(end, 0, i % 3 != 0)
            })
            .collect();
        rays.push(Ray::new(origin, 0, true));
        let made: Vec<Ray> = rays.iter().copied().filter(|r| r.key != SKIPPED).collect();
        let extent = bounds(&rays, origin);
        let mut bufs = Buffers::default();
        for mode in [
            RayMode::UniqueEnd,
            RayMode::Subsample { factor: 1 },
            RayMode::Subsample { factor: 4 },
        ] {
            let mut want = made.clone();
            thin_hashed(&mut want, origin, mode);
            assert!(
                want.len() < made.len() / 2 && want.len() > 1000,
                "{mode:?}: {}",
                want.len()
            );
            for threads in [1, 2, 3, 5] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                // Buffers left by the modes and thread counts before.
                let got = pool.install(|| thinned(&rays, origin, mode, &extent, &mut bufs, None));
                // The same rays (a chunk's may change order as dropped ones leave it).
                assert_eq!(as_set(&got), as_set(&want), "{mode:?} on {threads} threads");
            }
        }
        // A box too large for bit sets takes the partitioned hash sets: the same rays.
        let cells = |f| CellKeys::new(origin, f);
        assert!(CellBox::new(&extent, &cells(64)).is_none());
        assert!(CellBox::new(&extent, &cells(1)).is_some());
        for (mode, factor) in [
            (RayMode::Subsample { factor: 4 }, 4),
            (RayMode::UniqueEnd, 1),
        ] {
            let mut want = made.clone();
            thin_hashed(&mut want, origin, mode);
            for threads in [1, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let keys: Vec<u64> = rays.iter().map(|r| cells(factor).key(r)).collect();
                let keep: Vec<AtomicBool> = keys.iter().map(|_| AtomicBool::new(false)).collect();
                pool.install(|| firsts_hashed(&keys, &keep));
                let got: Vec<Ray> = (rays.iter().zip(&keep))
                    .filter(|(r, k)| r.key != SKIPPED && k.load(Ordering::Relaxed))
                    .map(|(r, _)| {
                        if mode == RayMode::UniqueEnd {
                            to_centre(r)
                        } else {
                            *r
                        }
                    })
                    .collect();
                let ends = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit)).collect::<Vec<_>>();
                assert!(
                    ends(&got) == ends(&want),
                    "{mode:?} hashed on {threads} threads"
                );
            }
        }
        let mut want = made.clone();
        thin_hashed(&mut want, origin, RayMode::Subsample { factor: 64 });
        let mode = RayMode::Subsample { factor: 64 };
        let got = thinned(&rays, origin, mode, &extent, &mut Buffers::default(), None);
        assert_eq!(got.len(), want.len());
    }

    /// A small frame in a large box has its sets cleared by the bits it marked (when the
    /// next frame chooses): the frames after it choose as with fresh buffers.
    #[test]
    fn sets_cleared_by_their_bits_leave_nothing_behind() {
        let mut rng = Rng(14);
        let origin = [0.5; 3];
        let frame = |rng: &mut Rng| -> Vec<Ray> {
            (0..2000)
                .map(|i| {
                    // Repeats within the frame: ends on a lattice of 4 voxels.
                    let end = [0, 1, 2].map(|_| (rng.f() * 25.0).floor() * 4.0 - 50.0);
                    Ray::new(end, 0, i % 2 == 0)
                })
                .collect()
        };
        let mut bufs = Buffers::default();
        for _ in 0..4 {
            let rays = frame(&mut rng);
            let extent = bounds(&rays, origin);
            let cells = CellKeys::new(origin, 1);
            // A box of about 100^3 voxels, each of two bits, against 1000 rays a run.
            let b = CellBox::new(&extent, &cells).unwrap();
            assert!(b.bits() / 64 > 1000 * 8, "{}", b.bits());
            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let mode = RayMode::UniqueEnd;
                let got = pool.install(|| thinned(&rays, origin, mode, &extent, &mut bufs, None));
                let mut fresh = Buffers::default();
                let want = pool.install(|| thinned(&rays, origin, mode, &extent, &mut fresh, None));
                assert!(got.len() < rays.len() && got.len() > 1000, "{}", got.len());
                assert_eq!(as_set(&got), as_set(&want));
            }
        }
    }

    /// Laid out by sides, a mode casts the same rays, with the same extent (checked in
    /// `thinned`), as in scan order: dropped rays leave the layout, kept ones keep their
    /// side and order.
    #[test]
    fn the_layout_keeps_what_the_mode_keeps() {
        let mut rng = Rng(13);
        let origin = [0.5, 1.5, -0.5];
        let rays: Vec<Ray> = (0..20_000)
            .map(|i| {
                let end = [0, 1, 2].map(|a| origin[a] + (rng.f() * 16.0 - 8.0).round() / 2.0);
                Ray::new(end, 0, i % 4 != 0)
            })
            .collect();
        let extent = bounds(&rays, origin);
        let sort = |mut v: Vec<([f64; 3], bool)>| {
            v.sort_by(|a, b| a.partial_cmp(b).unwrap());
            v
        };
        let axis = [0.6, 0.8, 0.0];
        for mode in [
            RayMode::UniqueEnd,
            RayMode::Bundle { threshold: 2 },
            RayMode::Subsample { factor: 2 },
        ] {
            let mut bufs = Buffers::default();
            let want = thinned(&rays, origin, mode, &extent, &mut bufs, None);
            assert!(want.len() < rays.len() / 2, "{mode:?}");
            let got = thinned(&rays, origin, mode, &extent, &mut bufs, Some(axis));
            let pairs = |v: &[Ray]| sort(v.iter().map(|r| (r.end, r.hit)).collect());
            assert!(pairs(&got) == pairs(&want), "{mode:?}");
        }
    }

    /// Bundles: the same groups and means as the sort-based reference (which sums a group
    /// in another order: equal to rounding), and exactly the same rays on any thread count,
    /// by the counting sort and by the hash partitions.
    #[test]
    fn bundles_match_the_sorted_reference_on_any_thread_count() {
        let mut rng = Rng(12);
        let origin = [0.25, 0.5, -0.75];
        let rays: Vec<Ray> = (0..50_000)
            .map(|i| {
                let end = [0, 1, 2].map(|a| origin[a] + rng.f() * 12.0 - 6.0);
                Ray::new(end, 0, i % 5 != 0)
            })
            .collect();
        let extent = bounds(&rays, origin);
        let sorted = |v: &[Ray]| {
            let mut e: Vec<_> = v
                .iter()
                .map(|r| (r.end.map(f64::floor), r.hit, r.end))
                .collect();
            e.sort_by(|a, b| a.partial_cmp(b).unwrap());
            e
        };
        for threshold in [1, 3, 1_000_000] {
            let mode = RayMode::Bundle { threshold };
            let mut want = rays.clone();
            thin_hashed(&mut want, origin, mode);
            let pool = |n| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build()
                    .unwrap()
            };
            let mut bufs = Buffers::default();
            let one = pool(1).install(|| thinned(&rays, origin, mode, &extent, &mut bufs, None));
            let (w, g) = (sorted(&want), sorted(&one));
            assert_eq!(w.len(), g.len(), "threshold {threshold}");
            for (a, b) in w.iter().zip(&g) {
                assert_eq!((a.0, a.1), (b.0, b.1));
                assert!(
                    (0..3).all(|k| (a.2[k] - b.2[k]).abs() < 1e-9),
                    "{a:?} {b:?}"
                );
            }
            if threshold == 1_000_000 {
                // No group is bundled: every ray, in scan order.
                let ends = |v: &[Ray]| v.iter().map(|r| r.end).collect::<Vec<_>>();
                assert!(ends(&one) == ends(&rays));
            } else {
                assert!(
                    one.len() < rays.len() * 9 / 10,
                    "{} of {}",
                    one.len(),
                    rays.len()
                );
            }
            let fields = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit, r.key)).collect::<Vec<_>>();
            for n in [2, 3, 5] {
                let got =
                    pool(n).install(|| thinned(&rays, origin, mode, &extent, &mut bufs, None));
                assert!(
                    fields(&got) == fields(&one),
                    "threshold {threshold} on {n} threads"
                );
            }
            // The partitioned hash tables, which boxes too large for the counting sort
            // take, bundle exactly the same rays.
            let cells = CellKeys::new(origin, 1);
            assert!(CellBox::new(&extent, &cells).is_some());
            let keys: Vec<u64> = rays.iter().map(|r| cells.key(r)).collect();
            let places: Vec<u16> = (0..rays.len()).map(|i| (i % RAY_CHUNK) as u16).collect();
            for n in [1, 3] {
                let mut got = rays.clone();
                let keep: Vec<AtomicBool> = keys.iter().map(|_| AtomicBool::new(false)).collect();
                let layout = Layout { places: &places };
                let means = pool(n).install(|| bundle(&got, &layout, threshold, &keys, &keep));
                set_means(&mut got, origin, means);
                let got: Vec<Ray> = (got.iter().zip(&keep))
                    .filter(|(_, k)| k.load(Ordering::Relaxed))
                    .map(|(r, _)| *r)
                    .collect();
                assert_eq!(
                    as_set(&got),
                    as_set(&one),
                    "hashed, threshold {threshold} on {n} threads"
                );
            }
        }
    }
}
