//! Encoding a map into a snapshot buffer.

use super::layout::*;
use crate::coord::{VoxelCoord, WorldPoint};
use crate::grid::{Leaf, LEAF_VOXELS};
use crate::map::OccupancyMap;
use crate::mask::Mask512;

/// Which part of the map a snapshot holds.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Scope {
    Whole,
    /// Voxels whose centres lie in the axis-aligned box [min, max] (world metres).
    Box {
        min: [f64; 3],
        max: [f64; 3],
    },
}

/// Metadata stamped into the header.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Meta {
    pub sequence: u64,
    pub timestamp_ns: u64,
    /// Store per-voxel log-odds (512 bytes per leaf) besides the masks.
    pub with_values: bool,
}

struct PlannedLeaf<'a> {
    origin: VoxelCoord,
    leaf: &'a Leaf<i8>,
    /// Voxels of the leaf inside the scope.
    keep: Mask512,
}

/// Voxels of `keep` whose value is at or above the threshold, a word at a time.
fn occupied_mask(leaf: &Leaf<i8>, keep: &Mask512, threshold: i8) -> Mask512 {
    let mut occ = Mask512::EMPTY;
    for (w, out) in occ.words.iter_mut().enumerate() {
        if keep.words[w] == 0 {
            continue;
        }
        let vals = &leaf.values[w * 64..w * 64 + 64];
        let mut bits = 0u64;
        for (b, &v) in vals.iter().enumerate() {
            bits |= u64::from(v >= threshold) << b;
        }
        *out = bits & keep.words[w];
    }
    occ
}

/// Grow inclusive bounds by the voxels of `keep` in the leaf at `origin`, using the mask's
/// extent per axis rather than visiting voxels.
fn extend_bounds(lo: &mut [i32; 3], hi: &mut [i32; 3], origin: VoxelCoord, keep: &Mask512) {
    // Bit x|y<<3 of a word; word index z.
    let (mut xs, mut ys, mut zs) = (0u8, 0u8, 0u8);
    for (z, &w) in keep.words.iter().enumerate() {
        if w != 0 {
            zs |= 1 << z;
            for y in 0..8 {
                let row = (w >> (8 * y)) as u8;
                if row != 0 {
                    ys |= 1 << y;
                    xs |= row;
                }
            }
        }
    }
    if zs == 0 {
        return;
    }
    let o = origin.to_array();
    for (a, m) in [xs, ys, zs].into_iter().enumerate() {
        lo[a] = lo[a].min(o[a] + m.trailing_zeros() as i32);
        hi[a] = hi[a].max(o[a] + 7 - m.leading_zeros() as i32);
    }
}

/// A snapshot laid out but not yet written: size it with [`Plan::encoded_len`], then
/// [`Plan::write`] it into a buffer of at least that many bytes.
pub struct Plan<'a> {
    map: &'a OccupancyMap,
    leaves: Vec<PlannedLeaf<'a>>,
    meta: Meta,
    table_capacity: u64,
}

impl<'a> Plan<'a> {
    pub fn new(map: &'a OccupancyMap, scope: Scope, meta: Meta) -> Self {
        let mut leaves: Vec<PlannedLeaf<'a>> = match scope {
            Scope::Whole => map
                .grid()
                .leaves()
                .filter(|(_, l)| !l.active.is_empty())
                .map(|(origin, leaf)| PlannedLeaf {
                    origin,
                    leaf,
                    keep: leaf.active,
                })
                .collect(),
            Scope::Box { min, max } => {
                let tf = map.transform();
                // Voxels whose centre is inside [min, max].
                let lo = tf.voxel_of(&WorldPoint::from(min.map(|c| c - tf.resolution() * 0.5)));
                let hi = tf.voxel_of(&WorldPoint::from(max.map(|c| c - tf.resolution() * 0.5)));
                match (lo, hi) {
                    (Some(lo), Some(hi)) => {
                        let lo = lo + VoxelCoord::new(1, 1, 1);
                        map.grid()
                            .leaves()
                            .filter_map(|(origin, leaf)| {
                                let mut keep = Mask512::EMPTY;
                                for i in leaf.active.iter_ones() {
                                    let v = crate::grid::voxel_at(origin, i);
                                    if lo.x <= v.x
                                        && v.x <= hi.x
                                        && lo.y <= v.y
                                        && v.y <= hi.y
                                        && lo.z <= v.z
                                        && v.z <= hi.z
                                    {
                                        keep.set(i);
                                    }
                                }
                                (!keep.is_empty()).then_some(PlannedLeaf { origin, leaf, keep })
                            })
                            .collect()
                    }
                    _ => Vec::new(),
                }
            }
        };
        leaves.sort_unstable_by_key(|p| (p.origin.z, p.origin.y, p.origin.x));
        let n = leaves.len() as u64;
        let table_capacity = if n == 0 {
            1
        } else {
            (2 * n).next_power_of_two()
        };
        Self {
            map,
            leaves,
            meta,
            table_capacity,
        }
    }

    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
    }

    fn sections(&self) -> (u64, u64, u64, u64, u64) {
        let n = self.leaves.len() as u64;
        let table = HEADER_SIZE as u64;
        let origins = align8(table + 4 * self.table_capacity);
        let masks = align8(origins + ORIGIN_SIZE as u64 * n);
        let values_end = masks + MASKS_PER_LEAF as u64 * n;
        let (values, total) = if self.meta.with_values {
            (values_end, values_end + VALUES_PER_LEAF as u64 * n)
        } else {
            (0, values_end)
        };
        (table, origins, masks, values, total)
    }

    /// Bytes [`Plan::write`] needs.
    pub fn encoded_len(&self) -> usize {
        self.sections().4 as usize
    }

    /// Write the snapshot into `buf[..encoded_len()]`; returns the length written.
    pub fn write(&self, buf: &mut [u8]) -> Result<usize, SnapshotError> {
        let (table, origins, masks, values, total) = self.sections();
        let total_us = total as usize;
        if buf.len() < total_us {
            return Err(SnapshotError::BufferTooSmall {
                needed: total_us,
                got: buf.len(),
            });
        }
        let buf = &mut buf[..total_us];
        buf[HEADER_SIZE..].fill(0);
        let q = self.map.quantized();
        let mut known = 0u64;
        let mut occupied = 0u64;
        let mut lo = [i32::MAX; 3];
        let mut hi = [i32::MIN; 3];
        let mask = self.table_capacity - 1;
        for (i, p) in self.leaves.iter().enumerate() {
            let o = p.origin.to_array();
            // Table slot.
            let mut s = table_hash(o, mask);
            loop {
                let at = (table + 4 * s) as usize;
                if buf[at..at + 4] == [0; 4] {
                    buf[at..at + 4].copy_from_slice(&(i as u32 + 1).to_le_bytes());
                    break;
                }
                s = (s + 1) & mask;
            }
            let at = origins as usize + ORIGIN_SIZE * i;
            for (k, c) in o.iter().enumerate() {
                buf[at + 4 * k..at + 4 * k + 4].copy_from_slice(&c.to_le_bytes());
            }
            let occ = occupied_mask(p.leaf, &p.keep, q.threshold);
            extend_bounds(&mut lo, &mut hi, p.origin, &p.keep);
            known += u64::from(p.keep.count());
            occupied += u64::from(occ.count());
            let at = masks as usize + MASKS_PER_LEAF * i;
            for (w, word) in p.keep.words.iter().chain(&occ.words).enumerate() {
                buf[at + 8 * w..at + 8 * w + 8].copy_from_slice(&word.to_le_bytes());
            }
            if self.meta.with_values {
                let at = values as usize + VALUES_PER_LEAF * i;
                for v in 0..LEAF_VOXELS {
                    buf[at + v] = if p.keep.get(v) {
                        p.leaf.values[v] as u8
                    } else {
                        0
                    };
                }
            }
        }
        let h = Header {
            magic: MAGIC,
            version: FORMAT_VERSION,
            flags: if self.meta.with_values {
                FLAG_VALUES
            } else {
                0
            },
            header_size: HEADER_SIZE as u32,
            frac_bits: q.frac_bits,
            threshold: q.threshold,
            clamp_min: q.min,
            clamp_max: q.max,
            resolution: self.map.resolution(),
            sequence: self.meta.sequence,
            timestamp_ns: self.meta.timestamp_ns,
            leaf_count: self.leaves.len() as u64,
            known_count: known,
            occupied_count: occupied,
            bounds_min: lo,
            bounds_max: hi,
            table_capacity: self.table_capacity,
            table_offset: table,
            origins_offset: origins,
            masks_offset: masks,
            values_offset: values,
            total_len: total,
            checksum: crc32fast::hash(&buf[HEADER_SIZE..]),
            reserved: 0,
        };
        buf[..HEADER_SIZE].copy_from_slice(bytemuck::bytes_of(&h));
        Ok(total_us)
    }

    /// Encode into a new vector.
    pub fn to_vec(&self) -> Vec<u8> {
        let mut v = vec![0; self.encoded_len()];
        self.write(&mut v).expect("sized by encoded_len");
        v
    }
}
