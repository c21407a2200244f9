//! [`DistanceField`]: a band-limited exact distance field kept beside an occupancy map.
//!
//! The field is recomputed tile by tile (32³ voxels, `tile.rs`). After a frame,
//! [`DistanceField::update`] compares the obstacles of the map's leaves in the frame's box
//! with the copy it kept of them; a tile is transformed again when an obstacle changed
//! within the radius of it, when it holds a leaf the field has not seen, or when a moving
//! window newly covers it. Each transform is exact and depends only on the obstacles, so
//! the field after any sequence of updates equals the field built from scratch, and does
//! not depend on the thread count: tiles run in parallel on the current rayon pool and
//! their results are stored in tile order.

use super::tile::{self, Region, Scratch, TILE, TILE_LOG2};
use super::FieldConfig;
use crate::coord::{ConfigError, VoxelCoord, WorldPoint};
use crate::grid::Grid;
use crate::map::OccupancyMap;
use crate::mask::Mask512;
use crate::tree::LEAF_VOXELS;
use rayon::prelude::*;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// What one update did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FieldReport {
    /// Map leaves whose obstacles changed, and leaves the field had not seen.
    pub changed_leaves: u64,
    pub new_leaves: u64,
    /// Tiles transformed.
    pub tiles: u64,
    pub time: Duration,
}

/// One leaf's share of the field: which voxels are in the band, and their offsets.
struct LeafField {
    band: Mask512,
    offsets: [[i8; 3]; LEAF_VOXELS],
}

/// A distance field over an [`OccupancyMap`] (see the module doc of [`crate::field`]).
///
/// ```
/// use voxmap_core::{OccupancyMap, SensorModel, VoxelCoord};
/// use voxmap_core::field::{DistanceField, FieldConfig};
/// let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
/// map.set_value(VoxelCoord::new(0, 0, 0), 100);      // one occupied voxel
/// map.set_value(VoxelCoord::new(3, 4, 0), -10);      // a free one, 0.5 m away
/// let mut field = DistanceField::new(FieldConfig::default(), map.resolution()).unwrap();
/// field.rebuild(&map, None);
/// assert_eq!(field.nearest(VoxelCoord::new(3, 4, 0)), Some([-3, -4, 0]));
/// assert_eq!(field.distance(VoxelCoord::new(3, 4, 0)), Some(0.5));
/// ```
pub struct DistanceField {
    cfg: FieldConfig,
    radius: u32,
    resolution: f64,
    /// Offsets of the voxels in the band (active), per map leaf with any.
    grid: Grid<[i8; 3]>,
    /// Every map leaf the field has seen; `marked`: its obstacles when last transformed.
    seen: Grid<()>,
    /// The voxels covered (inclusive), when a window is set and placed.
    window: Option<(VoxelCoord, VoxelCoord)>,
    /// Per pool thread: the transform's buffers.
    scratch: Vec<Mutex<Scratch>>,
    /// The kernel the transform is compiled for (the process's).
    kernel: crate::kernel::Kernel,
}

impl std::fmt::Debug for DistanceField {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DistanceField")
            .field("config", &self.cfg)
            .field("radius", &self.radius)
            .field("window", &self.window)
            .finish_non_exhaustive()
    }
}

impl DistanceField {
    /// An empty field for a map of `resolution`.
    pub fn new(cfg: FieldConfig, resolution: f64) -> Result<Self, ConfigError> {
        let radius = cfg.radius(resolution)?;
        Ok(Self {
            cfg,
            radius,
            resolution,
            grid: Grid::new(),
            seen: Grid::new(),
            window: None,
            scratch: Vec::new(),
            kernel: crate::kernel::Kernel::process(),
        })
    }

    pub fn config(&self) -> &FieldConfig {
        &self.cfg
    }

    /// The band's radius in voxels.
    pub fn radius(&self) -> u32 {
        self.radius
    }

    /// The largest distance kept, metres: the radius in whole voxels.
    pub fn max_distance(&self) -> f64 {
        f64::from(self.radius) * self.resolution
    }

    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// The voxels the field covers (inclusive), or `None` for all of the map's leaves.
    pub fn window(&self) -> Option<(VoxelCoord, VoxelCoord)> {
        self.window
    }

    /// Whether the field holds voxel `v`: not outside the window.
    pub fn covers(&self, v: VoxelCoord) -> bool {
        self.window.is_none_or(|(lo, hi)| inside(v, lo, hi))
    }

    /// Voxels in the band.
    pub fn band_voxels(&self) -> u64 {
        self.grid.active_count()
    }

    /// Heap bytes held: the band's leaves and the copy of the map's obstacles, in the leaf
    /// pools' whole chunks (of 3272 leaves each; the pages of a chunk's unused leaves are
    /// reserved, not touched).
    pub fn memory_bytes(&self) -> usize {
        self.grid.memory_bytes() + self.seen.memory_bytes()
    }

    /// Bytes of the leaves in use: the band's (offsets and masks) and the copy of the map's
    /// obstacles, without the chunks' unused leaves and the internal nodes.
    pub fn leaf_bytes(&self) -> usize {
        self.grid.leaf_count() * std::mem::size_of::<crate::grid::Leaf<[i8; 3]>>()
            + self.seen.leaf_count() * std::mem::size_of::<crate::grid::Leaf<()>>()
    }

    /// The offset from `v` to its nearest obstacle voxel, if one lies within the radius
    /// (`[0, 0, 0]` on an obstacle). `None` also where the field does not reach: outside
    /// the window or in a leaf the map does not hold.
    pub fn nearest(&self, v: VoxelCoord) -> Option<[i8; 3]> {
        if !self.covers(v) {
            return None;
        }
        self.grid.get(v)
    }

    /// The distance (metres) from `v`'s centre to its nearest obstacle's, if below
    /// [`Self::max_distance`].
    pub fn distance(&self, v: VoxelCoord) -> Option<f64> {
        self.nearest(v)
            .map(|o| f64::from(super::offset_len2(o)).sqrt() * self.resolution)
    }

    /// Every leaf with voxels in the band, as (origin, band mask, offsets), in no
    /// particular order.
    pub fn leaves(&self) -> impl Iterator<Item = (VoxelCoord, &Mask512, &[[i8; 3]; 512])> + '_ {
        (self.grid.leaves())
            .filter(|(_, l)| !l.active.is_empty())
            .map(|(o, l)| (o, &l.active, &l.values))
    }

    /// The band of the leaf at `origin`, if it has one.
    pub fn leaf(&self, origin: VoxelCoord) -> Option<(&Mask512, &[[i8; 3]; 512])> {
        let l = self.grid.leaf(self.grid.leaf_index(origin)?);
        (!l.active.is_empty()).then_some((&l.active, &l.values))
    }

    /// A field read back from a file (see `io::mapfile`) for `map`, covering `window`:
    /// refused, with the reason, unless its offsets lie in the band and its obstacles are
    /// exactly the map's (every obstacle stored at offset 0, nothing else there).
    pub fn restore(
        cfg: FieldConfig,
        map: &OccupancyMap,
        window: Option<(VoxelCoord, VoxelCoord)>,
        leaves: Vec<(VoxelCoord, Mask512, [[i8; 3]; LEAF_VOXELS])>,
    ) -> Result<Self, String> {
        let mut f = Self::new(cfg, map.resolution()).map_err(|e| e.to_string())?;
        f.window = window;
        let (policy, r2) = (cfg.unknown, (f.radius * f.radius) as i32);
        let absent = tile::absent_obstacles(policy);
        let obstacles_at = |o: VoxelCoord| match map.grid().leaf_index(o) {
            Some(i) => tile::obstacles(map.grid().leaf(i), policy),
            None => absent,
        };
        for (o, band, offsets) in leaves {
            if o.to_array()
                .iter()
                .any(|c| c & 7 != 0 || c.unsigned_abs() >= 1 << 30)
            {
                return Err(format!(
                    "leaf origin {o:?} not leaf-aligned or out of range"
                ));
            }
            let obstacles = obstacles_at(o);
            for i in band.iter_ones() {
                let len2 = super::offset_len2(offsets[i]);
                if len2 >= r2 {
                    return Err(format!("an offset of leaf {o:?} reaches beyond the radius"));
                }
                if (len2 == 0) != obstacles.get(i) {
                    return Err(format!("leaf {o:?} disagrees with the map's obstacles"));
                }
            }
            let li = f.grid.leaf_index_or_insert(o, None);
            let leaf = f.grid.leaf_mut(li);
            if !leaf.active.is_empty() {
                return Err(format!("leaf {o:?} stored twice"));
            }
            leaf.active = band;
            leaf.values = offsets;
        }
        // Every obstacle of the map's leaves that the field covers is in it, at offset 0.
        for (o, leaf) in map.grid().leaves() {
            let obstacles = tile::obstacles(leaf, policy);
            let li = f.seen.leaf_index_or_insert(o, None);
            f.seen.leaf_mut(li).marked = obstacles;
            for i in obstacles.iter_ones() {
                let v = crate::tree::voxel_at(o, i);
                if f.covers(v) && f.grid.get(v) != Some([0; 3]) {
                    return Err(format!("the map's obstacle at {v:?} is missing"));
                }
            }
        }
        Ok(f)
    }

    /// Forget everything (after the map was cleared).
    pub fn clear(&mut self) {
        self.grid = Grid::new();
        self.seen = Grid::new();
    }

    /// Build the field of the whole map from scratch (after a load), around `sensor` when
    /// a window is set.
    pub fn rebuild(&mut self, map: &OccupancyMap, sensor: Option<WorldPoint>) -> FieldReport {
        self.clear();
        self.window = None;
        self.update(map, None, sensor)
    }

    /// Bring the field up to date with the map after a change inside the inclusive voxel
    /// box `touched` (an [`crate::IntegrateReport`]'s `bounds`), or anywhere when `None`.
    /// `sensor` places the window, if one is set; without one the window stays where it
    /// was (or covers the whole map before it is first placed).
    pub fn update(
        &mut self,
        map: &OccupancyMap,
        touched: Option<(VoxelCoord, VoxelCoord)>,
        sensor: Option<WorldPoint>,
    ) -> FieldReport {
        let t0 = Instant::now();
        let policy = self.cfg.unknown;
        let r = self.radius as i32;
        let old_window = self.window;
        if let (Some(half), Some(p)) = (self.cfg.window, sensor) {
            self.window = window_around(map, &p, half);
        }
        // Which map leaves changed, read in parallel against the copy.
        let (lo, hi) = touched.unwrap_or((
            VoxelCoord::new(i32::MIN, i32::MIN, i32::MIN),
            VoxelCoord::new(i32::MAX, i32::MAX, i32::MAX),
        ));
        let seen = &self.seen;
        let absent = tile::absent_obstacles(policy);
        let changes: Vec<(VoxelCoord, Mask512, bool)> =
            map.grid().filter_map_leaves_in_box(lo, hi, |origin, leaf| {
                let now = tile::obstacles(leaf, policy);
                match seen.leaf_index(origin) {
                    None => Some((origin, now, true)),
                    Some(i) => (seen.leaf(i).marked != now).then_some((origin, now, false)),
                }
            });
        let mut report = FieldReport::default();
        // Per tile to transform again, the box of its voxels that may have changed (in
        // leaves, tile-local, inclusive).
        let mut dirty: hashbrown::HashMap<VoxelCoord, ([i32; 3], [i32; 3])> =
            hashbrown::HashMap::new();
        let tile_of = |v: VoxelCoord| v.shr(TILE_LOG2);
        // Mark the voxels [lo, hi] (global, inclusive) as to be transformed again.
        let mut mark = |lo: VoxelCoord, hi: VoxelCoord| {
            let (a, b) = (tile_of(lo), tile_of(hi));
            for z in a.z..=b.z {
                for y in a.y..=b.y {
                    for x in a.x..=b.x {
                        let t = VoxelCoord::new(x, y, z);
                        let o = t.shl(TILE_LOG2).to_array();
                        let last = TILE as i32 - 1;
                        let (l, h) = (lo.to_array(), hi.to_array());
                        let blo = [0, 1, 2].map(|k| (l[k] - o[k]).clamp(0, last) & !7);
                        let bhi = [0, 1, 2].map(|k| (h[k] - o[k]).clamp(0, last) | 7);
                        let e = dirty.entry(t).or_insert((blo, bhi));
                        for k in 0..3 {
                            e.0[k] = e.0[k].min(blo[k]);
                            e.1[k] = e.1[k].max(bhi[k]);
                        }
                    }
                }
            }
        };
        for &(origin, now, new) in &changes {
            let was = match new {
                true => absent,
                false => {
                    self.seen
                        .leaf(self.seen.leaf_index(origin).expect("seen"))
                        .marked
                }
            };
            if new {
                report.new_leaves += 1;
                mark(origin, origin + VoxelCoord::new(7, 7, 7));
            }
            if was != now {
                report.changed_leaves += 1;
                // The tiles within the radius of a voxel whose obstacle changed.
                let flipped = Mask512 {
                    words: std::array::from_fn(|w| was.words[w] ^ now.words[w]),
                };
                let (lo, hi) = flipped.extent().expect("masks differ");
                mark(
                    VoxelCoord::new(
                        origin.x + lo[0] - r,
                        origin.y + lo[1] - r,
                        origin.z + lo[2] - r,
                    ),
                    VoxelCoord::new(
                        origin.x + hi[0] + r,
                        origin.y + hi[1] + r,
                        origin.z + hi[2] + r,
                    ),
                );
            }
            let li = self.seen.leaf_index_or_insert(origin, None);
            self.seen.leaf_mut(li).marked = now;
        }
        // A window that moved: drop what it left, transform what it newly covers.
        if self.window != old_window {
            if let Some((wlo, whi)) = self.window {
                self.drop_outside(wlo, whi);
                let (a, b) = (tile_of(wlo), tile_of(whi));
                for z in a.z..=b.z {
                    for y in a.y..=b.y {
                        for x in a.x..=b.x {
                            let t = VoxelCoord::new(x, y, z);
                            let covered = old_window.is_some_and(|(olo, ohi)| {
                                let (tlo, thi) = tile_box(t);
                                inside(tlo, olo, ohi) && inside(thi, olo, ohi)
                            });
                            if !covered {
                                let (tlo, thi) = tile_box(t);
                                mark(tlo, thi);
                            }
                        }
                    }
                }
            }
        }
        let mut tiles: Vec<(VoxelCoord, Region)> = dirty
            .into_iter()
            .filter(|&(t, _)| {
                self.window.is_none_or(|(wlo, whi)| {
                    let (tlo, thi) = tile_box(t);
                    overlaps(tlo, thi, wlo, whi)
                })
            })
            .map(|(t, (lo, hi))| (t, (lo.map(|c| c as usize), hi.map(|c| c as usize + 1))))
            .collect();
        tiles.sort_unstable_by_key(|(t, _)| (t.z, t.y, t.x));
        report.tiles = tiles.len() as u64;
        self.transform_tiles(map, &tiles);
        report.time = t0.elapsed();
        report
    }

    /// Transform `tiles` in parallel and store their leaves' bands.
    fn transform_tiles(&mut self, map: &OccupancyMap, tiles: &[(VoxelCoord, Region)]) {
        let threads = rayon::current_num_threads();
        while self.scratch.len() < threads {
            self.scratch.push(Mutex::new(Scratch::default()));
        }
        let (scratch, radius, policy, kernel, window) = (
            &self.scratch,
            self.radius,
            self.cfg.unknown,
            self.kernel,
            self.window,
        );
        let grid = map.grid();
        let results: Vec<Vec<(VoxelCoord, Option<Box<LeafField>>)>> = tiles
            .par_iter()
            .map(|&(t, region)| {
                let origin = t.shl(TILE_LOG2);
                // The map's leaves in the tile's region (in the window): only they get a
                // band.
                let per = TILE / 8;
                let mut leaves = Vec::with_capacity(per * per * per);
                let (lo, hi) = (region.0.map(|c| c / 8), region.1.map(|c| c.div_ceil(8)));
                for z in lo[2]..hi[2] {
                    for y in lo[1]..hi[1] {
                        for x in lo[0]..hi[0] {
                            let o =
                                origin + VoxelCoord::new(8 * x as i32, 8 * y as i32, 8 * z as i32);
                            let inside_window = window.is_none_or(|(wlo, whi)| {
                                overlaps(o, o + VoxelCoord::new(7, 7, 7), wlo, whi)
                            });
                            if inside_window && grid.leaf_index(o).is_some() {
                                leaves.push((o, [x, y, z]));
                            }
                        }
                    }
                }
                if leaves.is_empty() {
                    return Vec::new();
                }
                let slot = rayon::current_thread_index().unwrap_or(0) % scratch.len();
                let mut s = scratch[slot].lock().unwrap_or_else(|e| e.into_inner());
                if !tile::transform(&mut s, grid, policy, origin, radius, kernel, region) {
                    return leaves.into_iter().map(|(o, _)| (o, None)).collect();
                }
                let far = tile::far_key(radius);
                leaves
                    .into_iter()
                    .map(|(o, [lx, ly, lz])| {
                        let mut band = Mask512::EMPTY;
                        let mut offsets = [[0i8; 3]; LEAF_VOXELS];
                        for z in 0..8 {
                            for y in 0..8 {
                                let row = ((8 * lz + z) * TILE + 8 * ly + y) * TILE + 8 * lx;
                                for x in 0..8 {
                                    let key = s.keys[row + x];
                                    if key < far {
                                        let i = x | y << 3 | z << 6;
                                        band.set(i);
                                        offsets[i] = tile::decode(key);
                                    }
                                }
                            }
                        }
                        let leaf =
                            (!band.is_empty()).then(|| Box::new(LeafField { band, offsets }));
                        (o, leaf)
                    })
                    .collect()
            })
            .collect();
        for (origin, leaf) in results.into_iter().flatten() {
            match leaf {
                Some(l) => {
                    let i = self.grid.leaf_index_or_insert(origin, None);
                    let g = self.grid.leaf_mut(i);
                    g.active = l.band;
                    g.values = l.offsets;
                }
                None => {
                    if let Some(i) = self.grid.leaf_index(origin) {
                        self.grid.leaf_mut(i).active = Mask512::EMPTY;
                    }
                }
            }
        }
    }

    /// Empty the band of every leaf outside the window.
    fn drop_outside(&mut self, lo: VoxelCoord, hi: VoxelCoord) {
        let out: Vec<u32> = (self.grid.leaves())
            .filter(|(o, l)| {
                !l.active.is_empty() && !overlaps(*o, *o + VoxelCoord::new(7, 7, 7), lo, hi)
            })
            .filter_map(|(o, _)| self.grid.leaf_index(o))
            .collect();
        for i in out {
            self.grid.leaf_mut(i).active = Mask512::EMPTY;
        }
    }
}

/// The window around `p`: the voxels within `half` metres per axis.
fn window_around(
    map: &OccupancyMap,
    p: &WorldPoint,
    half: [f64; 3],
) -> Option<(VoxelCoord, VoxelCoord)> {
    let tf = map.transform();
    let lo = tf.voxel_of(&WorldPoint::new(
        p.x - half[0],
        p.y - half[1],
        p.z - half[2],
    ))?;
    let hi = tf.voxel_of(&WorldPoint::new(
        p.x + half[0],
        p.y + half[1],
        p.z + half[2],
    ))?;
    Some((lo, hi))
}

/// Inclusive voxel box of a tile.
fn tile_box(t: VoxelCoord) -> (VoxelCoord, VoxelCoord) {
    let lo = t.shl(TILE_LOG2);
    let e = TILE as i32 - 1;
    (lo, lo + VoxelCoord::new(e, e, e))
}

fn inside(v: VoxelCoord, lo: VoxelCoord, hi: VoxelCoord) -> bool {
    (lo.x..=hi.x).contains(&v.x) && (lo.y..=hi.y).contains(&v.y) && (lo.z..=hi.z).contains(&v.z)
}

fn overlaps(alo: VoxelCoord, ahi: VoxelCoord, blo: VoxelCoord, bhi: VoxelCoord) -> bool {
    alo.x <= bhi.x
        && blo.x <= ahi.x
        && alo.y <= bhi.y
        && blo.y <= ahi.y
        && alo.z <= bhi.z
        && blo.z <= ahi.z
}
