//! Subsample and unique-end chosen as the rays are made ([`choose_as_made`]), where a box of
//! cells about the sensor holds every end a ray can have (max range each way) in
//! [`DENSE_CELL_BITS`](super::DENSE_CELL_BITS).
//!
//! The frame's points are cut into runs in scan order, one per thread. A run makes its
//! rays chunk by chunk, notes each ray's cell bit and side four rays at a time, and marks
//! the cells in a bit set of its own; a ray whose cell the run had marked is not laid out
//! at all, so nothing moves it or drops it later. The
//! runs after the first then drop from their layout the rays whose cell an earlier run
//! marked. That keeps the first ray of each cell in scan order, as the other paths of
//! [`super::choose`] do, on any thread count.

use super::{scan_runs, sized, to_centre, zero, CellBox, BEHIND};
use crate::integrate::ray::{
    CellKeys, ExtentSum, Ray, RayMaker, Sides, NO_CELL, RAY_CHUNK, SKIPPED,
};
use crate::prefetch::own_lines;
use rayon::prelude::*;
use std::time::{Duration, Instant};

/// What [`choose_as_made`] keeps from frame to frame: in fresh memory a frame's sets and
/// notes would cost a page fault every 4 KiB, every frame.
#[derive(Default)]
pub(crate) struct AsMade {
    /// Per run, its bit set over the box.
    runs: Vec<RunSet>,
    /// Each laid-out ray's cell bit, in the ray's place.
    placed: Vec<u32>,
}

impl AsMade {
    /// Bytes of the sets and notes, as allocated.
    pub(crate) fn memory_bytes(&self) -> usize {
        self.placed.capacity() * 4
            + (self.runs.iter())
                .map(|r| r.set.capacity() * 8 + r.marked.capacity() * 4)
                .sum::<usize>()
    }
}

/// A run's bit set: all zeros but for the bits of the first `count` of `marked`.
#[derive(Default)]
struct RunSet {
    set: Vec<u64>,
    marked: Vec<u32>,
    count: usize,
}

impl RunSet {
    /// All zeros, `words` long.
    fn clear(&mut self, words: usize) {
        if self.set.len() == words {
            zero(&mut self.set, &self.marked[..self.count]);
        } else {
            self.set.clear();
            self.set.resize(words, 0);
        }
        self.count = 0;
    }

    fn has(&self, bit: u32) -> bool {
        self.set[bit as usize / 64] >> (bit % 64) & 1 != 0
    }
}

/// What a run needs to make and choose its rays.
#[derive(Clone, Copy)]
pub(crate) struct Chooser<'a> {
    pub(crate) maker: &'a RayMaker,
    pub(crate) sides: &'a Sides,
    pub(crate) cells: &'a CellKeys,
    pub(crate) cells_box: &'a CellBox,
    /// Unique-end: each ray kept goes to the centre of its end voxel.
    pub(crate) centre: bool,
}

/// Make the rays to `points` into `rays` (as long), laid out by sides in chunks with the
/// counts in `counts` as the exact mode's are, but only the first ray of each cell in scan
/// order. Returns the sum over all rays made, how many rays kept are cut at max range,
/// and the time spent choosing (keying, marking and laying out, then dropping what an
/// earlier run saw).
pub(crate) fn choose_as_made(
    rays: &mut [Ray],
    counts: &mut [[u32; 2]],
    points: &[[f32; 3]],
    how: Chooser<'_>,
    bufs: &mut AsMade,
) -> (ExtentSum, u64, Duration) {
    let n = rays.len();
    let (runs, per) = scan_runs(n);
    let words = how.cells_box.bits().div_ceil(64);
    bufs.runs
        .resize_with(runs.max(bufs.runs.len()), RunSet::default);
    sized(&mut bufs.placed, n, || 0);
    let AsMade { runs: sets, placed } = bufs;
    let made: Vec<(ExtentSum, u64, Duration)> = (rays.par_chunks_mut(per))
        .zip(points.par_chunks(per))
        .zip(placed.par_chunks_mut(per))
        .zip(counts.par_chunks_mut(per / RAY_CHUNK))
        .zip(sets[..runs].par_iter_mut())
        .map(|((((out, pts), placed), counts), run)| {
            let t = Instant::now();
            run.clear(words);
            sized(&mut run.marked, out.len(), || 0);
            let mut took = t.elapsed();
            let (sum, cut, choosing) = make_run(how, pts, out, placed, counts, run);
            took += choosing;
            (sum, cut, took)
        })
        .collect();
    let origin = how.maker.origin;
    let (sum, mut cut, took) = (made.into_iter()).fold(
        (ExtentSum::new(origin), 0, Duration::ZERO),
        |(s, c, t), (s2, c2, t2)| (ExtentSum::join(s, s2), c + c2, t.max(t2)),
    );
    if runs < 2 {
        return (sum, cut, took);
    }
    let t = Instant::now();
    let chunks = per / RAY_CHUNK;
    let sets = &sets[..runs];
    let dropped: u64 = (rays.par_chunks_mut(RAY_CHUNK))
        .zip(placed.par_chunks_mut(RAY_CHUNK))
        .zip(counts.par_iter_mut())
        .enumerate()
        .skip(chunks)
        .map(|(c, ((out, placed), side))| drop_seen(out, placed, side, &sets[..c / chunks]))
        .sum();
    cut -= dropped;
    (sum, cut, took + t.elapsed())
}

/// Make a run's rays, chunk by chunk, keeping the first of each cell the run sees
/// (marked in `run`); returns the sum over all rays made, the cut rays kept and the time
/// spent choosing.
fn make_run(
    how: Chooser<'_>,
    pts: &[[f32; 3]],
    out: &mut [Ray],
    placed: &mut [u32],
    counts: &mut [[u32; 2]],
    run: &mut RunSet,
) -> (ExtentSum, u64, Duration) {
    let (maker, origin) = (how.maker, how.maker.origin);
    let mut sum = ExtentSum::new(origin);
    let (mut cut, mut took) = (0, Duration::ZERO);
    let mut made = vec![Ray::new([0.0; 3], SKIPPED, false); RAY_CHUNK];
    let mut notes = [NO_CELL; RAY_CHUNK];
    let RunSet { set, marked, count } = run;
    for (((pts, out), placed), side) in (pts.chunks(RAY_CHUNK))
        .zip(out.chunks_mut(RAY_CHUNK))
        .zip(placed.chunks_mut(RAY_CHUNK))
        .zip(counts.iter_mut())
    {
        let (made, notes) = (&mut made[..pts.len()], &mut notes[..pts.len()]);
        // The layout's stores find their lines here, not on the core that read the rays
        // in the last walk: with one store a line, many of those fetches overlap, where
        // among the layout's other stores few did.
        own_lines(out);
        own_lines(placed);
        own_lines(&mut marked[*count..*count + pts.len()]);
        // On AVX2 made, summed and noted in one pass (bit for bit the three below), which
        // also asks for the words of `set` that `mark` will read.
        let fused = (maker.kernels.make_noted)(how, pts, made, notes, set);
        let (chunk_sum, t) = match fused {
            // Noted as made: the choosing's time starts with the marking.
            Some(s) => (s, Instant::now()),
            // Noted first and the set's words asked for, so that they come while the
            // extent is summed.
            None => {
                maker.make_all(made, pts);
                let t = Instant::now();
                how.cells_box
                    .notes_of(how.cells, how.sides, maker.kernels, made, notes);
                prefetch_set_words(worth_prefetching(set), notes);
                // (The choosing's time takes in the sum: a pass over the chunk in cache.)
                let s = (maker.kernels.extent_of)(origin, made);
                (s, t)
            }
        };
        sum = ExtentSum::join(sum, chunk_sum);
        // First the cells, marked with nothing else depending on the set's words, so that
        // their cache misses overlap; then the layout, from the notes.
        mark(notes, set);
        if how.centre {
            made.iter_mut().for_each(|r| *r = to_centre(r));
        }
        let (front, back, kept_cut) = lay_out(made, notes, out, placed, &mut marked[*count..]);
        *count += front + (out.len() - back);
        cut += kept_cut;
        *side = [front as u32, (out.len() - back) as u32];
        took += t.elapsed();
    }
    (sum, cut, took)
}

/// `set` if its words are to be asked for before they are marked, else nothing: a set
/// that fits the core's level 2 cache (0.5-2 MiB; unique-end's at 6 m is 0.5 MB) stays
/// there.
pub(super) fn worth_prefetching(set: &[u64]) -> &[u64] {
    if std::mem::size_of_val(set) > 1 << 20 {
        set
    } else {
        &[]
    }
}

/// Ask for the words of `ahead` (a set as [`worth_prefetching`] gives it) that hold the cells of
/// `notes`, which [`mark`] reads next. A skipped point's note ([`NO_CELL`]) lies past the set
/// and asks for nothing.
#[inline(always)]
pub(super) fn prefetch_set_words(ahead: &[u64], notes: &[u64]) {
    for &k in notes {
        crate::prefetch::prefetch(ahead, k as u32 as usize / 64);
    }
}

/// Mark the cell bit of each note ([`CellBox::note_of`], but [`NO_CELL`]) in `set`, adding
/// 1 << 32 to the note if `set` did not have it. This and [`lay_out`] are functions of
/// their own: inlined into the run's loop, their counters lived on the stack, and the
/// layout took half again as long.
#[inline(never)]
fn mark(notes: &mut [u64], set: &mut [u64]) {
    for k in notes.iter_mut().filter(|k| **k != NO_CELL) {
        let b = *k as u32 as usize;
        let (w, m) = (b / 64, 1u64 << (b % 64));
        let first = set[w] & m == 0;
        set[w] |= m;
        *k |= u64::from(first) << 32;
    }
}

/// Lay out the rays `made` whose note in `notes` ([`mark`]'s) says first of their cell,
/// into `out` by the sides the notes give, their cell bits into `placed` by place and into
/// `marked` in order; returns the sides' ends (front, back) and the cut rays laid out.
#[inline(never)]
fn lay_out(
    made: &[Ray],
    notes: &[u64],
    out: &mut [Ray],
    placed: &mut [u32],
    marked: &mut [u32],
) -> (usize, usize, u64) {
    let n = made.len();
    assert!(notes.len() == n && out.len() == n && placed.len() == n && marked.len() >= n);
    let (mut front, mut back, mut count, mut cut) = (0, n, 0, 0);
    let (o, pl, mk) = (out.as_mut_ptr(), placed.as_mut_ptr(), marked.as_mut_ptr());
    for (r, &k) in made.iter().zip(notes) {
        if k == NO_CELL {
            continue;
        }
        let (b, first, behind) = (k as u32, k >> 32 & 1 == 1, k & BEHIND != 0);
        // Written whatever the ray, counted only for the first: no branch on a cell's
        // novelty, a coin flip in many scans. Each ray laid out or not leaves a place
        // between `front` and `back`, and in `marked`.
        let place = if behind { back - 1 } else { front };
        // SAFETY: before the i-th ray at most i rays took a place, so `front < back <= n`
        // and `place` (`front` or `back - 1`) is below `n`, the length of `out` and
        // `placed`; `count` is at most i, below `n <= marked.len()`. A ray is 32 bytes,
        // all initialised (explicit padding), copied as four words: as a `Ray` it was
        // copied field by field, six loads and stores.
        unsafe {
            mk.add(count).write(b);
            let words = std::ptr::from_ref(r).cast::<[u64; 4]>().read();
            o.add(place).cast::<[u64; 4]>().write(words);
            pl.add(place).write(b);
        }
        count += usize::from(first);
        front += usize::from(first & !behind);
        back -= usize::from(first & behind);
        cut += u64::from(first & !r.hit);
    }
    (front, back, cut)
}

/// Drop from a chunk's layout (counts in `side`) the rays whose cell an `earlier` run
/// marked, closing each side's gap with its last rays; returns how many of those dropped
/// were cut at max range.
fn drop_seen(out: &mut [Ray], placed: &mut [u32], side: &mut [u32; 2], earlier: &[RunSet]) -> u64 {
    let seen = |b: u32| earlier.iter().any(|s| s.has(b));
    let mut cut = 0;
    let mut drop = |out: &mut [Ray], placed: &mut [u32], at: usize, with: usize| {
        // The box has a hit bit: the cell's lowest.
        cut += u64::from(placed[at] & 1 == 0);
        out[at] = out[with];
        placed[at] = placed[with];
    };
    // Front: places 0..end, the last ray fills a hole.
    let (mut i, mut end) = (0, side[0] as usize);
    while i < end {
        if seen(placed[i]) {
            end -= 1;
            drop(out, placed, i, end);
        } else {
            i += 1;
        }
    }
    side[0] = end as u32;
    // Back: places start..len, the first ray fills a hole.
    let len = out.len();
    let (mut i, mut start) = (len, len - side[1] as usize);
    while i > start {
        if seen(placed[i - 1]) {
            drop(out, placed, i - 1, start);
            start += 1;
        } else {
            i -= 1;
        }
    }
    side[1] = (len - start) as u32;
    cut
}
