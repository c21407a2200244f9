//! [`DistanceField`]: a band-limited exact distance field kept beside an occupancy map.
//!
//! The field is recomputed patch by patch (32³ voxels, `patch.rs`). After a frame,
//! [`DistanceField::update`] compares the obstacles of the map's leaves in the frame's box
//! with the copy it kept of them; a patch is transformed again when an obstacle changed
//! within the radius of it, when it holds a leaf the field has not seen, or when a moving
//! window newly covers it. Each transform is exact and depends only on the obstacles, so
//! the field after any sequence of updates equals the field built from scratch, and does
//! not depend on the thread count: patches run in parallel on the current rayon pool and
//! their results are stored in patch order.

use super::patch::{self, Region, Scratch, PATCH, PATCH_LOG2};
use super::{check_bands, leaf_in_window, Band, FieldConfig};
use crate::coord::{ConfigError, VoxelCoord, WorldPoint};
use crate::grid::Leaf;
use crate::mask::Mask512;
use crate::occupancy::OccupancyMap;
use crate::tree::{leaf_offset, leaf_origin, LEAF_VOXELS};
use hashbrown::HashMap;
use rayon::prelude::*;
use std::sync::Mutex;
use std::time::{Duration, Instant};
use voxmap_reader::mapfile::BandRecord;

/// Patches transformed in parallel before their bands are stored: at most 256 × 64 leaves'
/// new bands exist beside the old ones.
const PATCHES_AT_ONCE: usize = 256;

/// What one update did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FieldReport {
    /// Map leaves whose obstacles changed, and leaves the field had not seen.
    pub changed_leaves: u64,
    pub new_leaves: u64,
    /// Patches transformed.
    pub patches: u64,
    /// The voxel box (inclusive) of the patches transformed, whose leaves' bands may have
    /// changed.
    pub transformed: Option<(VoxelCoord, VoxelCoord)>,
    pub time: Duration,
}

/// One map leaf's share of the band: which of its voxels lie in it and, packed in voxel
/// order, their offsets to the nearest obstacle (the `k`-th voxel of the mask has the
/// `k`-th offset). A leaf pays for the voxels of its band alone, not for all 512.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LeafBand {
    mask: Mask512,
    /// The voxels at offset zero: the leaf's obstacles when it was transformed, which the
    /// next update compares the map's with (a copy, for a 64-byte compare per leaf).
    obstacles: Mask512,
    offsets: Box<[[i8; 3]]>,
}

impl LeafBand {
    /// A band of the voxels of `mask` with `offsets` in voxel order; `None` unless there
    /// is exactly one offset per voxel.
    pub fn new(mask: Mask512, offsets: Vec<[i8; 3]>) -> Option<Self> {
        if mask.count() as usize != offsets.len() {
            return None;
        }
        let band = (mask, offsets);
        let obstacles = band.obstacles();
        let (mask, offsets) = band;
        Some(Self {
            mask,
            obstacles,
            offsets: offsets.into_boxed_slice(),
        })
    }

    /// The in-leaf voxels (`x | y << 3 | z << 6`) in the band.
    pub fn mask(&self) -> &Mask512 {
        &self.mask
    }

    /// The offsets of the mask's voxels, in voxel order.
    pub fn offsets(&self) -> &[[i8; 3]] {
        &self.offsets
    }

    /// The offset of in-leaf voxel `i`, if it lies in the band.
    #[inline]
    pub fn get(&self, i: usize) -> Option<[i8; 3]> {
        let i = i & (LEAF_VOXELS - 1);
        if !self.mask.get(i) {
            return None;
        }
        self.offsets.get(self.mask.rank(i) as usize).copied()
    }

    /// (in-leaf voxel, offset) of each voxel of the band, in voxel order.
    pub fn iter(&self) -> impl Iterator<Item = (usize, [i8; 3])> + '_ {
        self.mask.iter_ones().zip(self.offsets.iter().copied())
    }

    /// Heap bytes: the band's box and its offsets' allocation.
    fn heap_bytes(&self) -> usize {
        allocation(std::mem::size_of::<Self>()) + allocation(3 * self.offsets.len())
    }
}

impl Band for LeafBand {
    fn mask(&self) -> &Mask512 {
        &self.mask
    }

    fn offsets(&self) -> &[[i8; 3]] {
        &self.offsets
    }
}

/// What the allocator takes for `n` bytes: glibc's malloc rounds a request plus its
/// 8-byte header up to 16 bytes, at least 32.
fn allocation(n: usize) -> usize {
    if n == 0 {
        return 0;
    }
    (n + 8).div_ceil(16).max(2) * 16
}

/// Bytes of a hash map's table: each slot's entry and control byte.
fn table_bytes<K, V>(m: &HashMap<K, V>) -> usize {
    m.capacity() * (std::mem::size_of::<(K, V)>() + 1)
}

/// A distance field over an [`OccupancyMap`] (see the module doc of [`crate::field`]).
///
/// ```
/// use voxmap_map::{OccupancyMap, SensorModel, VoxelCoord};
/// use voxmap_map::field::{DistanceField, FieldConfig};
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
    /// Every map leaf the field has seen, by origin, with its band where it has one. The
    /// band's voxels at offset zero are the leaf's obstacles when it was last
    /// transformed: what the next update compares the map with.
    leaves: HashMap<VoxelCoord, Option<Box<LeafBand>>>,
    /// The obstacles of seen leaves outside the window (which hold no band), where they
    /// have any.
    outside: HashMap<VoxelCoord, Mask512>,
    /// Voxels in the band.
    band_count: u64,
    /// Heap bytes of the bands (as [`LeafBand::heap_bytes`] counts them).
    band_heap: usize,
    /// The voxels covered (inclusive), when a window is set and placed.
    window: Option<(VoxelCoord, VoxelCoord)>,
    /// Per pool thread: the transform's buffers.
    scratch: Vec<Mutex<Scratch>>,
    /// The kernel the transform runs (the process's).
    kernels: &'static crate::kernel::Kernels,
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
            leaves: HashMap::new(),
            outside: HashMap::new(),
            band_count: 0,
            band_heap: 0,
            window: None,
            scratch: Vec::new(),
            kernels: crate::kernel::Kernels::process_or_scalar(),
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
        self.band_count
    }

    /// Heap bytes held: the tables of the leaves seen (with their spare slots) and of the
    /// obstacles outside the window, and each band's allocations as the allocator rounds
    /// them. The transform's per-thread buffers are not counted.
    pub fn memory_bytes(&self) -> usize {
        table_bytes(&self.leaves) + table_bytes(&self.outside) + self.band_heap
    }

    /// How far (voxels) beyond a voxel whose obstacle changed an update may read the map:
    /// the radius to the patches it marks, a patch, and the radius those patches read
    /// around them. A map with a tile store keeps the tiles within this reach of a frame's
    /// box in memory while the field follows the frame, and those within the radius and a
    /// patch of the window's box.
    pub fn reach(&self) -> u32 {
        2 * self.radius + PATCH as u32
    }

    /// How far (voxels) beyond the window's box an update may read the map: the patches
    /// a moved window newly covers read the radius around them.
    pub fn window_reach(&self) -> u32 {
        self.radius + PATCH as u32
    }

    /// Bytes of the bands themselves: two 64-byte masks (the band's and the obstacles')
    /// and 3 bytes per voxel, per leaf with a band.
    pub fn leaf_bytes(&self) -> usize {
        (self.leaves.values().flatten())
            .map(|b| 128 + 3 * b.offsets.len())
            .sum()
    }

    /// The offset from `v` to its nearest obstacle voxel, if one lies within the radius
    /// (`[0, 0, 0]` on an obstacle). `None` also where the field does not reach: outside
    /// the window or in a leaf the map does not hold.
    pub fn nearest(&self, v: VoxelCoord) -> Option<[i8; 3]> {
        if !self.covers(v) {
            return None;
        }
        self.leaf(leaf_origin(v))?.get(leaf_offset(v))
    }

    /// The distance (metres) from `v`'s centre to its nearest obstacle's, if below
    /// [`Self::max_distance`].
    pub fn distance(&self, v: VoxelCoord) -> Option<f64> {
        self.nearest(v)
            .map(|o| f64::from(super::offset_len2(o)).sqrt() * self.resolution)
    }

    /// Every leaf with voxels in the band, by origin, in no particular order.
    pub fn leaves(&self) -> impl Iterator<Item = (VoxelCoord, &LeafBand)> + '_ {
        (self.leaves.iter()).filter_map(|(o, b)| Some((*o, &**b.as_ref()?)))
    }

    /// The band of the leaf at `origin`, if it has one.
    pub fn leaf(&self, origin: VoxelCoord) -> Option<&LeafBand> {
        self.leaves.get(&origin)?.as_deref()
    }

    /// Store `band` as the band of the map leaf at `origin` (none: it has no voxel in it).
    fn set_band(&mut self, origin: VoxelCoord, band: Option<LeafBand>) {
        let new = band.map(Box::new);
        if let Some(b) = &new {
            self.band_count += b.offsets.len() as u64;
            self.band_heap += b.heap_bytes();
        }
        if let Some(Some(old)) = self.leaves.insert(origin, new) {
            self.uncount(&old);
        }
    }

    /// Take a band that leaves the field out of the counters.
    fn uncount(&mut self, band: &LeafBand) {
        self.band_count -= band.offsets.len() as u64;
        self.band_heap -= band.heap_bytes();
    }

    /// Forget the leaves at `origins` (a tile going to the store, its bands with it):
    /// their bands and the obstacles kept of them.
    pub fn forget_leaves(&mut self, origins: impl IntoIterator<Item = VoxelCoord>) {
        for o in origins {
            if let Some(Some(band)) = self.leaves.remove(&o) {
                self.uncount(&band);
            }
            self.outside.remove(&o);
        }
        // Tables that emptied by far give their memory back (a map under a budget).
        if self.leaves.len() * 4 < self.leaves.capacity() && self.leaves.capacity() > 1024 {
            self.leaves.shrink_to_fit();
        }
        if self.outside.len() * 4 < self.outside.capacity() && self.outside.capacity() > 1024 {
            self.outside.shrink_to_fit();
        }
    }

    /// Take back the leaves of a tile from the store (`leaves`, now in the map) with the
    /// bands stored with them. Bands outside the window are dropped, and all of them while
    /// a window is asked for and not yet placed (the first update places it and
    /// transforms all it covers); those in it must pass `field::check_bands` against the
    /// leaves, or the whole tile is refused, changing nothing. The caller keeps the
    /// invariant that makes the bands current: a tile was in memory whenever an update
    /// could change its bands (see [`Self::reach`]).
    pub fn restore_tile(
        &mut self,
        leaves: &[(VoxelCoord, Leaf<i8>)],
        bands: Vec<BandRecord>,
    ) -> Result<(), String> {
        let n = bands.len();
        let mut kept: HashMap<VoxelCoord, LeafBand> = HashMap::with_capacity(n);
        for (o, mask, offsets) in bands {
            let band = LeafBand::new(mask, offsets)
                .ok_or_else(|| format!("band of leaf {o:?}: offsets do not match its mask"))?;
            if self.holds_band(o) && kept.insert(o, band).is_some() {
                return Err(format!("band of leaf {o:?} stored twice"));
            }
        }
        let policy = self.cfg.unknown;
        let origins: hashbrown::HashSet<VoxelCoord> = leaves.iter().map(|(o, _)| *o).collect();
        let obstacles = leaves
            .iter()
            .map(|(o, l)| (*o, patch::obstacles(l, policy)));
        let placed = self.window_placed();
        check_bands(
            &kept,
            false,
            self.radius,
            self.window,
            |o| origins.contains(&o),
            obstacles.filter(|_| placed),
        )?;
        for (o, leaf) in leaves {
            let band = kept.remove(o);
            if !self.holds_band(*o) {
                let obstacles = patch::obstacles(leaf, policy);
                if !obstacles.is_empty() {
                    self.outside.insert(*o, obstacles);
                }
            }
            self.set_band(*o, band);
        }
        Ok(())
    }

    /// A field read back from a file (see `io::mapfile`) for `map`, covering `window`:
    /// refused, with the reason, unless its bands pass `field::check_bands` (offsets in the
    /// band, obstacles exactly the map's: every obstacle stored at offset 0, nothing else).
    pub fn restore(
        cfg: FieldConfig,
        map: &OccupancyMap,
        window: Option<(VoxelCoord, VoxelCoord)>,
        leaves: Vec<(VoxelCoord, LeafBand)>,
    ) -> Result<Self, String> {
        let mut f = Self::new(cfg, map.resolution()).map_err(|e| e.to_string())?;
        f.window = window;
        let n = leaves.len();
        let bands: HashMap<VoxelCoord, LeafBand> = leaves.into_iter().collect();
        let policy = cfg.unknown;
        let map_leaves = (map.grid().leaves()).map(|(o, leaf)| (o, patch::obstacles(leaf, policy)));
        let is_leaf = |o| map.grid().leaf_index(o).is_some();
        check_bands(
            &bands,
            bands.len() != n,
            f.radius,
            window,
            is_leaf,
            map_leaves,
        )?;
        for (o, band) in bands {
            f.set_band(o, Some(band));
        }
        // Every map leaf has its entry (none where it has no band); those the window leaves
        // out keep their obstacles apart.
        for (o, leaf) in map.grid().leaves() {
            f.leaves.entry(o).or_insert(None);
            if !leaf_in_window(window, o) {
                let obstacles = patch::obstacles(leaf, policy);
                if !obstacles.is_empty() {
                    f.outside.insert(o, obstacles);
                }
            }
        }
        Ok(f)
    }

    /// Whether the field holds a band for the leaf at `origin` when it has one: the leaf
    /// reaches into the window, which is placed if one is asked for.
    pub fn holds_band(&self, origin: VoxelCoord) -> bool {
        self.overlaps_window(origin) && self.window_placed()
    }

    /// No window is asked for, or it has been placed (by an update with a sensor).
    fn window_placed(&self) -> bool {
        self.cfg.window.is_none() || self.window.is_some()
    }

    /// Whether the leaf at `origin` reaches into the window (or there is none).
    fn overlaps_window(&self, origin: VoxelCoord) -> bool {
        leaf_in_window(self.window, origin)
    }

    /// Forget everything (after the map was cleared).
    pub fn clear(&mut self) {
        self.leaves = HashMap::new();
        self.outside = HashMap::new();
        self.band_count = 0;
        self.band_heap = 0;
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
        // The bands the window left, their obstacles kept apart.
        if self.window != old_window {
            self.drop_outside();
        }
        // Which map leaves changed, read in parallel: against the band's obstacles (its
        // voxels at offset zero), or those kept for a leaf outside the window.
        let (lo, hi) = touched.unwrap_or((
            VoxelCoord::new(i32::MIN, i32::MIN, i32::MIN),
            VoxelCoord::new(i32::MAX, i32::MAX, i32::MAX),
        ));
        let (leaves, outside) = (&self.leaves, &self.outside);
        let absent = patch::absent_obstacles(policy);
        let changes: Vec<(VoxelCoord, Mask512, Option<Mask512>)> =
            map.grid().filter_map_leaves_in_box(lo, hi, |origin, leaf| {
                let now = patch::obstacles(leaf, policy);
                let was = match leaves.get(&origin) {
                    None => return Some((origin, now, None)),
                    Some(Some(band)) => band.obstacles,
                    Some(None) => outside.get(&origin).copied().unwrap_or(Mask512::EMPTY),
                };
                (was != now).then_some((origin, now, Some(was)))
            });
        let mut report = FieldReport::default();
        // Per patch to transform again, the box of its voxels that may have changed (in
        // leaves, patch-local, inclusive).
        let mut dirty: hashbrown::HashMap<VoxelCoord, ([i32; 3], [i32; 3])> =
            hashbrown::HashMap::new();
        let patch_of = |v: VoxelCoord| v.shr(PATCH_LOG2);
        // Mark the voxels [lo, hi] (global, inclusive) as to be transformed again.
        let mut mark = |lo: VoxelCoord, hi: VoxelCoord| {
            let (a, b) = (patch_of(lo), patch_of(hi));
            for z in a.z..=b.z {
                for y in a.y..=b.y {
                    for x in a.x..=b.x {
                        let t = VoxelCoord::new(x, y, z);
                        let o = t.shl(PATCH_LOG2).to_array();
                        let last = PATCH as i32 - 1;
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
        for &(origin, now, seen) in &changes {
            let was = seen.unwrap_or(absent);
            if seen.is_none() {
                report.new_leaves += 1;
                mark(origin, origin + VoxelCoord::new(7, 7, 7));
            }
            if was != now {
                report.changed_leaves += 1;
                // The patches within the radius of a voxel whose obstacle changed.
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
            // A leaf in the window gets its obstacles with its band (its patch is
            // transformed); one outside keeps them apart.
            self.leaves.entry(origin).or_insert(None);
            if !self.overlaps_window(origin) {
                match now.is_empty() {
                    true => self.outside.remove(&origin),
                    false => self.outside.insert(origin, now),
                };
            }
        }
        // A window that moved: transform what it newly covers.
        if self.window != old_window {
            if let Some((wlo, whi)) = self.window {
                let (a, b) = (patch_of(wlo), patch_of(whi));
                for z in a.z..=b.z {
                    for y in a.y..=b.y {
                        for x in a.x..=b.x {
                            let t = VoxelCoord::new(x, y, z);
                            let covered = old_window.is_some_and(|(olo, ohi)| {
                                let (tlo, thi) = patch_box(t);
                                inside(tlo, olo, ohi) && inside(thi, olo, ohi)
                            });
                            if !covered {
                                let (tlo, thi) = patch_box(t);
                                mark(tlo, thi);
                            }
                        }
                    }
                }
            }
        }
        let mut patches: Vec<(VoxelCoord, Region)> = dirty
            .into_iter()
            .filter(|&(t, _)| {
                self.window.is_none_or(|(wlo, whi)| {
                    let (tlo, thi) = patch_box(t);
                    overlaps(tlo, thi, wlo, whi)
                })
            })
            .map(|(t, (lo, hi))| (t, (lo.map(|c| c as usize), hi.map(|c| c as usize + 1))))
            .collect();
        patches.sort_unstable_by_key(|(t, _)| (t.z, t.y, t.x));
        report.patches = patches.len() as u64;
        report.transformed = patches.iter().fold(None, |acc, &(t, _)| {
            let (lo, hi) = patch_box(t);
            Some(acc.map_or((lo, hi), |(a, b): (VoxelCoord, VoxelCoord)| {
                (a.min(lo), b.max(hi))
            }))
        });
        // In chunks: the new bands of a chunk replace the old before the next chunk is
        // made, so a frame that transforms much of the field does not hold it twice.
        for chunk in patches.chunks(PATCHES_AT_ONCE) {
            self.transform_patches(map, chunk);
        }
        report.time = t0.elapsed();
        report
    }

    /// Transform `patches` in parallel and store their leaves' bands.
    fn transform_patches(&mut self, map: &OccupancyMap, patches: &[(VoxelCoord, Region)]) {
        let threads = rayon::current_num_threads();
        while self.scratch.len() < threads {
            self.scratch.push(Mutex::new(Scratch::default()));
        }
        let (scratch, radius, policy, kernels, window) = (
            &self.scratch,
            self.radius,
            self.cfg.unknown,
            self.kernels,
            self.window,
        );
        let grid = map.grid();
        let results: Vec<Vec<(VoxelCoord, Option<LeafBand>)>> = patches
            .par_iter()
            .map(|&(t, region)| {
                let origin = t.shl(PATCH_LOG2);
                // The map's leaves in the patch's region (in the window): only they get a
                // band.
                let per = PATCH / 8;
                let mut leaves = Vec::with_capacity(per * per * per);
                let (lo, hi) = (region.0.map(|c| c / 8), region.1.map(|c| c.div_ceil(8)));
                for z in lo[2]..hi[2] {
                    for y in lo[1]..hi[1] {
                        for x in lo[0]..hi[0] {
                            let o =
                                origin + VoxelCoord::new(8 * x as i32, 8 * y as i32, 8 * z as i32);
                            if leaf_in_window(window, o) && grid.leaf_index(o).is_some() {
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
                if !patch::transform(&mut s, grid, policy, origin, radius, kernels, region) {
                    return leaves.into_iter().map(|(o, _)| (o, None)).collect();
                }
                let far = patch::far_key(radius);
                leaves
                    .into_iter()
                    .map(|(o, [lx, ly, lz])| {
                        let mut mask = Mask512::EMPTY;
                        let mut offsets = [[0i8; 3]; LEAF_VOXELS];
                        let mut n = 0;
                        for z in 0..8 {
                            for y in 0..8 {
                                let row = ((8 * lz + z) * PATCH + 8 * ly + y) * PATCH + 8 * lx;
                                for x in 0..8 {
                                    let key = s.keys[row + x];
                                    if key < far {
                                        mask.set(x | y << 3 | z << 6);
                                        offsets[n] = patch::decode(key);
                                        n += 1;
                                    }
                                }
                            }
                        }
                        let band = (!mask.is_empty())
                            .then(|| LeafBand::new(mask, offsets[..n].to_vec()))
                            .flatten();
                        (o, band)
                    })
                    .collect()
            })
            .collect();
        // A leaf in the window holds its obstacles in its band (none without one).
        for (origin, band) in results.into_iter().flatten() {
            self.set_band(origin, band);
            self.outside.remove(&origin);
        }
    }

    /// Drop the band of every leaf outside the window, keeping its obstacles apart.
    fn drop_outside(&mut self) {
        let out: Vec<VoxelCoord> = (self.leaves())
            .filter(|(o, _)| !self.overlaps_window(*o))
            .map(|(o, _)| o)
            .collect();
        for o in out {
            if let Some(band) = self.leaves.get_mut(&o).and_then(Option::take) {
                self.uncount(&band);
                let obstacles = band.obstacles;
                if !obstacles.is_empty() {
                    self.outside.insert(o, obstacles);
                }
            }
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

/// Inclusive voxel box of a patch.
fn patch_box(t: VoxelCoord) -> (VoxelCoord, VoxelCoord) {
    let lo = t.shl(PATCH_LOG2);
    let e = PATCH as i32 - 1;
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
