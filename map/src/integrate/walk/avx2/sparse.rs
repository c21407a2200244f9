//! The sparse walk on AVX2, lane by lane ([`walk_sparse`]): a voxel is [`Packed`]; each
//! lane stores its current plane's marks, and the voxel, to its current leaf's entry on
//! every step, and moves to its next entry when it leaves the leaf ([`SparseMarks`]).

use super::*;

/// Walk `rays` from `origin` four at a time, OR-ing their marks into the frame's tables
/// through `cache`; returns voxels visited. The same marks and count as
/// `walk::sparse::walk_rays`. The rays are sorted by direction and the lanes take the
/// next ones in turn, so they walk side by side and find the leaves they flush in `cache`
/// and in the CPU's caches. See [`SparseMarks`] for how marks are kept.
#[target_feature(enable = "avx2,bmi1,bmi2")]
pub(crate) fn walk_sparse(cache: &mut LeafCache<'_>, origin: [f64; 3], rays: &[Ray]) -> u64 {
    let v = crate::coord::units_to_voxel(origin).expect("origin checked");
    let packed = Packed::around(v);
    // No box: a ray's fields stay inside `Packed`'s (`Packed::around`), so every end is
    // "inside" bounds no coordinate reaches.
    let axes: [Axis; 3] =
        std::array::from_fn(|a| Axis::new(origin[a], Packed::STRIDES[a], i32::MIN, 1 << 33));
    let feed = Feed::all(rays);
    let start = packed.pack(v);
    let mut marks = SparseMarks {
        cache,
        packed,
        start: v,
        words: vec![Entry::default(); 4 * RING].into_boxed_slice(),
        keys: vec![0; 4 * RING].into_boxed_slice(),
        entry: _mm256_setr_epi64x(0, RING as i64, 2 * RING as i64, 3 * RING as i64),
        plane: _mm256_setzero_si256(),
        flush: Vec::with_capacity(4 * RING),
    };
    let from = Start {
        axes: &axes,
        origin,
        start,
        covered: None,
    };
    walk(&mut marks, &from, feed).0
}

/// Leaf entries per lane of [`SparseMarks`]: a burst crosses at most one leaf a step.
const RING: usize = 128;

/// A leaf's marks in [`SparseMarks`]: word z holds plane z, bit `x | y << 3`.
#[derive(Clone, Default)]
#[repr(C, align(64))]
struct Entry([u64; 8]);

/// The sparse walk's marks. Each lane keeps the marks of its current z plane in a vector
/// lane, and stores it on every step, with the voxel, to the plane's word of its current
/// leaf entry; when it leaves a leaf it moves on to its next entry. So a step has no
/// branch for the lanes that changed plane or leaf, the one-ray walk's costliest
/// (mispredicted) branch besides the axis choice. After each burst of steps, the
/// leaves each lane finished are OR-ed into the frame's tables. Aligned to a cache line so
/// that the walk's frame is (see `avx512::SparseLanes`).
#[repr(align(64))]
struct SparseMarks<'c, 'a> {
    cache: &'c mut LeafCache<'a>,
    packed: Packed,
    start: VoxelCoord,
    /// Lane `l`'s entries are `l * RING..(l + 1) * RING`: 8 words (z planes) of a leaf,
    /// and a voxel of the leaf (packed).
    words: Box<[Entry]>,
    keys: Box<[u64]>,
    /// Per lane its current entry, and its current plane's marks, bit `x | y << 3`.
    entry: __m256i,
    plane: __m256i,
    /// The leaves a burst finished: their slots and entries.
    flush: Vec<(&'a Slot, usize)>,
}

impl Marks for SparseMarks<'_, '_> {
    const BURST: i64 = RING as i64 - 1;

    fn idle(&self) -> u64 {
        self.packed.pack(self.start)
    }

    #[inline(never)]
    unsafe fn steps(
        &mut self,
        k: i64,
        t: &mut [__m256i; 3],
        p: &mut __m256i,
        fixed: &Fixed,
        live: __m256i,
    ) {
        // Checked, not assumed: the writes below rely on it (once a burst, not a step).
        assert!(k <= Self::BURST, "a burst longer than the ring");
        let at = (self.words.as_mut_ptr().cast(), self.keys.as_mut_ptr());
        // SAFETY: a lane starts a burst at its first entry (`burst_done`) and moves to the
        // next at most once a step, so in `k < RING` steps (checked above) it stays in its
        // `RING` entries; the CPU has AVX2 (the caller's promise).
        unsafe { sparse_steps(k, t, p, fixed, live, &mut self.entry, &mut self.plane, at) };
    }

    #[target_feature(enable = "avx2,bmi1,bmi2")]
    unsafe fn burst_done(&mut self, p: [i64; 4], ended: u32, hit: u32) {
        let entry = to_array(self.entry);
        let mut plane = to_array(self.plane);
        // Look up every finished leaf's slot and prefetch it, then OR them all, so that
        // their cache misses overlap.
        let mut flush = std::mem::take(&mut self.flush);
        for (l, &e) in entry.iter().enumerate() {
            let (first, cur) = (l * RING, e as usize);
            // The leaves the lane left, and its current one if its ray ended. A ray's last
            // step may enter a leaf only to end there: nothing free to mark, and a slot
            // would give the map an empty leaf.
            for j in first..cur + usize::from(ended >> l & 1 != 0) {
                let words = &self.words[j].0;
                if words.iter().fold(0, |a, &w| a | w) != 0 {
                    let slot = self.cache.slot_for(self.packed.unpack(self.keys[j]).shr(3));
                    crate::prefetch::prefetch(std::slice::from_ref(&slot.free), 0);
                    flush.push((slot, j));
                }
            }
        }
        for &(slot, j) in &flush {
            let at = self.words[j].0.as_mut_ptr().cast::<__m256i>();
            let to = slot.free.as_ptr().cast::<__m256i>().cast_mut();
            // SAFETY: an `Entry` is 8 u64, two 32-byte vectors, aligned to 64. `free` is
            // eight AtomicU64 of the same layout, at the start of a `Slot`, which is
            // aligned to 64. Only the task holding this cache's table accesses the table's
            // slots until it is released (see `FrameMarks`), so this plain
            // read-modify-write races with nothing, as `Slot::or_free`'s does not.
            unsafe {
                for k in 0..2 {
                    let (at, to) = (at.add(k), to.add(k));
                    _mm256_store_si256(
                        to,
                        _mm256_or_si256(_mm256_load_si256(to), _mm256_load_si256(at)),
                    );
                    _mm256_store_si256(at, _mm256_setzero_si256());
                }
            }
        }
        flush.clear();
        self.flush = flush;
        for (l, &e) in entry.iter().enumerate() {
            let (first, cur) = (l * RING, e as usize);
            if ended >> l & 1 != 0 {
                plane[l] = 0;
            } else if cur != first {
                // Its current leaf goes on in its first entry. (Its key needs no copy:
                // the next burst's first step stores it again.)
                self.words[first] = std::mem::take(&mut self.words[cur]);
            }
        }
        for l in BitIter(u64::from(hit)) {
            self.cache.set_hit(self.packed.unpack(p[l] as u64));
        }
        self.entry = from_array(std::array::from_fn(|l| (l * RING) as i64));
        self.plane = from_array(plane);
    }

    fn hit_at(&mut self, p: u64) {
        self.cache.set_hit(self.packed.unpack(p));
    }
}

/// The sparse walk's `k` steps from crossings `t` and [`Packed`] voxels `p`, for
/// [`SparseMarks`]: each step ORs the lane's voxel into its `plane` (live lanes only),
/// stores the plane and the voxel in the lane's `entry` of `at` (words, keys), and moves
/// the lane to its next entry when the step leaves the leaf. Not inlined, as `walk_steps`.
///
/// # Safety
/// Every lane's `entry` must stay inside `at`'s entries for `k` steps: a live lane moves
/// to its next at most once a step, an idle lane (increments 0) not at all. The CPU must
/// have AVX2.
#[inline(never)]
#[target_feature(enable = "avx2,bmi1,bmi2")]
#[allow(clippy::too_many_arguments)]
unsafe fn sparse_steps(
    k: i64,
    t: &mut [__m256i; 3],
    p: &mut __m256i,
    fixed: &Fixed,
    live: __m256i,
    entry: &mut __m256i,
    plane: &mut __m256i,
    (words, keys): (*mut u64, *mut u64),
) {
    const _: () = assert!(Packed::F == 21);
    let seven = _mm256_set1_epi64x(7);
    let row = _mm256_set1_epi64x(7 << 3);
    let leaf = _mm256_set1_epi64x(Packed::LEAF as i64);
    let z_field = _mm256_set1_epi64x(Packed::Z_FIELD as i64);
    let one = _mm256_and_si256(live, _mm256_set1_epi64x(1));
    let zero = _mm256_setzero_si256();
    let (mut tv, mut pv, mut e, mut pl) = (*t, *p, *entry, *plane);
    for _ in 0..k {
        let xy = _mm256_or_si256(
            _mm256_and_si256(pv, seven),
            _mm256_and_si256(_mm256_srli_epi64::<18>(pv), row),
        );
        pl = _mm256_or_si256(pl, _mm256_sllv_epi64(one, xy));
        let word = _mm256_add_epi64(
            _mm256_slli_epi64::<3>(e),
            _mm256_and_si256(_mm256_srli_epi64::<42>(pv), seven),
        );
        let (wa, pa, va) = (to_array(word), to_array(pl), to_array(pv));
        for l in 0..4 {
            // SAFETY: the lane's entry is inside `at` (the caller's promise), and `word`
            // is 8 entry + z with z < 8.
            unsafe {
                *words.add(wa[l] as usize) = pa[l] as u64;
                *keys.add((wa[l] >> 3) as usize) = va[l] as u64;
            }
        }
        let (next, inc) = step(tv, fixed);
        tv = next;
        let was = pv;
        pv = _mm256_add_epi64(pv, inc);
        let moved = _mm256_xor_si256(was, pv);
        let same_leaf = _mm256_cmpeq_epi64(_mm256_and_si256(moved, leaf), zero);
        let same_plane = _mm256_cmpeq_epi64(_mm256_and_si256(moved, z_field), zero);
        pl = _mm256_and_si256(pl, _mm256_and_si256(same_leaf, same_plane));
        // Lanes that left their leaf (all ones, -1) move to their next entry.
        e = _mm256_sub_epi64(e, _mm256_xor_si256(same_leaf, _mm256_set1_epi64x(-1)));
    }
    (*t, *p, *entry, *plane) = (tv, pv, e, pl);
}
