//! [`SnapshotView`]: queries on a snapshot read in place.

use super::layout::*;
use super::record::{self, MaskRef};
use crate::coord::{GridTransform, VoxelCoord, WorldPoint};
use crate::mask::BitIter;
use crate::model::{QuantizedModel, VoxelState};
use crate::tree::{
    block_origin, leaf_box_mask, leaf_in_block, leaf_of_block, leaf_offset, leaf_origin, voxel_at,
};
use bytemuck::Zeroable;

/// Longest segment [`SnapshotView::first_hit`] walks, per axis, in voxels.
pub const MAX_SEGMENT_VOXELS: f64 = 65536.0;

/// A segment [`SnapshotView::first_hit`] cannot walk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InvalidSegment {
    /// An end point is not finite or lies outside the voxel index space.
    OutsideIndexSpace,
    /// Longer than [`MAX_SEGMENT_VOXELS`] on some axis.
    TooLong,
}

impl std::fmt::Display for InvalidSegment {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::OutsideIndexSpace => write!(
                f,
                "segment end point is not finite or outside the index space"
            ),
            Self::TooLong => write!(f, "segment longer than {MAX_SEGMENT_VOXELS} voxels"),
        }
    }
}

impl std::error::Error for InvalidSegment {}

/// A box [`SnapshotView::is_box_free`] cannot answer for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InvalidBox {
    /// A corner is not finite or lies outside the voxel index space.
    OutsideIndexSpace,
    /// `min` is above `max` on some axis.
    Inverted,
}

impl std::fmt::Display for InvalidBox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::OutsideIndexSpace => {
                write!(f, "box corner is not finite or outside the index space")
            }
            Self::Inverted => write!(f, "box min is above its max on some axis"),
        }
    }
}

impl std::error::Error for InvalidBox {}

#[cfg(not(target_endian = "little"))]
compile_error!(
    "snapshots are little-endian and read in place; big-endian targets are not supported"
);

/// Voxels whose lookups [`SnapshotView::states`] overlaps: about the cache misses a core
/// keeps in flight (10 to 20 on current x86 and Arm cores). 32 was no faster.
const STATES_GROUP: usize = 16;

/// Snapshots up to this size are taken to sit in a core's cache (L2 is 0.5 to 4 MiB on
/// current cores), where [`SnapshotView::states`] only adds work: 5-12% slower per query
/// on a 195 kB snapshot.
const STATES_IN_CACHE: usize = 512 << 10;

/// Ask for the cache line holding `bytes[at]`, if there is one, to be loaded.
#[inline(always)]
fn prefetch(bytes: &[u8], at: u64) {
    // Measured on x86 with the prefetch taken out, on the 116 MB random 500k 60 m
    // snapshot: 191-250 ns per query, against 111-120 ns with it and 296-324 ns one
    // `state` call each.
    if let Ok(at) = usize::try_from(at) {
        crate::prefetch::prefetch(bytes, at);
    }
}

/// A block entry's origin.
#[inline]
fn block_origin_of(b: &[u8; BLOCK_SIZE]) -> [i32; 3] {
    let c = |k: usize| i32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]]);
    [c(0), c(1), c(2)]
}

/// A block entry's first leaf.
#[inline]
fn block_first(b: &[u8; BLOCK_SIZE]) -> u32 {
    u32::from_le_bytes([b[12], b[13], b[14], b[15]])
}

/// Stored leaves in words `..w` (< 8) of a block entry's leaf bits.
#[inline]
fn block_rank(b: &[u8; BLOCK_SIZE], w: usize) -> u16 {
    let at = BLOCK_RANKS_AT + 2 * (w & 7);
    u16::from_le_bytes([b[at], b[at + 1]])
}

/// Word `w` (< 8) of a block entry's leaf bits.
#[inline]
pub(super) fn block_word(b: &[u8; BLOCK_SIZE], w: usize) -> u64 {
    let at = BLOCK_LEAVES_AT + 8 * (w & 7);
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap_or([0; 8]))
}

/// A sink writing states as their codes (`state as u8`) into a byte buffer, in order.
#[doc(hidden)]
pub struct StateCodes<'o>(pub std::slice::IterMut<'o, u8>);

impl Extend<VoxelState> for StateCodes<'_> {
    fn extend<I: IntoIterator<Item = VoxelState>>(&mut self, states: I) {
        // States first: `zip` takes from its first iterator before it learns the second is
        // done, and an output slot taken that way would be skipped.
        for (s, o) in states.into_iter().zip(self.0.by_ref()) {
            *o = s as u8;
        }
    }
}

/// A leaf found in the table: its index (for the values section) and mask record.
#[derive(Clone, Copy, Debug)]
pub(super) struct LeafRef {
    pub(super) index: u64,
    record: u32,
    kinds: (u8, u8),
}

/// A validated snapshot over borrowed bytes (e.g. a shared-memory sample): no copy, no
/// deserialization. Construction checks every offset, length and count; afterwards each
/// query is O(1) per voxel and cannot panic, whatever the bytes held. (A map written into
/// a snapshot and read back: the example of `voxmap_map::snapshot`.)
#[derive(Clone, Copy)]
pub struct SnapshotView<'a> {
    bytes: &'a [u8],
    /// The table section's slots, the blocks and the leaves sections' entries, sliced once
    /// at open so a lookup is one bounds check per read.
    table: &'a [[u8; 4]],
    blocks: &'a [[u8; BLOCK_SIZE]],
    leaves: &'a [[u8; ENTRY_SIZE]],
    /// The mask records (the masks section without its padding).
    masks: &'a [u8],
    header: Header,
    /// The distance field section, when there is one ([`FLAG_FIELD`]).
    field: Option<super::field::FieldParts<'a>>,
    /// The table is a dense array ([`FLAG_DENSE_INDEX`]).
    dense: bool,
    tf: GridTransform,
    q: QuantizedModel,
}

/// The header and length, not the (possibly hundreds of MB of) bytes.
impl std::fmt::Debug for SnapshotView<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SnapshotView")
            .field("len", &self.bytes.len())
            .field("header", &self.header)
            .finish_non_exhaustive()
    }
}

impl<'a> SnapshotView<'a> {
    /// Validate structure (not the checksum; see [`Self::open_checked`]).
    pub fn open(bytes: &'a [u8]) -> Result<Self, SnapshotError> {
        let got = bytes.len() as u64;
        let hb = bytes.get(..HEADER_SIZE).ok_or(SnapshotError::Truncated {
            needed: HEADER_SIZE as u64,
            got,
        })?;
        let h: Header = bytemuck::pod_read_unaligned(hb);
        if h.magic != MAGIC {
            return Err(SnapshotError::BadMagic);
        }
        if h.version != FORMAT_VERSION {
            return Err(SnapshotError::UnsupportedVersion(h.version));
        }
        if h.header_size as usize != HEADER_SIZE {
            return Err(SnapshotError::BadHeader("header_size"));
        }
        if h.flags & !(FLAG_VALUES | FLAG_DENSE_INDEX | FLAG_FIELD) != 0 {
            return Err(SnapshotError::BadHeader("unknown flags"));
        }
        if h.total_len > got {
            return Err(SnapshotError::Truncated {
                needed: h.total_len,
                got,
            });
        }
        let tf =
            GridTransform::new(h.resolution).map_err(|_| SnapshotError::BadHeader("resolution"))?;
        if h.frac_bits > 12 || !(h.clamp_min <= h.threshold && h.threshold <= h.clamp_max) {
            return Err(SnapshotError::BadHeader("log-odds parameters"));
        }
        let n = h.leaf_count;
        if n > u64::from(u32::MAX - 1) {
            return Err(SnapshotError::BadHeader("leaf_count"));
        }
        let nb = h.block_count;
        if nb > n {
            return Err(SnapshotError::BadHeader("block_count"));
        }
        let cap = h.table_capacity;
        let dense = h.flags & FLAG_DENSE_INDEX != 0;
        if dense {
            let slots = h
                .index_dims
                .iter()
                .map(|&d| u128::from(d))
                .product::<u128>();
            if h.index_dims.contains(&0) || slots != u128::from(cap) {
                return Err(SnapshotError::BadHeader("index_dims"));
            }
        } else if h.index_lo != [0; 3] || h.index_dims != [0; 3] {
            return Err(SnapshotError::BadHeader("index fields of a hash table"));
        }
        if (!dense && cap <= nb) || cap >= 1 << 32 {
            return Err(SnapshotError::BadHeader("table_capacity"));
        }
        if h.masks_len > MAX_MASKS_LEN {
            return Err(SnapshotError::BadHeader("masks_len"));
        }
        if h.known_count > n * 512 || h.occupied_count > h.known_count {
            return Err(SnapshotError::BadHeader("voxel counts"));
        }
        let section = |name, off: u64, len: Option<u64>| -> Result<(), SnapshotError> {
            let end = len
                .and_then(|l| off.checked_add(l))
                .ok_or(SnapshotError::SectionOutOfBounds(name))?;
            if !off.is_multiple_of(8) || off < HEADER_SIZE as u64 || end > h.total_len {
                return Err(SnapshotError::SectionOutOfBounds(name));
            }
            Ok(())
        };
        section("table", h.table_offset, cap.checked_mul(4))?;
        section("blocks", h.blocks_offset, nb.checked_mul(BLOCK_SIZE as u64))?;
        section("leaves", h.leaves_offset, n.checked_mul(ENTRY_SIZE as u64))?;
        section("masks", h.masks_offset, Some(align8(h.masks_len)))?;
        if h.flags & FLAG_VALUES != 0 {
            section(
                "values",
                h.values_offset,
                n.checked_mul(VALUES_PER_LEAF as u64),
            )?;
        }
        let q = QuantizedModel {
            frac_bits: h.frac_bits,
            hit: 0,
            miss: 0,
            min: h.clamp_min,
            max: h.clamp_max,
            threshold: h.threshold,
        };
        // In bounds: every section was checked to lie inside total_len <= bytes.len().
        let sub = |off: u64, len: u64| &bytes[off as usize..(off + len) as usize];
        let mut v = SnapshotView {
            field: None,
            bytes: &bytes[..h.total_len as usize],
            table: bytemuck::cast_slice(sub(h.table_offset, 4 * cap)),
            blocks: bytemuck::cast_slice(sub(h.blocks_offset, BLOCK_SIZE as u64 * nb)),
            leaves: bytemuck::cast_slice(sub(h.leaves_offset, ENTRY_SIZE as u64 * n)),
            masks: sub(h.masks_offset, h.masks_len),
            header: h,
            dense,
            tf,
            q,
        };
        // Block origins are block-aligned, ranks count the leaf bits, and the blocks'
        // leaves follow one another from leaf 0 to the last: each leaf belongs to one
        // block, and a rank stays in range.
        let mut next = 0u64;
        for b in v.blocks {
            if block_origin_of(b).iter().any(|c| c & 63 != 0) {
                return Err(SnapshotError::BadIndex("block origin not a multiple of 64"));
            }
            if u64::from(block_first(b)) != next {
                return Err(SnapshotError::BadIndex("blocks' leaves out of sequence"));
            }
            let words = std::array::from_fn(|w| block_word(b, w));
            let ranks = BlockEntry::ranks_of(&words);
            if (0..8).any(|w| block_rank(b, w) != ranks[w]) {
                return Err(SnapshotError::BadIndex("block rank miscounts its leaves"));
            }
            next += words.iter().map(|w| u64::from(w.count_ones())).sum::<u64>();
        }
        if next != n {
            return Err(SnapshotError::BadIndex(
                "blocks do not hold leaf_count leaves",
            ));
        }
        // Every table entry names an existing block; a dense array's, the block at its
        // place (so a lookup needs no origin compare); and a hash table has an empty slot,
        // so probing always terminates.
        let mut empty = 0u64;
        let [dx, dy, _] = h.index_dims.map(u64::from);
        for s in 0..cap {
            match v.slot(s) {
                0 => empty += 1,
                e if u64::from(e) > nb => {
                    return Err(SnapshotError::BadIndex("table entry beyond block_count"))
                }
                e if dense => {
                    let at = [s % dx, s / dx % dy, s / dx / dy];
                    let want = [0, 1, 2].map(|k| (i64::from(h.index_lo[k]) + at[k] as i64) << 6);
                    let origin = block_origin_of(&v.blocks[e as usize - 1]);
                    if origin.map(i64::from) != want {
                        return Err(SnapshotError::BadIndex(
                            "dense index slot names another block",
                        ));
                    }
                }
                _ => {}
            }
        }
        if empty == 0 && !dense {
            return Err(SnapshotError::BadIndex("block table has no empty slot"));
        }
        for i in 0..n {
            let e = v.entry(i);
            if e.reserved != [0; 2] {
                return Err(SnapshotError::BadIndex("leaf entry reserved bytes set"));
            }
            let (k, o) = e.kinds();
            if record::checked_len(v.masks, u64::from(e.record), k, o).is_none() {
                return Err(SnapshotError::BadIndex(
                    "leaf mask kinds or record malformed",
                ));
            }
        }
        if h.flags & FLAG_FIELD != 0 {
            let end = (h.masks_offset + align8(h.masks_len)).max(if h.flags & FLAG_VALUES != 0 {
                h.values_offset + n * VALUES_PER_LEAF as u64
            } else {
                0
            });
            let at = align8(end);
            let body = v
                .bytes
                .get(at as usize..)
                .ok_or(SnapshotError::SectionOutOfBounds("field"))?;
            v.field = Some(super::field::FieldParts::open(
                body,
                at,
                v.blocks,
                n,
                h.resolution,
            )?);
        }
        Ok(v)
    }

    /// [`Self::open`] plus the CRC-32 over everything after the header.
    pub fn open_checked(bytes: &'a [u8]) -> Result<Self, SnapshotError> {
        let v = Self::open(bytes)?;
        let computed = crc32fast::hash(&v.bytes[HEADER_SIZE..]);
        if computed != v.header.checksum {
            return Err(SnapshotError::ChecksumMismatch {
                stored: v.header.checksum,
                computed,
            });
        }
        Ok(v)
    }

    /// The bytes this view reads (exactly `total_len` of them).
    pub fn as_bytes(&self) -> &'a [u8] {
        self.bytes
    }

    pub fn header(&self) -> &Header {
        &self.header
    }

    pub fn transform(&self) -> &GridTransform {
        &self.tf
    }

    pub fn resolution(&self) -> f64 {
        self.tf.resolution()
    }

    pub fn sequence(&self) -> u64 {
        self.header.sequence
    }

    pub fn timestamp_ns(&self) -> u64 {
        self.header.timestamp_ns
    }

    pub fn leaf_count(&self) -> u64 {
        self.header.leaf_count
    }

    /// Known and occupied voxels.
    pub fn counts(&self) -> (u64, u64) {
        (self.header.known_count, self.header.occupied_count)
    }

    /// Inclusive voxel bounds of the known voxels, `None` when empty.
    pub fn bounds(&self) -> Option<(VoxelCoord, VoxelCoord)> {
        let (lo, hi) = (self.header.bounds_min, self.header.bounds_max);
        (lo[0] <= hi[0]).then(|| (VoxelCoord::from_array(lo), VoxelCoord::from_array(hi)))
    }

    /// The distance field, if the snapshot carries one: queries on it read in place.
    pub fn distance_field(&self) -> Option<super::field::FieldView<'a>> {
        self.field
            .map(|parts| super::field::FieldView::new(*self, parts))
    }

    pub fn has_values(&self) -> bool {
        self.header.flags & FLAG_VALUES != 0
    }

    /// Table slot `s`: block index + 1, or 0 (empty).
    #[inline]
    fn slot(&self, s: u64) -> u32 {
        self.table
            .get(s as usize)
            .map_or(0, |b| u32::from_le_bytes(*b))
    }

    #[inline]
    fn entry(&self, i: u64) -> LeafEntry {
        self.leaves
            .get(i as usize)
            .map_or(LeafEntry::zeroed(), |b| bytemuck::pod_read_unaligned(b))
    }

    /// The leaf holding voxel `v`.
    #[inline]
    pub(super) fn find_leaf(&self, v: VoxelCoord) -> Option<LeafRef> {
        let b = block_origin(v).to_array();
        let block = self.find_block(b)?;
        self.leaf_index(block, leaf_in_block(v))
            .map(|i| self.leaf_ref(i))
    }

    /// The block with origin `b`.
    #[inline]
    fn find_block(&self, b: [i32; 3]) -> Option<&'a [u8; BLOCK_SIZE]> {
        self.block_from(b, self.home(b)?)
    }

    /// The block with origin `b` and its index.
    #[inline]
    pub(super) fn find_block_at(&self, b: [i32; 3]) -> Option<(usize, &'a [u8; BLOCK_SIZE])> {
        let i = self.block_index_from(b, self.home(b)?)?;
        Some((i, self.blocks.get(i)?))
    }

    /// The table slot where a lookup of the block with origin `b` starts; `None` outside
    /// a dense array.
    #[inline]
    fn home(&self, b: [i32; 3]) -> Option<u64> {
        let h = &self.header;
        if self.dense {
            dense_slot(block_coords(b), h.index_lo, h.index_dims)
        } else {
            Some(table_hash(b, h.table_capacity))
        }
    }

    /// The block with origin `b`, looked up from its [`Self::home`] slot `s`.
    #[inline]
    fn block_from(&self, b: [i32; 3], s: u64) -> Option<&'a [u8; BLOCK_SIZE]> {
        self.blocks.get(self.block_index_from(b, s)?)
    }

    /// The index of the block with origin `b`, looked up from its [`Self::home`] slot `s`:
    /// a dense index's slot names it; a hash table is probed from `s`.
    #[inline]
    fn block_index_from(&self, b: [i32; 3], mut s: u64) -> Option<usize> {
        if self.dense {
            return (self.slot(s) as usize).checked_sub(1);
        }
        let cap = self.header.table_capacity;
        // Bounded: validated tables have an empty slot; the bound guards nothing else.
        for _ in 0..cap {
            let e = self.slot(s) as usize;
            if block_origin_of(self.blocks.get(e.checked_sub(1)?)?) == b {
                return Some(e - 1);
            }
            s = if s + 1 == cap { 0 } else { s + 1 };
        }
        None
    }

    /// Index of leaf `j` (in-block index) of a block, if stored: the block's first plus
    /// the number of its stored leaves before `j`.
    #[inline]
    fn leaf_index(&self, block: &[u8; BLOCK_SIZE], j: usize) -> Option<u64> {
        let (w, bit) = (j / 64, j % 64);
        let word = block_word(block, w);
        if word >> bit & 1 == 0 {
            return None;
        }
        let rank = u32::from(block_rank(block, w)) + (word & ((1 << bit) - 1)).count_ones();
        Some(u64::from(block_first(block)) + u64::from(rank))
    }

    #[inline]
    fn leaf_ref(&self, index: u64) -> LeafRef {
        let entry = self.entry(index);
        LeafRef {
            index,
            record: entry.record,
            kinds: entry.kinds(),
        }
    }

    /// Every stored leaf as (origin, entry), in leaf order.
    #[doc(hidden)]
    pub fn stored_leaves(&self) -> impl Iterator<Item = (VoxelCoord, LeafEntry)> + 'a {
        let v = *self;
        self.blocks.iter().flat_map(move |b| {
            let origin = VoxelCoord::from_array(block_origin_of(b));
            let first = u64::from(block_first(b));
            (0..8)
                .flat_map(move |w| BitIter(block_word(b, w)).map(move |bit| w * 64 + bit))
                .enumerate()
                .map(move |(k, j)| (leaf_of_block(origin, j), v.entry(first + k as u64)))
        })
    }

    /// The known and occupied masks of a leaf.
    #[inline]
    fn masks_of(&self, e: &LeafEntry) -> (MaskRef, MaskRef) {
        let (k, o) = e.kinds();
        record::masks_at(self.masks, u64::from(e.record), k, o)
    }

    #[inline]
    fn leaf_state(&self, leaf: LeafRef, i: usize) -> VoxelState {
        let (k, o) = leaf.kinds;
        match record::voxel_bits(self.masks, u64::from(leaf.record), k, o, i) {
            (false, _) => VoxelState::Unknown,
            (true, true) => VoxelState::Occupied,
            (true, false) => VoxelState::Free,
        }
    }

    /// State of a voxel.
    #[inline]
    pub fn state(&self, v: VoxelCoord) -> VoxelState {
        match self.find_leaf(v) {
            Some(l) => self.leaf_state(l, leaf_offset(v)),
            None => VoxelState::Unknown,
        }
    }

    /// States of many voxels, appended to `out` in order: the same as [`Self::state`] on
    /// each, and about twice as fast per voxel when the snapshot is much bigger than the
    /// CPU cache (e.g. a collision check of a whole trajectory). A lone query waits for
    /// its memory reads one after another (table slot, leaf entry, mask record: each a
    /// cache miss on a big map); here those of a group of voxels are issued together, so
    /// their waits overlap. Snapshots small enough to sit in cache are read one voxel at a
    /// time, which is faster there.
    pub fn states(&self, voxels: &[VoxelCoord], out: &mut Vec<VoxelState>) {
        out.reserve(voxels.len());
        let staged = self.bytes.len() > STATES_IN_CACHE;
        self.states_of(voxels.iter().map(|v| Some(*v)), staged, out);
    }

    /// [`Self::states`] at world points, as [`Self::state_at`] on each.
    pub fn states_at(&self, points: &[WorldPoint], out: &mut Vec<VoxelState>) {
        out.reserve(points.len());
        self.states_at_each(points.iter().copied(), out);
    }

    /// [`Self::states_at`] over any points into any sink (a binding's output buffer, points
    /// read from a caller's array), without collecting either.
    pub fn states_at_each(
        &self,
        points: impl ExactSizeIterator<Item = WorldPoint>,
        out: &mut impl Extend<VoxelState>,
    ) {
        let staged = self.bytes.len() > STATES_IN_CACHE;
        self.states_of(points.map(|p| self.tf.voxel_of(&p)), staged, out);
    }

    /// [`Self::states_at`] for the C and Python APIs: points as x, y, z after one another
    /// (a C or NumPy array), each state written as its code (`state as u8`) into `out`.
    /// Points beyond `out.len()` are not read; codes beyond the points are left alone.
    pub fn state_codes_at(&self, xyz: &[f64], out: &mut [u8]) {
        let points = xyz
            .chunks_exact(3)
            .take(out.len())
            .map(|c| WorldPoint::new(c[0], c[1], c[2]));
        self.states_at_each(points, &mut StateCodes(out.iter_mut()));
    }

    /// `None`: outside the index space, unknown. Not `staged`: one [`Self::state`] each.
    #[doc(hidden)]
    pub fn states_of(
        &self,
        voxels: impl ExactSizeIterator<Item = Option<VoxelCoord>>,
        staged: bool,
        out: &mut impl Extend<VoxelState>,
    ) {
        if !staged {
            out.extend(voxels.map(|v| v.map_or(VoxelState::Unknown, |v| self.state(v))));
            return;
        }
        let mut voxels = voxels.peekable();
        while voxels.peek().is_some() {
            let mut group = [None; STATES_GROUP];
            let mut n = 0;
            for (g, v) in group.iter_mut().zip(voxels.by_ref()) {
                *g = v;
                n += 1;
            }
            self.states_group(&group[..n], out);
        }
    }

    /// At most [`STATES_GROUP`] lookups, in stages: each stage's reads are independent of
    /// one another and prefetched before the next stage needs them. The table and blocks
    /// are small and mostly in cache; the leaf entries and mask records are where the
    /// misses are.
    fn states_group(&self, voxels: &[Option<VoxelCoord>], out: &mut impl Extend<VoxelState>) {
        let h = &self.header;
        let mut slot = [None; STATES_GROUP];
        for (s, v) in slot.iter_mut().zip(voxels) {
            *s = v.and_then(|v| self.home(block_origin(v).to_array()));
            if let Some(home) = *s {
                prefetch(self.bytes, h.table_offset + 4 * home);
            }
        }
        let mut index = [None; STATES_GROUP];
        for ((i, v), s) in index.iter_mut().zip(voxels).zip(slot) {
            *i = v.and_then(|v| {
                let block = self.block_from(block_origin(v).to_array(), s?)?;
                let i = self.leaf_index(block, leaf_in_block(v))?;
                prefetch(self.bytes, h.leaves_offset + ENTRY_SIZE as u64 * i);
                Some(i)
            });
        }
        let mut leaf = [None; STATES_GROUP];
        for (l, i) in leaf.iter_mut().zip(index) {
            *l = i.map(|index| {
                let l = self.leaf_ref(index);
                // A record spans one to three cache lines; the voxel's row is most often
                // in the first two.
                prefetch(self.masks, u64::from(l.record));
                prefetch(self.masks, u64::from(l.record) + 64);
                l
            });
        }
        out.extend(voxels.iter().zip(leaf).map(|(v, l)| match (v, l) {
            (Some(v), Some(l)) => self.leaf_state(l, leaf_offset(*v)),
            _ => VoxelState::Unknown,
        }));
    }

    /// State at a world point; points outside the index space are unknown.
    pub fn state_at(&self, p: &WorldPoint) -> VoxelState {
        self.tf
            .voxel_of(p)
            .map_or(VoxelState::Unknown, |v| self.state(v))
    }

    /// Occupancy probability of a known voxel, when the snapshot stores values.
    pub fn probability(&self, v: VoxelCoord) -> Option<f64> {
        if !self.has_values() {
            return None;
        }
        let l = self.find_leaf(v)?;
        let i = leaf_offset(v);
        if self.leaf_state(l, i) == VoxelState::Unknown {
            return None;
        }
        let at = (self.header.values_offset + VALUES_PER_LEAF as u64 * l.index) as usize + i;
        let raw = *self.bytes.get(at)? as i8;
        Some(crate::model::probability(self.q.to_logodds(raw)))
    }

    /// The first voxel along the segment `from` -> `to` (world metres) that is occupied,
    /// or also unknown when `unknown_blocks`; `Ok(None)` when the line of sight is clear.
    pub fn first_hit(
        &self,
        from: &WorldPoint,
        to: &WorldPoint,
        unknown_blocks: bool,
    ) -> Result<Option<VoxelCoord>, InvalidSegment> {
        if self.tf.voxel_of(from).is_none() || self.tf.voxel_of(to).is_none() {
            return Err(InvalidSegment::OutsideIndexSpace);
        }
        let o = self.tf.point_to_units(from);
        let e = self.tf.point_to_units(to);
        if (0..3).any(|k| (o[k] - e[k]).abs() > MAX_SEGMENT_VOXELS) {
            return Err(InvalidSegment::TooLong);
        }
        // Leaves with no blocking voxel (most, on a large map) are passed whole, on the
        // walk's leaves; the voxel walk is taken up only in leaves that have one.
        enum Leaf {
            Clear,
            Blocked,
            Mixed(LeafRef),
        }
        // The walk stays in one block for up to 8 leaves per axis: its table lookup is
        // made once. (An origin that is no multiple of 64 matches no block.)
        let mut block: ([i32; 3], Option<&[u8; BLOCK_SIZE]>) = ([1; 3], None);
        let mut class = |lo: VoxelCoord| {
            let b = block_origin(lo).to_array();
            if b != block.0 {
                block = (b, self.find_block(b));
            }
            let leaf = block
                .1
                .and_then(|blk| self.leaf_index(blk, leaf_in_block(lo)))
                .map(|i| self.leaf_ref(i));
            match leaf {
                None if unknown_blocks => Leaf::Blocked,
                None => Leaf::Clear,
                // Kinds 0: nothing occupied; all known.
                Some(l) if l.kinds.1 == 0 && (!unknown_blocks || l.kinds.0 == 0) => Leaf::Clear,
                Some(l) => Leaf::Mixed(l),
            }
        };
        let start = crate::raycast::Dda::new(o, e);
        let mut leaves = start.leaves();
        loop {
            let origin = leaves.origin();
            let class = class(origin);
            if !matches!(class, Leaf::Clear) {
                // The voxel walk as it enters this leaf.
                let mut d = match leaves.entry() {
                    Some((t, axis)) => start.after_crossing(t, axis),
                    None => start.clone(),
                };
                let Leaf::Mixed(l) = class else {
                    return Ok(Some(d.voxel()));
                };
                loop {
                    let v = d.voxel();
                    if leaf_origin(v) != origin {
                        break;
                    }
                    let s = self.leaf_state(l, leaf_offset(v));
                    if s == VoxelState::Occupied || (unknown_blocks && s == VoxelState::Unknown) {
                        return Ok(Some(v));
                    }
                    if d.steps() == 0 {
                        return Ok(None);
                    }
                    d.step();
                }
            }
            if !leaves.advance() {
                return Ok(None);
            }
        }
    }

    /// Whether no voxel the box [min, max] (world metres) overlaps is occupied, nor unknown
    /// unless `unknown_is_free`: OctoMap's bounding-box convention, every voxel from the one
    /// holding `min` to the one holding `max`, so a voxel reaching into the box by any part
    /// counts (a point on a face belongs to the voxel above it, as everywhere).
    pub fn is_box_free(
        &self,
        min: &WorldPoint,
        max: &WorldPoint,
        unknown_is_free: bool,
    ) -> Result<bool, InvalidBox> {
        if (0..3).any(|k| min[k] > max[k]) {
            return Err(InvalidBox::Inverted);
        }
        let (Some(lo), Some(hi)) = (self.tf.voxel_of(min), self.tf.voxel_of(max)) else {
            return Err(InvalidBox::OutsideIndexSpace);
        };
        Ok(self.voxels_free(lo, hi, unknown_is_free))
    }

    /// Whether no voxel in `lo..=hi` is occupied, nor unknown unless `unknown_is_free`.
    fn voxels_free(&self, lo: VoxelCoord, hi: VoxelCoord, unknown_is_free: bool) -> bool {
        let (llo, lhi) = (leaf_origin(lo), leaf_origin(hi));
        // Up to 2^28 leaves per axis: the product can pass u64.
        let leaves_in_box = ((lhi.x - llo.x) as u64 / 8 + 1)
            .saturating_mul((lhi.y - llo.y) as u64 / 8 + 1)
            .saturating_mul((lhi.z - llo.z) as u64 / 8 + 1);
        if unknown_is_free && leaves_in_box > self.leaf_count() {
            // Cheaper to scan the stored leaves than the box.
            return self.leaf_occupancy().all(|l| {
                let inside = leaf_box_mask(l.origin, lo, hi);
                l.occupied.and(&inside).is_empty()
            });
        }
        let mut z = llo.z;
        while z <= lhi.z {
            let mut y = llo.y;
            while y <= lhi.y {
                let mut x = llo.x;
                while x <= lhi.x {
                    let o = VoxelCoord::new(x, y, z);
                    match self.find_leaf(o) {
                        None if !unknown_is_free => return false,
                        None => {}
                        Some(l) => {
                            for i in leaf_box_mask(o, lo, hi).iter_ones() {
                                match self.leaf_state(l, i) {
                                    VoxelState::Occupied => return false,
                                    VoxelState::Unknown if !unknown_is_free => return false,
                                    _ => {}
                                }
                            }
                        }
                    }
                    x += 8;
                }
                y += 8;
            }
            z += 8;
        }
        true
    }

    /// Every leaf's occupancy masks, in leaf order. Occupied bits outside the known mask
    /// (possible only in corrupt bytes) are dropped.
    pub fn leaf_occupancy(&self) -> impl Iterator<Item = crate::tree::LeafOccupancy> + 'a {
        let v = *self;
        self.stored_leaves().map(move |(origin, e)| {
            let (k, o) = v.masks_of(&e);
            let known = k.decode(v.masks);
            let mut occupied = o.decode(v.masks);
            occupied
                .words
                .iter_mut()
                .zip(known.words)
                .for_each(|(o, k)| *o &= k);
            crate::tree::LeafOccupancy {
                origin,
                known,
                occupied,
            }
        })
    }

    /// Occupied voxels, in leaf order.
    pub fn occupied_voxels(&self) -> impl Iterator<Item = VoxelCoord> + 'a {
        let v = *self;
        self.stored_leaves()
            .filter(|(_, e)| e.kinds().1 != 0)
            .flat_map(move |(origin, e)| {
                let (k, o) = v.masks_of(&e);
                let (known, occupied) = (k.decode(v.masks), o.decode(v.masks));
                (0..8).flat_map(move |w| {
                    let bits = occupied.words[w] & known.words[w];
                    crate::mask::BitIter(bits).map(move |b| voxel_at(origin, w * 64 + b))
                })
            })
    }

    /// World centres of the occupied voxels.
    pub fn occupied_centers(&self) -> impl Iterator<Item = WorldPoint> + 'a {
        let tf = self.tf;
        self.occupied_voxels().map(move |v| tf.voxel_center(v))
    }
}
