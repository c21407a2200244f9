//! One tile record: the leaves of one tile (an internal node, 128³ voxels) as the map
//! file's leaf records, then the distance field's bands of those leaves as the map file's
//! band records, compressed with zstd and framed by a header with two CRC-32s.
//!
//! ```text
//! head (48 bytes): magic "VXTR" | version u32 | tile origin [i32; 3] | last observed u64
//!                  | leaf count u32 | raw length u32 | payload length u32
//!                  | payload crc32 u32 | head crc32 u32 (over the 44 bytes before it)
//! payload: zstd frame of
//!          leaf count × RECORD bytes (origin, known mask, values), in block order,
//!          then (version 2) band records (origin, band mask, offsets) of leaves of the
//!          record, in block order, to the raw length's end
//! ```
//! All integers little-endian. A record is checked whole (both CRCs, the lengths, each
//! leaf inside its tile, in block order, values in the clamping range; each band a leaf's
//! of the record) before any leaf of it goes into a map. Version 1 records (no bands) read
//! as version 2 records without bands.

use crate::coord::VoxelCoord;
use crate::field::DistanceField;
use crate::grid::{Grid, Leaf, INTERNAL_CHILDREN, INTERNAL_TOTAL_LOG2};
use crate::io::mapfile::{write_band_record, write_leaf_record, RECORD};
use crate::model::QuantizedModel;
use crate::tree::LEAF_VOXELS;
use voxmap_reader::mapfile::{band_record, block_order, fill_leaf, record_origin, BAND_HEAD};

pub use voxmap_reader::mapfile::BandRecord;

pub const RECORD_MAGIC: [u8; 4] = *b"VXTR";
/// The tile record version this build reads and writes.
pub const RECORD_VERSION: u32 = 2;
/// Bytes of a record's head.
pub const HEAD: usize = 48;
/// Raw bytes of one leaf at most: its leaf record and a band of all its voxels.
const LEAF_MAX: usize = RECORD + BAND_HEAD + 3 * LEAF_VOXELS;
/// The longest record a tile can have: its head and the compression bound of all its
/// leaves with their bands.
pub const MAX_RECORD: usize =
    HEAD + INTERNAL_CHILDREN * LEAF_MAX + INTERNAL_CHILDREN * LEAF_MAX / 128 + (64 << 10);
/// The zstd level tile records are written with (see docs/file-formats.md for the sizes).
pub const ZSTD_LEVEL: i32 = 1;

/// A tile's head, as read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RecordHead {
    pub tile: VoxelCoord,
    pub last_observed: u64,
    pub leaves: u32,
    pub raw_len: u32,
    pub payload_len: u32,
    pub payload_crc: u32,
}

/// Why a tile record was refused.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RecordError {
    /// Fewer bytes than the head says.
    Truncated { have: usize, need: usize },
    /// Not a tile record (magic) or its head's CRC fails.
    BadHead(&'static str),
    /// A version this build does not read.
    Version(u32),
    /// The payload's CRC fails, it does not decompress to its length, or its leaves are
    /// not a tile's.
    Corrupt(String),
}

impl std::fmt::Display for RecordError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Truncated { have, need } => {
                write!(f, "truncated: {have} bytes where the record needs {need}")
            }
            Self::BadHead(why) => write!(f, "bad record head: {why}"),
            Self::Version(v) => write!(
                f,
                "tile record version {v} (this build reads 1 to {RECORD_VERSION})"
            ),
            Self::Corrupt(why) => write!(f, "corrupt tile record: {why}"),
        }
    }
}

impl std::error::Error for RecordError {}

/// The origin of the tile holding voxel `v`.
pub fn tile_of(v: VoxelCoord) -> VoxelCoord {
    v.shr(INTERNAL_TOTAL_LOG2).shl(INTERNAL_TOTAL_LOG2)
}

/// A tile's record uncompressed: its leaf records, then its band records.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RawTile {
    pub bytes: Vec<u8>,
    /// Leaf records at the start of `bytes`.
    pub leaves: u32,
}

impl RawTile {
    /// The leaf records and the band records after them.
    pub fn split(&self) -> (&[u8], &[u8]) {
        self.bytes
            .split_at((self.leaves as usize * RECORD).min(self.bytes.len()))
    }

    /// The record's leaves and bands, checked ([`leaves_of`], [`bands_of`]).
    pub fn decode(&self, tile: VoxelCoord, q: &QuantizedModel) -> Result<TileRecord, RecordError> {
        let (leaf_bytes, band_bytes) = self.split();
        let leaves = leaves_of(leaf_bytes, tile, q)?;
        let bands = bands_of(band_bytes, &leaves)?;
        Ok(TileRecord { leaves, bands })
    }
}

/// A tile's record decoded: its leaves in block order and the bands stored with them.
#[derive(Clone, Debug, Default)]
pub struct TileRecord {
    pub leaves: Vec<(VoxelCoord, Leaf<i8>)>,
    pub bands: Vec<BandRecord>,
}

impl TileRecord {
    /// Bytes it holds in memory (for the loader's ready set).
    pub fn heap_bytes(&self) -> usize {
        self.leaves.len() * std::mem::size_of::<(VoxelCoord, Leaf<i8>)>()
            + (self.bands.iter())
                .map(|b| std::mem::size_of::<BandRecord>() + 3 * b.2.len())
                .sum::<usize>()
    }
}

/// The tile at `tile` as uncompressed leaf records (its leaves with a known voxel, in
/// block order), followed by the bands `field` keeps of those leaves.
pub fn raw_tile(grid: &Grid<i8>, tile: VoxelCoord, field: Option<&DistanceField>) -> RawTile {
    // Sized once, not grown by doubling: thousands of evictions and exports allocate it.
    let known = (grid.leaves_of_node(tile))
        .filter(|(_, l)| !l.active.is_empty())
        .count();
    let mut raw = Vec::with_capacity(known * RECORD);
    let mut n = 0;
    for (o, leaf) in grid.leaves_of_node(tile) {
        if leaf.active.is_empty() {
            continue;
        }
        let at = raw.len();
        raw.resize(at + RECORD, 0);
        write_leaf_record(&mut raw[at..], o, leaf);
        n += 1;
    }
    if let Some(f) = field {
        for (o, leaf) in grid.leaves_of_node(tile) {
            if let (false, Some(band)) = (leaf.active.is_empty(), f.leaf(o)) {
                write_band_record(&mut raw, o, band);
            }
        }
    }
    RawTile {
        bytes: raw,
        leaves: n,
    }
}

/// A whole record (head and payload) of a tile's raw records.
pub fn encode(tile: VoxelCoord, last_observed: u64, raw: &RawTile) -> Vec<u8> {
    let payload = zstd::bulk::compress(&raw.bytes, ZSTD_LEVEL).expect("zstd compresses into a Vec");
    let mut out = Vec::with_capacity(HEAD + payload.len());
    out.extend_from_slice(&RECORD_MAGIC);
    out.extend_from_slice(&RECORD_VERSION.to_le_bytes());
    for c in tile.to_array() {
        out.extend_from_slice(&c.to_le_bytes());
    }
    out.extend_from_slice(&last_observed.to_le_bytes());
    out.extend_from_slice(&raw.leaves.to_le_bytes());
    out.extend_from_slice(&(raw.bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
    let head_crc = crc32fast::hash(&out[..HEAD - 4]);
    out.extend_from_slice(&head_crc.to_le_bytes());
    out.extend_from_slice(&payload);
    out
}

/// The head of a record, checked (magic, version, CRC, lengths within a tile's).
pub fn read_head(bytes: &[u8]) -> Result<RecordHead, RecordError> {
    if bytes.len() < HEAD {
        return Err(RecordError::Truncated {
            have: bytes.len(),
            need: HEAD,
        });
    }
    let u32_at = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"));
    if bytes[..4] != RECORD_MAGIC {
        return Err(RecordError::BadHead("not a tile record"));
    }
    if crc32fast::hash(&bytes[..HEAD - 4]) != u32_at(HEAD - 4) {
        return Err(RecordError::BadHead("head checksum mismatch"));
    }
    let version = u32_at(4);
    if !(1..=RECORD_VERSION).contains(&version) {
        return Err(RecordError::Version(version));
    }
    let c = |k: usize| u32_at(8 + 4 * k) as i32;
    let head = RecordHead {
        tile: VoxelCoord::new(c(0), c(1), c(2)),
        last_observed: u64::from_le_bytes(bytes[20..28].try_into().expect("8 bytes")),
        leaves: u32_at(28),
        raw_len: u32_at(32),
        payload_len: u32_at(36),
        payload_crc: u32_at(40),
    };
    if tile_of(head.tile) != head.tile
        || head
            .tile
            .to_array()
            .iter()
            .any(|v| v.unsigned_abs() >= 1 << 30)
    {
        return Err(RecordError::Corrupt("tile origin not a tile's".into()));
    }
    let (leaves, raw) = (head.leaves as usize, head.raw_len as usize);
    let bands_fit = match version {
        1 => raw == leaves * RECORD,
        _ => raw >= leaves * RECORD && raw <= leaves * LEAF_MAX,
    };
    if leaves > INTERNAL_CHILDREN || !bands_fit {
        return Err(RecordError::Corrupt(format!(
            "{} leaves in {} bytes",
            head.leaves, head.raw_len
        )));
    }
    // zstd never grows incompressible data by more than a small bound.
    if head.payload_len as usize > zstd::zstd_safe::compress_bound(head.raw_len as usize) {
        return Err(RecordError::Corrupt(
            "payload longer than its data could make".into(),
        ));
    }
    Ok(head)
}

/// The record's raw records, decompressed and checked against the head (CRC, length);
/// [`RawTile::decode`] checks the leaves and bands. `bytes` is the whole record.
pub fn decode(bytes: &[u8]) -> Result<(RecordHead, RawTile), RecordError> {
    let head = read_head(bytes)?;
    let need = HEAD + head.payload_len as usize;
    if bytes.len() < need {
        return Err(RecordError::Truncated {
            have: bytes.len(),
            need,
        });
    }
    let payload = &bytes[HEAD..need];
    if crc32fast::hash(payload) != head.payload_crc {
        return Err(RecordError::Corrupt("payload checksum mismatch".into()));
    }
    let raw = zstd::bulk::decompress(payload, head.raw_len as usize)
        .map_err(|e| RecordError::Corrupt(format!("payload does not decompress: {e}")))?;
    if raw.len() != head.raw_len as usize {
        return Err(RecordError::Corrupt("payload decompresses short".into()));
    }
    let raw = RawTile {
        bytes: raw,
        leaves: head.leaves,
    };
    Ok((head, raw))
}

/// Raw leaf records of the tile at `tile` as leaves, checked: inside the tile, in strictly
/// increasing block order, values within `q`'s clamping range.
pub fn leaves_of(
    raw: &[u8],
    tile: VoxelCoord,
    q: &QuantizedModel,
) -> Result<Vec<(VoxelCoord, Leaf<i8>)>, RecordError> {
    let bad = |s: String| RecordError::Corrupt(s);
    let mut out: Vec<(VoxelCoord, Leaf<i8>)> = Vec::with_capacity(raw.len() / RECORD);
    let mut last: Option<[i32; 9]> = None;
    for rec in raw.chunks_exact(RECORD) {
        let o = record_origin(rec).map_err(|e| bad(e.to_string()))?;
        if tile_of(o) != tile {
            return Err(bad(format!("leaf {:?} outside the tile", o.to_array())));
        }
        let order = block_order(o);
        if last.is_some_and(|l| l >= order) {
            return Err(bad("leaves out of block order or stored twice".into()));
        }
        last = Some(order);
        let mut leaf: Leaf<i8> = bytemuck::Zeroable::zeroed();
        if !fill_leaf(rec, q, &mut leaf) {
            return Err(bad("log-odds value outside the clamping range".into()));
        }
        out.push((o, leaf));
    }
    Ok(out)
}

/// The band records of a record (its raw bytes after the leaf records), checked: each
/// band of a leaf of `leaves` (the record's), in strictly increasing block order, with one
/// offset per band voxel. What the offsets mean is the field's to check.
pub fn bands_of(
    mut raw: &[u8],
    leaves: &[(VoxelCoord, Leaf<i8>)],
) -> Result<Vec<BandRecord>, RecordError> {
    let bad = |s: String| RecordError::Corrupt(s);
    let mut out = Vec::new();
    let mut at = 0;
    while !raw.is_empty() {
        let (band, rest) = band_record(raw).map_err(|e| bad(e.to_string()))?;
        let order = block_order(band.0);
        // The leaves are in block order: walk them to the band's.
        while at < leaves.len() && block_order(leaves[at].0) < order {
            at += 1;
        }
        if leaves.get(at).is_none_or(|(o, _)| *o != band.0) {
            return Err(bad(format!(
                "band of {:?}, not a leaf of the record or out of order",
                band.0.to_array()
            )));
        }
        at += 1;
        out.push(band);
        raw = rest;
    }
    Ok(out)
}
