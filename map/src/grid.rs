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
pub struct LeafPool<V> {
    chunks: Vec<Zeroed<Leaf<V>>>,
    len: usize,
}

impl<V: GridValue> LeafPool<V> {
    fn new() -> Self {
        Self {
            chunks: Vec::new(),
            len: 0,
        }
    }

    fn push_zeroed(&mut self) -> u32 {
        self.push_zeroed_n(1)
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

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
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

    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
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
            return li;
        }
        let li = self.leaves.push_zeroed();
        let node = &mut self.internals[ii as usize];
        node.child_mask[ci >> 6] |= 1 << (ci & 63);
        node.children[ci] = li;
        li
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
        let first_new = self.leaves.len() as u32;
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
                    let l = self.leaf_index_or_insert(o, Some(&mut hint));
                    (l, (tag, l >= first_new))
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
        let mut next = first_new;
        let starts: Vec<u32> = (new.iter())
            .map(|&n| {
                next += n;
                next - n
            })
            .collect();
        self.leaves.push_zeroed_n((next - first_new) as usize);
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
                    let l = match node.child(ci) {
                        Some(l) => l,
                        None => {
                            node.child_mask[ci >> 6] |= 1 << (ci & 63);
                            node.children[ci] = next;
                            next += 1;
                            next - 1
                        }
                    };
                    at.write((l, (tag, l >= first_new)));
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
mod tests {
    use super::*;

    #[test]
    fn set_get_across_signs_and_nodes() {
        let mut g = Grid::<i8>::new();
        let pts = [
            VoxelCoord::new(0, 0, 0),
            VoxelCoord::new(-1, -1, -1),
            VoxelCoord::new(7, 8, -8),
            VoxelCoord::new(127, 128, -129),
            VoxelCoord::new(i32::MAX >> 2, i32::MIN >> 2, 5),
        ];
        for (i, &p) in pts.iter().enumerate() {
            g.set(p, i as i8 + 1);
        }
        for (i, &p) in pts.iter().enumerate() {
            assert_eq!(g.get(p), Some(i as i8 + 1), "{p:?}");
            assert_eq!(g.accessor().get(p), Some(i as i8 + 1));
        }
        assert_eq!(g.get(VoxelCoord::new(1, 0, 0)), None);
        assert_eq!(g.leaf_count(), 5);
        let mut got: Vec<_> = g.active_voxels().collect();
        got.sort();
        let mut want: Vec<_> = pts
            .iter()
            .enumerate()
            .map(|(i, &p)| (p, i as i8 + 1))
            .collect();
        want.sort();
        assert_eq!(got, want);
    }

    #[test]
    fn leaf_box_masks_hold_the_voxels_inside() {
        let mut rng = crate::test_rng::Rng(3);
        for _ in 0..2000 {
            let o = VoxelCoord::new(rng.i(-40, 40), rng.i(-40, 40), rng.i(-40, 40))
                .shr(3)
                .shl(3);
            let mut c = || rng.i(-50, 50);
            let (a, b) = (
                VoxelCoord::new(c(), c(), c()),
                VoxelCoord::new(c(), c(), c()),
            );
            let (lo, hi) = (
                VoxelCoord::new(a.x.min(b.x), a.y.min(b.y), a.z.min(b.z)),
                VoxelCoord::new(a.x.max(b.x), a.y.max(b.y), a.z.max(b.z)),
            );
            let m = leaf_box_mask(o, lo, hi);
            for i in 0..LEAF_VOXELS {
                let v = voxel_at(o, i);
                let inside = (0..3).all(|k| {
                    lo.to_array()[k] <= v.to_array()[k] && v.to_array()[k] <= hi.to_array()[k]
                });
                assert_eq!(m.get(i), inside, "{o:?} [{lo:?}, {hi:?}] {v:?}");
            }
        }
        let (near, far) = (
            VoxelCoord::new(i32::MIN, i32::MIN, i32::MIN),
            VoxelCoord::new(i32::MAX, i32::MAX, i32::MAX),
        );
        assert_eq!(
            leaf_box_mask(VoxelCoord::new(-8, 0, 0), near, far),
            crate::mask::Mask512::FULL
        );
    }

    #[test]
    fn leaves_inserted_by_groups_are_those_inserted_one_by_one() {
        let mut rng = crate::test_rng::Rng(11);
        let mut leaf = || {
            VoxelCoord::new(rng.i(-300, 300), rng.i(-300, 300), rng.i(-40, 40))
                .shr(LEAF_LOG2)
                .shl(LEAF_LOG2)
        };
        let before: Vec<VoxelCoord> = (0..300).map(|_| leaf()).collect();
        let mut origins: Vec<VoxelCoord> = (0..4000).map(|_| leaf()).collect();
        let node = |o: &VoxelCoord| {
            let k = internal_key(*o);
            (k.z, k.y, k.x)
        };
        origins.sort_by_key(|o| (node(o), o.z, o.y, o.x));
        origins.dedup();
        // Grouped by internal node, in a scrambled order of nodes, one group empty.
        let mut groups: Vec<Vec<(VoxelCoord, usize)>> = Vec::new();
        for (i, &o) in origins.iter().enumerate() {
            match groups.last_mut() {
                Some(g) if internal_key(g[0].0) == internal_key(o) => g.push((o, i)),
                _ => groups.push(vec![(o, i)]),
            }
        }
        groups.reverse();
        groups.swap(0, 3);
        let as_nodes = |groups: &[Vec<(VoxelCoord, usize)>]| -> Vec<NodeLeaves<usize>> {
            (groups.iter())
                .map(|g| {
                    let node = internal_key(g[0].0).shl(INTERNAL_TOTAL_LOG2);
                    let children = g.iter().map(|&(o, i)| (child_index(o) as u16, i));
                    let children: Vec<_> = children.collect();
                    for (&(o, _), &(c, _)) in g.iter().zip(&children) {
                        assert_eq!(child_origin(node, c), o);
                    }
                    NodeLeaves { node, children }
                })
                .collect()
        };
        let mut nodes = as_nodes(&groups);
        let empty = NodeLeaves {
            node: VoxelCoord::new(128, 0, -256),
            children: Vec::new(),
        };
        nodes.insert(2, empty);
        // Two groups in one node: the one-by-one path.
        let mut shared = nodes.clone();
        let half = shared[1].children.len() / 2;
        let tail = shared[1].children.split_off(half);
        shared.push(NodeLeaves {
            node: shared[1].node,
            children: tail,
        });
        // Refused on either path: a child out of range, a node origin that is not one.
        for (base, bad) in [&nodes, &shared]
            .into_iter()
            .flat_map(|b| [(b, (0, 1 << 12)), (b, (1, 0))])
        {
            let mut refused = base.clone();
            refused[1].node.x += bad.0;
            refused[1].children[0].0 += bad.1;
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                Grid::<i8>::new().leaf_indices_or_insert(&refused)
            }));
            assert!(r.is_err(), "{bad:?} must be refused");
        }
        for (case, groups) in [nodes, shared].iter().enumerate() {
            let (mut grouped, mut single) = (Grid::<i8>::new(), Grid::<i8>::new());
            for g in [&mut grouped, &mut single] {
                for &o in &before {
                    g.leaf_index_or_insert(o, None);
                }
            }
            let first_new = single.leaf_count() as u32;
            let want: Vec<(u32, (usize, bool))> = (groups.iter())
                .flat_map(|g| (g.children.iter()).map(|&(c, i)| (child_origin(g.node, c), i)))
                .map(|(o, i)| {
                    let l = single.leaf_index_or_insert(o, None);
                    (l, (i, l >= first_new))
                })
                .collect();
            let nodes_before = grouped.internals.len();
            let got = grouped.leaf_indices_or_insert(groups);
            assert!(grouped.internals.len() > nodes_before);
            assert_eq!(got, want, "case {case}");
            assert!(got.iter().any(|&(_, (_, new))| !new) && got.iter().any(|&(_, (_, new))| new));
            assert_eq!(grouped.leaf_count(), single.leaf_count());
            for &o in origins.iter().chain(&before) {
                assert_eq!(
                    grouped.leaf_index_or_insert(o, None),
                    single.leaf_index_or_insert(o, None)
                );
            }
            assert_eq!(
                grouped.leaf_count(),
                single.leaf_count(),
                "nothing new after"
            );
        }
    }

    #[test]
    fn leaf_geometry() {
        let v = VoxelCoord::new(-1, 9, -9);
        assert_eq!(leaf_origin(v), VoxelCoord::new(-8, 8, -16));
        assert_eq!(voxel_at(leaf_origin(v), leaf_offset(v)), v);
    }

    #[test]
    fn memory_grows_with_leaves_and_accessor_matches_get() {
        let mut g = Grid::<i8>::new();
        let m0 = g.memory_bytes();
        let mut rng = 12345u64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng % 2000) as i32 - 1000
        };
        let mut pts = Vec::new();
        for _ in 0..5000 {
            let p = VoxelCoord::new(next(), next(), next());
            g.set(p, 1);
            pts.push(p);
        }
        assert!(g.memory_bytes() >= g.leaf_count() * std::mem::size_of::<Leaf<i8>>());
        assert!(g.memory_bytes() > m0);
        let mut acc = g.accessor();
        for _ in 0..20000 {
            let p = VoxelCoord::new(next(), next(), next());
            assert_eq!(acc.get(p), g.get(p));
        }
        for p in pts {
            assert_eq!(acc.get(p), Some(1));
        }
    }

    /// Each leaf once; each block's leaves together and by in-block index; blocks of one
    /// internal node by origin (z, y, x); the same as the parallel form.
    #[test]
    fn block_order_groups_blocks_and_sorts_within() {
        let mut g = Grid::<i8>::new();
        let mut rng = crate::test_rng::Rng(7);
        let mut want = std::collections::BTreeSet::new();
        for _ in 0..3000 {
            let v = VoxelCoord::new(rng.i(-300, 300), rng.i(-300, 300), rng.i(-140, 140));
            g.set(v, 1);
            want.insert(leaf_origin(v));
        }
        let order: Vec<VoxelCoord> = g.leaves_in_block_order().map(|(o, _)| o).collect();
        assert_eq!(order.len(), want.len());
        assert_eq!(
            order
                .iter()
                .copied()
                .collect::<std::collections::BTreeSet<_>>(),
            want
        );
        let key = |o: VoxelCoord| {
            let b = block_origin(o);
            (internal_key(o), (b.z, b.y, b.x), leaf_in_block(o))
        };
        let mut done = std::collections::HashSet::new();
        for w in order.windows(2) {
            let (a, b) = (key(w[0]), key(w[1]));
            if a.0 == b.0 {
                assert!(a < b, "{:?} before {:?}", w[0], w[1]);
            }
            if block_origin(w[0]) != block_origin(w[1]) {
                assert!(done.insert(block_origin(w[0])), "block {:?} split", w[0]);
            }
        }
        let par = g.leaf_indices_in_block_order();
        assert_eq!(par.iter().map(|&(o, _)| o).collect::<Vec<_>>(), order);
        for (o, i) in par {
            assert_eq!(g.leaf_index(o), Some(i));
        }
        let v = VoxelCoord::new(-65, 70, 200);
        assert_eq!(block_origin(v), VoxelCoord::new(-128, 64, 192));
        assert_eq!(leaf_in_block(v), 7 + (1 << 6)); // (7, 0, 1)
        assert_eq!(
            leaf_of_block(block_origin(v), leaf_in_block(v)),
            leaf_origin(v)
        );
    }

    #[test]
    fn par_update_touches_each_listed_leaf_once() {
        let mut g = Grid::<i8>::new();
        let idx: Vec<u32> = (0..1000)
            .map(|i| g.leaf_index_or_insert(VoxelCoord::new(i * 8, 0, 0), None))
            .collect();
        let items: Vec<(u32, i8)> = idx
            .iter()
            .step_by(3)
            .map(|&i| (i, (i % 100) as i8))
            .collect();
        let n = g.leaf_pool_mut().par_update(
            &items,
            |_| (),
            |leaf, &v| {
                leaf.values[0] += v;
                leaf.active.set(0);
                1
            },
        );
        assert_eq!(n, items.len() as u64);
        for (k, &li) in idx.iter().enumerate() {
            let want = if k % 3 == 0 {
                Some((li % 100) as i8)
            } else {
                None
            };
            assert_eq!(g.leaf(li).get(0), want);
        }
    }
}
