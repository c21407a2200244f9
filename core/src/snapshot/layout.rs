//! The byte layout of a snapshot, version 3. All integers little-endian; every section
//! starts on an 8-byte boundary.
//!
//! ```text
//! offset  size                 what
//! 0       160                  Header
//! table   4 * table_capacity   u32 per slot: leaf index + 1, 0 = empty (linear probing)
//! leaves  16 * leaf_count      LeafEntry: origin and mask kinds, record offset; block order
//! masks   masks_len            one mask record per leaf (see `record`), in leaf order,
//!                              zero-padded to a multiple of 8
//! values  512 * leaf_count     i8 log-odds per voxel (only with FLAG_VALUES)
//! ```
//!
//! Version 3 stores each leaf's masks in the smallest of a few O(1)-readable encodings
//! (see `record`); version 2 stored a whole 64-byte mask or none. The entry that the table
//! lookup loads already says how and where the leaf's masks are stored.

use bytemuck::{Pod, Zeroable};

pub const MAGIC: [u8; 8] = *b"VXMSNAP\0";
pub const FORMAT_VERSION: u32 = 3;
/// The snapshot carries per-voxel log-odds.
pub const FLAG_VALUES: u32 = 1;
pub const HEADER_SIZE: usize = std::mem::size_of::<Header>();
pub const VALUES_PER_LEAF: usize = 512;
pub const ENTRY_SIZE: usize = 16;
/// Bytes the masks section may hold: record offsets are `u32`.
pub const MAX_MASKS_LEN: u64 = u32::MAX as u64;

/// One leaf in the `leaves` section.
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct LeafEntry {
    /// The leaf origin in voxels, whose coordinates are multiples of 8, with the known
    /// mask's kind in the low 3 bits of x and the occupied mask's kind in those of y
    /// (z's are zero). Use [`LeafEntry::origin`] and [`LeafEntry::kinds`].
    pub key: [i32; 3],
    /// Byte offset of the leaf's mask record in the masks section.
    pub record: u32,
}

impl LeafEntry {
    pub fn new(origin: [i32; 3], known_kind: u8, occupied_kind: u8, record: u32) -> Self {
        LeafEntry {
            key: [
                origin[0] | i32::from(known_kind & 7),
                origin[1] | i32::from(occupied_kind & 7),
                origin[2],
            ],
            record,
        }
    }

    #[inline]
    pub fn origin(&self) -> [i32; 3] {
        self.key.map(|c| c & !7)
    }

    /// (known kind, occupied kind).
    #[inline]
    pub fn kinds(&self) -> (u8, u8) {
        ((self.key[0] & 7) as u8, (self.key[1] & 7) as u8)
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
    /// Bytes of mask records (the section is zero-padded to a multiple of 8).
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

/// Table slots for `n` leaves. A snapshot that fits in cache is read at the speed of its
/// probes: each extra probe is a dependent load and a mispredicted branch. Up to
/// [`SPACIOUS_TABLE_LEAVES`] leaves (a table of at most 256 KiB) the load factor is 1/4;
/// point queries on the 6 m workloads' snapshots went from 51-58 to 35-50 ns (random,
/// 2,320 leaves) and from 31-40 to 20-31 ns (structured, 416 leaves), for 10 bytes more
/// per leaf. Bigger snapshots miss cache on every lookup whatever the load, so there it is
/// about 2/3 (6 bytes per leaf), with no power-of-two rounding.
pub fn table_capacity_for(n: u64) -> u64 {
    if n <= SPACIOUS_TABLE_LEAVES {
        4 * n + 1
    } else {
        n + n / 2 + 1
    }
}

/// The most leaves for which [`table_capacity_for`] trades bytes for probes.
pub const SPACIOUS_TABLE_LEAVES: u64 = 1 << 14;

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
    /// The table points at a leaf that does not exist, or a leaf entry's kinds or mask
    /// record are malformed.
    BadIndex(&'static str),
    /// The map needs more mask bytes than a leaf entry can address.
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
            Self::TooLarge => write!(f, "map too large for one snapshot (> 4 GiB of masks)"),
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
