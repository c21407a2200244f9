//! The tile store: a map kept on disk tile by tile, for a map larger than its memory
//! budget and for saves that write only what changed.
//!
//! A store is a directory:
//! ```text
//! manifest            the live record of every tile, the map's parameters, a generation;
//!                     replaced atomically (temporary file, fsync, rename, fsync the directory)
//! seg-00000001.vxs    append-only segment files of tile records (`record`), each a head
//!                     "VXMSEG\0\0" | version u32 | 0 u32, then records back to back
//! ```
//! Records are appended by a writer thread of the store's own (write-behind), so that
//! evicting a tile costs the frame only a copy of its leaves. [`TileStore::commit`] waits
//! for the writer, syncs the segments and writes a new manifest; only a committed manifest
//! is what a later [`TileStore::open`] sees, so a crash at any moment leaves the last
//! committed map. A process opening a store starts a new segment and never appends to one
//! a crash may have cut short; segments no committed manifest names are removed at the next
//! commit.

pub(crate) mod export;
pub mod record;

pub use export::{export, ExportError};

use crate::coord::VoxelCoord;
use crate::field::FieldConfig;
use crate::model::{QuantizedModel, SensorModel};
use hashbrown::HashMap;
use record::{RawTile, RecordError, TileRecord};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};

pub const MANIFEST_MAGIC: [u8; 8] = *b"VXMSTORE";
/// The manifest version this build reads and writes.
pub const MANIFEST_VERSION: u32 = 2;
pub const SEGMENT_MAGIC: [u8; 8] = *b"VXMSEG\0\0";
pub const SEGMENT_VERSION: u32 = 1;
const SEGMENT_HEAD: u64 = 16;
/// A segment is closed and a new one started past this many bytes.
const SEGMENT_MAX: u64 = 64 << 20;
/// The longest manifest a store may have (a tile entry is about 40 bytes).
const MAX_MANIFEST: usize = 1 << 30;
const MANIFEST: &str = "manifest";

/// The map parameters a store is kept with; a store refuses a map of others.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoreParams {
    pub resolution: f64,
    pub model: SensorModel,
    pub frac_bits: u8,
    /// The distance field whose bands the tiles hold, if any.
    pub field: Option<FieldConfig>,
}

impl std::fmt::Display for StoreParams {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "resolution {} m, sensor model {:?}, ",
            self.resolution, self.model
        )?;
        match &self.field {
            None => write!(f, "no distance field"),
            Some(c) => write!(
                f,
                "a distance field to {} m (unknown as {:?}, window {:?})",
                c.max_distance, c.unknown, c.window
            ),
        }
    }
}

/// Where a tile's live record is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileEntry {
    pub tile: [i32; 3],
    pub segment: u32,
    pub offset: u64,
    /// The whole record's bytes (head and payload).
    pub len: u32,
    pub leaves: u32,
}

/// What a manifest holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub params: StoreParams,
    /// Commits so far.
    pub generation: u64,
    /// The last frame in the map when committed: sequence and time stamp (ns).
    pub last_frame: (u64, u64),
    /// The segment a new writer starts.
    pub next_segment: u32,
    pub tiles: Vec<TileEntry>,
}

/// Why a store operation failed; a failed operation changes no committed state.
#[derive(Debug)]
#[non_exhaustive]
pub enum StoreError {
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The directory holds a store already (creating) or none (opening).
    Exists(PathBuf),
    Missing(PathBuf),
    /// The manifest is damaged or of another version.
    Manifest {
        path: PathBuf,
        problem: String,
    },
    /// The store was made for a map of other parameters.
    Params {
        path: PathBuf,
        problem: String,
    },
    /// One tile's record was refused: the tile is named, its region reads as unknown.
    Tile {
        tile: [i32; 3],
        segment: PathBuf,
        offset: u64,
        source: RecordError,
    },
    /// The writer thread failed to write a record (the tile stays in memory).
    Write(String),
}

impl std::fmt::Display for StoreError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Io { path, source } => write!(f, "{}: {source}", path.display()),
            Self::Exists(p) => write!(
                f,
                "{} holds a tile store already (continue it with --load, or name another directory)",
                p.display()
            ),
            Self::Missing(p) => write!(f, "{} holds no tile store (no manifest)", p.display()),
            Self::Manifest { path, problem } => {
                write!(f, "{}: bad store manifest: {problem}", path.display())
            }
            Self::Params { path, problem } => write!(f, "{}: {problem}", path.display()),
            Self::Tile {
                tile,
                segment,
                offset,
                source,
            } => write!(
                f,
                "tile {tile:?} (record at {} byte {offset}) refused: {source}",
                segment.display()
            ),
            Self::Write(e) => write!(f, "writing tile records: {e}"),
        }
    }
}

impl std::error::Error for StoreError {}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.into(),
        source,
    }
}

fn segment_name(id: u32) -> String {
    format!("seg-{id:08}.vxs")
}

/// A tile's latest record: written (`Loc`), or waiting for the writer thread.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Loc {
    segment: u32,
    offset: u64,
    len: u32,
    leaves: u32,
}

/// What the store's owner and its writer thread share.
#[derive(Default)]
struct Shared {
    index: HashMap<VoxelCoord, Loc>,
    /// Raw records handed to the writer and not yet written, with the put's number: the
    /// latest put of a tile wins.
    pending: HashMap<VoxelCoord, (u64, Arc<RawTile>)>,
    pending_bytes: usize,
    /// The writer's first failure, reported by the next put or commit.
    error: Option<String>,
    /// Bytes in the segments this process wrote (records).
    written_bytes: u64,
    records_written: u64,
    /// Records copied out of mostly dead segments.
    records_copied: u64,
    /// The owner is closing the store: copies are skipped (no commit would name them).
    closing: bool,
    /// Each segment's bytes of live records (those the index names).
    live: HashMap<u32, u64>,
    /// The segment being written and its length.
    active: (u32, u64),
    /// Tiles the loader thread decoded ahead of need.
    ready: HashMap<VoxelCoord, Prefetched>,
    ready_bytes: usize,
}

enum Job {
    Put {
        tile: VoxelCoord,
        put: u64,
        last_observed: u64,
        raw: Arc<RawTile>,
    },
    /// Copy the tile's record at `from` (in a segment mostly of dead records) to the
    /// active segment, unless a newer record has replaced it meanwhile.
    Copy {
        tile: VoxelCoord,
        from: Loc,
    },
    Flush(mpsc::Sender<Result<(), String>>),
}

/// Counters of a store, for `stats` and `inspect`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StoreCounters {
    /// Tiles with a record (written or waiting).
    pub tiles: u64,
    pub pending_bytes: u64,
    pub records_written: u64,
    /// Records copied out of segments of mostly dead records (compaction).
    pub records_copied: u64,
    pub written_bytes: u64,
    /// Bytes of the segment files on disk.
    pub disk_bytes: u64,
    pub generation: u64,
}

/// An open tile store.
pub struct TileStore {
    dir: PathBuf,
    params: StoreParams,
    q: QuantizedModel,
    shared: Arc<Mutex<Shared>>,
    jobs: Option<mpsc::Sender<Job>>,
    writer: Option<std::thread::JoinHandle<()>>,
    loads: Option<mpsc::Sender<Vec<VoxelCoord>>>,
    loader: Option<std::thread::JoinHandle<()>>,
    puts: u64,
    generation: u64,
    /// Open segment files for reading.
    readers: HashMap<u32, File>,
}

impl TileStore {
    /// A new, empty store in `dir` (made if missing); refused where `dir` holds one.
    pub fn create(dir: &Path, params: StoreParams) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        if dir.join(MANIFEST).exists() {
            return Err(StoreError::Exists(dir.into()));
        }
        let manifest = Manifest {
            params,
            generation: 0,
            last_frame: (0, 0),
            next_segment: 1,
            tiles: Vec::new(),
        };
        write_manifest(dir, &manifest)?;
        Self::start(dir, manifest, true)
    }

    /// The store in `dir` as its last commit left it.
    pub fn open(dir: &Path) -> Result<(Self, Manifest), StoreError> {
        Self::open_with(dir, true)
    }

    /// [`Self::open`] for reading only: no writer, nothing in `dir` changes; puts and
    /// commits are refused.
    pub fn open_read_only(dir: &Path) -> Result<(Self, Manifest), StoreError> {
        Self::open_with(dir, false)
    }

    fn open_with(dir: &Path, writable: bool) -> Result<(Self, Manifest), StoreError> {
        let manifest = read_manifest(dir)?;
        for e in &manifest.tiles {
            if e.segment >= manifest.next_segment {
                return Err(StoreError::Manifest {
                    path: dir.join(MANIFEST),
                    problem: format!("tile {:?} in a segment not yet started", e.tile),
                });
            }
        }
        let store = Self::start(dir, manifest.clone(), writable)?;
        Ok((store, manifest))
    }

    fn start(dir: &Path, manifest: Manifest, writable: bool) -> Result<Self, StoreError> {
        let q = manifest
            .params
            .model
            .quantize()
            .map_err(|e| StoreError::Params {
                path: dir.into(),
                problem: format!("sensor model: {e}"),
            })?;
        let mut shared = Shared::default();
        for e in &manifest.tiles {
            let loc = Loc {
                segment: e.segment,
                offset: e.offset,
                len: e.len,
                leaves: e.leaves,
            };
            let tile = VoxelCoord::from_array(e.tile);
            if shared.index.insert(tile, loc).is_some() {
                return Err(StoreError::Manifest {
                    path: dir.join(MANIFEST),
                    problem: format!("tile {:?} listed twice", e.tile),
                });
            }
            *shared.live.entry(e.segment).or_default() += u64::from(e.len);
        }
        let mut store = Self {
            dir: dir.into(),
            params: manifest.params,
            q,
            shared: Arc::new(Mutex::new(Shared::default())),
            jobs: None,
            writer: None,
            loads: None,
            loader: None,
            puts: 0,
            generation: manifest.generation,
            readers: HashMap::new(),
        };
        if !writable {
            store.shared = Arc::new(Mutex::new(shared));
            return Ok(store);
        }
        // A new segment for this process: never append after a tail a crash may have cut.
        let id = manifest.next_segment;
        let path = dir.join(segment_name(id));
        let seg = new_segment(&path).map_err(io_err(&path))?;
        shared.active = (id, SEGMENT_HEAD);
        let shared = Arc::new(Mutex::new(shared));
        let (tx, rx) = mpsc::channel();
        let writer = {
            let (shared, at) = (shared.clone(), dir.to_path_buf());
            std::thread::Builder::new()
                .name("voxmap-store".into())
                .spawn(move || write_records(&at, seg, &shared, &rx))
                .map_err(io_err(dir))?
        };
        let (ltx, lrx) = mpsc::channel();
        let loader = {
            let (shared, at, q) = (shared.clone(), dir.to_path_buf(), q);
            std::thread::Builder::new()
                .name("voxmap-load".into())
                .spawn(move || load_ahead(&at, &q, &shared, &lrx))
                .map_err(io_err(dir))?
        };
        store.shared = shared;
        store.jobs = Some(tx);
        store.writer = Some(writer);
        store.loads = Some(ltx);
        store.loader = Some(loader);
        Ok(store)
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn params(&self) -> &StoreParams {
        &self.params
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Shared> {
        // The writer never panics holding the lock; a poisoned lock still holds valid maps.
        self.shared.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Every tile with a record (written or waiting for the writer).
    pub fn tiles(&self) -> Vec<VoxelCoord> {
        let s = self.lock();
        let mut t: Vec<VoxelCoord> = s.index.keys().copied().collect();
        t.extend(s.pending.keys().filter(|k| !s.index.contains_key(*k)));
        t
    }

    /// Whether the tile has a record.
    pub fn has(&self, tile: VoxelCoord) -> bool {
        let s = self.lock();
        s.index.contains_key(&tile) || s.pending.contains_key(&tile)
    }

    /// Raw bytes waiting for the writer thread (memory the store holds).
    pub fn pending_bytes(&self) -> usize {
        self.lock().pending_bytes
    }

    /// Hand a tile's raw records ([`record::raw_tile`]) to the writer thread, as the
    /// tile's latest record. Fails, keeping nothing, where the writer has failed before.
    pub fn put(
        &mut self,
        tile: VoxelCoord,
        last_observed: u64,
        raw: RawTile,
    ) -> Result<(), StoreError> {
        let raw = Arc::new(raw);
        self.puts += 1;
        {
            let mut s = self.lock();
            if let Some(e) = &s.error {
                return Err(StoreError::Write(e.clone()));
            }
            s.pending_bytes += raw.bytes.len();
            if let Some((_, old)) = s.pending.insert(tile, (self.puts, raw.clone())) {
                s.pending_bytes -= old.bytes.len();
            }
        }
        let job = Job::Put {
            tile,
            put: self.puts,
            last_observed,
            raw,
        };
        self.jobs
            .as_ref()
            .and_then(|j| j.send(job).ok())
            .ok_or_else(|| {
                StoreError::Write("the store is open read-only or its writer has ended".into())
            })
    }

    /// The tile's leaves and bands from its latest record, checked; `None` where it has
    /// none.
    pub fn get(&mut self, tile: VoxelCoord) -> Result<Option<TileRecord>, StoreError> {
        {
            let mut s = self.lock();
            if let Some(p) = s.ready.remove(&tile) {
                s.ready_bytes -= p.bytes;
                if Some(p.source) == source_of(&s, tile) {
                    return Ok(Some(p.leaves));
                }
            }
        }
        Ok(self.fetch(tile)?.map(|(_, leaves)| leaves))
    }

    /// The error refusing `tile`'s latest record for `source`, naming where it lies.
    pub fn refusal(&self, tile: VoxelCoord, source: RecordError) -> StoreError {
        let loc = self.lock().index.get(&tile).copied();
        StoreError::Tile {
            tile: tile.to_array(),
            segment: loc.map_or(PathBuf::from("(memory)"), |l| {
                self.dir.join(segment_name(l.segment))
            }),
            offset: loc.map_or(0, |l| l.offset),
            source,
        }
    }

    /// The tile's raw records from its latest record, checked as [`Self::get`] does.
    pub fn get_raw(&mut self, tile: VoxelCoord) -> Result<Option<RawTile>, StoreError> {
        Ok(self.fetch(tile)?.map(|(raw, _)| raw))
    }

    fn fetch(&mut self, tile: VoxelCoord) -> Result<Option<(RawTile, TileRecord)>, StoreError> {
        let (pending, loc) = {
            let s = self.lock();
            (
                s.pending.get(&tile).map(|p| p.1.clone()),
                s.index.get(&tile).copied(),
            )
        };
        if let Some(raw) = pending {
            let decoded = raw
                .decode(tile, &self.q)
                .map_err(|source| StoreError::Tile {
                    tile: tile.to_array(),
                    segment: PathBuf::from("(memory)"),
                    offset: 0,
                    source,
                })?;
            return Ok(Some(((*raw).clone(), decoded)));
        }
        let Some(loc) = loc else { return Ok(None) };
        read_record(&self.dir, &self.q, &mut self.readers, tile, loc).map(Some)
    }

    /// Decode the stored tiles listed (those the next frames will likely reach) on the
    /// loader thread, so that [`Self::get`] finds them ready. Tiles made ready for an
    /// earlier list and not in this one are dropped.
    pub fn prefetch(&mut self, tiles: Vec<VoxelCoord>) {
        {
            let mut s = self.lock();
            let Shared {
                ready, ready_bytes, ..
            } = &mut *s;
            ready.retain(|k, p| {
                let keep = tiles.contains(k);
                if !keep {
                    *ready_bytes -= p.bytes;
                }
                keep
            });
        }
        if let Some(l) = &self.loads {
            let _ = l.send(tiles);
        }
    }

    /// Bytes of tiles decoded ahead of need.
    pub fn ready_bytes(&self) -> usize {
        self.lock().ready_bytes
    }

    /// Drop the tile's record from the store (a refused tile, a cleared map); the next
    /// commit no longer names it.
    pub fn forget(&mut self, tile: VoxelCoord) {
        let mut s = self.lock();
        if let Some(loc) = s.index.remove(&tile) {
            *s.live.entry(loc.segment).or_default() -= u64::from(loc.len);
        }
        if let Some((_, raw)) = s.pending.remove(&tile) {
            s.pending_bytes -= raw.bytes.len();
        }
    }

    /// Wait until the writer thread has written every record handed to it.
    pub fn flush(&mut self) -> Result<(), StoreError> {
        let (tx, rx) = mpsc::channel();
        self.jobs
            .as_ref()
            .and_then(|j| j.send(Job::Flush(tx)).ok())
            .ok_or_else(|| StoreError::Write("the writer thread has ended".into()))?;
        rx.recv()
            .map_err(|_| StoreError::Write("the writer thread has ended".into()))?
            .map_err(StoreError::Write)
    }

    /// Make everything handed to the store so far the store's committed state: wait for
    /// the writer, sync the segments, replace the manifest. Then remove the segments no
    /// live record is in. Returns the new generation.
    pub fn commit(&mut self, last_frame: (u64, u64)) -> Result<u64, StoreError> {
        self.flush()?;
        let (tiles, next_segment, keep) = {
            let s = self.lock();
            let mut tiles: Vec<TileEntry> = (s.index.iter())
                .map(|(t, l)| TileEntry {
                    tile: t.to_array(),
                    segment: l.segment,
                    offset: l.offset,
                    len: l.len,
                    leaves: l.leaves,
                })
                .collect();
            tiles.sort_unstable_by_key(|e| (e.tile[2], e.tile[1], e.tile[0]));
            let mut keep: Vec<u32> = s
                .live
                .iter()
                .filter(|(_, &b)| b > 0)
                .map(|(&k, _)| k)
                .collect();
            keep.push(s.active.0);
            (tiles, s.active.0 + 1, keep)
        };
        // The flush synced the active segment; closed ones were synced when closed.
        let manifest = Manifest {
            params: self.params,
            generation: self.generation + 1,
            last_frame,
            next_segment,
            tiles,
        };
        write_manifest(&self.dir, &manifest)?;
        self.generation += 1;
        self.remove_segments_but(&keep);
        self.compact();
        Ok(self.generation)
    }

    /// Hand the live records of closed segments that hold mostly dead records (replaced
    /// or forgotten tiles) to the writer, to be copied into the active segment; a later
    /// commit names none of theirs and removes them. Without this a long mission that
    /// keeps revisiting its tiles would grow its store without bound. At most half a
    /// segment's bytes a commit, copied behind: the next save waits for what is left.
    fn compact(&mut self) {
        let Some(jobs) = &self.jobs else { return };
        let copies = {
            let s = self.lock();
            if s.error.is_some() {
                return;
            }
            let size =
                |id: u32| std::fs::metadata(self.dir.join(segment_name(id))).map_or(0, |m| m.len());
            let mut sparse: Vec<(u32, u64)> = (s.live.iter())
                .filter(|&(&id, &live)| id != s.active.0 && live > 0 && live * 2 < size(id))
                .map(|(&id, &live)| (id, live))
                .collect();
            sparse.sort_unstable();
            let mut room = SEGMENT_MAX / 2;
            let mut copies = Vec::new();
            for (id, live) in sparse {
                if live > room {
                    break;
                }
                room -= live;
                copies.extend((s.index.iter()).filter(|(_, l)| l.segment == id));
            }
            copies
                .into_iter()
                .map(|(t, l)| (*t, *l))
                .collect::<Vec<_>>()
        };
        for (tile, from) in copies {
            let _ = jobs.send(Job::Copy { tile, from });
        }
    }

    /// Remove segment files whose number is not in `keep` (best effort: a file left is
    /// removed by a later commit).
    fn remove_segments_but(&mut self, keep: &[u32]) {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name();
            let Some(id) = name.to_str().and_then(|n| {
                n.strip_prefix("seg-")?
                    .strip_suffix(".vxs")?
                    .parse::<u32>()
                    .ok()
            }) else {
                continue;
            };
            if !keep.contains(&id) {
                self.readers.remove(&id);
                let _ = std::fs::remove_file(e.path());
            }
        }
    }

    pub fn counters(&self) -> StoreCounters {
        let tiles = self.tiles().len();
        let s = self.lock();
        let disk_bytes = std::fs::read_dir(&self.dir)
            .map(|d| {
                d.flatten()
                    .filter(|e| e.file_name().to_string_lossy().ends_with(".vxs"))
                    .filter_map(|e| e.metadata().ok())
                    .map(|m| m.len())
                    .sum()
            })
            .unwrap_or(0);
        StoreCounters {
            tiles: tiles as u64,
            pending_bytes: s.pending_bytes as u64,
            records_written: s.records_written,
            records_copied: s.records_copied,
            written_bytes: s.written_bytes,
            disk_bytes,
            generation: self.generation,
        }
    }
}

impl Drop for TileStore {
    /// The writer finishes what it was handed (nothing is committed).
    fn drop(&mut self) {
        self.lock().closing = true;
        self.jobs = None;
        self.loads = None;
        if let Some(w) = self.writer.take() {
            let _ = w.join();
        }
        if let Some(l) = self.loader.take() {
            let _ = l.join();
        }
    }
}

/// Which record of a tile a copy was decoded from: one waiting for the writer (its put's
/// number) or one written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Source {
    Pending(u64),
    Written(Loc),
}

/// The latest record of `tile`, if any.
fn source_of(s: &Shared, tile: VoxelCoord) -> Option<Source> {
    match (s.pending.get(&tile), s.index.get(&tile)) {
        (Some((put, _)), _) => Some(Source::Pending(*put)),
        (None, Some(loc)) => Some(Source::Written(*loc)),
        (None, None) => None,
    }
}

/// A tile decoded ahead of need.
struct Prefetched {
    source: Source,
    leaves: TileRecord,
    bytes: usize,
}

/// Tiles kept decoded ahead of need at most.
const MAX_READY: usize = 24;

/// The record at `loc`, read and checked: its raw records, decoded.
fn read_record(
    dir: &Path,
    q: &QuantizedModel,
    files: &mut HashMap<u32, File>,
    tile: VoxelCoord,
    loc: Loc,
) -> Result<(RawTile, TileRecord), StoreError> {
    let path = dir.join(segment_name(loc.segment));
    let refused = |source| StoreError::Tile {
        tile: tile.to_array(),
        segment: path.clone(),
        offset: loc.offset,
        source,
    };
    let file = match files.entry(loc.segment) {
        hashbrown::hash_map::Entry::Occupied(f) => f.into_mut(),
        hashbrown::hash_map::Entry::Vacant(v) => {
            v.insert(File::open(&path).map_err(io_err(&path))?)
        }
    };
    let mut bytes = vec![0u8; loc.len as usize];
    let got = read_at_most(file, &mut bytes, loc.offset).map_err(io_err(&path))?;
    bytes.truncate(got);
    let (head, raw) = record::decode(&bytes).map_err(refused)?;
    let decoded = raw.decode(tile, q).map_err(refused)?;
    if head.tile != tile || head.leaves != loc.leaves || bytes.len() != loc.len as usize {
        return Err(refused(RecordError::Corrupt(format!(
            "the record is of tile {:?} with {} leaves, the manifest says {:?} with {}",
            head.tile.to_array(),
            head.leaves,
            tile.to_array(),
            loc.leaves
        ))));
    }
    Ok((raw, decoded))
}

/// The loader thread: decode each listed tile's latest record into the ready set, unless
/// it is there or the set is full. A record it cannot read is left for
/// [`TileStore::get`] to refuse.
fn load_ahead(
    dir: &Path,
    q: &QuantizedModel,
    shared: &Mutex<Shared>,
    lists: &mpsc::Receiver<Vec<VoxelCoord>>,
) {
    let lock = || shared.lock().unwrap_or_else(|e| e.into_inner());
    let mut files = HashMap::new();
    while let Ok(mut tiles) = lists.recv() {
        // Only the newest list matters.
        while let Ok(newer) = lists.try_recv() {
            tiles = newer;
        }
        for tile in tiles {
            let (source, pending) = {
                let s = lock();
                if s.ready.len() >= MAX_READY || s.ready.contains_key(&tile) {
                    continue;
                }
                (
                    source_of(&s, tile),
                    s.pending.get(&tile).map(|p| p.1.clone()),
                )
            };
            let leaves = match (source, pending) {
                (Some(Source::Pending(_)), Some(raw)) => raw.decode(tile, q).ok(),
                (Some(Source::Written(loc)), _) => {
                    read_record(dir, q, &mut files, tile, loc).ok().map(|r| r.1)
                }
                _ => None,
            };
            if let (Some(source), Some(leaves)) = (source, leaves) {
                let bytes = leaves.heap_bytes();
                let mut s = lock();
                let p = Prefetched {
                    source,
                    leaves,
                    bytes,
                };
                if let Some(old) = s.ready.insert(tile, p) {
                    s.ready_bytes -= old.bytes;
                }
                s.ready_bytes += bytes;
            }
        }
    }
}

/// A new segment file at `path`, its head written.
fn new_segment(path: &Path) -> std::io::Result<File> {
    let mut seg = File::create(path)?;
    let mut head = SEGMENT_MAGIC.to_vec();
    head.extend_from_slice(&SEGMENT_VERSION.to_le_bytes());
    head.extend_from_slice(&0u32.to_le_bytes());
    debug_assert_eq!(head.len() as u64, SEGMENT_HEAD);
    seg.write_all(&head)?;
    Ok(seg)
}

/// Read into `buf` from `at` until it is full or the file ends; returns the bytes read.
fn read_at_most(f: &File, buf: &mut [u8], at: u64) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match f.read_at(&mut buf[got..], at + got as u64) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// The writer thread: compress and append each record handed to it, then point the index
/// at it; copy the live records of mostly dead segments; sync on a flush and when a
/// segment is closed.
fn write_records(dir: &Path, mut seg: File, shared: &Mutex<Shared>, jobs: &mpsc::Receiver<Job>) {
    let lock = || shared.lock().unwrap_or_else(|e| e.into_inner());
    // Closed segments that copies read from.
    let mut old: HashMap<u32, File> = HashMap::new();
    for job in jobs {
        match job {
            Job::Flush(reply) => {
                let r = match lock().error.clone() {
                    Some(e) => Err(e),
                    None => seg
                        .sync_data()
                        .map_err(|e| format!("syncing a segment: {e}")),
                };
                let _ = reply.send(r);
            }
            Job::Put {
                tile,
                put,
                last_observed,
                raw,
            } => {
                if lock().error.is_some() {
                    continue;
                }
                let bytes = record::encode(tile, last_observed, &raw);
                let Some(loc) = append(dir, &mut seg, shared, &bytes, raw.leaves) else {
                    // The tile stays pending, in memory: nothing is lost, the owner hears.
                    continue;
                };
                let mut s = lock();
                point_index(&mut s, tile, loc);
                if s.pending.get(&tile).is_some_and(|p| p.0 == put) {
                    s.pending.remove(&tile);
                    s.pending_bytes -= raw.bytes.len();
                }
            }
            Job::Copy { tile, from } => {
                {
                    let s = lock();
                    if s.error.is_some() || s.closing || s.index.get(&tile) != Some(&from) {
                        continue;
                    }
                }
                let path = dir.join(segment_name(from.segment));
                let mut bytes = vec![0u8; from.len as usize];
                // A record that cannot be read back whole stays where it is (its segment
                // with it); reading it for a frame will say why.
                let read = match old.entry(from.segment) {
                    hashbrown::hash_map::Entry::Occupied(f) => Ok(f.into_mut()),
                    hashbrown::hash_map::Entry::Vacant(v) => File::open(&path).map(|f| v.insert(f)),
                }
                .and_then(|f| read_at_most(f, &mut bytes, from.offset));
                if read.ok() != Some(bytes.len()) {
                    continue;
                }
                let Some(loc) = append(dir, &mut seg, shared, &bytes, from.leaves) else {
                    continue;
                };
                let mut s = lock();
                // A put of the tile may have been written between the check and now.
                if s.index.get(&tile) == Some(&from) {
                    point_index(&mut s, tile, loc);
                    s.records_copied += 1;
                }
            }
        }
    }
    let _ = seg.sync_data();
}

/// Append a whole record to the active segment (a new one past [`SEGMENT_MAX`]); where it
/// went, or `None` after recording the failure for the owner.
fn append(
    dir: &Path,
    seg: &mut File,
    shared: &Mutex<Shared>,
    bytes: &[u8],
    leaves: u32,
) -> Option<Loc> {
    let lock = || shared.lock().unwrap_or_else(|e| e.into_inner());
    let (mut id, mut len) = lock().active;
    let written = (|| -> std::io::Result<()> {
        if len + bytes.len() as u64 > SEGMENT_MAX && len > SEGMENT_HEAD {
            seg.sync_data()?;
            id += 1;
            *seg = new_segment(&dir.join(segment_name(id)))?;
            len = SEGMENT_HEAD;
        }
        seg.write_all(bytes)
    })();
    let mut s = lock();
    if let Err(e) = written {
        s.error = Some(format!("segment {}: {e}", segment_name(id)));
        return None;
    }
    s.active = (id, len + bytes.len() as u64);
    s.records_written += 1;
    s.written_bytes += bytes.len() as u64;
    Some(Loc {
        segment: id,
        offset: len,
        len: bytes.len() as u32,
        leaves,
    })
}

/// Point the index at the tile's new record, moving its bytes' liveness with it.
fn point_index(s: &mut Shared, tile: VoxelCoord, loc: Loc) {
    if let Some(old) = s.index.insert(tile, loc) {
        *s.live.entry(old.segment).or_default() -= u64::from(old.len);
    }
    *s.live.entry(loc.segment).or_default() += u64::from(loc.len);
}

fn write_manifest(dir: &Path, m: &Manifest) -> Result<(), StoreError> {
    let body =
        bincode::serde::encode_to_vec(m, bincode::config::standard()).expect("a manifest encodes");
    let mut out = MANIFEST_MAGIC.to_vec();
    out.extend_from_slice(&MANIFEST_VERSION.to_le_bytes());
    out.extend_from_slice(&(body.len() as u64).to_le_bytes());
    out.extend_from_slice(&body);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    let path = dir.join(MANIFEST);
    crate::io::mapfile::write_atomic(&path, &out).map_err(|e| StoreError::Io {
        path,
        source: std::io::Error::other(e.to_string()),
    })
}

/// Whether `dir` holds a store (a manifest, sound or not).
pub fn exists(dir: &Path) -> bool {
    dir.join(MANIFEST).exists()
}

/// The committed manifest of the store in `dir`, checked.
pub fn read_manifest(dir: &Path) -> Result<Manifest, StoreError> {
    let path = dir.join(MANIFEST);
    if !path.exists() {
        return Err(StoreError::Missing(dir.into()));
    }
    let bytes = std::fs::read(&path).map_err(io_err(&path))?;
    decode_manifest(&bytes).map_err(|problem| StoreError::Manifest { path, problem })
}

/// A manifest's bytes, checked (magic, version, length, CRC, parameters); what is wrong
/// with them otherwise.
pub fn decode_manifest(bytes: &[u8]) -> Result<Manifest, String> {
    let bad = |problem: String| problem;
    if bytes.len() < 24 || bytes[..8] != MANIFEST_MAGIC {
        return Err(bad("not a voxmap store manifest".into()));
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
    if version != MANIFEST_VERSION {
        return Err(bad(format!(
            "version {version} (this build reads {MANIFEST_VERSION})"
        )));
    }
    let len = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes"));
    if len > MAX_MANIFEST as u64 || bytes.len() as u64 != 24 + len {
        return Err(bad(format!(
            "{} bytes where the head says {len} and 24 more",
            bytes.len()
        )));
    }
    let (head, crc) = bytes.split_at(bytes.len() - 4);
    if crc32fast::hash(head) != u32::from_le_bytes(crc.try_into().expect("4 bytes")) {
        return Err(bad("checksum mismatch".into()));
    }
    let config = bincode::config::standard().with_limit::<MAX_MANIFEST>();
    let (m, used): (Manifest, usize) = bincode::serde::decode_from_slice(&head[20..], config)
        .map_err(|e| bad(format!("does not decode: {e}")))?;
    if used != head.len() - 20 {
        return Err(bad("trailing bytes".into()));
    }
    m.params
        .model
        .quantize()
        .map_err(|e| bad(format!("sensor model: {e}")))?;
    crate::coord::GridTransform::new(m.params.resolution)
        .map_err(|e| bad(format!("resolution: {e}")))?;
    for e in &m.tiles {
        let t = VoxelCoord::from_array(e.tile);
        if record::tile_of(t) != t
            || e.leaves as usize > crate::grid::INTERNAL_CHILDREN
            || (e.len as usize) < record::HEAD
            || e.len as usize > record::MAX_RECORD
            || e.offset < SEGMENT_HEAD
        {
            return Err(bad(format!("tile entry {e:?} is not a tile record's")));
        }
    }
    Ok(m)
}

#[cfg(test)]
mod tests;
