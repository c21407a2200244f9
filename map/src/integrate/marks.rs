//! The per-frame mark tables ([`FrameMarks`]): which voxels this frame's rays crossed
//! (free) and ended in (hit), per touched leaf, kept apart from the map until the update.

use crate::coord::VoxelCoord;
use crate::grid::{leaf_offset, NodeLeaves};
use crate::pages::{Zeroed, HUGE_PAGE};
use crossbeam_utils::CachePadded;
use rayon::prelude::*;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering::*};
use std::sync::OnceLock;

/// Leaves per node edge (a node is 16^3 leaves, 128^3 voxels).
pub(crate) const CELL_LOG2: u32 = 4;
pub(crate) const CELL_ENTRIES: usize = 1 << (3 * CELL_LOG2);
/// Pool chunks of one huge page each (see [`Zeroed`]).
pub(crate) const SLOT_CHUNK: usize = HUGE_PAGE / std::mem::size_of::<Slot>();
pub(crate) const ENTRIES_CHUNK: usize = HUGE_PAGE / std::mem::size_of::<NodeEntries>();

/// Free and hit marks of one 8x8x8 leaf, bit `x | y << 3 | z << 6` as in a leaf. Aligned
/// to 64 bytes, so each of the two is one cache line and the vector walks OR it with
/// aligned accesses.
#[derive(bytemuck::Zeroable)]
#[repr(C, align(64))]
pub(crate) struct Slot {
    pub(crate) free: [AtomicU64; 8],
    pub(crate) hit: [AtomicU64; 8],
}

impl Slot {
    /// OR free marks in: plain loads and stores, no test first, as only the task holding
    /// the slot's table writes it, and the line is about to be read anyway.
    #[inline]
    pub(crate) fn or_free(&self, bits: &[u64; 8]) {
        for (w, &b) in self.free.iter().zip(bits) {
            w.store(w.load(Relaxed) | b, Relaxed);
        }
    }

    /// Ask for the slot's two cache lines to be loaded, for a loop that reads it a few
    /// iterations later. Only speed changes.
    #[inline]
    pub(crate) fn prefetch(&self) {
        crate::prefetch::prefetch(std::slice::from_ref(&self.free), 0);
        crate::prefetch::prefetch(std::slice::from_ref(&self.hit), 0);
    }

    /// OR `other`'s marks into this one's, leaving `other` zero. Only between phases,
    /// when no walk writes.
    pub(crate) fn absorb(&self, other: &Slot) {
        let pairs = self.free.iter().zip(&other.free);
        for (w, o) in pairs.chain(self.hit.iter().zip(&other.hit)) {
            w.store(w.load(Relaxed) | o.load(Relaxed), Relaxed);
        }
        other.zero();
    }

    /// Word `w`'s free and hit marks, leaving them zero for the next frame: the update
    /// takes a slot's marks as it reads them, while its lines are in cache, so that no
    /// pass over all the frame's slots (hundreds of MB at 60 m) has to zero them again.
    /// Only the task updating the slot's leaf reads or writes the slot.
    #[inline]
    pub(crate) fn take(&self, w: usize) -> (u64, u64) {
        let (free, hit) = (self.free[w].load(Relaxed), self.hit[w].load(Relaxed));
        if free | hit != 0 {
            self.free[w].store(0, Relaxed);
            self.hit[w].store(0, Relaxed);
        }
        (free, hit)
    }
}

// A node covers exactly one grid internal node, and both number their 16^3
// children x | y << 4 | z << 8: walking nodes and their entries in order is walking the
// grid's internal nodes and their children in order.
const _: () = assert!(3 + CELL_LOG2 == crate::grid::INTERNAL_TOTAL_LOG2);

/// The leaf entries of one node: slot id + 1, or 0.
#[derive(bytemuck::Zeroable)]
pub(crate) struct NodeEntries(pub(crate) [AtomicU32; CELL_ENTRIES]);

impl Zero for NodeEntries {
    fn zero(&self) {
        self.0.iter().for_each(|e| e.store(0, Relaxed));
    }

    fn is_zero(&self) -> bool {
        self.0.iter().all(|e| e.load(Relaxed) == 0)
    }
}

/// Pool items: valid all-zero, and zeroed in place.
pub(crate) trait Zero: bytemuck::Zeroable + Send + Sync {
    fn zero(&self);
    fn is_zero(&self) -> bool;
}

impl Zero for Slot {
    fn zero(&self) {
        self.free
            .iter()
            .chain(&self.hit)
            .for_each(|w| w.store(0, Relaxed));
    }

    fn is_zero(&self) -> bool {
        self.free
            .iter()
            .chain(&self.hit)
            .all(|w| w.load(Relaxed) == 0)
    }
}

/// A growable pool of zero-initialised `T`, handed out by id from any thread. Ids and
/// storage persist across frames; the items' readers leave them zero, and `restart` hands
/// the same ids out again.
pub(crate) struct Pool<T, const CHUNK: usize> {
    pub(crate) chunks: Vec<OnceLock<Zeroed<T>>>,
    /// On cache lines of its own: the threads bump it while they read the fields beside
    /// it on every lookup, and on their lines each bump took those from the other
    /// threads' caches.
    pub(crate) next: CachePadded<AtomicU32>,
}

impl<T, const CHUNK: usize> Pool<T, CHUNK> {
    /// Bytes of the chunks made so far.
    pub(crate) fn memory_bytes(&self) -> usize {
        self.chunks.iter().filter(|c| c.get().is_some()).count() * CHUNK * std::mem::size_of::<T>()
    }
}

impl<T, const CHUNK: usize> Default for Pool<T, CHUNK> {
    fn default() -> Self {
        Self {
            chunks: Vec::new(),
            next: CachePadded::new(AtomicU32::new(0)),
        }
    }
}

impl<T: Zero, const CHUNK: usize> Pool<T, CHUNK> {
    pub(crate) fn reserve(&mut self, n: usize) {
        let want = n.div_ceil(CHUNK);
        while self.chunks.len() < want {
            self.chunks.push(OnceLock::new());
        }
    }

    pub(crate) fn alloc(&self) -> u32 {
        let id = self.next.fetch_add(1, Relaxed);
        self.get_or_init(id);
        id
    }

    /// Reserve `n` consecutive ids at once; each must be initialised with `get_or_init`
    /// before use. Ids reserved but never used stay zero, and are cleared like used ones.
    pub(crate) fn reserve_ids(&self, n: u32) -> Range<u32> {
        let first = self.next.fetch_add(n, Relaxed);
        first..first + n
    }

    #[inline]
    pub(crate) fn get_or_init(&self, id: u32) -> &T {
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
    pub(crate) fn get(&self, id: u32) -> &T {
        let id = id as usize;
        &self.chunks[id / CHUNK].get().expect("allocated id")[id % CHUNK]
    }

    pub(crate) fn used(&self) -> u32 {
        self.next.load(Relaxed)
    }

    /// Hand ids out from the first again. The items used must be zero by now (checked in
    /// debug builds): their readers zero them while they have them in cache, where a pass
    /// of its own here went over memory long out of the cache.
    pub(crate) fn restart(&mut self) {
        if cfg!(debug_assertions) {
            let n = self.used() as usize;
            for (c, chunk) in self.chunks[..n.div_ceil(CHUNK)].iter().enumerate() {
                if let Some(items) = chunk.get() {
                    let end = (n - c * CHUNK).min(CHUNK);
                    assert!(
                        items[..end].iter().all(T::is_zero),
                        "a used item left marked"
                    );
                }
            }
        }
        self.next.store(0, Relaxed);
    }
}

/// The id stored in a table's `entry` (as id + 1), allocated on first use. No other task
/// writes the table meanwhile, so a plain load and store suffice.
#[inline]
pub(crate) fn claim(entry: &AtomicU32, alloc: impl FnOnce() -> u32) -> u32 {
    match entry.load(Relaxed) {
        0 => {
            let id = alloc();
            entry.store(id + 1, Relaxed);
            id
        }
        e => e - 1,
    }
}

/// The per-frame mark tables, one per pool thread: a dense array of nodes over the
/// frame's bounding box, each pointing to the node's leaf entries, each pointing to a
/// [`Slot`]. Only touched leaves get a slot; slots are contiguous, so the merge pass walks
/// a compact list.
///
/// A table is written by one task at a time: [`FrameMarks::cache`] takes one, and dropping
/// the cache gives it back. So marks are plain read-modify-writes, not locked ones. A
/// locked OR holds back every later load until its cache line arrives; at 60 m, where most
/// marks miss cache, that was a quarter of the walk. A leaf walked from several tables
/// has a slot in each, and [`FrameMarks::leaves_in_order`] ORs them into one. The tables
/// cost little: rayon gives each thread long runs of neighbouring chunks, and rays sorted
/// by direction, so the tables share leaves only near the sensor.
#[derive(Default)]
pub(crate) struct FrameMarks {
    pub(crate) lo: VoxelCoord,
    pub(crate) nodes_dim: [usize; 3],
    /// Coarse nodes of the box.
    pub(crate) nnodes: usize,
    /// Table t's nodes are `nodes[t * nnodes..][..nnodes]`: [`NodeEntries`] id + 1, or 0.
    pub(crate) nodes: Vec<AtomicU32>,
    /// Whether each table is held by a live [`LeafCache`].
    pub(crate) taken: Vec<AtomicBool>,
    /// Per table, the slot ids its last cache reserved and left unused (start << 32 |
    /// end), for its next: a task's leftover batch is not lost, so that a batch can be
    /// large and only the tables' last batches stay unused. Read and written only by the
    /// table's holder.
    pub(crate) spare: Vec<AtomicU64>,
    pub(crate) entries: Pool<NodeEntries, ENTRIES_CHUNK>,
    pub(crate) slots: Pool<Slot, SLOT_CHUNK>,
}

/// A task's hold on one table of the [`FrameMarks`], with its recent lookups: the last
/// node's entries, and a direct-mapped cache of leaves (by the low bits of their coordinates) to
/// slots. Sorted rays revisit the same leaves near the sensor over and over; a hit here
/// skips the table walk.
pub(crate) struct LeafCache<'a> {
    pub(crate) marks: &'a FrameMarks,
    pub(crate) table: usize,
    pub(crate) node: usize,
    pub(crate) node_entries: Option<u32>,
    pub(crate) leaves: [Option<(VoxelCoord, &'a Slot)>; LEAF_CACHE],
    /// Slot ids this table has reserved and not yet used: one shared counter increment
    /// per [`SLOT_BATCH`] new leaves instead of one per leaf, which at 60 m (a new slot
    /// every few steps) made the threads fight over the counter's cache line; and each
    /// thread's new slots lie together.
    pub(crate) spare_slots: Range<u32>,
}

/// Slot ids a table reserves at once.
pub(crate) const SLOT_BATCH: u32 = 512;

/// Leaves in a [`LeafCache`], 16 per axis (96 KiB, in L2). A chunk's rays cross about
/// 170 leaves each at 60 m, in a cone wider than 8 leaves: with 512 (8 per axis), the
/// AVX-512 sparse walk's ray phase took 1539-1805 ms against 1267-1367 ms (random 500k
/// 60 m, one thread, three alternated runs).
pub(crate) const LEAF_CACHE: usize = 4096;

#[inline]
pub(crate) fn leaf_cache_index(b: VoxelCoord) -> usize {
    ((b.x & 15) | (b.y & 15) << 4 | (b.z & 15) << 8) as usize
}

impl FrameMarks {
    /// Bytes of the tables and pools, as allocated.
    pub(crate) fn memory_bytes(&self) -> usize {
        self.nodes.capacity() * 4
            + self.taken.capacity()
            + self.spare.capacity() * 8
            + self.entries.memory_bytes()
            + self.slots.memory_bytes()
    }

    /// Prepare for a frame whose voxels lie in `[lo, hi]`, cast on `tables` threads.
    pub(crate) fn reset(&mut self, lo: VoxelCoord, hi: VoxelCoord, tables: usize) {
        let tables = tables.max(1);
        self.lo = lo.shr(3 + CELL_LOG2).shl(3 + CELL_LOG2);
        let d = hi.shr(3 + CELL_LOG2) - lo.shr(3 + CELL_LOG2);
        self.nodes_dim = [d.x as usize + 1, d.y as usize + 1, d.z as usize + 1];
        self.nnodes = self.nodes_dim.iter().product::<usize>();
        self.nodes.clear();
        self.nodes
            .resize_with(self.nnodes * tables, || AtomicU32::new(0));
        self.taken.clear();
        self.taken.resize_with(tables, || AtomicBool::new(false));
        self.spare.clear();
        self.spare.resize_with(tables, || AtomicU64::new(0));
        self.entries.reserve(self.nnodes * tables);
        // Each table may leave a batch of reserved ids unused.
        self.slots
            .reserve((self.nnodes * CELL_ENTRIES + SLOT_BATCH as usize) * tables);
    }

    /// Take a free table for one task. Each thread holds at most one cache at a time and
    /// there are as many tables as threads, so one is free; the thread's own index is tried
    /// first, so that a thread keeps finding its own nodes' entries.
    pub(crate) fn cache(&self) -> LeafCache<'_> {
        let n = self.taken.len();
        let first = rayon::current_thread_index().unwrap_or(0);
        let mut i = 0;
        let table = loop {
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
        let spare = self.spare[table].load(Relaxed);
        LeafCache {
            marks: self,
            table,
            node: 0,
            node_entries: None,
            leaves: [None; LEAF_CACHE],
            spare_slots: (spare >> 32) as u32..spare as u32,
        }
    }

    /// Run `f` with a cache of its own ([`Self::cache`]). Not inlined: a cache holds
    /// [`LEAF_CACHE`] leaves (96 KiB), which, inlined into a rayon task, sat in each level
    /// of rayon's recursion and overflowed a worker's 2 MiB stack.
    #[inline(never)]
    pub(crate) fn with_cache<R>(&self, f: impl FnOnce(&mut LeafCache<'_>) -> R) -> R {
        f(&mut self.cache())
    }

    pub(crate) fn slot(&self, s: u32) -> &Slot {
        self.slots.get(s)
    }

    /// Every touched leaf's slot, per node in (z, y, x) order of nodes and, within
    /// a node, of leaves: a node is one internal node of the map (see `merge`), and its
    /// leaves are named by their index in it, as the map's nodes name their children. A
    /// leaf with slots in several tables gets the others' marks ORed into the first. The
    /// nodes are read in parallel, and their entries left zero (the frame's marks are then
    /// only in the listed slots). Call once a frame, between its phases, when no cache is
    /// live.
    pub(crate) fn leaves_in_order(&self) -> Vec<NodeLeaves<u32>> {
        (0..self.nnodes)
            .into_par_iter()
            .map(|c| self.node_leaves(c))
            .collect()
    }

    /// The touched leaves of node `c`, as [`FrameMarks::leaves_in_order`] lists them.
    fn node_leaves(&self, c: usize) -> NodeLeaves<u32> {
        let [dx, dy, _] = self.nodes_dim;
        let (n, tables) = (self.nnodes, self.taken.len());
        let node = VoxelCoord::new(
            (c % dx) as i32,
            (c / dx % dy) as i32,
            (c / (dx * dy)) as i32,
        );
        let node = self.lo + node.shl(3 + CELL_LOG2);
        let entries: Vec<&NodeEntries> = (0..tables)
            .filter_map(|l| match self.nodes[l * n + c].load(Relaxed) {
                0 => None,
                b => Some(self.entries.get(b - 1)),
            })
            .collect();
        let children = match entries[..] {
            [] => Vec::new(),
            [only] => {
                // One table's, as most nodes are away from the sensor: no slots to join,
                // and each entry written whether used or not, counted if used (a coin toss
                // for the branch predictor in a sparse frame).
                let ids = &only.0;
                let used = ids.iter().filter(|s| s.load(Relaxed) != 0).count();
                let mut out = Vec::with_capacity(used + 1);
                let room = &mut out.spare_capacity_mut()[..used + 1];
                let mut k = 0;
                for (e, s) in ids.iter().enumerate() {
                    let s = s.load(Relaxed);
                    room[k].write((e as u16, s.wrapping_sub(1)));
                    k += usize::from(s != 0);
                }
                // SAFETY: the loop wrote `room[k]` before every increment of `k` (and `k`
                // ends at `used`, the entries it counted), so the first `k` elements are
                // initialised.
                unsafe { out.set_len(k) };
                only.zero();
                out
            }
            _ => {
                let out = (0..CELL_ENTRIES)
                    .filter_map(|e| {
                        let mut ids = (entries.iter())
                            .map(|b| b.0[e].load(Relaxed))
                            .filter(|&s| s != 0);
                        let first = ids.next()? - 1;
                        let slot = self.slots.get(first);
                        ids.for_each(|s| slot.absorb(self.slots.get(s - 1)));
                        Some((e as u16, first))
                    })
                    .collect();
                entries.iter().for_each(|b| b.zero());
                out
            }
        };
        NodeLeaves { node, children }
    }

    /// Ready the pools for the next frame, keeping their memory. Everything this frame
    /// used must be zero again: the tables' entries by [`Self::leaves_in_order`], each
    /// leaf's slot by the update ([`Slot::take`]) or by the slot that absorbed it.
    pub(crate) fn clear_used(&mut self) {
        self.slots.restart();
        self.entries.restart();
    }
}

impl<'a> LeafCache<'a> {
    #[inline]
    pub(crate) fn slot_for(&mut self, leaf: VoxelCoord) -> &'a Slot {
        let ci = leaf_cache_index(leaf);
        if let Some((b, slot)) = self.leaves[ci] {
            if b == leaf {
                return slot;
            }
        }
        let slot = self.slot_lookup(leaf);
        self.leaves[ci] = Some((leaf, slot));
        slot
    }

    #[inline(never)]
    pub(crate) fn slot_lookup(&mut self, leaf: VoxelCoord) -> &'a Slot {
        let marks = self.marks;
        let r = leaf - marks.lo.shr(3);
        let (x, y, z) = (r.x as usize, r.y as usize, r.z as usize);
        let node = (x >> CELL_LOG2)
            + marks.nodes_dim[0] * ((y >> CELL_LOG2) + marks.nodes_dim[1] * (z >> CELL_LOG2));
        let entries = match self.node_entries {
            Some(b) if self.node == node => b,
            _ => {
                let b = claim(&marks.nodes[self.table * marks.nnodes + node], || {
                    marks.entries.alloc()
                });
                self.node = node;
                self.node_entries = Some(b);
                b
            }
        };
        let m = (1 << CELL_LOG2) - 1;
        let e = (x & m) | (y & m) << CELL_LOG2 | (z & m) << (2 * CELL_LOG2);
        let entry = &marks.entries.get(entries).0[e];
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

    /// OR a leaf's free marks into its slot ([`Slot::or_free`]).
    #[inline]
    pub(crate) fn or_free(&mut self, leaf: VoxelCoord, bits: &[u64; 8]) {
        self.slot_for(leaf).or_free(bits);
    }

    #[inline]
    pub(crate) fn set_hit(&mut self, v: VoxelCoord) {
        let slot = self.slot_for(v.shr(3));
        let i = leaf_offset(v);
        let w = &slot.hit[i >> 6];
        w.store(w.load(Relaxed) | 1u64 << (i & 63), Relaxed);
    }
}

impl Drop for LeafCache<'_> {
    fn drop(&mut self) {
        let Range { start, end } = self.spare_slots;
        self.marks.spare[self.table].store(u64::from(start) << 32 | u64::from(end), Relaxed);
        // Release: the next task to take this table, on any thread, sees these marks and
        // the spare ids.
        self.marks.taken[self.table].store(false, Release);
    }
}
