//! The sparse VDB-style grid: a hash-mapped root over fixed-size internal nodes over
//! 8x8x8 leaves.
//!
//! ```text
//! root     HashMap<internal key, internal index>        one entry per 128^3 voxels
//! internal 16^3 child slots + child mask (4096 bits)    children are leaf indices
//! leaf     active + marked masks (512 bits each), 8^3 values   stored in a pooled arena
//! ```
//!
//! Leaves live in a [`LeafPool`] of fixed-size chunks allocated zeroed, so a new leaf costs
//! no allocator call and the map never moves a leaf once created. Leaf indices are stable
//! and let the integration pass update disjoint leaves in parallel without `unsafe`.
//! Voxel `(x, y, z)` has in-leaf offset `x | y << 3 | z << 6` (`x`, `y`, `z` taken mod 8).

use crate::coord::VoxelCoord;
use crate::mask::BitIter;
use crate::pages::{Zeroed, HUGE_PAGE};
pub use crate::tree::*;
use hashbrown::HashMap;

/// Leaves per pool chunk: as many `Leaf<i8>`, in whole [`UPDATE_SPAN`]s, as fill one
/// huge page (3272 of 3276 640-byte leaves). Each chunk is its own mapping ([`Zeroed`]):
/// with chunks of 256 leaves a 60 m frame made 7000 mmap calls in the merge; 1024 cut the
/// random 500k 60 m merge from 133-195 to 111-118 ms (1 and 2 threads, interleaved runs).
const POOL_CHUNK: usize =
    HUGE_PAGE / std::mem::size_of::<Leaf<i8>>() / SPANS_PER_CHUNK * SPANS_PER_CHUNK;
/// Update spans per pool chunk: spans of 512 leaves left 204 of 3276 leaves of each chunk
/// unused (6%) once leaves grew to 640 bytes.
const SPANS_PER_CHUNK: usize = 8;
/// Leaves per parallel task of [`LeafPool::par_update`].
const UPDATE_SPAN: usize = POOL_CHUNK / SPANS_PER_CHUNK;
const _: () = assert!(UPDATE_SPAN >= 256);

#[inline]
fn internal_key(v: VoxelCoord) -> VoxelCoord {
    v.shr(INTERNAL_TOTAL_LOG2)
}

#[inline]
fn child_index(v: VoxelCoord) -> usize {
    let l = v.shr(LEAF_LOG2);
    let m = (1 << INTERNAL_LOG2) - 1;
    ((l.x & m) | (l.y & m) << INTERNAL_LOG2 | (l.z & m) << (2 * INTERNAL_LOG2)) as usize
}

/// The origin of child `child` (`x | y << 4 | z << 8`, in leaves) of the internal node at
/// `node`.
///
/// # Panics
/// If `child` is not below [`INTERNAL_CHILDREN`].
#[inline]
pub fn child_origin(node: VoxelCoord, child: u16) -> VoxelCoord {
    assert!(
        usize::from(child) < INTERNAL_CHILDREN,
        "child index out of range"
    );
    let (c, m) = (i32::from(child), (1 << INTERNAL_LOG2) - 1);
    let l = VoxelCoord::new(c & m, c >> INTERNAL_LOG2 & m, c >> (2 * INTERNAL_LOG2));
    node + l.shl(LEAF_LOG2)
}

/// Leaves of one internal node, for [`Grid::leaf_indices_or_insert`]: the node's origin (a
/// multiple of its 128 voxels on each axis) and its children (`x | y << 4 | z << 8`, in
/// leaves, below [`INTERNAL_CHILDREN`]), each with a tag.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NodeLeaves<T> {
    pub node: VoxelCoord,
    pub children: Vec<(u16, T)>,
}

/// Values a grid can hold: plain old data whose all-zero pattern is the background.
pub trait GridValue: bytemuck::Pod + Send + Sync + PartialEq + std::fmt::Debug {}
impl<T: bytemuck::Pod + Send + Sync + PartialEq + std::fmt::Debug> GridValue for T {}

struct Internal {
    origin: VoxelCoord,
    child_mask: [u64; INTERNAL_CHILDREN / 64],
    children: [u32; INTERNAL_CHILDREN],
}

/// Leaves in zeroed chunks of [`POOL_CHUNK`]; indices are stable for the pool's life.
/// The slots of removed leaves ([`Grid::remove_node`]) are zeroed and handed out again
/// before the pool grows, so that a map kept within a memory budget stays in the memory
/// it has.
pub struct LeafPool<V> {
    chunks: Vec<Zeroed<Leaf<V>>>,
    len: usize,
    /// Zeroed slots below `len`, free for new leaves.
    free: Vec<u32>,
}

/// The slots of a batch of new leaves ([`LeafPool::take_n`]): a run of fresh slots at the
/// pool's end, or, where removed leaves left slots, those first.
enum NewSlots {
    Run(u32),
    List(Vec<u32>),
}

impl NewSlots {
    #[inline]
    fn get(&self, k: u32) -> u32 {
        match self {
            Self::Run(first) => first + k,
            Self::List(v) => v[k as usize],
        }
    }
}

impl<V: GridValue> LeafPool<V> {
    fn new() -> Self {
        Self {
            chunks: Vec::new(),
            len: 0,
            free: Vec::new(),
        }
    }

    fn push_zeroed(&mut self) -> u32 {
        match self.free.pop() {
            Some(i) => i,
            None => self.push_zeroed_n(1),
        }
    }

    /// `n` zeroed slots: free ones first (lowest first), then new ones at the end.
    fn take_n(&mut self, n: usize) -> NewSlots {
        if self.free.is_empty() {
            return NewSlots::Run(self.push_zeroed_n(n));
        }
        let reused = n.min(self.free.len());
        // `free` is kept in descending order: its lowest slots are at its end.
        let mut list: Vec<u32> = self.free.split_off(self.free.len() - reused);
        list.reverse();
        if n > reused {
            let first = self.push_zeroed_n(n - reused);
            list.extend(first..first + (n - reused) as u32);
        }
        NewSlots::List(list)
    }

    /// Zero the slots and make them free for new leaves.
    fn release(&mut self, slots: &[u32]) {
        for &i in slots {
            *self.get_mut(i) = bytemuck::Zeroable::zeroed();
        }
        self.free.extend_from_slice(slots);
        self.free.sort_unstable_by(|a, b| b.cmp(a));
    }

    /// `n` more zeroed leaves; returns the first one's index. The chunks they need are
    /// mapped together ([`Zeroed::new_many`]).
    fn push_zeroed_n(&mut self, n: usize) -> u32 {
        let first = self.len;
        let want = first + n;
        let have = self.chunks.len() * POOL_CHUNK;
        if want > have {
            let mut more = (want - have).div_ceil(POOL_CHUNK);
            if self.chunks.is_empty() {
                // A small map's leaves: its first chunk comes from the allocator, and pays
                // for the pages it touches, not a zeroed 2 MiB page (0.3 ms of a 50k-point
                // 6 m frame). Where the allocator keeps freed memory (the service), it may
                // be memory freed before, which the allocator clears: once per map.
                self.chunks.push(Zeroed::from_allocator(POOL_CHUNK));
                more -= 1;
            }
            self.chunks.extend(Zeroed::new_many(POOL_CHUNK, more));
        }
        self.len = want;
        first as u32
    }

    #[inline]
    pub fn get(&self, i: u32) -> &Leaf<V> {
        let i = i as usize;
        &self.chunks[i / POOL_CHUNK][i % POOL_CHUNK]
    }

    #[inline]
    pub fn get_mut(&mut self, i: u32) -> &mut Leaf<V> {
        let i = i as usize;
        &mut self.chunks[i / POOL_CHUNK][i % POOL_CHUNK]
    }

    /// Slots in use or free: one past the highest leaf index.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Leaves in use.
    pub fn live(&self) -> usize {
        self.len - self.free.len()
    }

    /// Apply `f` to each listed leaf, in parallel across chunks, and sum what it returns.
    /// `items` must be sorted by leaf index with no index twice; each leaf is then borrowed
    /// mutably exactly once. `ahead` is told of each item a few before `f` takes it (to
    /// prefetch what `f` will read for it).
    pub fn par_update<T: Sync>(
        &mut self,
        items: &[(u32, T)],
        ahead: impl Fn(&T) + Sync,
        f: impl Fn(&mut Leaf<V>, &T) -> u64 + Sync,
    ) -> u64 {
        /// Items told to `ahead` before their turn.
        const AHEAD: usize = 8;
        use rayon::prelude::*;
        assert!(
            items.windows(2).all(|w| w[0].0 < w[1].0),
            "par_update: leaf indices must be strictly increasing"
        );
        // Split `items` into one run per span of leaves, then hand each run its span.
        let mut runs: Vec<(usize, &[(u32, T)])> = Vec::new();
        let mut rest = items;
        while let Some(first) = rest.first() {
            let c = first.0 as usize / UPDATE_SPAN;
            let n = rest.partition_point(|it| (it.0 as usize) / UPDATE_SPAN == c);
            runs.push((c, &rest[..n]));
            rest = &rest[n..];
        }
        // Chunks hold whole spans, so span k is the k-th of all chunks' spans.
        let mut spans: Vec<Option<&mut [Leaf<V>]>> = self
            .chunks
            .iter_mut()
            .flat_map(|c| c.chunks_mut(UPDATE_SPAN))
            .map(Some)
            .collect();
        type Work<'w, V, T> = Vec<(&'w mut [Leaf<V>], &'w [(u32, T)])>;
        let work: Work<'_, V, T> = runs
            .into_iter()
            .map(|(c, run)| (spans[c].take().expect("one run per span"), run))
            .collect();
        work.into_par_iter()
            .with_max_len(8)
            .map(|(span, run)| {
                run.iter().take(AHEAD).for_each(|(_, t)| ahead(t));
                run.iter()
                    .enumerate()
                    .map(|(k, (i, t))| {
                        if let Some((_, t)) = run.get(k + AHEAD) {
                            ahead(t);
                        }
                        f(&mut span[*i as usize % UPDATE_SPAN], t)
                    })
                    .sum::<u64>()
            })
            .sum()
    }
}

/// A sparse grid of `V` over the signed 32-bit voxel index space.
pub struct Grid<V> {
    root: HashMap<VoxelCoord, u32>,
    internals: Vec<Box<Internal>>,
    leaves: LeafPool<V>,
}

impl<V: GridValue> Default for Grid<V> {
    fn default() -> Self {
        Self::new()
    }
}

impl<V: GridValue> Grid<V> {
    pub fn new() -> Self {
        Self {
            root: HashMap::new(),
            internals: Vec::new(),
            leaves: LeafPool::new(),
        }
    }

    /// Leaves in the grid.
    pub fn leaf_count(&self) -> usize {
        self.leaves.live()
    }

    /// Leaf slots, in use or free: one past the highest leaf index.
    pub fn leaf_slots(&self) -> usize {
        self.leaves.len()
    }

    /// Internal nodes.
    pub fn node_count(&self) -> usize {
        self.internals.len()
    }

    /// Bytes the grid's leaves and nodes take where memory is budgeted: its leaves in use
    /// and its nodes, not free slots (which new leaves take before the pool grows).
    pub fn live_bytes(&self) -> usize {
        self.leaves.live() * std::mem::size_of::<Leaf<V>>()
            + self.internals.len() * std::mem::size_of::<Internal>()
            + self.root.capacity() * (std::mem::size_of::<(VoxelCoord, u32)>() + 1)
    }

    /// The origins of the internal nodes, in no particular order.
    pub fn node_origins(&self) -> impl Iterator<Item = VoxelCoord> + '_ {
        self.internals.iter().map(|n| n.origin)
    }

    /// The leaves of the internal node at `node` (its origin), in block order; none where
    /// the grid has no such node.
    pub fn leaves_of_node(
        &self,
        node: VoxelCoord,
    ) -> impl Iterator<Item = (VoxelCoord, &Leaf<V>)> + '_ {
        let n = self
            .root
            .get(&internal_key(node))
            .map(|&ii| &*self.internals[ii as usize])
            .filter(|n| n.origin == node);
        n.into_iter().flat_map(move |n| self.node_leaves(n))
    }

    /// Remove the internal node at `node` (its origin) with its leaves, whose slots new
    /// leaves then take; returns the leaves removed (0 where there was no such node).
    /// Other nodes' leaves keep their indices.
    pub fn remove_node(&mut self, node: VoxelCoord) -> usize {
        let key = internal_key(node);
        let Some(&ii) = self.root.get(&key) else {
            return 0;
        };
        if self.internals[ii as usize].origin != node {
            return 0;
        }
        self.root.remove(&key);
        let gone = self.internals.swap_remove(ii as usize);
        if let Some(moved) = self.internals.get(ii as usize) {
            self.root.insert(internal_key(moved.origin), ii);
        }
        let slots: Vec<u32> = Self::node_leaf_indices(&gone).map(|(_, i)| i).collect();
        self.leaves.release(&slots);
        slots.len()
    }

    /// Active voxels.
    pub fn active_count(&self) -> u64 {
        (0..self.leaves.len() as u32)
            .map(|i| u64::from(self.leaves.get(i).active.count()))
            .sum()
    }

    /// Bytes this grid holds on the heap: leaf chunks, internal nodes, root table.
    pub fn memory_bytes(&self) -> usize {
        let leaf = self.leaves.chunks.len() * POOL_CHUNK * std::mem::size_of::<Leaf<V>>()
            + self.leaves.chunks.capacity() * std::mem::size_of::<Box<[Leaf<V>]>>();
        let internal = self.internals.len() * std::mem::size_of::<Internal>()
            + self.internals.capacity() * std::mem::size_of::<Box<Internal>>();
        let root = self.root.capacity() * (std::mem::size_of::<(VoxelCoord, u32)>() + 1);
        leaf + internal + root
    }

    /// Index of the leaf with the given origin, if present.
    pub fn leaf_index(&self, origin: VoxelCoord) -> Option<u32> {
        let ii = *self.root.get(&internal_key(origin))?;
        self.internals[ii as usize].child(child_index(origin))
    }

    pub fn leaf(&self, index: u32) -> &Leaf<V> {
        self.leaves.get(index)
    }

    pub fn leaf_mut(&mut self, index: u32) -> &mut Leaf<V> {
        self.leaves.get_mut(index)
    }

    pub fn leaf_pool_mut(&mut self) -> &mut LeafPool<V> {
        &mut self.leaves
    }

    /// The value at `v` if active.
    pub fn get(&self, v: VoxelCoord) -> Option<V> {
        let li = self.leaf_index(leaf_origin(v))?;
        self.leaves.get(li).get(leaf_offset(v))
    }

    /// Set `v` active with `value`, creating its leaf if needed; returns the leaf (for its
    /// owner's marks).
    pub fn set(&mut self, v: VoxelCoord, value: V) -> &mut Leaf<V> {
        let li = self.leaf_index_or_insert(leaf_origin(v), None);
        let leaf = self.leaves.get_mut(li);
        leaf.active.set(leaf_offset(v));
        leaf.values[leaf_offset(v)] = value;
        leaf
    }

    /// Index of the leaf at `origin`, created (all inactive) if absent. `hint` is a cached
    /// internal node (key, index) that is used when it matches and updated otherwise.
    pub fn leaf_index_or_insert(
        &mut self,
        origin: VoxelCoord,
        hint: Option<&mut (VoxelCoord, u32)>,
    ) -> u32 {
        self.find_or_make_leaf(origin, hint).0
    }

    /// [`Self::leaf_index_or_insert`], and whether the leaf is new.
    fn find_or_make_leaf(
        &mut self,
        origin: VoxelCoord,
        hint: Option<&mut (VoxelCoord, u32)>,
    ) -> (u32, bool) {
        let key = internal_key(origin);
        let ii = match hint {
            Some(h) if h.0 == key && (h.1 as usize) < self.internals.len() => h.1,
            other => {
                let ii = match self.root.get(&key) {
                    Some(&ii) => ii,
                    None => {
                        let ii = self.internals.len() as u32;
                        self.internals
                            .push(Internal::new(key.shl(INTERNAL_TOTAL_LOG2)));
                        self.root.insert(key, ii);
                        ii
                    }
                };
                if let Some(h) = other {
                    *h = (key, ii);
                }
                ii
            }
        };
        let ci = child_index(origin);
        if let Some(li) = self.internals[ii as usize].child(ci) {
            return (li, false);
        }
        let li = self.leaves.push_zeroed();
        let node = &mut self.internals[ii as usize];
        node.child_mask[ci >> 6] |= 1 << (ci & 63);
        node.children[ci] = li;
        (li, true)
    }

    /// [`Self::leaf_index_or_insert`] for many leaves at once, in parallel on the current
    /// rayon pool: `groups` of distinct leaves of one internal node each, no two groups of
    /// the same node. Returns, group after group, each leaf's index, its tag and whether
    /// the leaf is new: what one call per leaf, in this order, would give. Where two groups
    /// share a node, all are inserted one by one.
    ///
    /// # Panics
    /// If a group repeats a child, names one out of range, or gives a node origin that is
    /// not one.
    pub fn leaf_indices_or_insert<T: Copy + Send + Sync>(
        &mut self,
        groups: &[NodeLeaves<T>],
    ) -> Vec<(u32, (T, bool))> {
        use rayon::prelude::*;
        // Each group's node key, none for an empty group.
        let group_keys: Vec<Option<VoxelCoord>> = (groups.iter())
            .map(|g| {
                let key = internal_key(g.node);
                assert!(key.shl(INTERNAL_TOTAL_LOG2) == g.node, "not a node origin");
                (!g.children.is_empty()).then_some(key)
            })
            .collect();
        let mut keys: Vec<VoxelCoord> = group_keys.iter().flatten().copied().collect();
        keys.par_sort_unstable_by_key(|k| (k.z, k.y, k.x));
        if keys.windows(2).any(|w| w[0] == w[1]) {
            let leaves: Vec<(VoxelCoord, T)> = (groups.iter())
                .flat_map(|g| (g.children.iter()).map(|&(c, tag)| (child_origin(g.node, c), tag)))
                .collect();
            let mut hint = (VoxelCoord::new(i32::MIN, 0, 0), u32::MAX);
            return (leaves.into_iter())
                .map(|(o, tag)| {
                    let (l, new) = self.find_or_make_leaf(o, Some(&mut hint));
                    (l, (tag, new))
                })
                .collect();
        }
        // Each group's internal node, made where missing (in parallel: a node is 16 KiB
        // to zero) and numbered in the groups' order as one by one; then how many leaves
        // each group adds (all of them in a node just made: its memory is not read before
        // it is written, see `apply` in the update), and the first one's index.
        let old_nodes = self.internals.len();
        let missing: Vec<VoxelCoord> = (group_keys.iter().flatten())
            .filter(|&k| !self.root.contains_key(k))
            .copied()
            .collect();
        let made: Vec<Box<Internal>> = (missing.par_iter())
            .map(|k| Internal::new(k.shl(INTERNAL_TOTAL_LOG2)))
            .collect();
        for (&key, node) in missing.iter().zip(made) {
            self.root.insert(key, self.internals.len() as u32);
            self.internals.push(node);
        }
        let nodes: Vec<Option<usize>> = (group_keys.iter())
            .map(|k| Some(self.root[k.as_ref()?] as usize))
            .collect();
        let internals = &self.internals;
        let new: Vec<u32> = (groups.par_iter().zip(&nodes))
            .map(|(g, &ii)| {
                ii.map_or(0, |ii| {
                    if ii >= old_nodes {
                        return g.children.len() as u32;
                    }
                    let node = &internals[ii];
                    (g.children.iter())
                        .filter(|&&(c, _)| node.child(usize::from(c)).is_none())
                        .count() as u32
                })
            })
            .collect();
        let mut next = 0;
        let starts: Vec<u32> = (new.iter())
            .map(|&n| {
                next += n;
                next - n
            })
            .collect();
        let slots = self.leaves.take_n(next as usize);
        // The groups' nodes, each borrowed by its group alone (they are distinct).
        let mut mine: Vec<Option<&mut Internal>> = (0..groups.len()).map(|_| None).collect();
        let mut owner: Vec<(usize, usize)> = (nodes.iter().enumerate())
            .filter_map(|(g, ii)| Some(((*ii)?, g)))
            .collect();
        owner.sort_unstable();
        let mut owner = owner.into_iter().peekable();
        for (ii, node) in self.internals.iter_mut().enumerate() {
            if let Some((_, g)) = owner.next_if(|&(o, _)| o == ii) {
                mine[g] = Some(node);
            }
        }
        // Each group writes its own part of the output.
        let total = groups.iter().map(|g| g.children.len()).sum();
        let mut out = Vec::with_capacity(total);
        let mut rest = &mut out.spare_capacity_mut()[..total];
        let mut parts = Vec::with_capacity(groups.len());
        for g in groups {
            let (part, tail) = rest.split_at_mut(g.children.len());
            parts.push(part);
            rest = tail;
        }
        let added: Vec<u32> = (groups.par_iter().zip(mine).zip(parts).zip(&starts))
            .map(|(((g, node), part), &start)| {
                let Some(node) = node else { return 0 };
                let mut next = start;
                for (&(c, tag), at) in g.children.iter().zip(part.iter_mut()) {
                    let ci = usize::from(c);
                    let (l, new) = match node.child(ci) {
                        Some(l) => (l, false),
                        None => {
                            let l = slots.get(next);
                            node.child_mask[ci >> 6] |= 1 << (ci & 63);
                            node.children[ci] = l;
                            next += 1;
                            (l, true)
                        }
                    };
                    at.write((l, (tag, new)));
                }
                next - start
            })
            .collect();
        assert_eq!(added, new, "a group repeats a child");
        // SAFETY: the parts tile `out`'s first `total` elements, and each group wrote every
        // element of its part, which is as long as the group.
        unsafe { out.set_len(total) };
        out
    }

    /// Every leaf as (origin, leaf), in no particular order.
    pub fn leaves(&self) -> impl Iterator<Item = (VoxelCoord, &Leaf<V>)> + '_ {
        self.internals
            .iter()
            .flat_map(move |node| self.node_leaves(node))
    }

    /// Every leaf in block order: internal nodes by origin (z, y, x); within one, its eight
    /// blocks of [`BLOCK_LEAVES`] leaves (64^3 voxels) by origin (z, y, x); within a block,
    /// the leaves by origin (z, y, x). So each block's leaves come together, in the order of
    /// their in-block index ([`leaf_in_block`]), which is what snapshots index by. The order
    /// depends only on which leaves exist, not on the order they were made in, and costs a
    /// sort of the internal nodes only.
    pub fn leaves_in_block_order(&self) -> impl Iterator<Item = (VoxelCoord, &Leaf<V>)> + '_ {
        self.internals_in_block_order()
            .into_iter()
            .flat_map(move |node| self.node_leaves(node))
    }

    /// Every leaf as (origin, leaf index), in block order ([`Self::leaves_in_block_order`]),
    /// listed in parallel on the current rayon pool. Each internal node's share of the
    /// output is counted from its child mask and written in place: collecting a parallel
    /// iteration of unknown length instead (rayon's list of vectors, then a copy) took
    /// 51-63 ms for the 1.8 M leaves of the random 500k 60 m map.
    pub fn leaf_indices_in_block_order(&self) -> Vec<(VoxelCoord, u32)> {
        use rayon::prelude::*;
        let nodes = self.internals_in_block_order();
        let counts: Vec<usize> = (nodes.iter())
            .map(|n| n.child_mask.iter().map(|w| w.count_ones() as usize).sum())
            .collect();
        let mut out = vec![(VoxelCoord::default(), 0); counts.iter().sum()];
        let mut parts = Vec::with_capacity(nodes.len());
        let mut rest = out.as_mut_slice();
        for n in counts {
            let (part, tail) = rest.split_at_mut(n);
            parts.push(part);
            rest = tail;
        }
        parts.into_par_iter().zip(nodes).for_each(|(part, node)| {
            for (slot, leaf) in part.iter_mut().zip(Self::node_leaf_indices(node)) {
                *slot = leaf;
            }
        });
        out
    }

    /// `f` applied in parallel (on the current rayon pool) to the leaves that overlap the
    /// voxel box [lo, hi], keeping the `Some`s in block order. Internal nodes and leaves
    /// outside the box are passed over without reading them, so the cost follows the box,
    /// not the map.
    pub fn filter_map_leaves_in_box<'a, T: Send>(
        &'a self,
        lo: VoxelCoord,
        hi: VoxelCoord,
        f: impl Fn(VoxelCoord, &'a Leaf<V>) -> Option<T> + Sync + Send,
    ) -> Vec<T> {
        use rayon::prelude::*;
        // Does [o, o + size) overlap the box on every axis?
        let overlaps = |o: VoxelCoord, size: i64| {
            let (o, lo, hi) = (o.to_array(), lo.to_array(), hi.to_array());
            (0..3).all(|k| {
                i64::from(o[k]) <= i64::from(hi[k]) && i64::from(lo[k]) < i64::from(o[k]) + size
            })
        };
        let mut nodes = self.internals_in_block_order();
        nodes.retain(|n| overlaps(n.origin, 1 << INTERNAL_TOTAL_LOG2));
        nodes
            .par_iter()
            .flat_map_iter(|node| {
                self.node_leaves(node)
                    .filter(|(o, _)| overlaps(*o, 1 << LEAF_LOG2))
                    .filter_map(|(o, l)| f(o, l))
            })
            .collect()
    }

    fn internals_in_block_order(&self) -> Vec<&Internal> {
        let mut order: Vec<&Internal> = self.internals.iter().map(|n| &**n).collect();
        order.sort_unstable_by_key(|n| (n.origin.z, n.origin.y, n.origin.x));
        order
    }

    fn node_leaves<'a>(
        &'a self,
        node: &'a Internal,
    ) -> impl Iterator<Item = (VoxelCoord, &'a Leaf<V>)> + 'a {
        Self::node_leaf_indices(node).map(|(o, i)| (o, self.leaves.get(i)))
    }

    /// A node's leaves as (origin, leaf index), in block order.
    fn node_leaf_indices(node: &Internal) -> impl Iterator<Item = (VoxelCoord, u32)> + '_ {
        // Child index x | y << 4 | z << 8 (x, y, z in leaves, 0..16): a block's row of 8
        // leaves along x at (y, z) is one byte of the child mask.
        (0..8 * BLOCK_LEAVES / 8).flat_map(move |row| {
            let (block, r) = (row / 64, row % 64);
            let (bx, by, bz) = (block & 1, block >> 1 & 1, block >> 2);
            let (y, z) = (by * 8 + (r & 7), bz * 8 + (r >> 3));
            let at = y << 4 | z << 8 | (bx * 8);
            let bits = (node.child_mask[at / 64] >> (at % 64)) & 0xFF;
            BitIter(bits).map(move |b| {
                let ci = at + b;
                let o = node.origin
                    + VoxelCoord::new((bx * 8 + b) as i32, y as i32, z as i32).shl(LEAF_LOG2);
                (o, node.children[ci])
            })
        })
    }

    /// Every active voxel as (coordinate, value), in no particular order.
    pub fn active_voxels(&self) -> impl Iterator<Item = (VoxelCoord, V)> + '_ {
        self.leaves().flat_map(|(o, leaf)| {
            leaf.active
                .iter_ones()
                .map(move |i| (voxel_at(o, i), leaf.values[i]))
        })
    }

    /// A read accessor that caches the last leaf it visited.
    pub fn accessor(&self) -> Accessor<'_, V> {
        Accessor {
            grid: self,
            leaf_key: None,
            leaf: None,
        }
    }
}

impl Internal {
    fn new(origin: VoxelCoord) -> Box<Self> {
        Box::new(Self {
            origin,
            child_mask: [0; INTERNAL_CHILDREN / 64],
            children: [0; INTERNAL_CHILDREN],
        })
    }

    #[inline]
    fn child(&self, ci: usize) -> Option<u32> {
        (self.child_mask[ci >> 6] >> (ci & 63) & 1 != 0).then(|| self.children[ci])
    }
}

/// Cached read access: remembers the last leaf, so spatially coherent lookups (along a
/// ray, across a box) skip the root hash and the internal node. One per thread.
///
/// ```
/// use voxmap_map::{grid::Grid, coord::VoxelCoord};
/// let mut g = Grid::<i8>::new();
/// g.set(VoxelCoord::new(1, 2, 3), 5);
/// let mut acc = g.accessor();
/// assert_eq!(acc.get(VoxelCoord::new(1, 2, 3)), Some(5));
/// assert_eq!(acc.get(VoxelCoord::new(1, 2, 4)), None); // same leaf: no hash lookup
/// ```
pub struct Accessor<'a, V> {
    grid: &'a Grid<V>,
    leaf_key: Option<VoxelCoord>,
    leaf: Option<&'a Leaf<V>>,
}

impl<'a, V: GridValue> Accessor<'a, V> {
    /// The leaf holding `v`, if any.
    #[inline]
    pub fn leaf(&mut self, v: VoxelCoord) -> Option<&'a Leaf<V>> {
        let o = leaf_origin(v);
        if self.leaf_key != Some(o) {
            self.leaf_key = Some(o);
            self.leaf = self.grid.leaf_index(o).map(|li| self.grid.leaf(li));
        }
        self.leaf
    }

    #[inline]
    pub fn get(&mut self, v: VoxelCoord) -> Option<V> {
        self.leaf(v)?.get(leaf_offset(v))
    }
}

#[cfg(test)]
mod tests;
