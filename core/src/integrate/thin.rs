//! The paper's trade-off modes ([`RayMode`] other than `Exact`): fewer rays for a coarser
//! map. Each keeps the first ray of a kind in scan order, so its result does not depend on
//! the thread count.
//!
//! Subsample and unique-end keep the first ray per cell (a sub-cell or the end voxel, and
//! whether the ray hits). Over a frame whose cells fit [`DENSE_CELL_BITS`], each thread
//! marks the cells of its own run of rays in a bit set over the frame's box, then drops
//! the rays whose cell an earlier run saw ([`firsts_dense`]); larger frames take a hash set
//! in scan order.
//!
//! Bundle groups the rays by end voxel: over a small frame's box with a counting sort by
//! cell ([`bundle_dense`]), over larger ones in hash tables by partition ([`bundle`]).
//! Both sum a group's ends in scan order, so the mean is the same on any thread count.

use super::prepare::{direction_key, Extent, Ray};
use super::RayMode;
use hashbrown::{HashMap, HashSet};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// Most cells (times two, hit or not) a frame's box may have for the bit-set path: 2^25
/// bits, 4 MiB per thread (and bit indices below 2^31).
pub(super) const DENSE_CELL_BITS: u64 = 1 << 25;

/// The buffers the trade-off modes reuse from frame to frame: in fresh memory a frame's
/// would cost a page fault every 4 KiB, every frame.
#[derive(Default)]
pub(in crate::integrate) struct Buffers {
    /// Each ray's cell bit ([`CellBox::bit`]).
    bits: Vec<u32>,
    /// [`bundle_dense`]'s (cell bit, ray) in cell order.
    sorted: Vec<AtomicU64>,
    /// Whether each ray is kept.
    keep: Vec<AtomicBool>,
}

/// `v` as long as `n`, writing only what it did not hold.
fn sized<T>(v: &mut Vec<T>, n: usize, new: impl FnMut() -> T) {
    v.truncate(n);
    v.resize_with(n, new);
}

/// Which rays a trade-off mode keeps, and as what. The layout by sides reads it as it
/// lays the rays out, so dropping rays costs no pass of its own.
pub(in crate::integrate) struct Kept<'a> {
    keep: &'a [AtomicBool],
    /// Unique-end: each ray kept goes to the centre of its end voxel.
    centre: bool,
}

impl Kept<'_> {
    /// Ray `i`, `r`, as kept, or `None`.
    #[inline]
    pub(in crate::integrate) fn ray(&self, i: usize, r: &Ray) -> Option<Ray> {
        let keep = self.keep[i].load(Ordering::Relaxed);
        keep.then(|| if self.centre { to_centre(r) } else { *r })
    }
}

/// Choose (or merge) the rays that `mode` trades for speed; `extent` bounds the rays'
/// ends. A bundle's mean is written into its first ray; the rays dropped are those the
/// returned [`Kept`] does not keep. `mode` is not `Exact`.
pub(super) fn thin_out<'b>(
    rays: &mut [Ray],
    origin: [f64; 3],
    mode: RayMode,
    extent: &Extent,
    bufs: &'b mut Buffers,
) -> Kept<'b> {
    sized(&mut bufs.keep, rays.len(), || AtomicBool::new(false));
    match mode {
        RayMode::Bundle { threshold } => match CellBox::new(extent, 1) {
            Some(cells) => bundle_dense(rays, origin, threshold, &cells, bufs),
            None => bundle(rays, origin, threshold, &bufs.keep),
        },
        RayMode::Subsample { factor } => firsts(rays, origin, factor, extent, bufs),
        RayMode::UniqueEnd => firsts(rays, origin, 1, extent, bufs),
        RayMode::Exact => unreachable!("exact rays are not thinned"),
    }
    Kept {
        keep: &bufs.keep,
        centre: mode == RayMode::UniqueEnd,
    }
}

/// Whether each ray is the first of its cell (`factor` per voxel edge) in scan order, into
/// `bufs.keep`: by bit sets over a small frame's box, by hash partitions over a larger one.
fn firsts(rays: &[Ray], origin: [f64; 3], factor: u32, extent: &Extent, bufs: &mut Buffers) {
    match CellBox::new(extent, factor) {
        Some(cells) => firsts_dense(rays, &cells, bufs),
        None => firsts_hashed(rays, origin, factor, &bufs.keep),
    }
}

/// A unique-end ray: to the centre of its end voxel.
fn to_centre(r: &Ray) -> Ray {
    Ray {
        end: r.end.map(|c| c.floor() + 0.5),
        ..*r
    }
}

/// Rays per run of [`firsts_hashed`]'s first pass: fixed, so that the partitions see the
/// rays in scan order whatever the thread count.
const HASH_RUN: usize = 16 * 1024;
/// Partitions of [`firsts_hashed`]'s cells (a power of two).
const PARTITIONS: usize = 64;

/// Per fixed run of rays and per partition of the cell keys (the cell `factor` per voxel
/// edge, relative to the origin's, with the hit flag), `item(index, key, ray)` of each ray
/// in scan order: a partition's items, run after run, are in scan order whatever the
/// thread count. The items carry what a partition needs, so that it reads them one after
/// another instead of the rays all over memory.
fn partitioned<T: Send>(
    rays: &[Ray],
    origin: [f64; 3],
    factor: u32,
    item: impl Fn(u32, u64, &Ray) -> T + Sync,
) -> Vec<Vec<Vec<T>>> {
    let f = f64::from(factor);
    let base = origin.map(|c| (c * f).floor() as i64);
    // Cells within max range (8192 voxels) times the factor (at most 64) of the origin's:
    // 21 bits an axis, and the hit flag.
    let key = |r: &Ray| {
        let c = [0, 1, 2].map(|a| (((r.end[a] * f).floor() as i64 - base[a]) & 0x1f_ffff) as u64);
        c[0] | c[1] << 21 | c[2] << 42 | u64::from(r.hit) << 63
    };
    let part = |k: u64| (k.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 58) as usize;
    rays.par_chunks(HASH_RUN)
        .enumerate()
        .map(|(j, rs)| {
            let mut lists: Vec<Vec<T>> = (0..PARTITIONS).map(|_| Vec::new()).collect();
            for (i, r) in rs.iter().enumerate() {
                let k = key(r);
                lists[part(k)].push(item((j * HASH_RUN + i) as u32, k, r));
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
fn firsts_hashed(rays: &[Ray], origin: [f64; 3], factor: u32, keep: &[AtomicBool]) {
    let runs = partitioned(rays, origin, factor, |i, k, _| (k, i));
    (0..PARTITIONS).into_par_iter().for_each(|p| {
        let mut seen = HashSet::with_capacity(runs.iter().map(|r| r[p].len()).sum());
        for &(k, i) in in_partition(&runs, p) {
            keep[i as usize].store(seen.insert(k), Ordering::Relaxed);
        }
    });
}

/// Bundle: the rays ending in one voxel (and alike in hitting) form a group; a group of
/// more than `threshold` becomes one ray to the mean of their ends, in the place of its
/// first ray; smaller groups keep their rays. Grouped by partition as [`firsts_hashed`]:
/// a group's ends are summed in scan order, so the mean is the same on any thread count.
fn bundle(rays: &mut [Ray], origin: [f64; 3], threshold: u32, keep: &[AtomicBool]) {
    let runs = partitioned(rays, origin, 1, |i, k, r| (k, i, r.end));
    // Per partition, the bundled groups as (first ray, mean end).
    let means: Vec<Vec<(u32, [f64; 3])>> = (0..PARTITIONS)
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
                keep[i as usize].store(n <= threshold || i == first, Ordering::Relaxed);
            }
            (groups.into_iter())
                .filter(|&(_, n, _)| n > threshold)
                .map(|(first, n, sum)| (first, sum.map(|c| c / f64::from(n))))
                .collect()
        })
        .collect();
    set_means(rays, origin, means.into_iter().flatten());
}

/// Low bits of a cell's bit that [`bundle_dense`] groups by within a bucket: a bucket's
/// tables (4096 cells' counts, first rays and sums, 128 KiB) stay in the L2 cache.
const BUCKET_BITS: u32 = 12;

/// [`bundle`] over a frame's box of cells ([`CellBox`], hit or not): the rays are sorted
/// by cell with one counting pass (buckets of the cells' high bits, stable, so a bucket
/// holds its rays in scan order), then each bucket groups its rays in a small table of
/// its own. A group's ends are summed in scan order, as [`bundle`] sums them.
fn bundle_dense(
    rays: &mut [Ray],
    origin: [f64; 3],
    threshold: u32,
    cells: &CellBox,
    bufs: &mut Buffers,
) {
    let n = rays.len();
    let (runs, per) = scan_runs(n);
    let buckets = cells.bits().div_ceil(1 << BUCKET_BITS);
    sized(&mut bufs.bits, n, || 0);
    // Each run's bucket counts, then where each run's part of each bucket starts.
    let mut counts: Vec<Vec<u32>> = (bufs.bits.par_chunks_mut(per))
        .zip(rays.par_chunks(per))
        .map(|(bits, rays)| {
            let mut c = vec![0u32; buckets];
            for (b, r) in bits.iter_mut().zip(rays) {
                *b = cells.bit(r) as u32;
                c[(*b >> BUCKET_BITS) as usize] += 1;
            }
            c
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
    // Stable scatter: (cell bit, ray) in bucket order; distinct runs write distinct places.
    sized(&mut bufs.sorted, n, || AtomicU64::new(0));
    let sorted = &bufs.sorted;
    (bufs.bits.par_chunks(per))
        .zip(counts.par_iter_mut())
        .enumerate()
        .for_each(|(j, (bits, at))| {
            for (i, &b) in bits.iter().enumerate() {
                let slot = &mut at[(b >> BUCKET_BITS) as usize];
                let item = u64::from(b) << 32 | (j * per + i) as u64;
                sorted[*slot as usize].store(item, Ordering::Relaxed);
                *slot += 1;
            }
        });
    // Per task, the bundled groups as (first ray, mean end). The tasks' buckets hold
    // about as many rays each: a structured scene puts most rays in a few buckets.
    let tasks = (runs * 16).min(buckets);
    let bounds: Vec<usize> = (0..=tasks)
        .map(|t| {
            starts
                .partition_point(|&s| (s as usize) < t * n / tasks)
                .min(buckets)
        })
        .collect();
    let (rays_read, keep) = (&*rays, &bufs.keep);
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
    let means: Vec<Vec<(u32, [f64; 3])>> = (0..tasks)
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
                    crate::prefetch::prefetch(rays_read, x as u32 as usize);
                }
                for x in items.iter().map(|x| x.load(Ordering::Relaxed)) {
                    let (l, i) = (low(x), x as u32);
                    let bundled = count[l] > threshold;
                    keep[i as usize].store(!bundled || i == first[l], Ordering::Relaxed);
                    if bundled {
                        let e = rays_read[i as usize].end;
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
        .collect();
    set_means(rays, origin, means.into_iter().flatten());
}

/// The runs of rays in scan order that [`firsts_dense`] and [`bundle_dense`] cut a
/// frame's `n` rays into, one per thread (fewer for few rays): how many and how long.
fn scan_runs(n: usize) -> (usize, usize) {
    let runs = rayon::current_num_threads().min(n / 4096).max(1);
    (runs, n.div_ceil(runs).max(1))
}

/// A bundle's first ray becomes the ray to the mean.
fn set_means(rays: &mut [Ray], origin: [f64; 3], means: impl Iterator<Item = (u32, [f64; 3])>) {
    for (first, end) in means {
        let r = &mut rays[first as usize];
        let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
        *r = Ray::new(end, direction_key(d), r.hit);
    }
}

/// The cells (`factor` per voxel edge) over a frame's voxel box, indexed densely.
struct CellBox {
    factor: f64,
    lo: [i64; 3],
    dims: [u64; 3],
}

impl CellBox {
    /// `None` when the box has more than [`DENSE_CELL_BITS`] / 2 cells.
    fn new(extent: &Extent, factor: u32) -> Option<Self> {
        let f = i64::from(factor);
        let (lo, hi) = (extent.lo.to_array(), extent.hi.to_array());
        let lo = lo.map(|c| i64::from(c) * f);
        let dims = [0, 1, 2].map(|a| ((i64::from(hi[a]) + 1) * f - lo[a]) as u64);
        let cells = dims[0]
            .checked_mul(dims[1])
            .and_then(|c| c.checked_mul(dims[2]))?;
        (cells.checked_mul(2)? <= DENSE_CELL_BITS).then_some(CellBox {
            factor: f64::from(factor),
            lo,
            dims,
        })
    }

    fn bits(&self) -> usize {
        (2 * self.dims[0] * self.dims[1] * self.dims[2]) as usize
    }

    /// The bit of a ray's cell and hit flag. Ends lie in the box, whose voxel bounds the
    /// extent gives; a float end on the box's upper face is clamped into its last cell.
    #[inline]
    fn bit(&self, r: &Ray) -> usize {
        let c = [0, 1, 2].map(|a| {
            let k = (r.end[a] * self.factor).floor() as i64 - self.lo[a];
            k.clamp(0, self.dims[a] as i64 - 1) as u64
        });
        let cell = (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0];
        (2 * cell + u64::from(r.hit)) as usize
    }
}

/// Whether each ray is the first of its cell in scan order, into `bufs.keep`. The rays
/// are cut into one run per thread; each run keeps its own firsts, marking them in a bit
/// set of its own, and the sets of the runs before it, OR-ed, then drop those an earlier
/// run saw. The first pass notes each ray's bit, so the second reads 4 bytes a ray
/// instead of the ray.
fn firsts_dense(rays: &[Ray], cells: &CellBox, bufs: &mut Buffers) {
    const FIRST: u32 = 1 << 31;
    let (_, per) = scan_runs(rays.len());
    let words = cells.bits().div_ceil(64);
    sized(&mut bufs.bits, rays.len(), || 0);
    let mut seen: Vec<Vec<u64>> = (bufs.bits.par_chunks_mut(per))
        .zip(rays.par_chunks(per))
        .map(|(noted, rays)| {
            let mut set = vec![0u64; words];
            for (n, r) in noted.iter_mut().zip(rays) {
                let b = cells.bit(r);
                let (w, m) = (b / 64, 1u64 << (b % 64));
                *n = b as u32 | if set[w] & m == 0 { FIRST } else { 0 };
                set[w] |= m;
            }
            set
        })
        .collect();
    // seen[j] becomes the cells of runs 0..=j.
    for j in 1..seen.len() {
        let (before, rest) = seen.split_at_mut(j);
        rest[0]
            .par_iter_mut()
            .zip(before[j - 1].par_iter())
            .for_each(|(w, p)| *w |= p);
    }
    (bufs.keep.par_chunks(per))
        .zip(bufs.bits.par_chunks(per))
        .enumerate()
        .for_each(|(j, (keep, noted))| {
            for (k, &n) in keep.iter().zip(noted) {
                let b = (n & !FIRST) as usize;
                let earlier = j > 0 && seen[j - 1][b / 64] & (1u64 << (b % 64)) != 0;
                k.store(n & FIRST != 0 && !earlier, Ordering::Relaxed);
            }
        });
}

/// The trade-off modes in one pass in scan order over a hash set (bundle: a sort): the
/// reference the faster paths are tested against.
#[cfg(test)]
fn thin_hashed(rays: &mut Vec<Ray>, origin: [f64; 3], mode: RayMode) {
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
    use crate::integrate::prepare::bounds;
    use crate::test_rng::Rng;

    /// The bit-set path keeps exactly the rays, in the order and with the ends, that the
    /// hash set in scan order keeps, on any number of threads; rays on the box's faces and
    /// repeated cells included.
    #[test]
    fn dense_firsts_keep_what_the_scan_order_hash_keeps() {
        let mut rng = Rng(11);
        let origin = [3.5, -2.25, 0.5];
        let mut rays: Vec<Ray> = (0..60_000)
            .map(|i| {
                // Ends on a coarse lattice (many repeats, some exactly on cell faces).
                let end = [0, 1, 2].map(|a| origin[a] + (rng.f() * 20.0 - 10.0).round() / 2.0);
                Ray::new(end, 0, i % 3 != 0)
            })
            .collect();
        rays.push(Ray::new(origin, 0, true));
        let extent = bounds(&rays, origin);
        let mut bufs = Buffers::default();
        for mode in [
            RayMode::UniqueEnd,
            RayMode::Subsample { factor: 1 },
            RayMode::Subsample { factor: 4 },
        ] {
            let mut want = rays.clone();
            thin_hashed(&mut want, origin, mode);
            assert!(
                want.len() < rays.len() / 2 && want.len() > 1000,
                "{mode:?}: {}",
                want.len()
            );
            for threads in [1, 2, 3, 5] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                // Buffers left by the modes and thread counts before.
                let got = pool.install(|| thinned(&rays, origin, mode, &extent, &mut bufs));
                let ends = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit)).collect::<Vec<_>>();
                assert!(ends(&got) == ends(&want), "{mode:?} on {threads} threads");
            }
        }
        // A box too large for bit sets takes the partitioned hash sets: the same rays.
        assert!(CellBox::new(&extent, 64).is_none());
        assert!(CellBox::new(&extent, 1).is_some());
        let mut want = rays.clone();
        thin_hashed(&mut want, origin, RayMode::Subsample { factor: 64 });
        for (mode, factor) in [
            (RayMode::Subsample { factor: 4 }, 4),
            (RayMode::UniqueEnd, 1),
        ] {
            let mut w = rays.clone();
            thin_hashed(&mut w, origin, mode);
            for threads in [1, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let mut bufs = Buffers::default();
                sized(&mut bufs.keep, rays.len(), || AtomicBool::new(false));
                pool.install(|| firsts_hashed(&rays, origin, factor, &bufs.keep));
                let centre = mode == RayMode::UniqueEnd;
                let got = kept_rays(&rays, &bufs.keep, centre);
                let ends = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit)).collect::<Vec<_>>();
                assert!(
                    ends(&got) == ends(&w),
                    "{mode:?} hashed on {threads} threads"
                );
            }
        }
        let mode = RayMode::Subsample { factor: 64 };
        let got = thinned(&rays, origin, mode, &extent, &mut Buffers::default());
        assert_eq!(got.len(), want.len());
    }

    /// The rays `thin_out` keeps, in scan order, as it keeps them.
    fn thinned(
        rays: &[Ray],
        origin: [f64; 3],
        mode: RayMode,
        extent: &Extent,
        bufs: &mut Buffers,
    ) -> Vec<Ray> {
        let mut rays = rays.to_vec();
        let kept = thin_out(&mut rays, origin, mode, extent, bufs);
        kept_rays(&rays, kept.keep, kept.centre)
    }

    /// The rays `keep` marks, in scan order, as kept (`centre`: unique-end's).
    fn kept_rays(rays: &[Ray], keep: &[AtomicBool], centre: bool) -> Vec<Ray> {
        let kept = Kept { keep, centre };
        (rays.iter().enumerate())
            .filter_map(|(i, r)| kept.ray(i, r))
            .collect()
    }

    /// The layout by sides drops the rays a mode drops as it lays out the others, and sums
    /// their extent: the same rays and extent as the rays kept, on either side.
    #[test]
    fn the_layout_keeps_what_the_mode_keeps() {
        use crate::integrate::prepare::{Sides, RAY_CHUNK};
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
        for mode in [RayMode::UniqueEnd, RayMode::Bundle { threshold: 2 }] {
            let want = thinned(&rays, origin, mode, &extent, &mut Buffers::default());
            assert!(want.len() < rays.len() / 2, "{mode:?}");
            for axis in [None, Some([0.6, 0.8, 0.0])] {
                let (mut got, mut bufs, mut sides) = (rays.clone(), Buffers::default(), vec![]);
                let kept = thin_out(&mut got, origin, mode, &extent, &mut bufs);
                let halves = Sides { origin, axis };
                let sum = halves.lay_out_kept(&mut got, &mut sides, |i, r| kept.ray(i, r));
                let laid: Vec<Ray> = (got.chunks(RAY_CHUNK).zip(&sides))
                    .flat_map(|(c, &[front, back])| {
                        let (f, b) = (front as usize, back as usize);
                        c[..f].iter().chain(&c[c.len() - b..]).copied()
                    })
                    .collect();
                let pairs = |v: &[Ray]| sort(v.iter().map(|r| (r.end, r.hit)).collect());
                assert!(pairs(&laid) == pairs(&want), "{mode:?}, axis {axis:?}");
                let (e, b) = (sum.extent(), bounds(&want, origin));
                assert_eq!((e.lo, e.hi, e.cut_rays), (b.lo, b.hi, b.cut_rays));
            }
        }
    }

    /// Bundles: the same groups and means as the sort-based reference (which sums a group
    /// in another order: equal to rounding), and exactly the same rays on any thread count.
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
            let one =
                pool(1).install(|| thinned(&rays, origin, mode, &extent, &mut Buffers::default()));
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
            for n in [2, 3, 5] {
                let got = pool(n)
                    .install(|| thinned(&rays, origin, mode, &extent, &mut Buffers::default()));
                let ends = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit, r.key)).collect::<Vec<_>>();
                assert!(
                    ends(&got) == ends(&one),
                    "threshold {threshold} on {n} threads"
                );
            }
            // The partitioned hash tables, which boxes too large for the counting sort
            // take, bundle exactly the same rays.
            assert!(CellBox::new(&extent, 1).is_some());
            for n in [1, 3] {
                let mut got = rays.clone();
                let mut bufs = Buffers::default();
                sized(&mut bufs.keep, rays.len(), || AtomicBool::new(false));
                pool(n).install(|| bundle(&mut got, origin, threshold, &bufs.keep));
                let got = kept_rays(&got, &bufs.keep, false);
                let ends = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit, r.key)).collect::<Vec<_>>();
                assert!(
                    ends(&got) == ends(&one),
                    "hashed, threshold {threshold} on {n} threads"
                );
            }
        }
    }
}
