//! Bundle: the rays ending in one voxel (and alike in hitting) form a group, and a group
//! larger than the threshold casts one ray to its mean end. Grouped with a counting sort
//! by cell over a small frame's box ([`bundle_dense`]), in hash tables by partition over a
//! larger one ([`bundle_hashed`]); both sum a group's ends in scan order, so the mean is the same
//! on any thread count.

use super::*;

/// A bundled group: its first ray's place in the layout and the mean of its ends.
type Mean = (u32, [f64; 3]);

/// Bundle: the rays ending in one voxel (and alike in hitting) form a group; a group of
/// more than `threshold` becomes one ray to the mean of their ends, in the place of its
/// first ray; smaller groups keep their rays. Grouped by partition as [`first_per_cell_hashed`]:
/// a group's ends are summed in scan order, so the mean is the same on any thread count.
/// Whether each ray is kept goes into `keep` by its place in the layout.
pub(super) fn bundle_hashed(
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

/// [`bundle_hashed`] over a frame's box of cells ([`CellBox`], hit or not): the rays are sorted
/// by cell with one counting pass (buckets of the cells' high bits, stable, so a bucket
/// holds its rays in scan order), then each bucket groups its rays in a small table of
/// its own. A group's ends are summed in scan order, as [`bundle_hashed`] sums them.
pub(super) fn bundle_dense(
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

/// A bundle's first ray becomes the ray to the mean.
pub(super) fn set_means(rays: &mut [Ray], origin: [f64; 3], means: Vec<Vec<Mean>>) {
    for (first, end) in means.into_iter().flatten() {
        let r = &mut rays[first as usize];
        let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
        *r = Ray::new(end, direction_key(d), r.hit);
    }
}
