//! Map files: the full map (log-odds, sensor model, resolution, and its distance field) in
//! a versioned, checksummed file, written atomically; and snapshot files. The format and
//! its checks are `voxmap-reader`'s `mapfile` (drawn out there and in
//! `docs/file-formats.md`); this module writes files and builds a map from one. A loaded
//! field is checked against its map (every obstacle at offset 0, nothing else there), so a
//! field of another map is refused. A file is loaded completely and verified before a map
//! is built, so a bad file changes nothing.

use crate::coord::VoxelCoord;
use crate::field::{DistanceField, LeafBand};
use crate::grid::Leaf;
use crate::occupancy::OccupancyMap;
use crate::snapshot::{OnPool, SnapshotError, SnapshotView};
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};
use voxmap_reader::mapfile::{self as format, fill_leaf, record_origin};
pub use voxmap_reader::mapfile::{
    Decode, FieldFileHeader, FileHeader, FileHeaderWithField, MAP_MAGIC, MAP_VERSION,
    MAP_VERSION_PLAIN, MASK_AT, RECORD, VALUES_AT,
};

/// A map or snapshot file could not be written or read.
#[derive(Debug)]
#[non_exhaustive]
pub enum MapFileError {
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The file is not what it claims: names the file and the problem.
    Corrupt {
        path: PathBuf,
        problem: String,
    },
    UnsupportedVersion {
        path: PathBuf,
        version: u32,
    },
    Snapshot {
        path: PathBuf,
        source: SnapshotError,
    },
    /// A distance field cannot be built for the map in the file (its settings do not fit
    /// the map's resolution).
    Field {
        path: PathBuf,
        source: crate::coord::ConfigError,
    },
}

impl std::fmt::Display for MapFileError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Io { path, source } => write!(f, "{}: {source}", path.display()),
            Self::Corrupt { path, problem } => {
                write!(f, "{}: corrupt map file: {problem}", path.display())
            }
            Self::UnsupportedVersion { path, version } => {
                write!(
                    f,
                    "{}: unsupported map file version {version} (this build reads {MAP_VERSION})",
                    path.display()
                )
            }
            Self::Snapshot { path, source } => write!(f, "{}: {source}", path.display()),
            Self::Field { path, source } => {
                write!(
                    f,
                    "{}: no distance field for this map: {source}",
                    path.display()
                )
            }
        }
    }
}

impl std::error::Error for MapFileError {}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> MapFileError + '_ {
    move |source| MapFileError::Io {
        path: path.into(),
        source,
    }
}

/// Write `bytes` to `path` atomically: a temporary file in the same directory, fsync,
/// rename over `path`, fsync the directory. A crash leaves the old file or the new one,
/// and its temporary file, which the next save to `path` removes.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), MapFileError> {
    write_atomic_parts(path, &[bytes])
}

/// [`write_atomic`] of the concatenation of `parts`, without concatenating them in memory.
pub fn write_atomic_parts(path: &Path, parts: &[&[u8]]) -> Result<(), MapFileError> {
    write_atomic_with(path, |f| parts.iter().try_for_each(|p| f.write_all(p)))
}

/// [`write_atomic`] of what `write` writes to the temporary file.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut std::fs::File) -> std::io::Result<()>,
) -> Result<(), MapFileError> {
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path.file_name().ok_or_else(|| MapFileError::Io {
        path: path.into(),
        source: std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file path"),
    })?;
    let stem = format!(".{}.tmp.", name.to_string_lossy());
    remove_dead_temporaries(dir, &stem);
    let tmp = dir.join(format!("{stem}{}", std::process::id()));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp).map_err(io_err(&tmp))?;
        write(&mut f).map_err(io_err(&tmp))?;
        f.sync_all().map_err(io_err(&tmp))?;
        std::fs::rename(&tmp, path).map_err(io_err(path))?;
        if let Ok(d) = std::fs::File::open(dir) {
            let _ = d.sync_all();
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Remove the temporary files `<stem><pid>` in `dir` of processes no longer running: a
/// save killed before its rename leaves one as large as the map, and a service that
/// crashes and restarts would fill the disk with them. Where the system does not say which
/// processes run (no `/proc`), nothing is removed.
fn remove_dead_temporaries(dir: &Path, stem: &str) {
    let proc = Path::new("/proc");
    if !proc.join("self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let pid = name
            .to_str()
            .and_then(|n| n.strip_prefix(stem))
            .and_then(|p| p.parse::<u32>().ok());
        if let Some(pid) = pid {
            if pid != std::process::id() && !proc.join(pid.to_string()).exists() {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

/// A map file in memory as its head (magic, version, header) and body (leaf records): the
/// body is most of it, and writing the two parts saves copying it once more.
pub struct EncodedMap {
    pub head: Vec<u8>,
    pub body: Vec<u8>,
    /// The distance field's records (empty without one).
    pub field: Vec<u8>,
}

impl EncodedMap {
    /// Write the file atomically (see [`write_atomic`]).
    pub fn write(&self, path: &Path) -> Result<(), MapFileError> {
        write_atomic_parts(path, &[&self.head, &self.body, &self.field])
    }

    pub fn len(&self) -> usize {
        self.head.len() + self.body.len() + self.field.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn into_bytes(self) -> Vec<u8> {
        let mut out = self.head;
        out.extend_from_slice(&self.body);
        out.extend_from_slice(&self.field);
        out
    }
}

/// Encode a map file in memory, as one buffer.
pub fn encode_map(map: &OccupancyMap) -> Vec<u8> {
    encode_map_parts(map).into_bytes()
}

/// Encode a map file in memory, as head and body. Leaves go in block order (see
/// [`crate::grid::Grid::leaves_in_block_order`]), so equal maps give equal files; records
/// are filled and checksummed in parallel on the current rayon pool.
pub fn encode_map_parts(map: &OccupancyMap) -> EncodedMap {
    encode_map_parts_with(map, None)
}

/// [`encode_map_parts`], with the distance field kept beside the map when given (a
/// version 2 file).
pub fn encode_map_parts_with(map: &OccupancyMap, field: Option<&DistanceField>) -> EncodedMap {
    use rayon::prelude::*;
    let leaves: Vec<_> = map
        .grid()
        .leaves_in_block_order()
        .filter(|(_, l)| !l.active.is_empty())
        .collect();
    let mut body = vec![0u8; leaves.len() * RECORD];
    body.par_chunks_mut(RECORD)
        .zip(&leaves)
        .with_min_len(256)
        .for_each(|(rec, (o, leaf))| write_leaf_record(rec, *o, leaf));
    let header = FileHeader {
        resolution: map.resolution(),
        model: *map.model(),
        frac_bits: map.quantized().frac_bits,
        leaf_count: leaves.len() as u64,
        body_crc32: par_crc32(&body),
    };
    let Some(f) = field else {
        return EncodedMap {
            head: encode_head(&header, MAP_VERSION_PLAIN),
            body,
            field: Vec::new(),
        };
    };
    // In block order, as the leaves: a tile store streams both tile by tile.
    let mut leaves: Vec<_> = f.leaves().collect();
    leaves.sort_unstable_by_key(|(o, _)| format::block_order(*o));
    let mut records = Vec::new();
    for (o, band) in &leaves {
        write_band_record(&mut records, *o, band);
    }
    let header = FileHeaderWithField {
        map: header,
        field: FieldFileHeader {
            config: *f.config(),
            window: f.window().map(|(lo, hi)| (lo.to_array(), hi.to_array())),
            leaf_count: leaves.len() as u64,
            body_len: records.len() as u64,
            body_crc32: par_crc32(&records),
        },
    };
    EncodedMap {
        head: encode_head(&header, MAP_VERSION),
        body,
        field: records,
    }
}

/// Append the band record of the leaf at `origin` (origin, band mask, offsets): what the
/// map file's field section and the tile store's band sections hold.
pub fn write_band_record(out: &mut Vec<u8>, origin: VoxelCoord, band: &LeafBand) {
    for c in origin.to_array() {
        out.extend_from_slice(&c.to_le_bytes());
    }
    for w in band.mask().words {
        out.extend_from_slice(&w.to_le_bytes());
    }
    for o in band.offsets() {
        out.extend(o.map(|c| c as u8));
    }
}

/// One body record ([`RECORD`] bytes) of the leaf at `origin`: what the map file's body
/// and the tile store's tile records hold.
pub fn write_leaf_record(rec: &mut [u8], origin: VoxelCoord, leaf: &Leaf<i8>) {
    for (k, c) in origin.to_array().into_iter().enumerate() {
        rec[4 * k..4 * k + 4].copy_from_slice(&c.to_le_bytes());
    }
    for (w, &word) in leaf.active.words.iter().enumerate() {
        rec[MASK_AT + 8 * w..][..8].copy_from_slice(&word.to_le_bytes());
        // Unknown voxels are stored as 0, whatever the leaf holds there.
        let vals = &leaf.values[64 * w..64 * w + 64];
        for (b, (out, &v)) in rec[VALUES_AT + 64 * w..][..64]
            .iter_mut()
            .zip(vals)
            .enumerate()
        {
            *out = (v as u8) & 0u8.wrapping_sub((word >> b & 1) as u8);
        }
    }
}

/// Where [`write_map_streamed`]'s pieces go: leaf records to the body, band records to
/// the distance field's section, each to a temporary file as they come, their lengths and
/// checksums counted.
pub struct StreamSink {
    parts: [Part; 2],
    bands: u64,
}

struct Part {
    path: PathBuf,
    out: std::io::BufWriter<std::fs::File>,
    crc: crc32fast::Hasher,
    len: u64,
}

impl Part {
    fn create(path: PathBuf) -> Result<Self, MapFileError> {
        let file = std::fs::File::create(&path).map_err(io_err(&path))?;
        Ok(Self {
            out: std::io::BufWriter::new(file),
            path,
            crc: crc32fast::Hasher::new(),
            len: 0,
        })
    }

    fn put(&mut self, bytes: &[u8]) -> Result<(), MapFileError> {
        self.crc.update(bytes);
        self.len += bytes.len() as u64;
        self.out.write_all(bytes).map_err(io_err(&self.path))
    }
}

impl StreamSink {
    /// Whole leaf records, in block order.
    pub fn leaves(&mut self, records: &[u8]) -> Result<(), MapFileError> {
        self.parts[0].put(records)
    }

    /// `count` whole band records (a field's), in block order of their leaves.
    pub fn bands(&mut self, records: &[u8], count: u64) -> Result<(), MapFileError> {
        self.bands += count;
        self.parts[1].put(records)
    }
}

/// The distance field's settings and window a streamed map file carries with its bands.
#[derive(Clone, Copy, Debug)]
pub struct StreamedField {
    pub config: crate::field::FieldConfig,
    pub window: Option<(VoxelCoord, VoxelCoord)>,
}

/// A map file written from its leaf records (and, with `field`, its band records) in
/// pieces: they go to temporary files as they come, then the head, the body and the
/// field's section to `path` atomically. For maps larger than memory (a tile store's).
/// Without a field it is a plain (version 1) file; band records given then are dropped.
/// Returns the leaves written.
pub fn write_map_streamed<E: From<MapFileError>>(
    path: &Path,
    map: &OccupancyMap,
    field: Option<StreamedField>,
    mut pieces: impl FnMut(&mut StreamSink) -> Result<(), E>,
) -> Result<u64, E> {
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map_or("map".into(), |n| n.to_string_lossy());
    let temp = |what: &str| dir.join(format!(".{name}.{what}.{}", std::process::id()));
    let paths = [temp("body"), temp("field")];
    let result = (|| {
        let mut sink = StreamSink {
            parts: [
                Part::create(paths[0].clone())?,
                Part::create(paths[1].clone())?,
            ],
            bands: 0,
        };
        pieces(&mut sink)?;
        let mut done = Vec::new();
        for part in sink.parts {
            let Part {
                path,
                mut out,
                crc,
                len,
            } = part;
            out.flush().map_err(io_err(&path))?;
            done.push((path, crc.finalize(), len));
        }
        let header = FileHeader {
            resolution: map.resolution(),
            model: *map.model(),
            frac_bits: map.quantized().frac_bits,
            leaf_count: done[0].2 / RECORD as u64,
            body_crc32: done[0].1,
        };
        let head = match field {
            None => encode_head(&header, MAP_VERSION_PLAIN),
            Some(f) => encode_head(
                &FileHeaderWithField {
                    map: header.clone(),
                    field: FieldFileHeader {
                        config: f.config,
                        window: f.window.map(|(lo, hi)| (lo.to_array(), hi.to_array())),
                        leaf_count: sink.bands,
                        body_len: done[1].2,
                        body_crc32: done[1].1,
                    },
                },
                MAP_VERSION,
            ),
        };
        let open = |p: &PathBuf| std::fs::File::open(p).map_err(io_err(p));
        let (mut body, mut bands) = (open(&paths[0])?, open(&paths[1])?);
        write_atomic_with(path, |f| {
            f.write_all(&head)?;
            std::io::copy(&mut body, f)?;
            if field.is_some() {
                std::io::copy(&mut bands, f)?;
            }
            Ok(())
        })?;
        Ok(header.leaf_count)
    })();
    for p in &paths {
        let _ = std::fs::remove_file(p);
    }
    result
}

/// A file's head: magic, version, header length, header, header checksum.
fn encode_head(header: &impl Serialize, version: u32) -> Vec<u8> {
    let hb = bincode::serde::encode_to_vec(header, bincode::config::standard())
        .expect("plain struct encodes");
    let mut head = Vec::with_capacity(20 + hb.len());
    head.extend_from_slice(&MAP_MAGIC);
    head.extend_from_slice(&version.to_le_bytes());
    head.extend_from_slice(&(hb.len() as u32).to_le_bytes());
    head.extend_from_slice(&hb);
    head.extend_from_slice(&crc32fast::hash(&hb).to_le_bytes());
    head
}

/// CRC-32 of `bytes`, in pieces on the current rayon pool, combined.
fn par_crc32(bytes: &[u8]) -> u32 {
    format::crc32(bytes, 8 << 20, &OnPool)
}

/// Save a map atomically.
pub fn save_map(map: &OccupancyMap, path: &Path) -> Result<(), MapFileError> {
    encode_map_parts(map).write(path)
}

/// Save a map and its distance field atomically (a version 2 file).
pub fn save_map_with_field(
    map: &OccupancyMap,
    field: Option<&DistanceField>,
    path: &Path,
) -> Result<(), MapFileError> {
    encode_map_parts_with(map, field).write(path)
}

/// Load a map file into a new map. Nothing is returned unless the whole file verified.
pub fn load_map(path: &Path) -> Result<OccupancyMap, MapFileError> {
    Ok(load_map_with_field(path)?.0)
}

/// Load a map file and the distance field it carries, if any. Nothing is returned unless
/// the whole file verified.
pub fn load_map_with_field(
    path: &Path,
) -> Result<(OccupancyMap, Option<DistanceField>), MapFileError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    decode_map_with_field(&bytes).map_err(decode_err(path))
}

fn decode_err(path: &Path) -> impl FnOnce(Decode) -> MapFileError + '_ {
    move |e| match e {
        Decode::Version(version) => MapFileError::UnsupportedVersion {
            path: path.into(),
            version,
        },
        Decode::Corrupt(problem) => MapFileError::Corrupt {
            path: path.into(),
            problem,
        },
    }
}

/// Decode map-file bytes into a new map (a distance field the file carries is checked and
/// dropped).
pub fn decode_map(bytes: &[u8]) -> Result<OccupancyMap, Decode> {
    Ok(decode_map_with_field(bytes)?.0)
}

/// Decode map-file bytes into a new map and the distance field the file carries.
pub fn decode_map_with_field(
    bytes: &[u8],
) -> Result<(OccupancyMap, Option<DistanceField>), Decode> {
    let bad = |s: &str| Decode::Corrupt(s.to_string());
    let parsed = format::parse(bytes, &OnPool)?;
    let h = &parsed.header;
    let mut map = OccupancyMap::new(h.resolution, h.model)
        .map_err(|e| Decode::Corrupt(format!("parameters: {e}")))?;
    let q = parsed.quantized()?;
    let body = parsed.body;
    // Leaves are created in record order, so record i fills leaf i; a leaf that exists
    // already is a record stored twice.
    let grid = map.grid_mut();
    let mut hint = (VoxelCoord::new(i32::MIN, 0, 0), u32::MAX);
    let mut items: Vec<(u32, &[u8])> = Vec::with_capacity(h.leaf_count as usize);
    for (i, rec) in body.chunks_exact(RECORD).enumerate() {
        let o = record_origin(rec)?;
        if grid.leaf_index_or_insert(o, Some(&mut hint)) as usize != i {
            return Err(bad("leaf stored twice"));
        }
        items.push((i as u32, rec));
    }
    let out_of_range = grid.leaf_pool_mut().par_update(
        &items,
        |_| (),
        |leaf, rec| u64::from(!fill_leaf(rec, &q, leaf)),
    );
    if out_of_range > 0 {
        return Err(bad("log-odds value outside the clamping range"));
    }
    let field = match &parsed.field {
        None => None,
        Some(fh) => Some(decode_field(&map, fh, parsed.field_body)?),
    };
    Ok((map, field))
}

/// The distance field records of a version 2 file, checked against its map.
fn decode_field(
    map: &OccupancyMap,
    fh: &FieldFileHeader,
    rec: &[u8],
) -> Result<DistanceField, Decode> {
    let bad = |s: &str| Decode::Corrupt(format!("distance field: {s}"));
    let mut leaves = Vec::new();
    for (origin, mask, offsets) in format::field_records(fh, rec)? {
        let band = LeafBand::new(mask, offsets).ok_or_else(|| bad("records truncated"))?;
        leaves.push((origin, band));
    }
    let window = fh
        .window
        .map(|(lo, hi)| (VoxelCoord::from_array(lo), VoxelCoord::from_array(hi)));
    DistanceField::restore(fh.config, map, window, leaves).map_err(|e| bad(&e))
}

/// Write snapshot bytes to a file atomically (after checking they open).
pub fn save_snapshot(bytes: &[u8], path: &Path) -> Result<(), MapFileError> {
    let v = SnapshotView::open_checked(bytes).map_err(|source| MapFileError::Snapshot {
        path: path.into(),
        source,
    })?;
    write_atomic(path, v.as_bytes())
}

/// Read a snapshot file and verify it (structure and checksum); open it with
/// [`SnapshotView::open`] afterwards.
pub fn read_snapshot(path: &Path) -> Result<Vec<u8>, MapFileError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    SnapshotView::open_checked(&bytes).map_err(|source| MapFileError::Snapshot {
        path: path.into(),
        source,
    })?;
    Ok(bytes)
}

/// A map file or a snapshot file as verified snapshot bytes, told apart by their magic: a
/// snapshot is read as [`read_snapshot`] does; a map is decoded and encoded as a whole-map
/// snapshot with its log-odds values (so probabilities can be read), sequence 0.
pub fn read_as_snapshot(path: &Path) -> Result<Vec<u8>, MapFileError> {
    read_as_snapshot_with(path, None)
}

/// [`read_as_snapshot`], and a map file's snapshot carries the distance field of `field`
/// built from its map (a snapshot file is returned as it is, with or without one).
pub fn read_as_snapshot_with_field(
    path: &Path,
    field: &crate::field::FieldConfig,
) -> Result<Vec<u8>, MapFileError> {
    read_as_snapshot_with(path, Some(field))
}

fn read_as_snapshot_with(
    path: &Path,
    field: Option<&crate::field::FieldConfig>,
) -> Result<Vec<u8>, MapFileError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    if !bytes.starts_with(&MAP_MAGIC) {
        SnapshotView::open_checked(&bytes).map_err(|source| MapFileError::Snapshot {
            path: path.into(),
            source,
        })?;
        return Ok(bytes);
    }
    let (map, carried) = decode_map_with_field(&bytes).map_err(decode_err(path))?;
    drop(bytes);
    let meta = crate::snapshot::Meta {
        with_values: true,
        ..Default::default()
    };
    let plan = crate::snapshot::Plan::new(&map, crate::snapshot::Scope::Whole, meta);
    // The field the file carries, unless the caller asks for another.
    let cfg = match (field, carried) {
        (None, None) => return Ok(plan.to_vec()),
        (None, Some(f)) => return Ok(plan.with_field(&f).to_vec()),
        (Some(cfg), Some(f)) if f.config() == cfg => return Ok(plan.with_field(&f).to_vec()),
        (Some(cfg), _) => cfg,
    };
    let mut f = crate::field::DistanceField::new(*cfg, map.resolution()).map_err(|source| {
        MapFileError::Field {
            path: path.into(),
            source,
        }
    })?;
    f.rebuild(&map, None);
    Ok(plan.with_field(&f).to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::FieldConfig;
    use crate::grid::LEAF_VOXELS;
    use crate::model::SensorModel;
    use crate::snapshot::{Meta, Plan, Scope};
    use voxmap_reader::mapfile::snapshot_of;

    fn sample_map() -> OccupancyMap {
        let model = SensorModel {
            p_hit: 0.8,
            ..Default::default()
        };
        let mut map = OccupancyMap::new(0.05, model).unwrap();
        let mut s = 99u64;
        for _ in 0..20000 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let v = VoxelCoord::new(
                (s >> 20) as i32 % 300 - 150,
                (s >> 30) as i32 % 300 - 150,
                (s >> 40) as i32 % 40 - 20,
            );
            map.set_value(v, (s >> 50) as i8);
        }
        map
    }

    fn voxels(map: &OccupancyMap) -> Vec<(VoxelCoord, i8)> {
        let mut v: Vec<_> = map.grid().active_voxels().collect();
        v.sort();
        v
    }

    #[test]
    fn save_load_round_trip() {
        let dir = std::env::temp_dir().join(format!("voxmap-mapfile-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("m.vxm");
        let map = sample_map();
        save_map(&map, &path).unwrap();
        let back = load_map(&path).unwrap();
        assert_eq!(voxels(&back), voxels(&map));
        back.assert_marks_in_step();
        assert_eq!(back.model(), map.model());
        assert_eq!(back.resolution(), 0.05);
        // No temporary file is left behind.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        // Snapshot files.
        let snap = Plan::new(
            &map,
            Scope::Whole,
            Meta {
                with_values: true,
                ..Default::default()
            },
        )
        .to_vec();
        let sp = dir.join("s.vxs");
        save_snapshot(&snap, &sp).unwrap();
        assert_eq!(read_snapshot(&sp).unwrap(), snap);
        std::fs::write(&sp, &snap[..snap.len() / 2]).unwrap();
        assert!(matches!(
            read_snapshot(&sp),
            Err(MapFileError::Snapshot { .. })
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn corrupt_files_are_clear_errors() {
        let good = encode_map(&sample_map());
        assert!(decode_map(&good).is_ok());
        let mut v = good.clone();
        v[8] = 7;
        assert_eq!(decode_map(&v).err(), Some(Decode::Version(7)));
        let mut v = good.clone();
        v[0] = b'X';
        assert!(matches!(decode_map(&v), Err(Decode::Corrupt(m)) if m.contains("magic")));
        let cut = &good[..good.len() - 100];
        assert!(matches!(decode_map(cut), Err(Decode::Corrupt(m)) if m.contains("body is")));
        let mut v = good.clone();
        let n = v.len();
        v[n - 3] ^= 0x40;
        assert!(matches!(decode_map(&v), Err(Decode::Corrupt(m)) if m.contains("body checksum")));
        let mut v = good.clone();
        v[17] ^= 1;
        assert!(matches!(decode_map(&v), Err(Decode::Corrupt(m)) if m.contains("header checksum")));
        let mut v = good.clone();
        v[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(decode_map(&v), Err(Decode::Corrupt(_))));
        for len in [0, 5, 16, 30] {
            assert!(decode_map(&good[..len.min(good.len())]).is_err());
        }
        let e = load_map(Path::new("/nonexistent/m.vxm")).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/m.vxm"));
    }

    /// Rewrite the header with `edit` applied, with a good header checksum.
    fn with_header(bytes: &[u8], edit: impl Fn(&mut FileHeader, &[u8])) -> Vec<u8> {
        let hlen = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
        let cfg = bincode::config::standard();
        let (mut h, _): (FileHeader, usize) =
            bincode::serde::decode_from_slice(&bytes[16..16 + hlen], cfg).unwrap();
        let body = &bytes[20 + hlen..];
        edit(&mut h, body);
        let mut out = encode_head(&h, MAP_VERSION_PLAIN);
        out.extend_from_slice(body);
        out
    }

    /// Recompute the body checksum after a test edited the body, so that the checks
    /// behind the checksum are reached.
    fn reseal(bytes: &[u8]) -> Vec<u8> {
        with_header(bytes, |h, body| h.body_crc32 = crc32fast::hash(body))
    }

    #[test]
    fn lying_records_behind_a_good_checksum_are_clear_errors() {
        let good = encode_map(&sample_map());
        let hlen = u32::from_le_bytes(good[12..16].try_into().unwrap()) as usize;
        let body = 20 + hlen;
        assert!(decode_map(&reseal(&good)).is_ok());
        let huge = with_header(&good, |h, _| h.leaf_count = 1 << 32);
        assert!(
            matches!(decode_map(&huge), Err(Decode::Corrupt(m)) if m.contains("leaf count out of range"))
        );
        let corrupt = |edit: &dyn Fn(&mut Vec<u8>), what: &str| {
            let mut v = good.clone();
            edit(&mut v);
            match decode_map(&reseal(&v)) {
                Err(Decode::Corrupt(m)) => assert!(m.contains(what), "{m}"),
                other => panic!("expected {what:?}, got {:?}", other.map(|_| ())),
            }
        };
        // The second record claims the first one's leaf.
        corrupt(
            &|v| v.copy_within(body..body + 12, body + RECORD),
            "leaf stored twice",
        );
        corrupt(&|v| v[body] ^= 3, "not leaf-aligned");
        corrupt(
            &|v| v[body + 8..body + 12].copy_from_slice(&(1i32 << 30).to_le_bytes()),
            "out of range",
        );
        // A known voxel's log-odds beyond the model's clamp.
        let known = |i: usize| {
            let w = u64::from_le_bytes(
                good[body + MASK_AT + 8 * (i / 64)..][..8]
                    .try_into()
                    .unwrap(),
            );
            w >> (i % 64) & 1 != 0
        };
        let b = (0..LEAF_VOXELS).find(|&i| known(i)).unwrap();
        corrupt(&|v| v[body + VALUES_AT + b] = 127, "clamping range");
        // An unknown voxel's value is not read: stored as anything, it loads as unknown.
        let free = (0..LEAF_VOXELS).find(|&i| !known(i)).unwrap();
        let mut v = good.clone();
        v[body + VALUES_AT + free] = 127;
        let back = decode_map(&reseal(&v)).ok().unwrap();
        assert_eq!(voxels(&back), voxels(&sample_map()));
    }

    /// A map of walls (random occupied and free voxels) and its field.
    fn field_of(map: &OccupancyMap, unknown: crate::field::UnknownPolicy) -> DistanceField {
        let cfg = FieldConfig {
            max_distance: 0.3,
            unknown,
            window: None,
        };
        let mut f = DistanceField::new(cfg, map.resolution()).unwrap();
        f.rebuild(map, None);
        f
    }

    /// Per band leaf: its origin, and (voxel, offset) of each of its band voxels.
    type Band = Vec<(VoxelCoord, Vec<(usize, [i8; 3])>)>;

    fn band(f: &DistanceField) -> Band {
        let mut v: Vec<_> = f.leaves().map(|(o, b)| (o, b.iter().collect())).collect();
        v.sort_by_key(|(o, _)| (o.z, o.y, o.x));
        v
    }

    #[test]
    fn the_distance_field_rides_along_and_is_checked_against_its_map() {
        use crate::field::UnknownPolicy;
        let map = sample_map();
        for unknown in [UnknownPolicy::Free, UnknownPolicy::Occupied] {
            let f = field_of(&map, unknown);
            assert!(f.band_voxels() > 1000);
            let bytes = encode_map_parts_with(&map, Some(&f)).into_bytes();
            assert_eq!(
                u32::from_le_bytes(bytes[8..12].try_into().unwrap()),
                MAP_VERSION
            );
            let (back, carried) = decode_map_with_field(&bytes).unwrap();
            assert_eq!(voxels(&back), voxels(&map));
            let carried = carried.expect("the field");
            assert_eq!(carried.config(), f.config());
            assert_eq!(band(&carried), band(&f));
            // The map alone reads as before; a file without a field stays version 1.
            assert_eq!(voxels(&decode_map(&bytes).unwrap()), voxels(&map));
            let plain = encode_map(&map);
            assert_eq!(u32::from_le_bytes(plain[8..12].try_into().unwrap()), 1);
            assert!(decode_map_with_field(&plain).unwrap().1.is_none());
            // Damage behind the field's checksum, a cut, and the field of another map.
            let mut v = bytes.clone();
            let n = v.len();
            v[n - 2] ^= 0x10;
            assert!(
                matches!(decode_map_with_field(&v), Err(Decode::Corrupt(m)) if m.contains("distance field checksum"))
            );
            assert!(decode_map_with_field(&bytes[..bytes.len() - 5]).is_err());
            let mut other = sample_map();
            other.set_value(VoxelCoord::new(200, 200, 0), 100);
            other.set_value(VoxelCoord::new(0, 0, 0), 100);
            let wrong = encode_map_parts_with(&other, Some(&f)).into_bytes();
            assert!(
                matches!(decode_map_with_field(&wrong), Err(Decode::Corrupt(m)) if m.contains("distance field")),
                "the field of another map is refused"
            );
        }
    }

    /// A planner's path (`voxmap_reader::mapfile::snapshot_of`: in order, from the file's
    /// records) gives the bytes the map's writer gives of the decoded map, without and with
    /// a distance field (both policies, whole and windowed), and refuses what the map's
    /// loader refuses.
    #[test]
    fn the_readers_snapshot_of_a_map_file_equals_the_writers() {
        use crate::field::UnknownPolicy;
        let map = sample_map();
        let meta = Meta {
            with_values: true,
            ..Default::default()
        };
        let plain = encode_map(&map);
        let want = Plan::new(&decode_map(&plain).unwrap(), Scope::Whole, meta).to_vec();
        assert_eq!(snapshot_of(&plain).unwrap(), want);
        for unknown in [UnknownPolicy::Free, UnknownPolicy::Occupied] {
            for window in [None, Some([2.0, 1.5, 0.5])] {
                let cfg = FieldConfig {
                    max_distance: 0.3,
                    unknown,
                    window,
                };
                let mut f = DistanceField::new(cfg, map.resolution()).unwrap();
                f.rebuild(&map, Some(crate::WorldPoint::new(1.0, -2.0, 0.0)));
                let bytes = encode_map_parts_with(&map, Some(&f)).into_bytes();
                let (back, carried) = decode_map_with_field(&bytes).unwrap();
                let carried = carried.expect("the field");
                let want = Plan::new(&back, Scope::Whole, meta)
                    .with_field(&carried)
                    .to_vec();
                let got = snapshot_of(&bytes).unwrap();
                assert!(got == want, "{unknown:?} {window:?}");
                assert!(SnapshotView::open_checked(&got)
                    .unwrap()
                    .distance_field()
                    .is_some());
            }
        }
        // The field of another map, a value out of range, a cut: refused by both.
        let f = field_of(&map, UnknownPolicy::Free);
        let mut other = sample_map();
        other.set_value(VoxelCoord::new(200, 200, 0), 100);
        other.set_value(VoxelCoord::new(0, 0, 0), 100);
        let wrong = encode_map_parts_with(&other, Some(&f)).into_bytes();
        assert!(
            matches!(snapshot_of(&wrong), Err(Decode::Corrupt(m)) if m.contains("distance field"))
        );
        let cut = &plain[..plain.len() - 3];
        assert!(snapshot_of(cut).is_err() && decode_map(cut).is_err());
        let lying = with_header(&plain, |h, _| h.leaf_count += 1);
        assert!(snapshot_of(&lying).is_err() && decode_map(&lying).is_err());
    }

    #[test]
    fn checksum_in_pieces_equals_the_whole() {
        let bytes: Vec<u8> = (0..20_000_017u32).map(|i| (i ^ i >> 9) as u8).collect();
        for n in [0, 1, 8 << 20, (8 << 20) + 1, bytes.len()] {
            assert_eq!(
                par_crc32(&bytes[..n]),
                crc32fast::hash(&bytes[..n]),
                "{n} bytes"
            );
        }
    }

    #[test]
    fn equal_maps_give_equal_files() {
        // The same voxels set in another order make other leaf indices, not another file.
        let a = sample_map();
        let mut b = OccupancyMap::new(a.resolution(), *a.model()).unwrap();
        let mut vs = voxels(&a);
        vs.reverse();
        for (v, x) in vs {
            b.set_value(v, x);
        }
        assert_eq!(encode_map(&a), encode_map(&b));
        let e = encode_map_parts(&a);
        assert_eq!(e.len(), encode_map(&a).len());
        assert_eq!(e.into_bytes(), encode_map(&a));
    }

    #[test]
    fn failed_save_leaves_the_old_file() {
        let dir = std::env::temp_dir().join(format!("voxmap-mapfile-old-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("m.vxm");
        save_map(&sample_map(), &path).unwrap();
        let before = std::fs::read(&path).unwrap();
        // A save of another map to the same path that fails before its rename (its temp
        // file's name is taken by a directory): the old file stays whole, no temp is left.
        let tmp = dir.join(format!(".m.vxm.tmp.{}", std::process::id()));
        std::fs::create_dir(&tmp).unwrap();
        let mut other = sample_map();
        other.set_value(VoxelCoord::new(100, 100, 100), 50);
        assert!(save_map(&other, &path).is_err());
        assert_eq!(std::fs::read(&path).unwrap(), before);
        std::fs::remove_dir(&tmp).unwrap();
        save_map(&other, &path).unwrap();
        assert_ne!(
            std::fs::read(&path).unwrap(),
            before,
            "the same save succeeds after"
        );
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_save_removes_what_killed_saves_left() {
        let dir = std::env::temp_dir().join(format!("voxmap-mapfile-dead-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("m.vxm");
        // Left by a process that no longer runs (no pid is this large), by one that runs
        // (pid 1), and a file that only looks similar.
        let dead = dir.join(format!(".m.vxm.tmp.{}", u32::MAX - 1));
        let live = dir.join(".m.vxm.tmp.1");
        let other = dir.join(".m.vxm.tmp.x");
        for f in [&dead, &live, &other] {
            std::fs::write(f, b"partial").unwrap();
        }
        save_map(&sample_map(), &path).unwrap();
        if Path::new("/proc/self").exists() {
            assert!(!dead.exists());
        }
        assert!(live.exists(), "a running process's save is left alone");
        assert!(other.exists());
        assert_eq!(load_map(&path).unwrap().counts(), sample_map().counts());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
