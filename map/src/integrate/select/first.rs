//! The first ray per cell in scan order, for subsample and unique-end where the rays are
//! not chosen as they are made: in bit sets over the frame's box of cells
//! ([`first_per_cell_dense`]), or in hash sets by partition where that box is too large
//! ([`first_per_cell_hashed`]).

use super::*;

/// [`first_per_cell_dense`] for boxes too large for bit sets: each cell goes to one of
/// [`PARTITIONS`] by a hash of its key; each partition, on a thread of its own, takes its
/// rays in scan order into a hash set of its own and keeps those it had not seen.
pub(super) fn first_per_cell_hashed(keys: &[u64], keep: &[AtomicBool]) {
    let runs = partitioned(keys, |i, k| (k, i));
    (0..PARTITIONS).into_par_iter().for_each(|p| {
        let mut seen = HashSet::with_capacity(runs.iter().map(|r| r[p].len()).sum());
        for &(k, i) in in_partition(&runs, p) {
            keep[i as usize].store(seen.insert(k), Ordering::Relaxed);
        }
    });
}

/// Which rays are the first of their cell in scan order, as [`Keep::FirstPerCell`] reads it;
/// returns the runs and their length. The rays are cut into one run per thread; each run
/// notes its own firsts, marking them in a bit set of its own, by which the runs after
/// the first then drop the rays an earlier run saw. The first pass notes each ray's bit,
/// so the second reads 4 bytes a ray instead of the key. The sets are left marked for
/// [`Buffers::clean`].
pub(super) fn first_per_cell_dense(cells: &CellBox, bufs: &mut Buffers) -> (usize, usize) {
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
                if k == NO_CELL {
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
