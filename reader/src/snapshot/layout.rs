//! The byte layout of a snapshot, version 5 ([`FORMAT_VERSION`]). All integers little-endian; every section
//! starts on an 8-byte boundary.
//!
//! ```text
//! offset  size                 what
//! 0       200                  Header
//! table   4 * table_capacity   u32 per slot: block index + 1, 0 = empty; a dense 3D array
//!                              over the blocks' bounds, or a hash table (linear probing)
//! blocks  96 * block_count     BlockEntry: origin, first leaf, which of its 512 leaves exist
//! leaves  8 * leaf_count       LeafEntry: mask kinds and record offset; block by block,
//!                              each block's leaves by in-block index
//! masks   masks_len            one mask record per leaf (see `record`), in leaf order,
//!                              zero-padded to a multiple of 8
//! values  512 * leaf_count     i8 log-odds per voxel (only with FLAG_VALUES)
//! ```
//!
//! A lookup hashes the voxel's block (64^3 voxels), reads which of the block's 8^3 leaves
//! exist, and takes the leaf's entry at the block's first leaf plus the count of leaves
//! before it (a rank over the block's presence bits). Version 3 hashed every leaf: a table
//! slot and a 16-byte entry per leaf, scattered over pages so that each leaf a `first_hit`
//! walk crossed cost two dependent cache and TLB misses on a large map. Here the table and
//! blocks of a 60 m map are a few hundred kB and stay in cache; a leaf costs 8 bytes of
//! entry, and neighbouring leaves' entries and records lie close together. Version 3 also
//! stored each leaf's masks in the smallest of a few O(1)-readable encodings (see
//! `record`), as this version does.

use bytemuck::{Pod, Zeroable};

pub const MAGIC: [u8; 8] = *b"VXMSNAP\0";
pub const FORMAT_VERSION: u32 = 5;
/// The snapshot carries per-voxel log-odds.
pub const FLAG_VALUES: u32 = 1;
/// The table is a dense array over the blocks' bounds (`index_lo`, `index_dims`), not a
/// hash table.
pub const FLAG_DENSE_INDEX: u32 = 2;
/// A distance field section follows the other sections ([`FieldHeader`]).
pub const FLAG_FIELD: u32 = 4;
pub const HEADER_SIZE: usize = std::mem::size_of::<Header>();
pub const VALUES_PER_LEAF: usize = 512;
pub const ENTRY_SIZE: usize = std::mem::size_of::<LeafEntry>();
pub const BLOCK_SIZE: usize = std::mem::size_of::<BlockEntry>();
/// Bytes the masks section may hold: record offsets are `u32`.
pub const MAX_MASKS_LEN: u64 = u32::MAX as u64;

/// One leaf in the `leaves` section.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct LeafEntry {
    /// Byte offset of the leaf's mask record in the masks section.
    pub record: u32,
    pub known_kind: u8,
    pub occupied_kind: u8,
    /// Zero.
    pub reserved: [u8; 2],
}

impl LeafEntry {
    pub fn new(known_kind: u8, occupied_kind: u8, record: u32) -> Self {
        LeafEntry {
            record,
            known_kind,
            occupied_kind,
            reserved: [0; 2],
        }
    }

    /// (known kind, occupied kind).
    #[inline]
    pub fn kinds(&self) -> (u8, u8) {
        (self.known_kind, self.occupied_kind)
    }
}

const _: () = assert!(ENTRY_SIZE == 8);

/// One block of 8x8x8 leaves in the `blocks` section.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct BlockEntry {
    /// Block origin in voxels: multiples of 64.
    pub origin: [i32; 3],
    /// Index of the block's first leaf; the blocks' leaves follow one another from 0.
    pub first: u32,
    /// `ranks[w]`: stored leaves in `leaves[..w]`, so a leaf's rank is one popcount.
    pub ranks: [u16; 8],
    /// Bit `i` (`grid::leaf_in_block`) set: the leaf is stored.
    pub leaves: [u64; 8],
}

const _: () = assert!(BLOCK_SIZE == 96);

impl BlockEntry {
    /// The `ranks` of these leaf bits: the stored leaves in the words before each.
    pub fn ranks_of(leaves: &[u64; 8]) -> [u16; 8] {
        let mut below = 0;
        leaves.map(|w| {
            let r = below;
            below += w.count_ones() as u16;
            r
        })
    }
}
/// Byte offset in a [`BlockEntry`] of its `ranks`.
pub const BLOCK_RANKS_AT: usize = std::mem::offset_of!(BlockEntry, ranks);
/// Byte offset in a [`BlockEntry`] of its `leaves` words.
pub const BLOCK_LEAVES_AT: usize = std::mem::offset_of!(BlockEntry, leaves);

/// Fixed header at offset 0.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct Header {
    pub magic: [u8; 8],
    pub version: u32,
    pub flags: u32,
    pub header_size: u32,
    /// Fixed-point log-odds: fraction bits, occupancy threshold, clamp min and max.
    pub frac_bits: u8,
    pub threshold: i8,
    pub clamp_min: i8,
    pub clamp_max: i8,
    /// Metres per voxel.
    pub resolution: f64,
    /// Sequence number of the last frame integrated.
    pub sequence: u64,
    pub timestamp_ns: u64,
    pub leaf_count: u64,
    pub known_count: u64,
    pub occupied_count: u64,
    /// Inclusive voxel bounds of the known voxels (min > max when empty).
    pub bounds_min: [i32; 3],
    pub bounds_max: [i32; 3],
    /// Slots in the block table, < 2^32: > block_count for a hash table, the product of
    /// `index_dims` for a dense one.
    pub table_capacity: u64,
    pub block_count: u64,
    /// With [`FLAG_DENSE_INDEX`]: the lowest block's coordinates (origin / 64) and the
    /// array's size in blocks, x fastest; zero otherwise.
    pub index_lo: [i32; 3],
    pub index_dims: [u32; 3],
    pub table_offset: u64,
    pub blocks_offset: u64,
    pub leaves_offset: u64,
    pub masks_offset: u64,
    /// Bytes of mask records (the section is zero-padded to a multiple of 8).
    pub masks_len: u64,
    /// 0 when FLAG_VALUES is clear.
    pub values_offset: u64,
    pub total_len: u64,
    /// CRC-32 (IEEE) of bytes [HEADER_SIZE, total_len).
    pub checksum: u32,
    pub reserved: u32,
}

const _: () = assert!(HEADER_SIZE == 200);
const _: () = assert!(std::mem::offset_of!(Header, resolution) == 24);
const _: () = assert!(std::mem::offset_of!(Header, bounds_min) == 72);
const _: () = assert!(std::mem::offset_of!(Header, table_capacity) == 96);
const _: () = assert!(std::mem::offset_of!(Header, index_lo) == 112);
const _: () = assert!(std::mem::offset_of!(Header, table_offset) == 136);
const _: () = assert!(std::mem::offset_of!(Header, masks_len) == 168);
const _: () = assert!(std::mem::offset_of!(Header, total_len) == 184);
const _: () = assert!(std::mem::offset_of!(Header, checksum) == 192);

/// The distance field section's header: it starts at the first 8-byte boundary after the
/// last other section (values, else masks) and runs to `total_len`. After it come one
/// [`FieldBlock`] per block and one [`FieldEntry`] per leaf (each in the snapshot's
/// order), zero padding up to the next 64-byte boundary of the snapshot, the distance
/// blocks ([`FIELD_DISTS`] bytes for each of `dist_blocks` leaves, in leaf order), then
/// `data_len` bytes of the leaves' offsets.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct FieldHeader {
    /// Distances are kept below this many metres: `radius` voxels.
    pub max_distance: f64,
    /// The band's radius in voxels, 1 to 63.
    pub radius: u32,
    /// What unknown voxels count as: 0 free, 1 occupied.
    pub unknown: u8,
    /// Steps per voxel of the quantised distances: [`field_steps`] of `radius`.
    pub steps: u8,
    pub reserved: [u8; 2],
    /// The voxels the field covers, inclusive (the whole index space when it has no
    /// window and the snapshot no box).
    pub window_lo: [i32; 3],
    pub window_hi: [i32; 3],
    /// Voxels stored (in the band).
    pub band_count: u64,
    /// Bytes of offsets (a multiple of 8, below 2^34).
    pub data_len: u64,
    /// Leaves with voxels in the band, each with a distance block.
    pub dist_blocks: u64,
}

pub const FIELD_HEADER_SIZE: usize = std::mem::size_of::<FieldHeader>();
const _: () = assert!(FIELD_HEADER_SIZE == 64);

/// Where the distance blocks of a field section at `at` (from the snapshot's start) for
/// `blocks` blocks and `leaves` leaves begin: on a 64-byte line, so that the distances of
/// an aligned 4x4x4 cube share a cache line.
#[inline]
pub fn field_dists_at(at: u64, blocks: u64, leaves: u64) -> u64 {
    (at + FIELD_HEADER_SIZE as u64
        + FIELD_BLOCK_SIZE as u64 * blocks
        + FIELD_ENTRY_SIZE as u64 * leaves)
        .div_ceil(64)
        * 64
}

/// A block's share of the distance field section: which of its leaves have a distance
/// block, and where theirs are, so that a query finds a leaf's distances from its block
/// (as a state query finds its leaf), without reading the leaf's entry.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct FieldBlock {
    /// The distance block of the block's first leaf in the band: the leaves in the band
    /// of the blocks before it.
    pub first: u32,
    pub reserved: u32,
    /// `ranks[w]`: set bits of `band` in words `..w`.
    pub ranks: [u16; 8],
    /// Bit `j` (as in [`BlockEntry::leaves`]) set when leaf `j` of the block has voxels in
    /// the band (a stored leaf).
    pub band: [u64; 8],
}

pub const FIELD_BLOCK_SIZE: usize = std::mem::size_of::<FieldBlock>();
const _: () = assert!(FIELD_BLOCK_SIZE == 88);
pub const FIELD_BLOCK_RANKS_AT: usize = std::mem::offset_of!(FieldBlock, ranks);
pub const FIELD_BLOCK_BAND_AT: usize = std::mem::offset_of!(FieldBlock, band);

/// The steps per voxel of a band of `radius` voxels' quantised distances: as many as keep
/// the radius within [`FIELD_DIST_FAR`] - 1.
#[inline]
pub fn field_steps(radius: u32) -> u8 {
    (u32::from(FIELD_DIST_FAR - 1) / radius.max(1)).min(255) as u8
}

/// The quantised distance of an offset of squared length `len2` (voxels²).
#[inline]
pub fn quantise(len2: i32, steps: u8) -> u8 {
    (f64::from(len2).sqrt() * f64::from(steps))
        .round()
        .min(f64::from(FIELD_DIST_FAR - 1)) as u8
}

/// A quantised distance of a voxel outside the band: at least the max distance.
pub const FIELD_DIST_FAR: u8 = 255;

/// The bytes of a leaf's distance block: one `u8` per voxel in Morton order, its distance
/// in 1/`steps` voxel rounded to nearest, or [`FIELD_DIST_FAR`] outside the band.
pub const FIELD_DISTS: usize = 512;

/// A leaf's share of the distance field section: where its offsets start in the data, in
/// 8-byte units, with [`FIELD_MASKED`] set when only some of its voxels lie in the band;
/// [`FieldEntry::NONE`] when none do. All of them: 512 offsets of 3 bytes (dx, dy, dz as
/// `i8`), Morton order. Some: a 64-byte mask (bit per Morton place, eight little-endian
/// words), then the offsets of the voxels it sets, in Morton order.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct FieldEntry {
    pub data: u32,
}

pub const FIELD_ENTRY_SIZE: usize = std::mem::size_of::<FieldEntry>();
/// The bit of [`FieldEntry::data`] that marks a masked leaf.
pub const FIELD_MASKED: u32 = 1 << 31;
/// The most 8-byte units a [`FieldEntry`] can place its offsets at (all bits set is
/// [`FieldEntry::NONE`]).
pub const FIELD_MAX_UNITS: u64 = (FIELD_MASKED - 2) as u64;

impl FieldEntry {
    /// A leaf with no voxel in the band.
    pub const NONE: Self = Self { data: u32::MAX };

    /// Where its offsets (all) or its mask and offsets (masked) start in the data.
    #[inline]
    pub fn data_at(&self) -> u64 {
        u64::from(self.data & !FIELD_MASKED) * 8
    }

    #[inline]
    pub fn masked(&self) -> bool {
        self.data & FIELD_MASKED != 0
    }
}

/// Hash table slots for `n` blocks: a load of 1/4, so a lookup nearly always ends at its
/// first probe. Blocks are few (a 60 m map has some thousands), so this costs 16 bytes a
/// block. The writer uses a dense array instead when it has no more slots than this.
pub fn table_capacity_for(n: u64) -> u64 {
    4 * n + 1
}

/// Block coordinates of a voxel: its block's origin / 64.
#[inline]
pub fn block_coords(v: [i32; 3]) -> [i32; 3] {
    v.map(|c| c >> 6)
}

/// Slot of block coordinates `b` in a dense array over `lo` and `dims`, if inside.
#[inline]
pub fn dense_slot(b: [i32; 3], lo: [i32; 3], dims: [u32; 3]) -> Option<u64> {
    let rel = |k: usize| {
        let r = i64::from(b[k]) - i64::from(lo[k]);
        (0..i64::from(dims[k])).contains(&r).then_some(r as u64)
    };
    let (x, y, z) = (rel(0)?, rel(1)?, rel(2)?);
    Some((z * u64::from(dims[1]) + y) * u64::from(dims[0]) + x)
}

/// Slot of a block origin in a table of `capacity` slots (before probing).
#[inline]
pub fn table_hash(o: [i32; 3], capacity: u64) -> u64 {
    let k = |c: i32, m: u64| ((c >> 6) as u32 as u64).wrapping_mul(m);
    let mut h = k(o[0], 0x9E37_79B1) ^ k(o[1], 0x85EB_CA77) ^ k(o[2], 0xC2B2_AE3D);
    h ^= h >> 29;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    // Range reduction by multiply-shift: uniform over [0, capacity) for capacity < 2^32.
    ((h >> 32) * capacity) >> 32
}

/// Round up to a multiple of 8.
#[inline]
pub fn align8(n: u64) -> u64 {
    n.div_ceil(8) * 8
}

/// Why bytes are not a readable snapshot.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum SnapshotError {
    /// Fewer bytes than a header, or than the header's `total_len`.
    Truncated {
        needed: u64,
        got: u64,
    },
    BadMagic,
    UnsupportedVersion(u32),
    /// A header field is out of range.
    BadHeader(&'static str),
    /// A section lies outside the buffer, overlaps the header or is misaligned.
    SectionOutOfBounds(&'static str),
    /// The table points at a block that does not exist, the blocks do not name each leaf
    /// once, or a leaf entry's kinds or mask record are malformed.
    BadIndex(&'static str),
    ChecksumMismatch {
        stored: u32,
        computed: u32,
    },
}

impl std::fmt::Display for SnapshotError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Truncated { needed, got } => {
                write!(f, "snapshot truncated: need {needed} bytes, have {got}")
            }
            Self::BadMagic => write!(f, "not a voxmap snapshot (bad magic)"),
            Self::UnsupportedVersion(v) => write!(
                f,
                "unsupported snapshot version {v} (this build reads {FORMAT_VERSION})"
            ),
            Self::BadHeader(what) => write!(f, "bad snapshot header: {what}"),
            Self::SectionOutOfBounds(s) => write!(f, "snapshot section '{s}' out of bounds"),
            Self::BadIndex(what) => write!(f, "bad snapshot index: {what}"),
            Self::ChecksumMismatch { stored, computed } => {
                write!(
                    f,
                    "snapshot checksum mismatch: stored {stored:#010x}, computed {computed:#010x}"
                )
            }
        }
    }
}

impl std::error::Error for SnapshotError {}

/// Why a snapshot could not be written (see `writer::Plan::write`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum EncodeError {
    /// The map needs more mask bytes than a leaf entry can address.
    TooLarge,
    /// The destination buffer is smaller than `encoded_len`.
    BufferTooSmall { needed: usize, got: usize },
}

impl std::fmt::Display for EncodeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooLarge => write!(f, "map too large for one snapshot (> 4 GiB of masks)"),
            Self::BufferTooSmall { needed, got } => {
                write!(f, "buffer too small: need {needed} bytes, have {got}")
            }
        }
    }
}

impl std::error::Error for EncodeError {}
