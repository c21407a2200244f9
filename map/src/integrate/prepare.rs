//! Phase 1, prepare: a frame's points become rays in voxel units (pose, face snap,
//! max-range cut), laid out by the sides of the sensor as they are made, with the frame's
//! extent summed up in the same pass (`ray`); a ray mode other than exact chooses among
//! them, in the same pass or from notes of it (`select`), and the rays it drops leave the
//! layout ([`compact`]); the sparse walk gets them sorted by direction
//! ([`order_by_direction`]).

use super::ray::{
    direction_key, first_bits, ray_count, CellKeys, ChunkOrder, Extent, ExtentSum, Ray, RayMaker,
    Sides, RAY_CHUNK, SKIPPED,
};
use super::select::{cell_factor, choose, choose_as_made, Buffers, CellBox, Chooser, Kept};
use super::{Frame, RayMode};
use crate::kernel::Kernels;
use crate::mask::BitIter;
use rayon::prelude::*;

pub(super) fn set_direction_keys(rays: &mut [Ray], origin: [f64; 3]) {
    rays.par_iter_mut()
        .for_each(|r| r.key = direction_key([0, 1, 2].map(|a| r.end[a] - origin[a])));
}

/// Put the rays in the sparse walk's order: gaps of skipped points and dropped rays
/// closed, sorted by direction, so that neighbouring rays walk neighbouring memory.
pub(super) fn order_by_direction(rays: &mut Vec<Ray>, counts: &[[u32; 2]], origin: [f64; 3]) {
    let mut to = 0;
    for (c, &[front, back]) in counts.iter().enumerate() {
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

/// Fill `rays` from the frame, laid out by `sides` with the counts per chunk in `counts`;
/// returns the number of non-finite points skipped, the rays' extent, and the time a
/// ray mode took to choose its rays and drop the others from the layout
/// ([`compact`]).
#[allow(clippy::too_many_arguments)]
pub(super) fn prepare_rays(
    rays: &mut Vec<Ray>,
    counts: &mut Vec<[u32; 2]>,
    sides: Sides,
    frame: &Frame<'_>,
    tf: &crate::coord::GridTransform,
    origin: [f64; 3],
    range_units: f64,
    mode: RayMode,
    kernels: &'static Kernels,
    select: &mut Buffers,
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
    counts.clear();
    counts.resize(n.div_ceil(RAY_CHUNK), [0; 2]);
    let cells = CellKeys::new(origin, cell_factor(mode));
    let around = match mode {
        RayMode::Subsample { .. } | RayMode::UniqueEnd => {
            CellBox::around(origin, range_units, &cells)
        }
        RayMode::Exact | RayMode::Bundle { .. } => None,
    };
    if let Some(cells_box) = around {
        // Every end the frame can have fits a bit set: the rays are chosen as they are
        // made ([`choose_as_made`]).
        let how = Chooser {
            maker: &maker,
            sides: &sides,
            cells: &cells,
            cells_box: &cells_box,
            centre: mode == RayMode::UniqueEnd,
        };
        let (sums, cut, took) =
            choose_as_made(rays, counts, frame.points, how, &mut select.as_made);
        return (sums.skipped, kept_extent(&sums, n, counts, cut), took);
    }
    let chunks = rays
        .par_chunks_mut(RAY_CHUNK)
        .zip(frame.points.par_chunks(RAY_CHUNK))
        .zip(counts.par_iter_mut());
    let sums = if mode == RayMode::Exact {
        chunks
            .map_init(Vec::new, |made, ((out, pts), side)| {
                let (counts, _, sum) = sides.make(&maker, pts, out, made, None);
                *side = counts;
                sum
            })
            .reduce(|| ExtentSum::new(origin), ExtentSum::join)
    } else {
        // The ray modes choose rays in scan order: the same pass notes each ray's
        // cell, in scan order, and where the layout put it, so that choosing reads 8 bytes
        // a ray instead of the ray, and dropping rays is a compaction of the layout.
        let (keys, orders) = select.notes(n);
        chunks
            .zip(keys.par_chunks_mut(RAY_CHUNK))
            .zip(orders.par_iter_mut())
            .map_init(Vec::new, |made, ((((out, pts), side), keys), order)| {
                let note = Some((&cells, keys));
                let (counts, o, sum) = sides.make(&maker, pts, out, made, note);
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
    let (kept, orders) = choose(rays, origin, mode, &sums.extent(), select);
    let cut = compact(rays, counts, orders, &kept);
    let thinned = t.elapsed();
    (skipped, kept_extent(&sums, n, counts, cut), thinned)
}

/// The extent of the rays a ray mode kept of a frame's `points` (laid out with the
/// counts `counts`, `cut` of them cut at max range), from the sum over all rays made: the
/// box of all rays holds those kept (a kept ray moves only within its end voxel), and the
/// walk's length is taken as the share of rays kept.
fn kept_extent(sums: &ExtentSum, points: usize, counts: &[[u32; 2]], cut: u64) -> Extent {
    let mut extent = sums.extent();
    let made = (points as u64 - sums.skipped).max(1) as f64;
    extent.steps *= ray_count(counts) as f64 / made;
    extent.cut_rays = cut;
    extent
}

/// Drop from the layout of each chunk the rays `kept` does not keep (a bundle's mean is
/// already in its first ray's place); `orders` says which ray of the scan lies where
/// ([`ChunkOrder`]). `counts` gets the new counts (what lies between is left as it was,
/// not rays); returns how many rays kept are cut at max range.
pub(super) fn compact(
    rays: &mut [Ray],
    counts: &mut [[u32; 2]],
    orders: &[ChunkOrder],
    kept: &Kept<'_>,
) -> u64 {
    rays.par_chunks_mut(RAY_CHUNK)
        .zip(counts.par_iter_mut())
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
        (0..RAY_CHUNK / 64).flat_map(move |w| BitIter(m[w]).map(move |b| w * 64 + b))
    };
    let holes = ones(std::array::from_fn(|w| !keep[w] & first(w)));
    let moved = ones(std::array::from_fn(|w| keep[w] & !first(w)));
    for (h, m) in holes.zip(moved) {
        chunk[at(h)] = chunk[at(m)];
    }
}
