//! Map files (`.vxm`) as bytes: the format, its checks, and a map file read as a snapshot
//! ([`snapshot_of`]) for a planner that opens one, with no thread pool and no integrator.
//! The map crate writes them and builds its grid from what [`parse`] checked.
//!
//! ```text
//! magic "VXMMAP\0\0" | version u32 | header length u32 | header (bincode) | header crc32 u32
//! body: leaf_count records of { origin [i32; 3], known mask [u64; 8], values [i8; 512] }
//! version 2 only, the distance field: field leaf_count records of
//!   { origin [i32; 3], band mask [u64; 8], one (dx, dy, dz) i8 offset per band voxel }
//! ```
//! A file without a distance field is version 1; one with a field is version 2, whose
//! header adds the field's settings, record count, length and CRC-32. All integers
//! little-endian. The header holds the body's CRC-32; a file is checked whole before
//! anything is built from it, so a bad file changes nothing.

use crate::coord::{GridTransform, VoxelCoord};
use crate::field::{check_bands, obstacles, FieldConfig};
use crate::mask::Mask512;
use crate::model::{QuantizedModel, SensorModel};
use crate::snapshot::{Encoder, FieldBands, InOrder, MapInfo, Meta, Pieces, PlannedLeaf};
use crate::tree::{Leaf, LEAF_VOXELS};
use hashbrown::HashMap;
use serde::{Deserialize, Serialize};

pub const MAP_MAGIC: [u8; 8] = *b"VXMMAP\0\0";
/// The newest version this build reads and writes: 2 with a distance field, else 1.
pub const MAP_VERSION: u32 = 2;
/// The version of files without a distance field.
pub const MAP_VERSION_PLAIN: u32 = 1;
/// A body record: origin, then known mask at `MASK_AT`, then values at `VALUES_AT`.
pub const MASK_AT: usize = 12;
pub const VALUES_AT: usize = MASK_AT + 64;
pub const RECORD: usize = VALUES_AT + LEAF_VOXELS;
/// The longest header a file may have.
pub const MAX_HEADER: usize = 4096;

/// A version 1 header: the map's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FileHeader {
    pub resolution: f64,
    pub model: SensorModel,
    pub frac_bits: u8,
    pub leaf_count: u64,
    pub body_crc32: u32,
}

/// A version 2 header: the map's, then the distance field's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FileHeaderWithField {
    pub map: FileHeader,
    pub field: FieldFileHeader,
}

/// The distance field's part of a version 2 header.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldFileHeader {
    pub config: FieldConfig,
    /// The voxels the field covered (its window when saved), inclusive.
    pub window: Option<([i32; 3], [i32; 3])>,
    pub leaf_count: u64,
    pub body_len: u64,
    pub body_crc32: u32,
}

/// Why map bytes did not decode.
#[derive(Debug, PartialEq)]
pub enum Decode {
    Version(u32),
    Corrupt(String),
}

impl std::fmt::Display for Decode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Version(v) => write!(
                f,
                "unsupported map file version {v} (this build reads {MAP_VERSION})"
            ),
            Self::Corrupt(problem) => write!(f, "corrupt map file: {problem}"),
        }
    }
}

impl std::error::Error for Decode {}

fn bad(s: &str) -> Decode {
    Decode::Corrupt(s.to_string())
}

/// A map file whose header, lengths and checksums were checked.
#[derive(Debug)]
pub struct Parsed<'a> {
    pub header: FileHeader,
    pub field: Option<FieldFileHeader>,
    /// `header.leaf_count` records of [`RECORD`] bytes.
    pub body: &'a [u8],
    /// The distance field's records (empty without a field).
    pub field_body: &'a [u8],
}

/// CRC-32 of `bytes`, in pieces of `piece` bytes run by `pieces`, combined.
pub fn crc32(bytes: &[u8], piece: usize, pieces: &impl Pieces) -> u32 {
    pieces
        .map(bytes.chunks(piece).collect(), |p| {
            let mut h = crc32fast::Hasher::new();
            h.update(p);
            h
        })
        .into_iter()
        .fold(crc32fast::Hasher::new(), |mut acc, h| {
            acc.combine(&h);
            acc
        })
        .finalize()
}

/// Check map-file bytes: magic, version, header and its checksum, the body's and the
/// field's lengths and checksums (computed in pieces run by `pieces`).
pub fn parse<'a>(bytes: &'a [u8], pieces: &impl Pieces) -> Result<Parsed<'a>, Decode> {
    const CRC_PIECE: usize = 8 << 20;
    if bytes.len() < 16 || bytes[..8] != MAP_MAGIC {
        return Err(bad("not a voxmap map file (bad magic)"));
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
    if version != MAP_VERSION && version != MAP_VERSION_PLAIN {
        return Err(Decode::Version(version));
    }
    let hlen = u32::from_le_bytes(bytes[12..16].try_into().expect("4 bytes")) as usize;
    if hlen > MAX_HEADER || bytes.len() < 16 + hlen + 4 {
        return Err(bad("header length out of range or file truncated"));
    }
    let hb = &bytes[16..16 + hlen];
    let hcrc = u32::from_le_bytes(bytes[16 + hlen..20 + hlen].try_into().expect("4 bytes"));
    if crc32fast::hash(hb) != hcrc {
        return Err(bad("header checksum mismatch"));
    }
    let cfg = bincode::config::standard().with_limit::<MAX_HEADER>();
    let (header, field) = if version == MAP_VERSION_PLAIN {
        let (h, _): (FileHeader, usize) = bincode::serde::decode_from_slice(hb, cfg)
            .map_err(|e| Decode::Corrupt(format!("header: {e}")))?;
        (h, None)
    } else {
        let (h, _): (FileHeaderWithField, usize) = bincode::serde::decode_from_slice(hb, cfg)
            .map_err(|e| Decode::Corrupt(format!("header: {e}")))?;
        (h.map, Some(h.field))
    };
    let mut body = &bytes[20 + hlen..];
    let mut field_body: &[u8] = &[];
    if let Some(fh) = &field {
        let split = header
            .leaf_count
            .checked_mul(RECORD as u64)
            .filter(|&n| n <= body.len() as u64)
            .ok_or_else(|| bad("file shorter than its leaves"))?;
        (body, field_body) = body.split_at(split as usize);
        if field_body.len() as u64 != fh.body_len {
            return Err(Decode::Corrupt(format!(
                "distance field is {} bytes, header says {}",
                field_body.len(),
                fh.body_len
            )));
        }
        if crc32(field_body, CRC_PIECE, pieces) != fh.body_crc32 {
            return Err(bad("distance field checksum mismatch"));
        }
    }
    // Leaf indices are u32.
    if header.leaf_count > u64::from(u32::MAX) {
        return Err(bad("leaf count out of range"));
    }
    let want = header.leaf_count * RECORD as u64;
    if body.len() as u64 != want {
        return Err(Decode::Corrupt(format!(
            "body is {} bytes, header says {} leaves ({want} bytes)",
            body.len(),
            header.leaf_count
        )));
    }
    if crc32(body, CRC_PIECE, pieces) != header.body_crc32 {
        return Err(bad("body checksum mismatch"));
    }
    Ok(Parsed {
        header,
        field,
        body,
        field_body,
    })
}

impl Parsed<'_> {
    /// The map's fixed-point sensor model, checked against the file's scale.
    pub fn quantized(&self) -> Result<QuantizedModel, Decode> {
        let q = self
            .header
            .model
            .quantize()
            .map_err(|e| Decode::Corrupt(format!("parameters: {e}")))?;
        if q.frac_bits != self.header.frac_bits {
            return Err(bad("fixed-point scale disagrees with the sensor model"));
        }
        Ok(q)
    }
}

/// The origin of a body record, checked: leaf-aligned, within the index space.
pub fn record_origin(rec: &[u8]) -> Result<VoxelCoord, Decode> {
    let c = |k: usize| i32::from_le_bytes(rec[4 * k..4 * k + 4].try_into().expect("4 bytes"));
    let o = VoxelCoord::new(c(0), c(1), c(2));
    if o.to_array()
        .iter()
        .any(|v| v & 7 != 0 || v.unsigned_abs() >= 1 << 30)
    {
        return Err(bad("leaf origin not leaf-aligned or out of range"));
    }
    Ok(o)
}

/// Fill `leaf` from a body record: its known voxels' values (the others 0) and its
/// occupied marks; false where a known value lies outside `q`'s clamping range.
pub fn fill_leaf(rec: &[u8], q: &QuantizedModel, leaf: &mut Leaf<i8>) -> bool {
    let mut bad = false;
    for w in 0..8 {
        let word = u64::from_le_bytes(rec[MASK_AT + 8 * w..][..8].try_into().expect("8 bytes"));
        leaf.active.words[w] = word;
        let vals = &rec[VALUES_AT + 64 * w..][..64];
        // The leaf's occupied marks (`Leaf::marked`), in the same pass.
        let mut occupied = 0u64;
        for (b, (out, &v)) in leaf.values[64 * w..64 * w + 64]
            .iter_mut()
            .zip(vals)
            .enumerate()
        {
            let known = word >> b & 1 != 0;
            let v = v as i8;
            bad |= known & !(q.min..=q.max).contains(&v);
            occupied |= u64::from(known & (v >= q.threshold)) << b;
            *out = if known { v } else { 0 };
        }
        leaf.marked.words[w] = occupied;
    }
    !bad
}

/// A distance field's band of one leaf, as a file holds it.
pub type BandRecord = (VoxelCoord, Mask512, Vec<[i8; 3]>);

/// The distance field records of a version 2 file: origin, band mask, offsets. Only their
/// framing is checked here; [`check_bands`] checks them against the map.
pub fn field_records(fh: &FieldFileHeader, mut rec: &[u8]) -> Result<Vec<BandRecord>, Decode> {
    if fh.leaf_count > u64::from(u32::MAX) {
        return Err(Decode::Corrupt(
            "distance field: leaf count out of range".into(),
        ));
    }
    let mut out = Vec::with_capacity(fh.leaf_count.min(1 << 20) as usize);
    for _ in 0..fh.leaf_count {
        let (band, rest) = band_record(rec)?;
        out.push(band);
        rec = rest;
    }
    if !rec.is_empty() {
        return Err(Decode::Corrupt(
            "distance field: bytes after the last record".into(),
        ));
    }
    Ok(out)
}

/// The first band record of `rec` (origin, band mask, one offset per band voxel: what a
/// map file's field section and a tile record's band section hold) and the bytes after it.
pub fn band_record(rec: &[u8]) -> Result<(BandRecord, &[u8]), Decode> {
    let truncated = || Decode::Corrupt("distance field: records truncated".into());
    if rec.len() < BAND_HEAD {
        return Err(truncated());
    }
    let c = |k: usize| i32::from_le_bytes(rec[4 * k..4 * k + 4].try_into().expect("4 bytes"));
    let origin = VoxelCoord::new(c(0), c(1), c(2));
    let mut mask = Mask512::EMPTY;
    for (w, word) in mask.words.iter_mut().enumerate() {
        *word = u64::from_le_bytes(rec[12 + 8 * w..20 + 8 * w].try_into().expect("8 bytes"));
    }
    let n = 3 * mask.count() as usize;
    let offsets_bytes = rec.get(BAND_HEAD..BAND_HEAD + n).ok_or_else(truncated)?;
    let offsets = (offsets_bytes.chunks_exact(3))
        .map(|o| [o[0] as i8, o[1] as i8, o[2] as i8])
        .collect();
    Ok(((origin, mask, offsets), &rec[BAND_HEAD + n..]))
}

/// Bytes of a band record before its offsets: origin and band mask.
pub const BAND_HEAD: usize = 76;

/// The place of the leaf at `origin` in block order: internal nodes (128³ voxels) by
/// origin (z, y, x), within a node its blocks (64³) by origin, within a block its leaves by
/// origin: the order of the map crate's `Grid::leaves_in_block_order`, which snapshots
/// index by.
pub fn block_order(o: VoxelCoord) -> [i32; 9] {
    let [x, y, z] = o.to_array();
    [
        z >> 7,
        y >> 7,
        x >> 7,
        z >> 6 & 1,
        y >> 6 & 1,
        x >> 6 & 1,
        z >> 3 & 7,
        y >> 3 & 7,
        x >> 3 & 7,
    ]
}

/// A field's bands read from a file, for the encoder.
struct FileBands {
    config: FieldConfig,
    radius: u32,
    resolution: f64,
    window: Option<(VoxelCoord, VoxelCoord)>,
    bands: HashMap<VoxelCoord, (Mask512, Vec<[i8; 3]>)>,
}

impl FieldBands for FileBands {
    fn config(&self) -> FieldConfig {
        self.config
    }

    fn radius(&self) -> u32 {
        self.radius
    }

    fn max_distance(&self) -> f64 {
        f64::from(self.radius) * self.resolution
    }

    fn window(&self) -> Option<(VoxelCoord, VoxelCoord)> {
        self.window
    }

    fn band(&self, origin: VoxelCoord) -> Option<(&Mask512, &[[i8; 3]])> {
        self.bands.get(&origin).map(|(m, o)| (m, o.as_slice()))
    }
}

/// A map file as a whole-map snapshot with its log-odds values (so probabilities can be
/// read) and the distance field it carries, sequence 0: the bytes the map crate's writer
/// makes of the same map, built here in order on the calling thread.
pub fn snapshot_of(bytes: &[u8]) -> Result<Vec<u8>, Decode> {
    let parsed = parse(bytes, &InOrder)?;
    let q = parsed.quantized()?;
    let resolution = parsed.header.resolution;
    GridTransform::new(resolution).map_err(|e| Decode::Corrupt(format!("parameters: {e}")))?;
    let mut leaves = Vec::with_capacity(parsed.header.leaf_count as usize);
    for rec in parsed.body.chunks_exact(RECORD) {
        let origin = record_origin(rec)?;
        let mut leaf: Leaf<i8> = bytemuck::Zeroable::zeroed();
        if !fill_leaf(rec, &q, &mut leaf) {
            return Err(bad("log-odds value outside the clamping range"));
        }
        leaves.push((origin, leaf));
    }
    leaves.sort_unstable_by_key(|(o, _)| block_order(*o));
    if leaves.windows(2).any(|w| w[0].0 == w[1].0) {
        return Err(bad("leaf stored twice"));
    }
    let field = match &parsed.field {
        None => None,
        Some(fh) => {
            let field_bad = |s: String| Decode::Corrupt(format!("distance field: {s}"));
            let radius = fh
                .config
                .radius(resolution)
                .map_err(|e| field_bad(e.to_string()))?;
            let window = fh
                .window
                .map(|(lo, hi)| (VoxelCoord::from_array(lo), VoxelCoord::from_array(hi)));
            let records = field_records(fh, parsed.field_body)?;
            let n = records.len();
            let bands: HashMap<_, _> = records.into_iter().map(|(o, m, d)| (o, (m, d))).collect();
            let is_leaf = |o: VoxelCoord| {
                leaves
                    .binary_search_by_key(&block_order(o), |(l, _)| block_order(*l))
                    .is_ok()
            };
            let policy = fh.config.unknown;
            let map_leaves = leaves
                .iter()
                .map(|(o, l)| (*o, obstacles(&l.active, &l.marked, policy)));
            check_bands(
                &bands,
                bands.len() != n,
                radius,
                window,
                is_leaf,
                map_leaves,
            )
            .map_err(field_bad)?;
            Some(FileBands {
                config: fh.config,
                radius,
                resolution,
                window,
                bands,
            })
        }
    };
    let planned = leaves
        .iter()
        .map(|(o, l)| PlannedLeaf::new(*o, l, None))
        .collect();
    let meta = Meta {
        with_values: true,
        ..Default::default()
    };
    let info = MapInfo {
        resolution,
        quantized: q,
    };
    let encoder = Encoder::new(info, planned, Vec::new(), None, meta, InOrder);
    let encoder = match &field {
        Some(f) => encoder.with_field(f),
        None => encoder,
    };
    Ok(encoder.to_vec())
}

/// A map file or snapshot file could not be opened as a snapshot; names the file.
#[derive(Debug)]
#[non_exhaustive]
pub enum OpenError {
    Io {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    /// A map file that is not what it claims.
    Map {
        path: std::path::PathBuf,
        source: Decode,
    },
    /// A snapshot file that does not open.
    Snapshot {
        path: std::path::PathBuf,
        source: crate::snapshot::SnapshotError,
    },
}

impl std::fmt::Display for OpenError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Io { path, source } => write!(f, "{}: {source}", path.display()),
            Self::Map { path, source } => write!(f, "{}: {source}", path.display()),
            Self::Snapshot { path, source } => write!(f, "{}: {source}", path.display()),
        }
    }
}

impl std::error::Error for OpenError {}

/// A map file or a snapshot file as verified snapshot bytes, told apart by their magic: a
/// snapshot is checked whole (structure and checksum); a map file becomes a whole-map
/// snapshot with its probabilities and the distance field it carries ([`snapshot_of`]).
pub fn read_as_snapshot(path: &std::path::Path) -> Result<Vec<u8>, OpenError> {
    let bytes = std::fs::read(path).map_err(|source| OpenError::Io {
        path: path.into(),
        source,
    })?;
    if bytes.starts_with(&MAP_MAGIC) {
        return snapshot_of(&bytes).map_err(|source| OpenError::Map {
            path: path.into(),
            source,
        });
    }
    crate::snapshot::SnapshotView::open_checked(&bytes).map_err(|source| OpenError::Snapshot {
        path: path.into(),
        source,
    })?;
    Ok(bytes)
}
