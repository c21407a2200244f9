//! A mapper's tiles when it keeps a tile store: which tiles are in memory (when last
//! observed, whether changed since their latest record) and which only in the store;
//! loading the tiles a frame will touch before it is integrated, and after it, under a
//! memory budget, evicting the least recently observed tiles, farthest from the sensor
//! first. A tile is one internal node of the grid (128³ voxels).

use crate::coord::{VoxelCoord, WorldPoint};
use crate::field::DistanceField;
use crate::grid::INTERNAL_TOTAL_LOG2;
use crate::integrate::Frame;
use crate::io::mapfile::StreamedField;
use crate::occupancy::OccupancyMap;
use crate::store::export::write_tiles;
use crate::store::record::{raw_tile, tile_of, RecordError};
use crate::store::{ExportError, StoreCounters, StoreError, TileStore};
use hashbrown::{HashMap, HashSet};
use std::time::{Duration, Instant};

const TILE: i32 = 1 << INTERNAL_TOTAL_LOG2;
/// Bytes of raw records a save lets wait for the store's writer before it waits too.
const SAVE_BACKLOG: usize = 16 << 20;
/// Tiles evicted after one frame while the map is within its share.
const EVICT_PER_FRAME: usize = 4;
/// Evictions between two returns of freed heap memory to the system.
const TRIM_EVERY: u32 = 16;

/// Return the allocator's free pages to the system. An evicted tile's distance field
/// bands are thousands of small allocations; freed, they leave holes that glibc's malloc
/// keeps, and the process's RSS would stay above the budget by tens of MiB.
fn give_back_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim takes no pointers and is thread-safe in glibc (it locks each
    // arena it trims); it only releases free memory.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// How a mapper keeps its store: where, and the memory budget (bytes) its map stays under.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoreConfig {
    pub dir: std::path::PathBuf,
    /// `None`: no budget; the store only makes saves incremental.
    pub memory_budget: Option<u64>,
    /// Continue the store in `dir` (its tiles loaded as frames reach them) rather than
    /// start one there.
    pub resume: bool,
}

/// What the tiles did around one frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TileReport {
    /// Tiles brought back from the store before the frame (or a region).
    pub loaded: u32,
    pub evicted: u32,
    /// Time spent loading, before the frame was integrated: what the frame waited for.
    pub load_time: Duration,
    /// Time spent evicting after the frame.
    pub evict_time: Duration,
    /// Tiles whose record was refused (each error names its tile); their regions read as
    /// unknown.
    pub refused: Vec<String>,
    /// The store's writer failed: eviction stops, tiles stay in memory.
    pub write_error: Option<String>,
}

/// What an incremental save wrote.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SaveReport {
    pub tiles_written: u64,
    pub generation: u64,
    pub time: Duration,
}

/// A resident tile.
#[derive(Clone, Copy, Debug)]
struct Resident {
    /// The mapper's frame count when a frame last touched it (or it was loaded).
    last_observed: u64,
    /// Changed since its latest record in the store (or it has none).
    dirty: bool,
}

/// Counters since the store was opened, for `stats`, the log and `inspect`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TileStats {
    pub memory_budget: Option<u64>,
    /// The map's resident bytes: leaves and nodes in use, records waiting for the store's
    /// writer, tiles its loader decoded ahead.
    pub resident_bytes: u64,
    pub tiles_resident: u64,
    /// Tiles only in the store.
    pub tiles_stored: u64,
    /// The integrator's buffers, which the budget holds besides the map.
    pub working_bytes: u64,
    pub evictions: u64,
    pub loads: u64,
    pub refused: u64,
    /// The longest a frame waited for its tiles to load.
    pub worst_wait: Duration,
    pub store: StoreCounters,
}

impl std::fmt::Display for TileStats {
    /// One line for a person: tiles in memory and stored, evictions, loads, refusals,
    /// the worst wait, resident bytes against the budget.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "tiles {} in memory, {} only stored, {} evicted, {} loaded, {} refused, worst wait {:.2} ms; resident {:.1} MiB of {}",
            self.tiles_resident,
            self.tiles_stored,
            self.evictions,
            self.loads,
            self.refused,
            self.worst_wait.as_secs_f64() * 1e3,
            self.resident_bytes as f64 / f64::from(1 << 20),
            self.memory_budget
                .map_or("unlimited".to_string(), |b| format!("{:.0} MiB", b as f64 / f64::from(1 << 20)))
        )
    }
}

/// What one frame changed, for [`Tiles::after_frame`].
pub(crate) struct Changed {
    /// The voxel box (inclusive) the frame's rays touched.
    pub bounds: Option<(VoxelCoord, VoxelCoord)>,
    /// The voxel box of the patches whose bands the field transformed.
    pub banded: Option<(VoxelCoord, VoxelCoord)>,
    pub sensor: WorldPoint,
}

/// The tile origins from tile `a` to tile `b` (inclusive, each axis), z slowest.
fn tiles_between(a: VoxelCoord, b: VoxelCoord) -> impl Iterator<Item = VoxelCoord> {
    let axis = |lo: i32, hi: i32| (lo..=hi).step_by(TILE as usize);
    axis(a.z, b.z).flat_map(move |z| {
        axis(a.y, b.y).flat_map(move |y| axis(a.x, b.x).map(move |x| VoxelCoord::new(x, y, z)))
    })
}

pub(crate) struct Tiles {
    pub(crate) store: TileStore,
    budget: Option<u64>,
    resident: HashMap<VoxelCoord, Resident>,
    stored: HashSet<VoxelCoord>,
    /// Frames integrated since the store was opened.
    clock: u64,
    stats: TileStats,
    /// The store's writer failed: no more evictions (told once, in that frame's report).
    write_failed: bool,
    /// Evictions since the freed memory was last given back.
    untrimmed: u32,
    /// The last frame's box (world) and the sensor positions of the last two frames: the
    /// next frame's box is guessed from them, to load its tiles ahead.
    frame_box: Option<([f64; 3], [f64; 3])>,
    sensors: [Option<WorldPoint>; 2],
}

impl Tiles {
    pub(crate) fn new(store: TileStore, budget: Option<u64>, stored: HashSet<VoxelCoord>) -> Self {
        Self {
            store,
            budget,
            resident: HashMap::new(),
            stored,
            clock: 0,
            write_failed: false,
            untrimmed: 0,
            frame_box: None,
            sensors: [None; 2],
            stats: TileStats {
                memory_budget: budget,
                ..Default::default()
            },
        }
    }

    /// Load the stored tiles the frame's rays can reach: those overlapping the box of the
    /// sensor and its points (cut at `max_range`); with a distance field, also those its
    /// update after the frame may read or change (its reach around that box, and the
    /// window's box around the sensor with the radius and a patch), so that every band is
    /// computed, and stays, from the whole map.
    pub(crate) fn load_for_frame(
        &mut self,
        map: &mut OccupancyMap,
        field: Option<&mut DistanceField>,
        frame: &Frame<'_>,
        max_range: f64,
        report: &mut TileReport,
    ) {
        let o = frame.pose.translation.vector;
        let (mut lo, mut hi) = ([o.x, o.y, o.z], [o.x, o.y, o.z]);
        for p in frame.points {
            let v = nalgebra::Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            let d = v.norm();
            if !d.is_finite() {
                continue;
            }
            let v = if d > max_range {
                v * (max_range / d)
            } else {
                v
            };
            let w = frame.pose.transform_point(&v.into());
            for k in 0..3 {
                lo[k] = lo[k].min(w[k]);
                hi[k] = hi[k].max(w[k]);
            }
        }
        if let Some(f) = field.as_deref() {
            let res = map.resolution();
            let reach = f64::from(f.reach()) * res;
            lo = lo.map(|c| c - reach);
            hi = hi.map(|c| c + reach);
            if let Some(half) = f.config().window {
                let around = f64::from(f.window_reach()) * res;
                for k in 0..3 {
                    lo[k] = lo[k].min(o[k] - half[k] - around);
                    hi[k] = hi[k].max(o[k] + half[k] + around);
                }
            }
        }
        self.frame_box = Some((lo, hi));
        self.load_box(map, field, lo, hi, report);
    }

    /// Load the stored tiles overlapping the world box [lo, hi].
    pub(crate) fn load_box(
        &mut self,
        map: &mut OccupancyMap,
        mut field: Option<&mut DistanceField>,
        lo: [f64; 3],
        hi: [f64; 3],
        report: &mut TileReport,
    ) {
        if self.stored.is_empty() {
            return;
        }
        let start = Instant::now();
        for k in self.stored_in(map, lo, hi) {
            self.load(map, field.as_deref_mut(), k, report);
        }
        let waited = start.elapsed();
        report.load_time += waited;
        self.stats.worst_wait = self.stats.worst_wait.max(report.load_time);
    }

    /// The stored tiles overlapping the world box [lo, hi], with a voxel of slack each way
    /// (a ray's last voxel may round across a face).
    fn stored_in(&self, map: &OccupancyMap, lo: [f64; 3], hi: [f64; 3]) -> Vec<VoxelCoord> {
        let t = map.transform();
        let corner = |p: [f64; 3], s: f64| {
            let u = t.point_to_units(&WorldPoint::new(p[0], p[1], p[2]));
            let c = |k: usize| {
                (u[k] + s)
                    .floor()
                    .clamp(-(1 << 30) as f64, ((1 << 30) - 1) as f64) as i32
            };
            tile_of(VoxelCoord::new(c(0), c(1), c(2)))
        };
        let (a, b) = (corner(lo, -1.0), corner(hi, 1.0));
        let span = |k: usize| {
            (i64::from(b.to_array()[k]) - i64::from(a.to_array()[k])) / i64::from(TILE) + 1
        };
        let keys = span(0).saturating_mul(span(1)).saturating_mul(span(2));
        let inside = |k: &VoxelCoord| {
            (0..3).all(|i| (a.to_array()[i]..=b.to_array()[i]).contains(&k.to_array()[i]))
        };
        // A box with more tiles than the store has (a huge query): go through the store.
        if keys > self.stored.len() as i64 {
            let mut v: Vec<VoxelCoord> =
                self.stored.iter().filter(|k| inside(k)).copied().collect();
            v.sort_unstable_by_key(|k| (k.z, k.y, k.x));
            return v;
        }
        tiles_between(a, b)
            .filter(|k| self.stored.contains(k))
            .collect()
    }

    fn load(
        &mut self,
        map: &mut OccupancyMap,
        field: Option<&mut DistanceField>,
        tile: VoxelCoord,
        report: &mut TileReport,
    ) {
        self.stored.remove(&tile);
        let got = self.store.get(tile).and_then(|record| {
            let record = record.unwrap_or_default();
            if let Some(f) = field {
                (f.restore_tile(&record.leaves, record.bands)).map_err(|problem| {
                    let why = format!("its distance field bands: {problem}");
                    self.store.refusal(tile, RecordError::Corrupt(why))
                })?;
            }
            Ok(record.leaves)
        });
        match got {
            Ok(leaves) => {
                let grid = map.grid_mut();
                let mut hint = (VoxelCoord::new(i32::MIN, 0, 0), u32::MAX);
                for (o, leaf) in leaves {
                    let i = grid.leaf_index_or_insert(o, Some(&mut hint));
                    *grid.leaf_mut(i) = leaf;
                }
                self.resident.insert(
                    tile,
                    Resident {
                        last_observed: self.clock,
                        dirty: false,
                    },
                );
                report.loaded += 1;
                self.stats.loads += 1;
            }
            Err(e) => {
                // The region reads as unknown from now on; the record is dropped so that no
                // later save names it.
                self.store.forget(tile);
                self.stats.refused += 1;
                report.refused.push(e.to_string());
            }
        }
    }

    /// After a frame: the tiles its rays touched are observed now and changed, and those
    /// whose bands the field transformed changed; then, over the budget, evict.
    pub(crate) fn after_frame(
        &mut self,
        map: &mut OccupancyMap,
        field: Option<&mut DistanceField>,
        changed: Changed,
        working: u64,
        report: &mut TileReport,
    ) {
        let Changed {
            bounds,
            banded,
            sensor,
        } = changed;
        self.clock += 1;
        self.stats.working_bytes = working;
        if let Some((lo, hi)) = bounds {
            for k in tiles_between(tile_of(lo), tile_of(hi)) {
                if let Some(r) = self.resident.get_mut(&k) {
                    *r = Resident {
                        last_observed: self.clock,
                        dirty: true,
                    };
                }
            }
        }
        if let Some((lo, hi)) = banded {
            for k in tiles_between(tile_of(lo), tile_of(hi)) {
                if let Some(r) = self.resident.get_mut(&k) {
                    r.dirty = true;
                }
            }
        }
        self.adopt_new_nodes(map);
        self.evict_over_budget(map, field, sensor, working, report);
        self.sensors = [self.sensors[1], Some(sensor)];
        self.load_ahead(map);
    }

    /// Ask the store's loader for the stored tiles the next two frames will likely reach:
    /// the last frame's box moved on by the sensor's last step, once and twice.
    fn load_ahead(&mut self, map: &OccupancyMap) {
        let (Some((lo, hi)), [Some(a), Some(b)]) = (self.frame_box, self.sensors) else {
            return;
        };
        if self.stored.is_empty() {
            return;
        }
        let step = b - a;
        let (mut lo2, mut hi2) = (lo, hi);
        for k in 0..3 {
            lo2[k] = (lo[k] + step[k]).min(lo[k] + 2.0 * step[k]);
            hi2[k] = (hi[k] + step[k]).max(hi[k] + 2.0 * step[k]);
        }
        let tiles = self.stored_in(map, lo2, hi2);
        self.store.prefetch(tiles);
    }

    /// Nodes the grid has and the list lacks (made by the frame) become resident tiles,
    /// observed now and changed.
    pub(crate) fn adopt_new_nodes(&mut self, map: &OccupancyMap) {
        if map.grid().node_count() == self.resident.len() {
            return;
        }
        for k in map.grid().node_origins() {
            self.resident.entry(k).or_insert(Resident {
                last_observed: self.clock,
                dirty: true,
            });
        }
    }

    /// The map's resident bytes: its leaves and nodes, its field's, the records waiting
    /// for the writer and those its loader decoded ahead.
    pub(crate) fn resident_bytes(&self, map: &OccupancyMap, field: Option<&DistanceField>) -> u64 {
        (map.grid().live_bytes()
            + field.map_or(0, DistanceField::memory_bytes)
            + self.store.pending_bytes()
            + self.store.ready_bytes()) as u64
    }

    /// Near or over the budget (the map's resident bytes and the integrator's `working`
    /// buffers), evict tiles toward seven eighths of the map's share.
    fn evict_over_budget(
        &mut self,
        map: &mut OccupancyMap,
        mut field: Option<&mut DistanceField>,
        sensor: WorldPoint,
        working: u64,
        report: &mut TileReport,
    ) {
        let Some(budget) = self.budget else { return };
        let share = budget.saturating_sub(working);
        let low = share / 8 * 7;
        let bytes = self.resident_bytes(map, field.as_deref());
        if self.write_failed || bytes <= low {
            return;
        }
        // Between seven eighths of the share and the share, a few tiles a frame: the map
        // grows by about a tile a frame, so eviction keeps pace in small steps, not in a
        // batch that stalls one frame. Over the share, as many as it takes.
        let most = if bytes <= share {
            EVICT_PER_FRAME
        } else {
            usize::MAX
        };
        let start = Instant::now();
        let s = map.transform().point_to_units(&sensor);
        let far = |k: &VoxelCoord| {
            let c = k.to_array().map(|v| f64::from(v) + f64::from(TILE) / 2.0);
            (0..3).map(|i| (c[i] - s[i]).powi(2)).sum::<f64>()
        };
        let mut order: Vec<(u64, f64, VoxelCoord)> = (self.resident.iter())
            .filter(|(_, r)| r.last_observed < self.clock)
            .map(|(k, r)| (r.last_observed, far(k), *k))
            .collect();
        // Least recently observed first; among those, farthest first.
        order.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(b.1.total_cmp(&a.1)));
        for (_, _, k) in order.into_iter().take(most) {
            if self.resident_bytes(map, field.as_deref()) <= low {
                break;
            }
            if let Err(e) = self.evict(map, field.as_deref_mut(), k) {
                self.write_failed = true;
                report.write_error = Some(e.to_string());
                break;
            }
            report.evicted += 1;
            self.untrimmed += 1;
        }
        if self.untrimmed >= TRIM_EVERY {
            self.untrimmed = 0;
            give_back_freed_memory();
        }
        report.evict_time = start.elapsed();
    }

    /// Write the tile (with its bands) to the store if changed, then drop it from memory.
    fn evict(
        &mut self,
        map: &mut OccupancyMap,
        field: Option<&mut DistanceField>,
        tile: VoxelCoord,
    ) -> Result<(), StoreError> {
        let r = self.resident[&tile];
        if r.dirty || !self.store.has(tile) {
            let raw = raw_tile(map.grid(), tile, field.as_deref());
            self.store.put(tile, r.last_observed, raw)?;
        }
        if let Some(f) = field {
            f.forget_leaves(map.grid().leaves_of_node(tile).map(|(o, _)| o));
        }
        map.grid_mut().remove_node(tile);
        self.resident.remove(&tile);
        self.stored.insert(tile);
        self.stats.evictions += 1;
        Ok(())
    }

    /// Hand every changed resident tile to the store, then commit.
    pub(crate) fn save(
        &mut self,
        map: &OccupancyMap,
        field: Option<&DistanceField>,
        last_frame: (u64, u64),
    ) -> Result<SaveReport, StoreError> {
        let start = Instant::now();
        let mut written = 0;
        let mut dirty: Vec<VoxelCoord> = (self.resident.iter())
            .filter(|(_, r)| r.dirty)
            .map(|(k, _)| *k)
            .collect();
        dirty.sort_unstable_by_key(|k| (k.z, k.y, k.x));
        for k in dirty {
            let raw = raw_tile(map.grid(), k, field);
            self.store.put(k, self.resident[&k].last_observed, raw)?;
            if let Some(r) = self.resident.get_mut(&k) {
                r.dirty = false;
            }
            written += 1;
            // Raw records wait uncompressed for the writer: a save of a whole resident
            // map would otherwise hold a second copy of it.
            if self.store.pending_bytes() > SAVE_BACKLOG {
                self.store.flush()?;
            }
        }
        let generation = self.store.commit(last_frame)?;
        Ok(SaveReport {
            tiles_written: written,
            generation,
            time: start.elapsed(),
        })
    }

    /// Forget every tile, in memory and in the store (the next commit holds none).
    pub(crate) fn clear(&mut self) {
        for k in self.store.tiles() {
            self.store.forget(k);
        }
        self.resident.clear();
        self.stored.clear();
    }

    /// The map file of every tile, in memory or only in the store, at `path`, with the
    /// bands of `field` (its window's).
    pub(crate) fn export(
        &mut self,
        map: &OccupancyMap,
        field: Option<&DistanceField>,
        path: &std::path::Path,
    ) -> Result<u64, ExportError> {
        let tiles: Vec<VoxelCoord> = self.resident.keys().chain(&self.stored).copied().collect();
        let (resident, store) = (&self.resident, &mut self.store);
        let keep = |o| field.is_some_and(|f| f.holds_band(o));
        let streamed = field.map(|f| {
            let s = StreamedField {
                config: *f.config(),
                window: f.window(),
            };
            (s, &keep as &dyn Fn(VoxelCoord) -> bool)
        });
        write_tiles(path, map, streamed, tiles, |k| {
            if resident.contains_key(&k) {
                return Ok(raw_tile(map.grid(), k, field));
            }
            Ok(store.get_raw(k)?.unwrap_or_default())
        })
    }

    pub(crate) fn stats(&self, map: &OccupancyMap, field: Option<&DistanceField>) -> TileStats {
        TileStats {
            resident_bytes: self.resident_bytes(map, field),
            tiles_resident: self.resident.len() as u64,
            tiles_stored: self.stored.len() as u64,
            store: self.store.counters(),
            ..self.stats
        }
    }
}
