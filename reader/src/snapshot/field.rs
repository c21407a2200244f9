//! The distance field section of a snapshot, read in place: [`FieldView`].
//!
//! Each leaf with voxels in the band has a distance block (a byte per voxel, its distance
//! quantised) and its offsets (the step from each voxel to its nearest obstacle voxel).
//! The interpolating queries find a leaf's distance block from its block alone, as the
//! table names it, and read eight bytes, most often on one cache line; the exact queries
//! (`distance`, `nearest_obstacle`) read the leaf's entry and its offsets.

use super::layout::*;
use super::view::{block_word, SnapshotView};
use super::SnapshotError;
use crate::coord::{VoxelCoord, WorldPoint, MAX_VOXEL_INDEX};
use crate::field::{offset_len2, UnknownPolicy, MAX_RADIUS};
use crate::mask::BitIter;
use crate::tree::{block_origin, leaf_in_block, leaf_offset, LEAF_VOXELS, MORTON};
use nalgebra::Vector3;

/// The validated pieces of a field section.
#[derive(Clone, Copy, Debug)]
pub(super) struct FieldParts<'a> {
    header: FieldHeader,
    /// One per block of the snapshot.
    blocks: &'a [[u8; FIELD_BLOCK_SIZE]],
    entries: &'a [[u8; FIELD_ENTRY_SIZE]],
    /// The distance blocks, [`FIELD_DISTS`] bytes each.
    dists: &'a [u8],
    /// The leaves' offsets.
    data: &'a [u8],
}

impl<'a> FieldParts<'a> {
    /// Check a field section (`body` runs from its start, at `at` in the snapshot, to the
    /// snapshot's end) for a snapshot of `map_blocks` (validated) holding `leaves` leaves
    /// at `resolution`.
    pub(super) fn open(
        body: &'a [u8],
        at: u64,
        map_blocks: &[[u8; BLOCK_SIZE]],
        leaves: u64,
        resolution: f64,
    ) -> Result<Self, SnapshotError> {
        let bad = SnapshotError::BadHeader;
        let hb = body
            .get(..FIELD_HEADER_SIZE)
            .ok_or(SnapshotError::SectionOutOfBounds("field"))?;
        let h: FieldHeader = bytemuck::pod_read_unaligned(hb);
        if !(1..=MAX_RADIUS).contains(&h.radius) {
            return Err(bad("field radius"));
        }
        let want = f64::from(h.radius) * resolution;
        if !(h.max_distance.is_finite() && (h.max_distance - want).abs() <= 1e-9 * want) {
            return Err(bad("field max_distance"));
        }
        if UnknownPolicy::from_code(h.unknown).is_none() {
            return Err(bad("field unknown policy"));
        }
        if h.steps != field_steps(h.radius) {
            return Err(bad("field steps"));
        }
        if h.reserved != [0; 2] {
            return Err(bad("field reserved bytes"));
        }
        if (0..3).any(|k| h.window_lo[k] > h.window_hi[k]) {
            return Err(bad("field window"));
        }
        if !h.data_len.is_multiple_of(8)
            || h.data_len / 8 > FIELD_MAX_UNITS
            || h.dist_blocks > leaves
        {
            return Err(bad("field lengths"));
        }
        let nb = map_blocks.len() as u64;
        let blocks_end = FIELD_HEADER_SIZE as u64 + nb * FIELD_BLOCK_SIZE as u64;
        let entries_end = blocks_end + leaves * FIELD_ENTRY_SIZE as u64;
        let dists_at = field_dists_at(at, nb, leaves) - at;
        let data_at = dists_at + FIELD_DISTS as u64 * h.dist_blocks;
        if data_at.checked_add(h.data_len) != Some(body.len() as u64) {
            return Err(SnapshotError::SectionOutOfBounds("field"));
        }
        if body[entries_end as usize..dists_at as usize]
            .iter()
            .any(|&b| b != 0)
        {
            return Err(bad("field padding"));
        }
        let blocks: &[[u8; FIELD_BLOCK_SIZE]] =
            bytemuck::cast_slice(&body[FIELD_HEADER_SIZE..blocks_end as usize]);
        let entries: &[[u8; FIELD_ENTRY_SIZE]] =
            bytemuck::cast_slice(&body[blocks_end as usize..entries_end as usize]);
        let dists = &body[dists_at as usize..data_at as usize];
        let data = &body[data_at as usize..];
        // Each block names the band leaves among its leaves and where their distance
        // blocks begin, one after another in leaf order; each leaf's entry agrees.
        let (mut band, mut next, mut leaf) = (0u64, 0u64, 0usize);
        for (b, fb) in map_blocks.iter().zip(blocks) {
            let fb: FieldBlock = bytemuck::pod_read_unaligned(fb);
            if u64::from(fb.first) != next
                || fb.reserved != 0
                || fb.ranks != BlockEntry::ranks_of(&fb.band)
            {
                return Err(SnapshotError::BadIndex("field block out of sequence"));
            }
            for (w, &bits) in fb.band.iter().enumerate() {
                let stored = block_word(b, w);
                if bits & !stored != 0 {
                    return Err(SnapshotError::BadIndex(
                        "field block names a leaf not stored",
                    ));
                }
                for bit in BitIter(stored) {
                    let e: FieldEntry = entries
                        .get(leaf)
                        .map(|e| bytemuck::pod_read_unaligned(e))
                        .ok_or(SnapshotError::BadIndex("field entries"))?;
                    leaf += 1;
                    if bits >> bit & 1 == 0 {
                        if e != FieldEntry::NONE {
                            return Err(SnapshotError::BadIndex(
                                "field data of a leaf without a band",
                            ));
                        }
                        continue;
                    }
                    next += 1;
                    let start = e.data_at();
                    let need = if e == FieldEntry::NONE {
                        return Err(SnapshotError::BadIndex("field band leaf without data"));
                    } else if e.masked() {
                        let count = mask_at(data, start)
                            .ok_or(SnapshotError::BadIndex(
                                "field leaf data outside the section",
                            ))?
                            .iter()
                            .map(|w| u64::from(w.count_ones()))
                            .sum::<u64>();
                        band += count;
                        64 + 3 * count
                    } else {
                        band += LEAF_VOXELS as u64;
                        3 * LEAF_VOXELS as u64
                    };
                    if start + need > h.data_len {
                        return Err(SnapshotError::BadIndex(
                            "field leaf data outside the section",
                        ));
                    }
                }
            }
        }
        if next != h.dist_blocks {
            return Err(bad("field dist_blocks"));
        }
        if band != h.band_count {
            return Err(bad("field band_count"));
        }
        Ok(Self {
            header: h,
            blocks,
            entries,
            dists,
            data,
        })
    }
}

/// The 64-byte mask at `at` in the data.
#[inline]
fn mask_at(data: &[u8], at: u64) -> Option<[u64; 8]> {
    let at = usize::try_from(at).ok()?;
    let b = data.get(at..at.checked_add(64)?)?;
    Some(std::array::from_fn(|w| {
        u64::from_le_bytes(b[8 * w..8 * w + 8].try_into().unwrap_or([0; 8]))
    }))
}

/// Where a point's nearest obstacle is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Nearest {
    /// The field does not cover the point (outside its window, or unknown space it does
    /// not hold).
    Unknown,
    /// No obstacle lies within the field's max distance.
    NoneWithin,
    /// The nearest obstacle voxel and the distance between its centre and the centre of
    /// the point's voxel (metres).
    At {
        voxel: VoxelCoord,
        centre: WorldPoint,
        distance: f64,
    },
}

/// One leaf's offsets, read from its entry (the exact queries' view of a leaf).
#[derive(Clone, Copy, Debug)]
enum Band<'a> {
    /// No voxel within the max distance.
    None,
    /// Every voxel: 512 offsets.
    All(&'a [u8]),
    /// The voxels of `mask`, their offsets in voxel order; `ranks[w]`: set bits before
    /// word `w`.
    Masked {
        mask: [u64; 8],
        ranks: [u32; 8],
        offsets: &'a [u8],
    },
}

/// A leaf's quantised distances as the interpolating queries see it.
#[derive(Clone, Copy, Debug)]
enum Dists<'a> {
    /// No leaf there: unknown space.
    Absent,
    /// No voxel of the leaf within the max distance.
    Far,
    /// One byte per voxel, Morton order.
    Near(&'a [u8; FIELD_DISTS]),
}

/// In-leaf offset steps from a voxel to the corners of the cube it spans (x fastest),
/// for a voxel not on the leaf's upper faces.
const CORNER_STEP: [usize; 8] = [0, 1, 8, 9, 64, 65, 72, 73];

/// One voxel of the field.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Cell {
    Unknown,
    Far,
    Near([i8; 3]),
}

/// The distance field of a snapshot, queried in place (from
/// [`SnapshotView::distance_field`]). Distances are in metres between voxel centres,
/// exact for the voxels (see [`crate::field`]); `distance_at` interpolates them. (A field
/// written into a snapshot and read back: the example of `voxmap_map::snapshot`.)
#[derive(Clone, Copy, Debug)]
pub struct FieldView<'a> {
    view: SnapshotView<'a>,
    parts: FieldParts<'a>,
    lo: VoxelCoord,
    hi: VoxelCoord,
    policy: UnknownPolicy,
    res: f64,
    max: f64,
    /// Metres per step of the quantised distances.
    unit: f64,
}

impl<'a> FieldView<'a> {
    pub(super) fn new(view: SnapshotView<'a>, parts: FieldParts<'a>) -> Self {
        let h = parts.header;
        Self {
            view,
            parts,
            lo: VoxelCoord::from_array(h.window_lo),
            hi: VoxelCoord::from_array(h.window_hi),
            policy: UnknownPolicy::from_code(h.unknown).unwrap_or_default(),
            res: view.resolution(),
            max: h.max_distance,
            unit: view.resolution() / f64::from(h.steps.max(1)),
        }
    }

    /// Distances at or above this are not kept: a query there answers this value.
    pub fn max_distance(&self) -> f64 {
        self.max
    }

    /// The band's radius in voxels.
    pub fn radius(&self) -> u32 {
        self.parts.header.radius
    }

    /// The step of the distances [`Self::distance_at`] and its kin interpolate (metres):
    /// each voxel's distance is kept to the nearest step, within half a step of its exact
    /// [`Self::distance`].
    pub fn step(&self) -> f64 {
        self.unit
    }

    /// What unknown voxels count as.
    pub fn unknown(&self) -> UnknownPolicy {
        self.policy
    }

    /// The voxels the field covers, inclusive.
    pub fn window(&self) -> (VoxelCoord, VoxelCoord) {
        (self.lo, self.hi)
    }

    /// Voxels stored (within the max distance of an obstacle).
    pub fn band_voxels(&self) -> u64 {
        self.parts.header.band_count
    }

    #[inline]
    fn covers(&self, v: VoxelCoord) -> bool {
        let (lo, hi) = (self.lo, self.hi);
        (lo.x <= v.x)
            & (v.x <= hi.x)
            & (lo.y <= v.y)
            & (v.y <= hi.y)
            & (lo.z <= v.z)
            & (v.z <= hi.z)
    }

    /// The offsets of leaf `index` (a leaf the snapshot holds), read once for its voxels.
    #[inline]
    fn band_of(&self, index: u64) -> Band<'a> {
        let e = self
            .parts
            .entries
            .get(index as usize)
            .map_or(FieldEntry::NONE, |e| bytemuck::pod_read_unaligned(e));
        if e == FieldEntry::NONE {
            return Band::None;
        }
        let (data, at) = (self.parts.data, e.data_at() as usize);
        if !e.masked() {
            return data
                .get(at..at + 3 * LEAF_VOXELS)
                .map_or(Band::None, Band::All);
        }
        let Some(mask) = mask_at(data, at as u64) else {
            return Band::None;
        };
        let mut ranks = [0u32; 8];
        let mut below = 0;
        for (r, w) in ranks.iter_mut().zip(mask) {
            *r = below;
            below += w.count_ones();
        }
        let at = at + 64;
        data.get(at..at + 3 * below as usize)
            .map_or(Band::None, |offsets| Band::Masked {
                mask,
                ranks,
                offsets,
            })
    }

    /// The quantised distances of the leaf holding `v` (inside the window), found from
    /// its block: the snapshot's block and the field's are read side by side, and the
    /// leaf's entry not at all.
    #[inline]
    fn dists_at(&self, v: VoxelCoord) -> Dists<'a> {
        let Some((i, block)) = self.view.find_block_at(block_origin(v).to_array()) else {
            return Dists::Absent;
        };
        let Some(fb) = self.parts.blocks.get(i) else {
            return Dists::Absent;
        };
        let j = leaf_in_block(v);
        let (w, bit) = ((j / 64) & 7, j % 64);
        if block_word(block, w) >> bit & 1 == 0 {
            return Dists::Absent;
        }
        let word = |at: usize| u64::from_le_bytes(fb[at..at + 8].try_into().unwrap_or([0; 8]));
        let band = word(FIELD_BLOCK_BAND_AT + 8 * w);
        if band >> bit & 1 == 0 {
            return Dists::Far;
        }
        let first = u32::from_le_bytes(fb[0..4].try_into().unwrap_or([0; 4])) as usize;
        let at = FIELD_BLOCK_RANKS_AT + 2 * w;
        let rank = usize::from(u16::from_le_bytes([fb[at], fb[at + 1]]))
            + (band & ((1 << bit) - 1)).count_ones() as usize;
        let at = (first + rank) * FIELD_DISTS;
        self.parts
            .dists
            .get(at..at + FIELD_DISTS)
            .and_then(|d| d.try_into().ok())
            .map_or(Dists::Far, Dists::Near)
    }

    /// Metres of in-leaf voxel `i` of a leaf's distances; `None` where unknown.
    #[inline]
    fn metres_in(&self, d: Dists<'_>, i: usize) -> Option<f64> {
        match d {
            Dists::Absent => self.metres(self.absent()),
            Dists::Far => Some(self.max),
            Dists::Near(q) => Some(self.metres_q(q[usize::from(MORTON[i & (LEAF_VOXELS - 1)])])),
        }
    }

    /// Metres of a quantised distance, capped at the max distance (which
    /// [`FIELD_DIST_FAR`] exceeds).
    #[inline]
    fn metres_q(&self, q: u8) -> f64 {
        (f64::from(q) * self.unit).min(self.max)
    }

    /// Voxel `i` (in-leaf offset) of a leaf's band, stored at its Morton place.
    #[inline]
    fn cell_in(band: &Band<'_>, i: usize) -> Cell {
        let m = usize::from(MORTON[i & (LEAF_VOXELS - 1)]);
        let at = match band {
            Band::None => return Cell::Far,
            Band::All(_) => 3 * m,
            Band::Masked { mask, ranks, .. } => {
                let (w, b) = ((m / 64) & 7, m % 64);
                if mask[w] >> b & 1 == 0 {
                    return Cell::Far;
                }
                3 * (ranks[w] + (mask[w] & ((1u64 << b) - 1)).count_ones()) as usize
            }
        };
        let offsets = match band {
            Band::All(o) | Band::Masked { offsets: o, .. } => o,
            Band::None => return Cell::Far,
        };
        match offsets.get(at..at + 3) {
            Some(o) => Cell::Near([o[0] as i8, o[1] as i8, o[2] as i8]),
            None => Cell::Far,
        }
    }

    /// A voxel no leaf of the snapshot holds: unknown space.
    #[inline]
    fn absent(&self) -> Cell {
        match self.policy {
            UnknownPolicy::Occupied => Cell::Near([0; 3]),
            UnknownPolicy::Free => Cell::Unknown,
        }
    }

    #[inline]
    fn cell(&self, v: VoxelCoord) -> Cell {
        if !self.covers(v) {
            return Cell::Unknown;
        }
        match self.view.find_leaf(v) {
            Some(l) => Self::cell_in(&self.band_of(l.index), leaf_offset(v)),
            None => self.absent(),
        }
    }

    #[inline]
    fn metres(&self, c: Cell) -> Option<f64> {
        match c {
            Cell::Unknown => None,
            Cell::Far => Some(self.max),
            Cell::Near(o) => Some(self.metres_of(offset_len2(o))),
        }
    }

    /// Metres of an offset of squared length `len2` (voxels²), capped at the max distance.
    #[inline]
    fn metres_of(&self, len2: i32) -> f64 {
        (f64::from(len2).sqrt() * self.res).min(self.max)
    }

    /// The distance from voxel `v`'s centre to the nearest obstacle's (metres), capped at
    /// [`Self::max_distance`]; `None` where the field does not reach.
    pub fn distance(&self, v: VoxelCoord) -> Option<f64> {
        self.metres(self.cell(v))
    }

    /// The eight voxels whose centres surround `p`, as quantised distances, and `p`'s
    /// place between them (0..1 per axis).
    #[inline]
    fn corners(&self, p: &WorldPoint) -> Option<([f64; 8], [f64; 3])> {
        let u = self.view.transform().point_to_units(p).map(|c| c - 0.5);
        if !u.iter().all(|c| c.is_finite() && c.abs() < MAX_VOXEL_INDEX) {
            return None;
        }
        let f = u.map(f64::floor);
        let t = [u[0] - f[0], u[1] - f[1], u[2] - f[2]];
        let b = VoxelCoord::new(f[0] as i32, f[1] as i32, f[2] as i32);
        if !(self.covers(b) & self.covers(b + VoxelCoord::new(1, 1, 1))) {
            return None;
        }
        let mut d = [0.0; 8];
        if (b.x & 7 != 7) & (b.y & 7 != 7) & (b.z & 7 != 7) {
            // All eight in one leaf (most points): one lookup, one entry, and eight bytes
            // of its distances, on one line when `b` is not on a 4x4x4 cube's upper face.
            match self.dists_at(b) {
                Dists::Absent => return self.metres(self.absent()).map(|x| ([x; 8], t)),
                Dists::Far => d = [self.max; 8],
                Dists::Near(q) => {
                    let i0 = leaf_offset(b);
                    for (k, out) in d.iter_mut().enumerate() {
                        let m = usize::from(MORTON[i0 + CORNER_STEP[k]]) & (LEAF_VOXELS - 1);
                        *out = self.metres_q(q[m]);
                    }
                }
            }
        } else {
            // `b` on a leaf's upper face: the eight span 2, 4 or 8 leaves, each looked up
            // and read once, found by which axes the corner steps into the next leaf.
            let next = [b.x & 7 == 7, b.y & 7 == 7, b.z & 7 == 7].map(usize::from);
            let mut leaves: [Option<Dists<'a>>; 8] = [None; 8];
            for (k, out) in d.iter_mut().enumerate() {
                let v = b + VoxelCoord::new((k & 1) as i32, (k >> 1 & 1) as i32, (k >> 2) as i32);
                let leaf = (k & next[0]) | (k & next[1] << 1) | (k & next[2] << 2);
                let dists = *leaves[leaf].get_or_insert_with(|| self.dists_at(v));
                *out = self.metres_in(dists, leaf_offset(v))?;
            }
        }
        Some((d, t))
    }

    /// The distance at `p` (metres), trilinear between the eight voxel centres around it,
    /// capped at [`Self::max_distance`]; `None` where the field does not reach any of
    /// them (outside its window, or unknown space under the `free` policy).
    pub fn distance_at(&self, p: &WorldPoint) -> Option<f64> {
        let (d, [tx, ty, tz]) = self.corners(p)?;
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let x00 = lerp(d[0], d[1], tx);
        let x10 = lerp(d[2], d[3], tx);
        let x01 = lerp(d[4], d[5], tx);
        let x11 = lerp(d[6], d[7], tx);
        Some(lerp(lerp(x00, x10, ty), lerp(x01, x11, ty), tz))
    }

    /// [`Self::distance_at`] and its gradient (the derivative of the interpolation, per
    /// metre): it points away from the nearest obstacles, and is zero where every
    /// surrounding voxel is at the max distance.
    pub fn distance_and_gradient_at(&self, p: &WorldPoint) -> Option<(f64, Vector3<f64>)> {
        let (d, [tx, ty, tz]) = self.corners(p)?;
        let (sy, sz) = (1.0 - ty, 1.0 - tz);
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let x00 = lerp(d[0], d[1], tx);
        let x10 = lerp(d[2], d[3], tx);
        let x01 = lerp(d[4], d[5], tx);
        let x11 = lerp(d[6], d[7], tx);
        let value = lerp(lerp(x00, x10, ty), lerp(x01, x11, ty), tz);
        let gx = ((d[1] - d[0]) * sy * sz
            + (d[3] - d[2]) * ty * sz
            + (d[5] - d[4]) * sy * tz
            + (d[7] - d[6]) * ty * tz)
            / self.res;
        let gy = ((x10 - x00) * sz + (x11 - x01) * tz) / self.res;
        let gz = (lerp(x01, x11, ty) - lerp(x00, x10, ty)) / self.res;
        Some((value, Vector3::new(gx, gy, gz)))
    }

    /// The obstacle voxel nearest to the voxel holding `p`.
    pub fn nearest_obstacle(&self, p: &WorldPoint) -> Nearest {
        let Some(v) = self.view.transform().voxel_of(p) else {
            return Nearest::Unknown;
        };
        match self.cell(v) {
            Cell::Unknown => Nearest::Unknown,
            Cell::Far => Nearest::NoneWithin,
            Cell::Near(o) => {
                let voxel = v + VoxelCoord::new(o[0].into(), o[1].into(), o[2].into());
                Nearest::At {
                    voxel,
                    centre: self.view.transform().voxel_center(voxel),
                    distance: f64::from(offset_len2(o)).sqrt() * self.res,
                }
            }
        }
    }

    /// [`Self::distance_at`] at many points, appended to `out` in order; NaN where the
    /// field does not reach.
    pub fn distances_at(&self, points: &[WorldPoint], out: &mut Vec<f64>) {
        out.extend(
            points
                .iter()
                .map(|p| self.distance_at(p).unwrap_or(f64::NAN)),
        );
    }

    /// [`Self::distance_and_gradient_at`] at many points, appended to `out` as
    /// `[distance, gx, gy, gz]`; all NaN where the field does not reach.
    pub fn distances_and_gradients_at(&self, points: &[WorldPoint], out: &mut Vec<[f64; 4]>) {
        out.extend(
            points
                .iter()
                .map(|p| match self.distance_and_gradient_at(p) {
                    Some((d, g)) => [d, g.x, g.y, g.z],
                    None => [f64::NAN; 4],
                }),
        );
    }

    /// [`Self::nearest_obstacle`] at many points, appended to `out` in order.
    pub fn nearest_obstacles(&self, points: &[WorldPoint], out: &mut Vec<Nearest>) {
        out.extend(points.iter().map(|p| self.nearest_obstacle(p)));
    }
}
