//! Encoding leaves into a snapshot buffer: [`Encoder`] plans the snapshot of a list of
//! leaves in block order (their records, blocks and table, and a distance field's bands),
//! sizes it, and writes it into a caller's buffer.
//!
//! A 60 m map is a gigabyte of leaves, so encoding is bound by reading them: the per-leaf
//! passes are cut into pieces that a [`Pieces`] runs, in order here ([`InOrder`], what a
//! map file opened by a planner needs) or in parallel (the map crate's writer, on its
//! thread pool). Both give the same bytes.

use super::layout::*;
use super::record;
use crate::coord::VoxelCoord;
use crate::field::{offset_len2, FieldConfig};
use crate::mask::Mask512;
use crate::model::QuantizedModel;
use crate::tree::{block_origin, leaf_in_block, Leaf, LEAF_VOXELS, MORTON, UNMORTON};

/// Runs the encoder's pieces of work: `f` on each job, in any order and on any thread,
/// the results in the jobs' order. Every way gives the same bytes.
pub trait Pieces: Sync {
    fn map<J: Send, R: Send>(&self, jobs: Vec<J>, f: impl Fn(J) -> R + Sync + Send) -> Vec<R>;

    /// Leaves per piece of work, and bytes per piece of the checksum (tests make them small,
    /// so that their maps span many pieces).
    fn sizes(&self) -> (usize, usize) {
        (4096, 4 << 20)
    }

    /// The record encoder of a piece of leaves: [`encode_piece`], or a form of it compiled
    /// for the CPU's vector instructions.
    fn encode_piece(&self) -> EncodePiece {
        encode_piece
    }
}

/// The records of a piece of leaves: their bytes, sums and how many had nothing known.
pub type EncodePiece = fn(&mut [PlannedLeaf<'_>], &[Mask512]) -> (Vec<u8>, Sums, usize);

/// Pieces one after another on the calling thread.
#[derive(Clone, Copy, Debug, Default)]
pub struct InOrder;

impl Pieces for InOrder {
    fn map<J: Send, R: Send>(&self, jobs: Vec<J>, f: impl Fn(J) -> R + Sync + Send) -> Vec<R> {
        jobs.into_iter().map(f).collect()
    }
}

/// A distance field's bands, as the encoder reads them: its settings and, per map leaf,
/// which voxels are in the band and their offsets to the nearest obstacle (in the mask's
/// order).
pub trait FieldBands: Sync {
    fn config(&self) -> FieldConfig;
    /// The band's radius, voxels.
    fn radius(&self) -> u32;
    /// The distance kept, metres.
    fn max_distance(&self) -> f64;
    /// The voxels the field covers (inclusive), `None` for all.
    fn window(&self) -> Option<(VoxelCoord, VoxelCoord)>;
    /// The band of the leaf at `origin`, if any voxel of it is in the band.
    fn band(&self, origin: VoxelCoord) -> Option<(&Mask512, &[[i8; 3]])>;
}

/// What the encoder needs of the map besides its leaves.
#[derive(Clone, Copy, Debug)]
pub struct MapInfo {
    pub resolution: f64,
    pub quantized: QuantizedModel,
}

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

/// A leaf to encode: its origin, the leaf, and which of its voxels the snapshot keeps.
pub struct PlannedLeaf<'a> {
    origin: VoxelCoord,
    leaf: &'a Leaf<i8>,
    /// The kinds of its known and occupied masks.
    kinds: (u8, u8),
    /// The record's offset in the masks section ([`LeafEntry::record`]).
    record: u32,
    /// Index into `Plan::keeps` of the voxels inside a box scope; `WHOLE`: all active.
    keep: u32,
}

const WHOLE: u32 = u32::MAX;

impl<'a> PlannedLeaf<'a> {
    /// The leaf at `origin`, keeping its active voxels (`keep` `None`) or those of mask
    /// `keep` of the encoder's `keeps`.
    pub fn new(origin: VoxelCoord, leaf: &'a Leaf<i8>, keep: Option<u32>) -> Self {
        PlannedLeaf {
            origin,
            leaf,
            kinds: (0, 0),
            record: 0,
            keep: keep.unwrap_or(WHOLE),
        }
    }
}
/// Leaves ahead of the one being encoded whose loads are started. Block order mostly
/// follows the leaf pool (87% of the random 500k 60 m map's leaves come right after their
/// predecessor in the pool), yet the CPU's own prefetching left each leaf read to miss
/// cache on its own. Measured when the pass read whole leaves (values too; now it reads
/// the two masks): whole-map encode, random 500k 60 m, minimum of 12 in alternated probe
/// runs, 262-288 ms without, 199-225 with 4 ahead, 179-256 with 8.
const PREFETCH_AHEAD: usize = 8;
/// [`PlannedLeaf::kinds`] of a leaf with nothing known, dropped from the plan.
const EMPTY: u8 = u8::MAX;

/// Grow inclusive bounds by the voxels of `keep` in the leaf at `origin`, using the mask's
/// extent per axis rather than visiting voxels.
#[inline(always)]
fn extend_bounds(lo: &mut [i32; 3], hi: &mut [i32; 3], origin: VoxelCoord, keep: &Mask512) {
    let Some((a, b)) = keep.extent() else {
        return;
    };
    let o = origin.to_array();
    for k in 0..3 {
        lo[k] = lo[k].min(o[k] + a[k]);
        hi[k] = hi[k].max(o[k] + b[k]);
    }
}

fn keep_of<'k>(keeps: &'k [Mask512], p: &'k PlannedLeaf<'_>) -> &'k Mask512 {
    if p.keep == WHOLE {
        &p.leaf.active
    } else {
        &keeps[p.keep as usize]
    }
}

/// Encode the records of one piece of leaves: their bytes, sums and how many had nothing
/// known. Portable.
pub fn encode_piece(piece: &mut [PlannedLeaf<'_>], keeps: &[Mask512]) -> (Vec<u8>, Sums, usize) {
    encode_piece_with(piece, keeps, None)
}

/// [`encode_piece`], its records compressed with VBMI2 stores given `avx512`. Inlined into
/// each entry point, so that one body serves all.
#[inline(always)]
fn encode_piece_with(
    piece: &mut [PlannedLeaf<'_>],
    keeps: &[Mask512],
    avx512: Option<record::Avx512Encode>,
) -> (Vec<u8>, Sums, usize) {
    // The most a record takes (two dense masks), so the piece never grows by
    // copying; pages not written to are never touched.
    let mut bytes = Vec::with_capacity(piece.len() * 2 * 64);
    let (mut sums, mut empty) = (Sums::default(), 0);
    for k in 0..piece.len() {
        if let Some(ahead) = piece.get(k + PREFETCH_AHEAD) {
            ahead.leaf.prefetch_masks();
        }
        let p = &mut piece[k];
        let keep = *keep_of(keeps, p);
        if keep.is_empty() {
            p.kinds = (EMPTY, 0);
            empty += 1;
            continue;
        }
        let occupied = p.leaf.marked.and(&keep);
        let known_choice = record::choose_known(&keep);
        let occupied_choice = record::choose_occupied(&occupied);
        p.kinds = (known_choice.kind, occupied_choice.kind);
        p.record = bytes.len() as u32;
        let at = bytes.len();
        bytes.resize(at + (known_choice.len + occupied_choice.len) as usize, 0);
        record::encode(
            &keep,
            p.kinds.0,
            &occupied,
            p.kinds.1,
            &mut bytes[at..],
            avx512,
        );
        extend_bounds(&mut sums.lo, &mut sums.hi, p.origin, &keep);
        sums.known += u64::from(keep.count());
        sums.occupied += u64::from(occupied.count());
    }
    (bytes, sums, empty)
}

/// [`encode_piece`] compiled for AVX-512: the mask work, popcounts and VBMI2 stores.
///
/// # Safety
/// The CPU must have every feature enabled here (the map crate's `Kernel::Avx512` checks
/// them).
#[cfg(target_arch = "x86_64")]
#[target_feature(
    enable = "avx512f,avx512bw,avx512vl,avx512vbmi2,avx512vpopcntdq,bmi1,bmi2,lzcnt,popcnt"
)]
pub unsafe fn encode_piece_avx512(
    piece: &mut [PlannedLeaf<'_>],
    keeps: &[Mask512],
) -> (Vec<u8>, Sums, usize) {
    // SAFETY: this function runs only where the CPU has AVX-512F and VBMI2 (enabled here).
    let token = unsafe { record::Avx512Encode::new() };
    encode_piece_with(piece, keeps, Some(token))
}

/// [`encode_piece`] compiled for AVX2 with BMI1/2, LZCNT and POPCNT (x86-64-v3): the mask
/// work's shifts, counts and bit scans.
///
/// # Safety
/// The CPU must have every feature enabled here (the map crate's `Kernel::Avx2` checks
/// them).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
pub unsafe fn encode_piece_avx2(
    piece: &mut [PlannedLeaf<'_>],
    keeps: &[Mask512],
) -> (Vec<u8>, Sums, usize) {
    encode_piece_with(piece, keeps, None)
}

/// The first `len` bytes of `bytes`, leaving it the rest.
fn take<'b>(bytes: &mut &'b mut [u8], len: usize) -> &'b mut [u8] {
    let (head, tail) = std::mem::take(bytes).split_at_mut(len);
    *bytes = tail;
    head
}

/// Counts and bounds gathered while writing leaves.
pub struct Sums {
    known: u64,
    occupied: u64,
    lo: [i32; 3],
    hi: [i32; 3],
}

impl Default for Sums {
    fn default() -> Self {
        Self {
            known: 0,
            occupied: 0,
            lo: [i32::MAX; 3],
            hi: [i32::MIN; 3],
        }
    }
}

impl Sums {
    fn add(a: Sums, b: Sums) -> Sums {
        Sums {
            known: a.known + b.known,
            occupied: a.occupied + b.occupied,
            lo: [0, 1, 2].map(|k| a.lo[k].min(b.lo[k])),
            hi: [0, 1, 2].map(|k| a.hi[k].max(b.hi[k])),
        }
    }
}

/// A snapshot laid out but not yet written: size it with [`Encoder::encoded_len`], then
/// [`Encoder::write`] it into a buffer of at least that many bytes.
pub struct Encoder<'a, P: Pieces> {
    info: MapInfo,
    pieces: P,
    leaves: Vec<PlannedLeaf<'a>>,
    keeps: Vec<Mask512>,
    meta: Meta,
    /// The leaves' blocks, in leaf order.
    blocks: Vec<BlockEntry>,
    table_capacity: u64,
    /// The dense index's lowest block and size, when the table is one.
    dense: Option<([i32; 3], [u32; 3])>,
    /// The masks section, already encoded, in pieces (in leaf order).
    records: Vec<Vec<u8>>,
    masks_len: u64,
    sums: Sums,
    /// The voxels a box scope keeps (inclusive), `None` for the whole map.
    scope_box: Option<(VoxelCoord, VoxelCoord)>,
    field: Option<FieldPlan<'a>>,
}

/// The distance field section, planned: header, blocks and entries; the distance blocks
/// and offsets are written from the field by [`Encoder::write`], piece by piece.
struct FieldPlan<'a> {
    field: &'a dyn FieldBands,
    header: FieldHeader,
    blocks: Vec<FieldBlock>,
    entries: Vec<FieldEntry>,
    /// Per piece of leaves: bytes of its distance blocks and of its offsets.
    pieces: Vec<(usize, usize)>,
    /// Quantised distances by squared offset length, for every length the band holds.
    quantised: Vec<u8>,
}

/// The field section of one piece of leaves, sized: entries with places counted from the
/// piece's start.
struct FieldPiece {
    entries: Vec<FieldEntry>,
    dists: usize,
    data: usize,
    band: u64,
}

/// Bytes of a band leaf's offsets with `count` voxels in the band.
fn offsets_len(count: u32) -> usize {
    if count == 512 {
        3 * LEAF_VOXELS
    } else {
        align8(64 + 3 * u64::from(count)) as usize
    }
}

/// Write the distance blocks and offsets of `leaves` (one piece) into `dists` and `data`,
/// sized for them by [`Plan::with_field`].
fn write_field_piece(
    leaves: &[PlannedLeaf<'_>],
    f: &FieldPlan<'_>,
    mut dists: &mut [u8],
    mut data: &mut [u8],
) {
    let steps = f.header.steps;
    let q = |o: [i8; 3]| {
        let len2 = offset_len2(o);
        f.quantised
            .get(len2 as usize)
            .map_or_else(|| quantise(len2, steps), |q| *q)
    };
    for p in leaves {
        let Some((mask, offsets)) = f.field.band(p.origin) else {
            continue;
        };
        let count = mask.count();
        let d = take(&mut dists, FIELD_DISTS);
        let o = take(&mut data, offsets_len(count));
        // Voxels in Morton order (`tree::MORTON`), the mask's bits too.
        if count == 512 {
            for (m, (d, o)) in d.iter_mut().zip(o.chunks_exact_mut(3)).enumerate() {
                let off = offsets[usize::from(UNMORTON[m])];
                *d = q(off);
                o.copy_from_slice(&off.map(|c| c as u8));
            }
        } else {
            d.fill(FIELD_DIST_FAR);
            let mut bits = Mask512::EMPTY;
            let mut by_place = [[0i8; 3]; LEAF_VOXELS];
            for (i, off) in mask.iter_ones().zip(offsets) {
                let m = usize::from(MORTON[i]);
                bits.set(m);
                d[m] = q(*off);
                by_place[m] = *off;
            }
            let (head, rest) = o.split_at_mut(64);
            for (h, w) in head.chunks_exact_mut(8).zip(bits.words) {
                h.copy_from_slice(&w.to_le_bytes());
            }
            let (offs, pad) = rest.split_at_mut(3 * count as usize);
            for (out, m) in offs.chunks_exact_mut(3).zip(bits.iter_ones()) {
                out.copy_from_slice(&by_place[m].map(|c| c as u8));
            }
            pad.fill(0);
        }
    }
}

/// Section offsets and the total length.
struct Sections {
    table: u64,
    blocks: u64,
    entries: u64,
    masks: u64,
    values: u64,
    /// 0 without a distance field.
    field: u64,
    total: u64,
}

/// The blocks of `leaves`, which come block by block and within a block by in-block index
/// (as [`crate::grid::Grid::leaves_in_block_order`] gives them).
fn blocks_of(leaves: &[PlannedLeaf<'_>]) -> Vec<BlockEntry> {
    let mut blocks: Vec<BlockEntry> = Vec::new();
    for (i, p) in leaves.iter().enumerate() {
        let origin = block_origin(p.origin).to_array();
        let j = leaf_in_block(p.origin);
        match blocks.last_mut() {
            Some(b) if b.origin == origin => {
                debug_assert!(
                    b.leaves[j / 64] >> (j % 64) == 0,
                    "leaves out of block order"
                );
                b.leaves[j / 64] |= 1 << (j % 64);
            }
            _ => {
                let mut b = BlockEntry {
                    origin,
                    first: i as u32,
                    ranks: [0; 8],
                    leaves: [0; 8],
                };
                b.leaves[j / 64] |= 1 << (j % 64);
                blocks.push(b);
            }
        }
    }
    for b in &mut blocks {
        b.ranks = BlockEntry::ranks_of(&b.leaves);
    }
    blocks
}

/// A dense index over the blocks' bounds (lowest block coordinates, size in blocks), if it
/// needs no more slots than a hash table would: the usual case, as maps are built from
/// rays and so are compact. A dense lookup is a bounds check and one read, no hashing,
/// probing or origin compare.
fn dense_index(blocks: &[BlockEntry]) -> Option<([i32; 3], [u32; 3])> {
    let first = block_coords(blocks.first()?.origin);
    let (mut lo, mut hi) = (first, first);
    for b in blocks {
        let c = block_coords(b.origin);
        for k in 0..3 {
            lo[k] = lo[k].min(c[k]);
            hi[k] = hi[k].max(c[k]);
        }
    }
    // Block coordinates span 2^26: each size fits u32, their product u128.
    let dims = [0, 1, 2].map(|k| (i64::from(hi[k]) - i64::from(lo[k]) + 1) as u32);
    let slots: u128 = dims.iter().map(|&d| u128::from(d)).product();
    (slots <= u128::from(table_capacity_for(blocks.len() as u64))).then_some((lo, dims))
}

/// Fill a zeroed table of `slots.len() / 4` slots with block `i` + 1 for each `home << 32 | i`
/// of `order`, sorted. Each takes the first free slot from its home, which in this order is
/// just past the last one filled; those pushed past the last slot wrap around to the first
/// free ones, and the table is full from their homes to its end, so probing reaches them.
/// Needs fewer blocks than slots.
fn fill_table(slots: &mut [u8], order: &[u64]) {
    let cap = (slots.len() / 4) as u64;
    let mut next = 0u64;
    let mut wrapped = Vec::new();
    for &o in order {
        let (home, i) = (o >> 32, o as u32);
        let s = home.max(next);
        if s < cap {
            slots[4 * s as usize..][..4].copy_from_slice(&(i + 1).to_le_bytes());
            next = s + 1;
        } else {
            wrapped.push(i);
        }
    }
    let mut s = 0;
    for i in wrapped {
        while slots[4 * s..4 * s + 4] != [0; 4] {
            s += 1;
        }
        slots[4 * s..4 * s + 4].copy_from_slice(&(i + 1).to_le_bytes());
    }
}

impl<'a, P: Pieces> Encoder<'a, P> {
    /// The snapshot of `leaves`, which come in block order (block by block, and within a
    /// block by in-block index: `Grid::leaves_in_block_order`'s order), each keeping its
    /// active voxels or one of `keeps`; `scope_box` the voxels a box scope keeps.
    pub fn new(
        info: MapInfo,
        mut leaves: Vec<PlannedLeaf<'a>>,
        keeps: Vec<Mask512>,
        scope_box: Option<(VoxelCoord, VoxelCoord)>,
        meta: Meta,
        pieces: P,
    ) -> Self {
        let piece = pieces.sizes().0;
        // Encode every leaf's record once, in pieces; `record` is the offset within the
        // piece until the pieces' offsets are known. Leaves with nothing known (possible
        // only in the whole scope) get no record and are dropped after.
        let encode = pieces.encode_piece();
        let encoded: Vec<(Vec<u8>, Sums, usize)> =
            pieces.map(leaves.chunks_mut(piece).collect(), |p| encode(p, &keeps));
        let mut starts = Vec::with_capacity(encoded.len());
        let mut at = 0u64;
        for (bytes, _, _) in &encoded {
            starts.push(at);
            at += bytes.len() as u64;
        }
        let jobs: Vec<_> = leaves.chunks_mut(piece).zip(&starts).collect();
        pieces.map(jobs, |(piece, &start)| {
            for p in piece {
                // Past MAX_MASKS_LEN the offset would wrap; `write` refuses such a plan.
                p.record = (start + u64::from(p.record)).min(MAX_MASKS_LEN) as u32;
            }
        });
        if encoded.iter().any(|(_, _, empty)| *empty > 0) {
            leaves.retain(|p| p.kinds.0 != EMPTY);
        }
        let mut sums = Sums::default();
        let mut records = Vec::with_capacity(encoded.len());
        for (bytes, piece_sums, _) in encoded {
            sums = Sums::add(sums, piece_sums);
            records.push(bytes);
        }
        let blocks = blocks_of(&leaves);
        let dense = dense_index(&blocks);
        let table_capacity = match dense {
            Some((_, dims)) => dims.iter().map(|&d| u64::from(d)).product(),
            None => table_capacity_for(blocks.len() as u64),
        };
        Self {
            info,
            pieces,
            leaves,
            keeps,
            meta,
            blocks,
            table_capacity,
            dense,
            records,
            masks_len: at,
            sums,
            scope_box,
            field: None,
        }
    }

    /// Carry `field` (kept beside the planned map) in the snapshot, for the leaves planned.
    pub fn with_field(mut self, field: &'a dyn FieldBands) -> Self {
        let whole = (
            VoxelCoord::new(i32::MIN, i32::MIN, i32::MIN),
            VoxelCoord::new(i32::MAX, i32::MAX, i32::MAX),
        );
        let (mut lo, mut hi) = field.window().unwrap_or(whole);
        if let Some((blo, bhi)) = self.scope_box {
            lo = lo.max(blo);
            hi = hi.min(bhi);
        }
        let steps = field_steps(field.radius());
        let r2 = (field.radius() * field.radius()) as i32;
        let quantised: Vec<u8> = (0..r2).map(|l| quantise(l, steps)).collect();
        let jobs: Vec<_> = self.leaves.chunks(self.pieces.sizes().0).collect();
        let pieces: Vec<FieldPiece> = self.pieces.map(jobs, |piece| {
            let mut out = FieldPiece {
                entries: Vec::with_capacity(piece.len()),
                dists: 0,
                data: 0,
                band: 0,
            };
            for p in piece {
                let Some((mask, _)) = field.band(p.origin) else {
                    out.entries.push(FieldEntry::NONE);
                    continue;
                };
                let count = mask.count();
                let units = (out.data / 8) as u32;
                out.entries.push(FieldEntry {
                    data: if count == 512 {
                        units
                    } else {
                        units | FIELD_MASKED
                    },
                });
                out.band += u64::from(count);
                out.dists += FIELD_DISTS;
                out.data += offsets_len(count);
            }
            out
        });
        let mut entries = Vec::with_capacity(self.leaves.len());
        let mut sizes = Vec::with_capacity(pieces.len());
        let (mut at, mut band_count) = (0u64, 0u64);
        for piece in pieces {
            // Places within a piece become places within the section; past the entries'
            // limit they would wrap, and `write` refuses the plan.
            entries.extend(piece.entries.into_iter().map(|e| {
                if e == FieldEntry::NONE {
                    return e;
                }
                let units = (at / 8 + u64::from(e.data & !FIELD_MASKED)).min(FIELD_MAX_UNITS);
                FieldEntry {
                    data: units as u32 | (e.data & FIELD_MASKED),
                }
            }));
            at += piece.data as u64;
            band_count += piece.band;
            sizes.push((piece.dists, piece.data));
        }
        // Each block's leaves in the band, found as its leaves are: by in-block index.
        let mut blocks = Vec::with_capacity(self.blocks.len());
        let mut first = 0u64;
        for b in &self.blocks {
            let mut band = [0u64; 8];
            let mut leaf = b.first as usize;
            for (w, word) in b.leaves.iter().enumerate() {
                for bit in crate::mask::BitIter(*word) {
                    if entries[leaf] != FieldEntry::NONE {
                        band[w] |= 1 << bit;
                    }
                    leaf += 1;
                }
            }
            blocks.push(FieldBlock {
                first: first.min(u64::from(u32::MAX)) as u32,
                reserved: 0,
                ranks: BlockEntry::ranks_of(&band),
                band,
            });
            first += band.iter().map(|w| u64::from(w.count_ones())).sum::<u64>();
        }
        self.field = Some(FieldPlan {
            header: FieldHeader {
                max_distance: field.max_distance(),
                radius: field.radius(),
                unknown: field.config().unknown.code(),
                steps,
                reserved: [0; 2],
                window_lo: lo.to_array(),
                window_hi: hi.to_array(),
                band_count,
                data_len: at,
                dist_blocks: first,
            },
            field,
            blocks,
            entries,
            pieces: sizes,
            quantised,
        });
        self
    }

    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
    }

    fn sections(&self) -> Sections {
        let n = self.leaves.len() as u64;
        let table = HEADER_SIZE as u64;
        let blocks = align8(table + 4 * self.table_capacity);
        let entries = blocks + BLOCK_SIZE as u64 * self.blocks.len() as u64;
        let masks = entries + ENTRY_SIZE as u64 * n;
        let values_end = masks + align8(self.masks_len);
        let (values, end) = if self.meta.with_values {
            (values_end, values_end + VALUES_PER_LEAF as u64 * n)
        } else {
            (0, values_end)
        };
        let (field, total) = match &self.field {
            Some(f) => {
                let at = align8(end);
                let dists = field_dists_at(at, f.blocks.len() as u64, f.entries.len() as u64);
                (
                    at,
                    dists + FIELD_DISTS as u64 * f.header.dist_blocks + f.header.data_len,
                )
            }
            None => (0, end),
        };
        Sections {
            table,
            blocks,
            entries,
            masks,
            values,
            field,
            total,
        }
    }

    /// Bytes [`Plan::write`] needs.
    pub fn encoded_len(&self) -> usize {
        self.sections().total as usize
    }

    /// Write the snapshot into `buf[..encoded_len()]`; returns the length written.
    pub fn write(&self, buf: &mut [u8]) -> Result<usize, EncodeError> {
        let Sections {
            table,
            blocks,
            entries,
            masks,
            values,
            field,
            total,
        } = self.sections();
        if self.masks_len > MAX_MASKS_LEN
            || self.field.as_ref().is_some_and(|f| {
                f.header.data_len / 8 > FIELD_MAX_UNITS
                    || f.header.dist_blocks > u64::from(u32::MAX)
            })
            || self.table_capacity >= 1 << 32
            || self.leaves.len() as u64 >= u64::from(u32::MAX)
        {
            return Err(EncodeError::TooLarge);
        }
        let total_us = total as usize;
        if buf.len() < total_us {
            return Err(EncodeError::BufferTooSmall {
                needed: total_us,
                got: buf.len(),
            });
        }
        let buf = &mut buf[..total_us];
        // Only the table (and its padding) is read before written; every other byte is
        // written below, so a reused sample needs no full clear.
        buf[HEADER_SIZE..blocks as usize].fill(0);
        let q = &self.info.quantized;
        let (piece, crc_piece) = self.pieces.sizes();
        let cap = self.table_capacity;
        let slots = &mut buf[table as usize..(table + 4 * cap) as usize];
        match self.dense {
            Some((lo, dims)) => {
                for (i, b) in self.blocks.iter().enumerate() {
                    let s = dense_slot(block_coords(b.origin), lo, dims).expect("in bounds");
                    slots[4 * s as usize..][..4].copy_from_slice(&(i as u32 + 1).to_le_bytes());
                }
            }
            None => {
                // Blocks in order of their home slots (ties by index, so the table does not
                // depend on scheduling), filled in one pass front to back (`fill_table`).
                let mut order: Vec<u64> = (self.blocks.iter().enumerate())
                    .map(|(i, b)| table_hash(b.origin, cap) << 32 | i as u64)
                    .collect();
                order.sort_unstable();
                fill_table(slots, &order);
            }
        }
        let (index_lo, index_dims) = self.dense.unwrap_or_default();
        buf[blocks as usize..entries as usize].copy_from_slice(bytemuck::cast_slice(&self.blocks));
        // Cut the sections into disjoint pieces and write them in parallel.
        let (_, rest) = buf.split_at_mut(entries as usize);
        let (entry_bytes, rest) = rest.split_at_mut((masks - entries) as usize);
        let (mask_section, rest) = rest.split_at_mut(align8(self.masks_len) as usize);
        let values_len = if self.meta.with_values {
            VALUES_PER_LEAF * self.leaves.len()
        } else {
            0
        };
        let (value_bytes, field_bytes) = rest.split_at_mut(values_len);
        let (mut mask_bytes, padding) = mask_section.split_at_mut(self.masks_len as usize);
        padding.fill(0);
        let mut record_pieces = Vec::with_capacity(self.records.len());
        for r in &self.records {
            record_pieces.push((take(&mut mask_bytes, r.len()), r));
        }
        self.pieces
            .map(record_pieces, |(out, r)| out.copy_from_slice(r));
        let jobs: Vec<_> = (entry_bytes.chunks_mut(ENTRY_SIZE * piece))
            .zip(self.leaves.chunks(piece))
            .collect();
        self.pieces.map(jobs, |(out, leaves)| {
            for (o, p) in out.chunks_exact_mut(ENTRY_SIZE).zip(leaves) {
                let (k, occ) = p.kinds;
                let entry = LeafEntry::new(k, occ, p.record);
                o.copy_from_slice(bytemuck::bytes_of(&entry));
            }
        });
        if self.meta.with_values {
            let jobs: Vec<_> = (value_bytes.chunks_mut(VALUES_PER_LEAF * piece))
                .zip(self.leaves.chunks(piece))
                .collect();
            self.pieces.map(jobs, |(out, leaves)| {
                for (o, p) in out.chunks_exact_mut(VALUES_PER_LEAF).zip(leaves) {
                    let keep = keep_of(&self.keeps, p);
                    for (v, b) in o.iter_mut().enumerate() {
                        *b = if keep.get(v) {
                            p.leaf.values[v] as u8
                        } else {
                            0
                        };
                    }
                }
            });
        }
        if let Some(f) = &self.field {
            // From the end of the last section: its padding, then the field section.
            let field_bytes = &mut field_bytes
                [(field - (masks + align8(self.masks_len) + values_len as u64)) as usize..];
            let (head, rest) = field_bytes.split_at_mut(FIELD_HEADER_SIZE);
            head.copy_from_slice(bytemuck::bytes_of(&f.header));
            let (block_out, rest) = rest.split_at_mut(FIELD_BLOCK_SIZE * f.blocks.len());
            block_out.copy_from_slice(bytemuck::cast_slice(&f.blocks));
            let (entry_out, rest) = rest.split_at_mut(FIELD_ENTRY_SIZE * f.entries.len());
            entry_out.copy_from_slice(bytemuck::cast_slice(&f.entries));
            let dists_at = field_dists_at(field, f.blocks.len() as u64, f.entries.len() as u64);
            let (pad, rest) = rest.split_at_mut(
                (dists_at - field) as usize
                    - FIELD_HEADER_SIZE
                    - FIELD_BLOCK_SIZE * f.blocks.len()
                    - FIELD_ENTRY_SIZE * f.entries.len(),
            );
            pad.fill(0);
            let (mut dists, mut data) =
                rest.split_at_mut(FIELD_DISTS * f.header.dist_blocks as usize);
            let mut pieces = Vec::with_capacity(f.pieces.len());
            for (leaves, &(d, o)) in self.leaves.chunks(piece).zip(&f.pieces) {
                pieces.push((leaves, take(&mut dists, d), take(&mut data, o)));
            }
            self.pieces
                .map(pieces, |(leaves, d, o)| write_field_piece(leaves, f, d, o));
        }
        let sums = &self.sums;
        let hashers = self
            .pieces
            .map(buf[HEADER_SIZE..].chunks(crc_piece).collect(), |c| {
                let mut h = crc32fast::Hasher::new();
                h.update(c);
                h
            });
        let checksum = hashers
            .into_iter()
            .fold(crc32fast::Hasher::new(), |mut a, b| {
                a.combine(&b);
                a
            })
            .finalize();
        let h = Header {
            magic: MAGIC,
            version: FORMAT_VERSION,
            flags: if self.meta.with_values {
                FLAG_VALUES
            } else {
                0
            } | if self.dense.is_some() {
                FLAG_DENSE_INDEX
            } else {
                0
            } | if self.field.is_some() { FLAG_FIELD } else { 0 },
            header_size: HEADER_SIZE as u32,
            frac_bits: q.frac_bits,
            threshold: q.threshold,
            clamp_min: q.min,
            clamp_max: q.max,
            resolution: self.info.resolution,
            sequence: self.meta.sequence,
            timestamp_ns: self.meta.timestamp_ns,
            leaf_count: self.leaves.len() as u64,
            known_count: sums.known,
            occupied_count: sums.occupied,
            bounds_min: sums.lo,
            bounds_max: sums.hi,
            table_capacity: self.table_capacity,
            block_count: self.blocks.len() as u64,
            index_lo,
            index_dims,
            table_offset: table,
            blocks_offset: blocks,
            leaves_offset: entries,
            masks_offset: masks,
            masks_len: self.masks_len,
            values_offset: values,
            total_len: total,
            checksum,
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

#[cfg(test)]
mod tests {
    use super::fill_table;
    use crate::test_rng::Rng;

    /// Every leaf lands once, and probing from its home reaches it before an empty slot,
    /// also when homes crowd the table's end and the leaves wrap around to its start.
    #[test]
    fn table_fill_is_a_linear_probing_table() {
        let mut rng = Rng(1);
        let mut wrapped_some = false;
        for trial in 0..2000u64 {
            let cap = rng.i(1, 40) as u64;
            let n = rng.i(0, cap as i32 - 1) as u64;
            // Half the trials put every home in the last quarter of the table.
            let lo = if trial % 2 == 0 {
                0
            } else {
                cap - cap.div_ceil(4)
            };
            let homes: Vec<u64> = (0..n)
                .map(|_| rng.i(lo as i32, cap as i32 - 1) as u64)
                .collect();
            let mut order: Vec<u64> = homes
                .iter()
                .enumerate()
                .map(|(i, &h)| h << 32 | i as u64)
                .collect();
            order.sort_unstable();
            let mut slots = vec![0u8; 4 * cap as usize];
            fill_table(&mut slots, &order);
            let slot =
                |s: u64| u32::from_le_bytes(slots[4 * s as usize..][..4].try_into().unwrap());
            let mut seen = vec![false; n as usize];
            for (i, &h) in homes.iter().enumerate() {
                let mut s = h;
                loop {
                    let e = slot(s);
                    assert_ne!(e, 0, "trial {trial}: leaf {i} not reached from home {h}");
                    if e == i as u32 + 1 {
                        break;
                    }
                    s = (s + 1) % cap;
                }
                wrapped_some |= s < h;
                assert!(!std::mem::replace(&mut seen[i], true));
            }
            assert_eq!((0..cap).filter(|&s| slot(s) != 0).count() as u64, n);
        }
        assert!(wrapped_some, "no trial wrapped around");
    }
}
