//! The byte layout of a snapshot, version 1. All integers little-endian; every section
//! starts on an 8-byte boundary.
//!
//! ```text
//! offset  size                 what
//! 0       152                  Header
//! table   4 * table_capacity   u32 per slot: leaf index + 1, 0 = empty (linear probing)
//! origins 12 * leaf_count      [i32; 3] leaf origin (voxel coords, multiples of 8), sorted
//! masks   128 * leaf_count     [u64; 8] known mask, then [u64; 8] occupied mask
//! values  512 * leaf_count     i8 log-odds per voxel (only with FLAG_VALUES)
//! ```

use bytemuck::{Pod, Zeroable};

pub const MAGIC: [u8; 8] = *b"VXMSNAP\0";
pub const FORMAT_VERSION: u32 = 1;
/// The snapshot carries per-voxel log-odds.
pub const FLAG_VALUES: u32 = 1;
pub const HEADER_SIZE: usize = std::mem::size_of::<Header>();
pub const MASKS_PER_LEAF: usize = 128;
pub const VALUES_PER_LEAF: usize = 512;
pub const ORIGIN_SIZE: usize = 12;

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
    /// Power of two, >= 2 * leaf_count (or 1 when empty).
    pub table_capacity: u64,
    pub table_offset: u64,
    pub origins_offset: u64,
    pub masks_offset: u64,
    /// 0 when FLAG_VALUES is clear.
    pub values_offset: u64,
    pub total_len: u64,
    /// CRC-32 (IEEE) of bytes [HEADER_SIZE, total_len).
    pub checksum: u32,
    pub reserved: u32,
}

const _: () = assert!(HEADER_SIZE == 152);
const _: () = assert!(std::mem::offset_of!(Header, resolution) == 24);
const _: () = assert!(std::mem::offset_of!(Header, bounds_min) == 72);
const _: () = assert!(std::mem::offset_of!(Header, table_capacity) == 96);
const _: () = assert!(std::mem::offset_of!(Header, total_len) == 136);
const _: () = assert!(std::mem::offset_of!(Header, checksum) == 144);

/// Slot of a leaf origin in the table (before probing).
#[inline]
pub fn table_hash(o: [i32; 3], mask: u64) -> u64 {
    let k = |c: i32, m: u64| ((c >> 3) as u32 as u64).wrapping_mul(m);
    let h = k(o[0], 0x9E37_79B1) ^ k(o[1], 0x85EB_CA77) ^ k(o[2], 0xC2B2_AE3D);
    (h ^ (h >> 29)) & mask
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
    /// The table points at a leaf that does not exist, or an origin is not leaf-aligned.
    BadIndex(&'static str),
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
