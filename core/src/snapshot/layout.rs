//! The byte layout of a snapshot, version 2. All integers little-endian; every section
//! starts on an 8-byte boundary.
//!
//! ```text
//! offset  size                 what
//! 0       160                  Header
//! table   4 * table_capacity   u32 per slot: leaf index + 1, 0 = empty (linear probing)
//! leaves  16 * leaf_count      LeafEntry: origin (voxels, multiples of 8), block order, + mask ref
//! masks   masks_len            per leaf, only what it needs: [u64; 8] known mask unless all
//!                              512 voxels are known, then [u64; 8] occupied mask unless
//!                              none is occupied
//! values  512 * leaf_count     i8 log-odds per voxel (only with FLAG_VALUES)
//! ```
//!
//! Version 2 drops what version 1 stored for every leaf regardless: the known mask of a
//! fully known leaf and the occupied mask of a leaf with nothing occupied (most leaves in
//! free space). The origin and the mask reference share 16 bytes, so the lookup that finds
//! a leaf has already loaded where its masks are.

use bytemuck::{Pod, Zeroable};

pub const MAGIC: [u8; 8] = *b"VXMSNAP\0";
pub const FORMAT_VERSION: u32 = 2;
/// The snapshot carries per-voxel log-odds.
pub const FLAG_VALUES: u32 = 1;
pub const HEADER_SIZE: usize = std::mem::size_of::<Header>();
pub const VALUES_PER_LEAF: usize = 512;
pub const ENTRY_SIZE: usize = 16;
/// [`LeafEntry::masks`] bit: the leaf stores a known mask (else all 512 voxels are known).
pub const HAS_KNOWN: u32 = 1;
/// [`LeafEntry::masks`] bit: the leaf stores an occupied mask (else none is occupied).
pub const HAS_OCCUPIED: u32 = 2;
/// Mask words a reference can address: `masks >> 2` is a word index below this.
pub const MAX_MASK_WORDS: u64 = 1 << 30;

/// One leaf in the `leaves` section.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct LeafEntry {
    pub origin: [i32; 3],
    /// `first mask word (u64 index into the masks section) << 2 | HAS_KNOWN | HAS_OCCUPIED`;
    /// the occupied mask follows the known mask when both are stored.
    pub masks: u32,
}

impl LeafEntry {
    /// Mask words this leaf stores.
    #[inline]
    pub fn mask_words(&self) -> u64 {
        8 * u64::from((self.masks & (HAS_KNOWN | HAS_OCCUPIED)).count_ones())
    }
}

const _: () = assert!(std::mem::size_of::<LeafEntry>() == ENTRY_SIZE);

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
    /// Slots in the leaf table: > leaf_count (about 1.5x), < 2^32.
    pub table_capacity: u64,
    pub table_offset: u64,
    pub leaves_offset: u64,
    pub masks_offset: u64,
    /// Bytes in the masks section (a multiple of 8).
    pub masks_len: u64,
    /// 0 when FLAG_VALUES is clear.
    pub values_offset: u64,
    pub total_len: u64,
    /// CRC-32 (IEEE) of bytes [HEADER_SIZE, total_len).
    pub checksum: u32,
    pub reserved: u32,
}

const _: () = assert!(HEADER_SIZE == 160);
const _: () = assert!(std::mem::offset_of!(Header, resolution) == 24);
const _: () = assert!(std::mem::offset_of!(Header, bounds_min) == 72);
const _: () = assert!(std::mem::offset_of!(Header, table_capacity) == 96);
const _: () = assert!(std::mem::offset_of!(Header, masks_len) == 128);
const _: () = assert!(std::mem::offset_of!(Header, total_len) == 144);
const _: () = assert!(std::mem::offset_of!(Header, checksum) == 152);

/// Table slots for `n` leaves: load factor about 2/3 with no power-of-two rounding, so the
/// table costs about 6 bytes per leaf.
pub fn table_capacity_for(n: u64) -> u64 {
    n + n / 2 + 1
}

/// Slot of a leaf origin in a table of `capacity` slots (before probing).
#[inline]
pub fn table_hash(o: [i32; 3], capacity: u64) -> u64 {
    let k = |c: i32, m: u64| ((c >> 3) as u32 as u64).wrapping_mul(m);
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
    /// The table points at a leaf that does not exist, an origin is not leaf-aligned, or a
    /// leaf's masks lie outside the masks section.
    BadIndex(&'static str),
    /// The map needs more mask words than a leaf entry can address.
    TooLarge,
    ChecksumMismatch {
        stored: u32,
        computed: u32,
    },
    /// The destination buffer is smaller than `encoded_len`.
    BufferTooSmall {
        needed: usize,
        got: usize,
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
            Self::TooLarge => write!(f, "map too large for one snapshot (> 8 GiB of masks)"),
            Self::ChecksumMismatch { stored, computed } => {
                write!(
                    f,
                    "snapshot checksum mismatch: stored {stored:#010x}, computed {computed:#010x}"
                )
            }
            Self::BufferTooSmall { needed, got } => {
                write!(f, "buffer too small: need {needed} bytes, have {got}")
            }
        }
    }
}

impl std::error::Error for SnapshotError {}
