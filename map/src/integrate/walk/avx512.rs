//! The raycast walks on AVX-512: eight rays at once, one per 64-bit lane.
//!
//! The scalar walks spend much of a step on the branch that picks the axis to cross: it
//! mispredicts often, as the axes interleave irregularly. Here that choice is three
//! compares into lane masks, and eight rays share every instruction. Lanes that end their
//! rays take their next ones, a few lanes at a time, so lanes stay busy however ray lengths
//! differ; the set-up of new rays (`Dda::new`) is vectorised too, for all lanes that need
//! one at once. Per lane the walk is [`Dda::step`] exactly (same crossings, same ties,
//! same end voxel).
//!
//! One walk ([`walk`]), two ways to keep marks ([`Lanes`]):
//! - dense ([`walk_dense`]): a voxel is its bit index in the thread's [`DenseBits`], so a
//!   step is one add and a mark one OR into memory that stays in cache;
//! - sparse ([`walk_sparse`]): a voxel is [`Packed`]; each lane keeps the marks of its
//!   current z plane in a vector lane and of its leaf in its own words, and ORs the
//!   leaf's into the frame's tables when it leaves the leaf, as the one-ray sparse walk
//!   does.

use super::covered::Covered;
use super::dense::{set_bit, DenseBits, DenseBox};
use super::{Packed, Spill};
use crate::integrate::marks::LeafCache;
use crate::integrate::ray::Ray;
use crate::mask::BitIter;
#[cfg(doc)]
use crate::raycast::Dda;
use crate::raycast::T_ONE;
use std::arch::x86_64::*;
use std::ops::Range;

/// Cap on `t` between crossings. An axis with a larger one crosses at most once (t = 1 is
/// 2^60), so the cap only changes sums that [`Dda::step`] never uses, and it keeps
/// `t + between` from overflowing, which `step` avoids by saturating.
const T_CAP: u64 = 1 << 62;

/// Whether marks are tested before they are written, for a frame of `steps_per_voxel`
/// estimated steps per voxel of its box: whether nearly all of them will find their bit
/// set already, as in a scan with many more steps than its box has voxels (97-99.6% of the
/// marks of the 500k 6 m workloads repeat). Those are tested first, eight with one gather,
/// and only new ones written. Min of 3 runs, 2 threads, ray phase: structured 500k 6 m
/// (117 steps per box voxel) 32.5 -> 22.7 ms, random 500k 6 m (18) 39.0 -> 37.2 ms. It
/// pays only when nearly no lane writes: at 12 steps per voxel (structured 50k 6 m,
/// structured 500k 60 m) it was 5-20% slower, at 1.8 (random 50k 6 m) twice as slow.
pub(super) fn test_first(steps_per_voxel: f64) -> bool {
    steps_per_voxel >= 16.0
}

/// Walk the rays `rays[ranges[l]]` from `origin`, lane `l` those of its range in turn,
/// setting their free and hit bits in `bits`; returns voxels visited. The same voxels and
/// count as `super::sparse::walk_rays`. `test_first` is [`test_first`] for the frame (tests
/// force it).
///
/// Feed the lanes from far apart in direction. Lanes on neighbouring rays OR into the same
/// word one after another near the sensor, and each OR then waits for the last: fed
/// neighbouring rays, the walk ran 2.3x slower (random 500k 6 m, one thread).
#[target_feature(enable = "avx512f,avx512dq")]
#[allow(clippy::too_many_arguments)]
pub(crate) fn walk_dense(
    bits: &mut DenseBits,
    dbox: &DenseBox,
    origin: [f64; 3],
    rays: &[Ray],
    ranges: [Range<usize>; 8],
    test_first: bool,
    covered: Option<&Covered>,
) -> (u64, u64) {
    let start = dbox.index(crate::coord::units_to_voxel(origin).expect("origin checked"));
    let (free, hits) = bits.words_mut();
    let sink = dbox.sink();
    let a = (
        start,
        dbox.strides(),
        origin,
        rays,
        Feed::Ranges(ranges),
        covered,
    );
    // Each choice is its own compiled loop, so that the loop for new marks does no more
    // work than before the choice existed.
    if test_first {
        walk(&mut DenseLanes::<true>::new(free, hits, sink), a)
    } else {
        walk(&mut DenseLanes::<false>::new(free, hits, sink), a)
    }
}

/// Walk `rays` from `origin` eight at a time, OR-ing their marks into the frame's tables
/// through `cache`; returns voxels visited. The same marks and count as
/// `super::sparse::walk_rays`, the one-ray sparse walk. The rays are sorted by direction and each
/// lane takes the next: the lanes walk side by side, so they find the leaves they flush in
/// `cache` and in the CPU's caches. Each lane gathers its current leaf's marks in its own
/// words, so lanes never write the same word.
#[target_feature(enable = "avx512f,avx512dq")]
pub(crate) fn walk_sparse(cache: &mut LeafCache<'_>, origin: [f64; 3], rays: &[Ray]) -> u64 {
    let v = crate::coord::units_to_voxel(origin).expect("origin checked");
    let packed = Packed::around(v);
    let mut lanes = SparseLanes {
        cache,
        packed,
        buffers: [[0; 8]; 8 * BUFFERS],
        queued_at: [0; QUEUE_LEN],
        queued_buffer: [0; QUEUE_LEN],
        queued: 0,
    };
    let a = (
        packed.pack(v),
        Packed::STRIDES,
        origin,
        rays,
        Feed::Next(0..rays.len()),
        None,
    );
    let (steps, _) = walk(&mut lanes, a);
    lanes.flush_queue();
    steps
}

/// What a lane walk does with the voxels its lanes visit. Voxels are `u64` indices with
/// fixed strides per axis: bit indices into a dense box, or [`Packed`] voxels.
///
/// # Safety
/// The methods use AVX-512F and DQ: call them only where the CPU has both (they are
/// `unsafe` for that alone, as trait methods cannot enable target features safely).
trait Lanes {
    /// Per-lane values the walk keeps in registers for the methods: the walk owns them,
    /// so that they are not stored and reloaded on every step.
    type Regs: Copy;
    fn regs(&self) -> Self::Regs;
    /// Mark free the voxels `p` of the lanes in `live`.
    unsafe fn mark(&mut self, r: &mut Self::Regs, p: __m512i, live: __mmask8);
    /// The lanes in `live` stepped from `was` to `p`.
    unsafe fn stepped(&mut self, r: &mut Self::Regs, was: __m512i, p: __m512i, live: __mmask8);
    /// The lanes in `end` ended their rays at `p`, those in `hit` in a hit.
    fn ended(&mut self, r: Self::Regs, p: __m512i, end: __mmask8, hit: __mmask8) -> Self::Regs;
    /// A ray ended in the voxel its walk starts from, `p`, in a hit.
    fn hit_at(&mut self, p: u64);
}

/// The dense walk's lanes: bits of the thread's grid over the frame's box; whether marks
/// are tested before they are written. Aligned to a cache line for the reason
/// [`SparseLanes`] is.
#[repr(align(64))]
struct DenseLanes<'a, const TEST_FIRST: bool> {
    free: &'a mut [u64],
    hits: &'a mut [u64],
    /// A bit past the box that lanes without a ray mark.
    sink: __m512i,
}

impl<'a, const TEST_FIRST: bool> DenseLanes<'a, TEST_FIRST> {
    #[target_feature(enable = "avx512f")]
    fn new(free: &'a mut [u64], hits: &'a mut [u64], sink: u64) -> Self {
        let sink = _mm512_set1_epi64(sink as i64);
        DenseLanes { free, hits, sink }
    }
}

impl<const TEST_FIRST: bool> Lanes for DenseLanes<'_, TEST_FIRST> {
    type Regs = ();

    fn regs(&self) {}

    #[inline]
    #[target_feature(enable = "avx512f,avx512dq")]
    unsafe fn mark(&mut self, _: &mut (), p: __m512i, live: __mmask8) {
        let free = &mut *self.free;
        if TEST_FIRST {
            // Most already are: the words are read with one gather and only lanes whose
            // bit is not yet set write.
            let word = _mm512_srli_epi64::<6>(p);
            let bit = _mm512_sllv_epi64(
                _mm512_set1_epi64(1),
                _mm512_and_si512(p, _mm512_set1_epi64(63)),
            );
            if _mm512_mask_cmpge_epu64_mask(live, word, _mm512_set1_epi64(free.len() as i64)) != 0 {
                outside_the_box();
            }
            // SAFETY: the lanes read, those in `live`, have `word < free.len()` (checked
            // just above), so every read is inside `free`.
            let words = unsafe {
                _mm512_mask_i64gather_epi64::<8>(
                    _mm512_setzero_si512(),
                    live,
                    word,
                    free.as_ptr().cast(),
                )
            };
            let unset = _mm512_mask_testn_epi64_mask(live, words, bit);
            if unset != 0 {
                let (word, bit) = (to_array(word), to_array(bit));
                for l in BitIter(u64::from(unset)) {
                    free[word[l] as usize] |= bit[l];
                }
            }
        } else {
            // Every lane ORs its bit in; a lane without a ray marks the sink bit. One
            // vector of bit indices, split into word and bit by scalar shifts: vectors
            // of words and of bits took twice the lane moves. The lanes are spilled
            // ([`Spill`]): eight extracts a step held the vector ports the step needs.
            let mut lanes = Spill::<8>::new();
            // SAFETY: the spill is 64 bytes aligned to 64, all `_mm512_store_si512` writes.
            unsafe {
                _mm512_store_si512(
                    lanes.ptr().cast(),
                    _mm512_mask_mov_epi64(self.sink, live, p),
                )
            };
            for q in lanes.lanes() {
                set_bit(free, q);
            }
        }
    }

    #[inline]
    unsafe fn stepped(&mut self, _: &mut (), _: __m512i, _: __m512i, _: __mmask8) {}

    #[inline]
    fn ended(&mut self, _: (), p: __m512i, _: __mmask8, hit: __mmask8) {
        if hit != 0 {
            let p = to_array(p);
            for l in BitIter(u64::from(hit)) {
                set_bit(self.hits, p[l]);
            }
        }
    }

    fn hit_at(&mut self, p: u64) {
        set_bit(self.hits, p);
    }
}

/// Leaf buffers per lane: the one it fills and up to `QUEUE_AT` waiting in the queue.
const BUFFERS: usize = 32;
/// Queued leaves that start a flush. A flush looks up all their slots first and prefetches
/// them, so that their cache misses overlap.
const QUEUE_AT: usize = 24;
/// Room for a queue of `QUEUE_AT - 1` and a whole vector more.
const QUEUE_LEN: usize = QUEUE_AT + 8;
// A lane queues at most one leaf per step and the queue is flushed once it holds
// `QUEUE_AT`, so a lane never has more than `QUEUE_AT` waiting: its next buffer is free.
const _: () = assert!(QUEUE_AT < BUFFERS && BUFFERS.is_power_of_two());

/// The sparse walk's lanes. Each gathers the marks of its current z plane in a vector
/// lane and those of its current leaf in a buffer of its own; when it leaves the leaf,
/// it queues the buffer and takes its next one, and the queue's leaves are OR-ed into the
/// frame's tables together.
///
/// Aligned to a cache line, which makes the walk's frame aligned too: the walk keeps some
/// of its per-lane vectors on the stack, and where the caller's stack left them across two
/// cache lines each step's reload missed store forwarding (the ray phase of random 50k
/// 60 m took 15-20% longer on an Intel AVX-512 CPU, the walk's code unchanged).
#[repr(align(64))]
struct SparseLanes<'c, 'a> {
    cache: &'c mut LeafCache<'a>,
    packed: Packed,
    /// 8 words (z planes) per buffer.
    buffers: [[u64; 8]; 8 * BUFFERS],
    /// Queued leaves: a voxel of each (packed) and its buffer.
    queued_at: [u64; QUEUE_LEN],
    queued_buffer: [u64; QUEUE_LEN],
    queued: usize,
}

impl SparseLanes<'_, '_> {
    /// OR the marks of buffer `b` into the leaf of `q` and clear them.
    #[inline]
    fn flush(&mut self, b: usize, q: u64) {
        self.cache
            .or_free(self.packed.unpack(q).shr(3), &self.buffers[b]);
        self.buffers[b] = [0; 8];
    }

    /// Flush the queue: look up every queued leaf's slot and prefetch it, then OR.
    #[inline(never)]
    #[target_feature(enable = "avx512f")]
    fn flush_queue(&mut self) {
        let n = self.queued;
        let mut slots = [None; QUEUE_LEN];
        for (slot, &q) in slots.iter_mut().zip(&self.queued_at[..n]) {
            let s = self.cache.slot_for(self.packed.unpack(q).shr(3));
            _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(s).cast());
            *slot = Some(s);
        }
        for (slot, &b) in slots[..n].iter().zip(&self.queued_buffer[..n]) {
            let words = &mut self.buffers[b as usize];
            let free = &slot.expect("looked up above").free;
            // SAFETY: `words` and `free` are 64 bytes each (eight u64, eight AtomicU64 of
            // the same layout). Only the task holding this cache's lane accesses the lane's
            // slots until the lane is released (see `FrameMarks`), so this plain
            // read-modify-write races with nothing, as `Slot::or_free`'s does not.
            unsafe {
                let at = free.as_ptr().cast::<__m512i>().cast_mut();
                let marks = _mm512_loadu_si512(words.as_ptr().cast());
                _mm512_storeu_si512(at, _mm512_or_si512(_mm512_loadu_si512(at), marks));
            }
            *words = [0; 8];
        }
        self.queued = 0;
    }
}

/// A sparse walk's per-lane registers.
#[derive(Clone, Copy)]
struct SparseRegs {
    /// Per lane the marks of its current z plane in its leaf, bit `x | y << 3`. A ray
    /// visits each plane of a leaf in one run, so a plane is stored once, when the lane
    /// leaves it.
    plane: __m512i,
    /// Per lane the index of its current buffer, `BUFFERS * lane + b`.
    buffer: __m512i,
}

impl Lanes for SparseLanes<'_, '_> {
    type Regs = SparseRegs;

    fn regs(&self) -> SparseRegs {
        SparseRegs {
            plane: per_lane(0),
            buffer: FIRST_BUFFERS,
        }
    }

    #[inline]
    #[target_feature(enable = "avx512f,avx512dq")]
    unsafe fn mark(&mut self, r: &mut SparseRegs, p: __m512i, live: __mmask8) {
        const _: () = assert!(Packed::F == 21);
        let xy = _mm512_or_si512(
            _mm512_and_si512(p, _mm512_set1_epi64(7)),
            _mm512_and_si512(_mm512_srli_epi64::<18>(p), _mm512_set1_epi64(7 << 3)),
        );
        let bit = _mm512_sllv_epi64(_mm512_set1_epi64(1), xy);
        r.plane = _mm512_mask_or_epi64(r.plane, live, r.plane, bit);
    }

    #[inline]
    #[target_feature(enable = "avx512f,avx512dq")]
    unsafe fn stepped(&mut self, r: &mut SparseRegs, was: __m512i, p: __m512i, live: __mmask8) {
        let moved = _mm512_xor_si512(was, p);
        let left = _mm512_mask_test_epi64_mask(live, moved, _mm512_set1_epi64(Packed::LEAF as i64));
        let done = left
            | _mm512_mask_test_epi64_mask(live, moved, _mm512_set1_epi64(Packed::Z_FIELD as i64));
        // Lanes that left their plane store it: word z of the lane's buffer.
        let word = _mm512_add_epi64(
            _mm512_slli_epi64::<3>(r.buffer),
            _mm512_and_si512(_mm512_srli_epi64::<42>(was), _mm512_set1_epi64(7)),
        );
        // SAFETY: `word` is 8 b + z with b < 8 * BUFFERS and z < 8: inside `buffers`.
        unsafe {
            _mm512_mask_i64scatter_epi64::<8>(self.buffers.as_mut_ptr().cast(), done, word, r.plane)
        };
        r.plane = _mm512_mask_mov_epi64(r.plane, done, _mm512_setzero_si512());
        // Lanes that left their leaf queue it and take their next buffer. Whole vectors
        // are stored at the queue's end, the queued lanes first; the rest is overwritten.
        let n = self.queued;
        debug_assert!(n < QUEUE_AT);
        // SAFETY: n < QUEUE_AT, so the 8 words from n are inside both queues (QUEUE_LEN).
        unsafe {
            _mm512_storeu_si512(
                self.queued_at.as_mut_ptr().add(n).cast(),
                _mm512_maskz_compress_epi64(left, was),
            );
            _mm512_storeu_si512(
                self.queued_buffer.as_mut_ptr().add(n).cast(),
                _mm512_maskz_compress_epi64(left, r.buffer),
            );
        }
        self.queued = n + left.count_ones() as usize;
        let next = _mm512_add_epi64(r.buffer, _mm512_set1_epi64(1));
        let wrapped = _mm512_or_si512(
            _mm512_and_si512(next, _mm512_set1_epi64(BUFFERS as i64 - 1)),
            FIRST_BUFFERS,
        );
        r.buffer = _mm512_mask_mov_epi64(r.buffer, left, wrapped);
        if self.queued >= QUEUE_AT {
            self.flush_queue();
        }
    }

    #[inline]
    fn ended(&mut self, r: SparseRegs, p: __m512i, end: __mmask8, hit: __mmask8) -> SparseRegs {
        let p = to_array(p);
        let mut plane = to_array(r.plane);
        let buffer = to_array(r.buffer);
        for l in BitIter(u64::from(end)) {
            let b = buffer[l] as usize;
            self.buffers[b][(p[l] >> (2 * Packed::F) & 7) as usize] |= plane[l];
            plane[l] = 0;
            // A ray's last step may enter a leaf only to end there: nothing free to
            // mark, and a slot would give the map an empty leaf.
            if self.buffers[b] != [0; 8] {
                self.flush(b, p[l]);
            }
            if hit >> l & 1 != 0 {
                self.cache.set_hit(self.packed.unpack(p[l]));
            }
        }
        SparseRegs {
            plane: from_array(plane),
            ..r
        }
    }

    fn hit_at(&mut self, p: u64) {
        self.cache.set_hit(self.packed.unpack(p));
    }
}

/// Which rays each lane of a walk takes.
enum Feed {
    /// Lane `l` those of the `l`-th range in turn, then half of what is left to another.
    Ranges([Range<usize>; 8]),
    /// Each lane the next ray no lane has taken: lanes walk neighbouring rays side by side.
    Next(Range<usize>),
}

/// Walk the rays of `feed` from `origin`, telling `lanes` the voxels each lane visits;
/// returns voxels visited. Voxel indices start at `start` (the origin's voxel) and change
/// by `strides` per step. A lane whose ray ends takes its next at once: the rays are set up
/// ahead, so that costs a few lane moves. (When each refill set up its rays, lanes waited
/// for three of them to end, idle meanwhile.)
#[target_feature(enable = "avx512f,avx512dq")]
#[allow(clippy::type_complexity)]
fn walk<L: Lanes>(
    lanes: &mut L,
    (start, strides, origin, rays, feed, covered): (
        u64,
        [i64; 3],
        [f64; 3],
        &[Ray],
        Feed,
        Option<&Covered>,
    ),
) -> (u64, u64) {
    let zero = _mm512_setzero_si512();
    let one = _mm512_set1_epi64(1);
    let never = _mm512_set1_epi64(-1);
    // Per axis: the origin, its voxel's floor, the distance to the voxel's upper and lower
    // faces, and the index stride.
    let axes: [Axis; 3] = std::array::from_fn(|a| {
        let s = origin[a].floor();
        Axis {
            o: _mm512_set1_pd(origin[a]),
            s: _mm512_set1_pd(s),
            up: _mm512_set1_pd(s + 1.0 - origin[a]),
            down: _mm512_set1_pd(origin[a] - s),
            stride: _mm512_set1_epi64(strides[a]),
        }
    });
    let (mut tx, mut ty, mut tz) = (never, never, never);
    let (mut dx, mut dy, mut dz) = (zero, zero, zero);
    let (mut lx, mut ly, mut lz) = (zero, zero, zero);
    let (mut mx, mut my, mut mz) = (zero, zero, zero);
    let (mut p, mut rem) = (zero, zero);
    let mut hit: __mmask8 = 0;
    // Per lane its next ray and the end of its range; with `Feed::Next`, the next ray not
    // taken and the end in every lane.
    let (next, (mut cur, mut lim)) = match feed {
        Feed::Ranges(r) => (
            false,
            (
                from_array(r.clone().map(|r| r.start as u64)),
                from_array(r.map(|r| r.end as u64)),
            ),
        ),
        Feed::Next(r) => (
            true,
            (
                _mm512_set1_epi64(r.start as i64),
                _mm512_set1_epi64(r.end as i64),
            ),
        ),
    };
    let (mut steps, mut skipped) = (zero, 0);
    let mut need: __mmask8 = 0xff;
    // Lanes walking a ray.
    let mut live: __mmask8 = 0;
    // Rays set up and not yet walked: set up eight at a time (a vectorised pass, as dear
    // for one lane as for eight), handed to the lanes that need them as they need them.
    let mut ahead = Ahead::of(0, &[AxisSetup::NONE; 3], zero, zero, 0);
    let mut regs = lanes.regs();
    loop {
        // Give each lane in `need` its next ray that takes a step, from the rays set up
        // ahead; rays that end in their start voxel are done as they are set up (a hit at
        // most).
        while need != 0 {
            if ahead.len == 0 {
                let (ray, avail) = if next {
                    let ray = _mm512_add_epi64(cur, IOTA);
                    let avail = _mm512_cmplt_epu64_mask(ray, lim);
                    cur = _mm512_add_epi64(cur, _mm512_set1_epi64(i64::from(avail.count_ones())));
                    (ray, avail)
                } else {
                    let dry = _mm512_cmpge_epu64_mask(cur, lim);
                    if dry != 0 {
                        (cur, lim) = share(cur, lim, dry);
                    }
                    let avail = _mm512_cmplt_epu64_mask(cur, lim);
                    let ray = cur;
                    cur = _mm512_mask_add_epi64(cur, avail, cur, one);
                    (ray, avail)
                };
                if avail == 0 {
                    break;
                }
                let at = _mm512_slli_epi64::<2>(ray); // Ray is four 8-byte words
                let base = rays.as_ptr().cast::<u8>();
                // SAFETY: lanes in `avail` have ray < lim <= rays.len(), so every word read
                // is inside `rays`: `end` is words 0..3 and `key`/`hit` word 3 of a `Ray`
                // (repr(C), every byte initialised, see `Ray`). Other lanes read nothing.
                let (ex, ey, ez, flags) = unsafe {
                    let word = |k: i64| _mm512_add_epi64(at, _mm512_set1_epi64(k));
                    (
                        _mm512_mask_i64gather_pd::<8>(_mm512_setzero_pd(), avail, at, base.cast()),
                        _mm512_mask_i64gather_pd::<8>(
                            _mm512_setzero_pd(),
                            avail,
                            word(1),
                            base.cast(),
                        ),
                        _mm512_mask_i64gather_pd::<8>(
                            _mm512_setzero_pd(),
                            avail,
                            word(2),
                            base.cast(),
                        ),
                        _mm512_mask_i64gather_epi64::<8>(zero, avail, word(3), base.cast()),
                    )
                };
                let mut set_up =
                    [(ex, &axes[0]), (ey, &axes[1]), (ez, &axes[2])].map(|(e, a)| a.setup(e));
                let mut n =
                    _mm512_add_epi64(_mm512_add_epi64(set_up[0].n, set_up[1].n), set_up[2].n);
                steps = _mm512_mask_add_epi64(steps, avail, steps, _mm512_add_epi64(n, one));
                let mut p0 = _mm512_set1_epi64(start as i64);
                if let Some(c) = covered {
                    let made;
                    (n, p0, made) = skip_covered(c, avail, start, &mut set_up, n);
                    skipped += made;
                }
                let ray_hit = _mm512_test_epi64_mask(flags, _mm512_set1_epi64(1 << 32));
                let empty = avail & _mm512_cmpeq_epi64_mask(n, zero);
                if empty & ray_hit != 0 {
                    let p0 = to_array(p0);
                    for l in BitIter(u64::from(empty & ray_hit)) {
                        lanes.hit_at(p0[l]);
                    }
                }
                ahead = Ahead::of(avail & !empty, &set_up, p0, n, ray_hit);
                continue;
            }
            // The lowest `len` lanes of `need` at most take the rays ahead, in order.
            let take = (BitIter(u64::from(need)).take(ahead.len as usize))
                .fold(0 as __mmask8, |m, l| m | 1 << l);
            let put =
                |v: &mut __m512i, from: __m512i| *v = _mm512_mask_expand_epi64(*v, take, from);
            let [x, y, z] = &ahead.axes;
            for (v, f) in [(&mut tx, x.t), (&mut ty, y.t), (&mut tz, z.t)] {
                put(v, f);
            }
            for (v, f) in [(&mut dx, x.d), (&mut dy, y.d), (&mut dz, z.d)] {
                put(v, f);
            }
            for (v, f) in [(&mut lx, x.last), (&mut ly, y.last), (&mut lz, z.last)] {
                put(v, f);
            }
            for (v, f) in [(&mut mx, x.inc), (&mut my, y.inc), (&mut mz, z.inc)] {
                put(v, f);
            }
            put(&mut p, ahead.p0);
            put(&mut rem, ahead.n);
            let hits = _mm512_movepi64_mask(_mm512_maskz_expand_epi64(take, ahead.hit));
            hit = (hit & !take) | hits;
            live |= take;
            need &= !take;
            ahead.drop_first(take.count_ones());
        }
        if live == 0 {
            break;
        }
        // Walk until a lane ends its ray.
        let ended = loop {
            // SAFETY: this function requires AVX-512F and DQ, all `Lanes` methods need.
            unsafe { lanes.mark(&mut regs, p, live) };
            let was = p;
            // Step: the axis whose crossing comes first (ties x, y, z). An axis past its
            // last crossing gets t = never, so it is never first again.
            let cx = _mm512_cmple_epu64_mask(tx, ty) & _mm512_cmple_epu64_mask(tx, tz);
            let cy = !cx & _mm512_cmple_epu64_mask(ty, tz);
            let cz = !(cx | cy);
            tx = _mm512_mask_add_epi64(tx, cx, tx, dx);
            ty = _mm512_mask_add_epi64(ty, cy, ty, dy);
            tz = _mm512_mask_add_epi64(tz, cz, tz, dz);
            tx = _mm512_mask_mov_epi64(tx, _mm512_mask_cmpgt_epu64_mask(cx, tx, lx), never);
            ty = _mm512_mask_mov_epi64(ty, _mm512_mask_cmpgt_epu64_mask(cy, ty, ly), never);
            tz = _mm512_mask_mov_epi64(tz, _mm512_mask_cmpgt_epu64_mask(cz, tz, lz), never);
            let inc = _mm512_mask_blend_epi64(cx, _mm512_mask_blend_epi64(cy, mz, my), mx);
            p = _mm512_add_epi64(p, inc);
            // SAFETY: as for `mark`.
            unsafe { lanes.stepped(&mut regs, was, p, live) };
            rem = _mm512_sub_epi64(rem, one);
            let end = _mm512_mask_cmpeq_epi64_mask(live, rem, zero);
            if end != 0 {
                regs = lanes.ended(regs, p, end, end & hit);
                live &= !end;
                break end;
            }
        };
        need = ended;
    }
    (to_array(steps).iter().sum(), skipped)
}

/// Rays set up and not yet walked, in the lowest `len` lanes of their vectors. (The axes'
/// `n` are not moved along and not read: the steps left are `n` below. Fields of its own
/// instead of `AxisSetup`s measured 10% slower, for reasons not investigated.)
struct Ahead {
    axes: [AxisSetup; 3],
    p0: __m512i,
    n: __m512i,
    /// All ones in the lanes of rays that hit.
    hit: __m512i,
    len: u32,
}

impl Ahead {
    /// The rays of the lanes in `keep`, moved to the lowest lanes.
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq")]
    fn of(keep: __mmask8, axes: &[AxisSetup; 3], p0: __m512i, n: __m512i, hit: __mmask8) -> Self {
        let c = |v: __m512i| _mm512_maskz_compress_epi64(keep, v);
        Ahead {
            axes: axes.map(|a| AxisSetup {
                t: c(a.t),
                d: c(a.d),
                last: c(a.last),
                inc: c(a.inc),
                n: a.n,
            }),
            p0: c(p0),
            n: c(n),
            hit: c(_mm512_movm_epi64(hit)),
            len: keep.count_ones(),
        }
    }

    /// Drop the first `k` rays.
    #[inline]
    #[target_feature(enable = "avx512f,avx512dq")]
    fn drop_first(&mut self, k: u32) {
        self.len -= k;
        if self.len == 0 {
            return;
        }
        let rest = (((1u32 << self.len) - 1) << k) as __mmask8;
        let c = |v: &mut __m512i| *v = _mm512_maskz_compress_epi64(rest, *v);
        for a in &mut self.axes {
            for v in [&mut a.t, &mut a.d, &mut a.last, &mut a.inc] {
                c(v);
            }
        }
        for v in [&mut self.p0, &mut self.n, &mut self.hit] {
            c(v);
        }
    }
}

/// Start the rays of the lanes in `lanes` where they first leave `c`: the crossings before
/// that made at once (those before its time, [`Covered::skip`], bit for bit), their
/// set-ups `axes` moved on, from the voxel `start`. Returns their steps left (of `n`),
/// each lane's first voxel, and the steps skipped. The crossings made are estimated in
/// doubles and then checked against the exact crossing times.
#[inline(never)]
#[target_feature(enable = "avx512f,avx512dq")]
fn skip_covered(
    c: &Covered,
    lanes: __mmask8,
    start: u64,
    axes: &mut [AxisSetup; 3],
    n: __m512i,
) -> (__m512i, __m512i, u64) {
    let (zero, one, never) = (
        _mm512_setzero_si512(),
        _mm512_set1_epi64(1),
        _mm512_set1_epi64(-1),
    );
    // The first crossing out of the box: per axis the one `leave` crossings on, where the
    // axis has that many (its `n` at least `leave`, so none for an axis without).
    let mut first = never;
    for (a, x) in axes.iter().enumerate() {
        let [down, up] = c.leave[a].map(|k| _mm512_set1_epi64(k as i64 - 1));
        let before = _mm512_mask_blend_epi64(_mm512_cmpgt_epi64_mask(x.inc, zero), down, up);
        let has = _mm512_cmpgt_epu64_mask(x.n, before);
        let at = _mm512_add_epi64(x.t, _mm512_mullo_epi64(x.d, before));
        first = _mm512_mask_min_epu64(first, has, first, at);
    }
    // A ray that never leaves makes all its crossings.
    let ends_inside = _mm512_cmpeq_epi64_mask(first, never);
    let (mut p, mut made) = (_mm512_set1_epi64(start as i64), zero);
    for x in axes.iter_mut() {
        // Crossings before `first`: x.t + j x.d < first for j < k, about
        // (first - x.t) / x.d rounded up, then checked one each way (the estimate is off
        // by far less than one crossing, so only rounding at a tie can miss).
        let due = _mm512_cmpgt_epu64_mask(first, x.t);
        let q = _mm512_div_pd(
            _mm512_cvtepu64_pd(_mm512_sub_epi64(first, x.t)),
            _mm512_cvtepu64_pd(x.d),
        );
        const CEIL: i32 = _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC;
        let est = _mm512_cvttpd_epu64(_mm512_roundscale_pd::<CEIL>(q));
        let k = _mm512_min_epu64(est, x.n);
        let next = _mm512_add_epi64(x.t, _mm512_mullo_epi64(x.d, k));
        let more = _mm512_cmpgt_epu64_mask(x.n, k) & _mm512_cmpgt_epu64_mask(first, next);
        let fewer = _mm512_cmpgt_epu64_mask(k, zero)
            & _mm512_cmpge_epu64_mask(_mm512_sub_epi64(next, x.d), first);
        let k = _mm512_mask_add_epi64(k, more, k, one);
        let k = _mm512_mask_sub_epi64(k, fewer, k, one);
        let k = _mm512_mask_mov_epi64(_mm512_maskz_mov_epi64(due, k), ends_inside, x.n);
        let done = _mm512_cmpeq_epi64_mask(k, x.n) & _mm512_cmpneq_epi64_mask(x.n, zero);
        let next = _mm512_add_epi64(x.t, _mm512_mullo_epi64(x.d, k));
        x.t = _mm512_mask_mov_epi64(next, done, never);
        p = _mm512_add_epi64(p, _mm512_mullo_epi64(k, x.inc));
        made = _mm512_add_epi64(made, k);
    }
    let left = _mm512_sub_epi64(n, made);
    let skipped = _mm512_reduce_add_epi64(_mm512_maskz_mov_epi64(lanes, made)) as u64;
    (left, p, skipped)
}

/// A walk stepped outside its box: a bug, stopped before any read outside the marks.
#[cold]
#[inline(never)]
fn outside_the_box() -> ! {
    panic!("dense walk left its box");
}

/// Give each lane in `dry` (whose rays are used up) the second half of the rays left to the
/// lane with the most, if it has two or more; returns the new cursors and limits. Lanes'
/// ranges can differ much in ray length (the eighth of a scan that sees the far wall
/// against the one that sees the floor): without sharing, the lanes done first would idle
/// until the task's longest range was walked.
#[inline(never)]
fn share(cur: __m512i, lim: __m512i, dry: __mmask8) -> (__m512i, __m512i) {
    let (mut c, mut l) = (to_array(cur), to_array(lim));
    for d in BitIter(u64::from(dry)) {
        let (j, left) = (0..8)
            .map(|j| (j, l[j].saturating_sub(c[j])))
            .max_by_key(|&(_, left)| left)
            .expect("eight lanes");
        if left < 2 {
            break;
        }
        let mid = c[j] + left / 2;
        (c[d], l[d]) = (mid, l[j]);
        l[j] = mid;
    }
    (from_array(c), from_array(l))
}

/// Per-axis constants of the rays' set-up: all rays start at the same origin.
struct Axis {
    o: __m512d,
    s: __m512d,
    up: __m512d,
    down: __m512d,
    stride: __m512i,
}

/// One axis of eight rays' set-up, as `Dda::new` computes it (with `between` capped).
#[derive(Clone, Copy)]
struct AxisSetup {
    /// Crossings: next, between (capped), last; `t` is `never` for an axis without any.
    t: __m512i,
    d: __m512i,
    last: __m512i,
    /// Index increment per step along the axis, and the steps.
    inc: __m512i,
    n: __m512i,
}

impl AxisSetup {
    /// No rays.
    const NONE: AxisSetup = AxisSetup {
        t: per_lane(0),
        d: per_lane(0),
        last: per_lane(0),
        inc: per_lane(0),
        n: per_lane(0),
    };
}

impl Axis {
    /// Lane by lane the same arithmetic as `raycast::axis`, in the same order, so the
    /// results are bit for bit those of `Dda::new`.
    #[inline(always)]
    fn setup(&self, e: __m512d) -> AxisSetup {
        // SAFETY: only called from `walk_dense`, which requires AVX-512F and DQ.
        unsafe { self.setup_impl(e) }
    }

    #[target_feature(enable = "avx512f,avx512dq")]
    fn setup_impl(&self, e: __m512d) -> AxisSetup {
        const FLOOR: i32 = _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC;
        let t = _mm512_roundscale_pd::<FLOOR>(e);
        let n = _mm512_cvttpd_epu64(_mm512_abs_pd(_mm512_sub_pd(t, self.s)));
        let some = _mm512_cmpneq_epi64_mask(n, _mm512_setzero_si512());
        let up = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(t, self.s);
        let inv = _mm512_div_pd(_mm512_set1_pd(1.0), _mm512_abs_pd(_mm512_sub_pd(e, self.o)));
        let face = _mm512_mask_blend_pd(up, self.down, self.up);
        let t0 = _mm512_cvttpd_epu64(_mm512_mul_pd(
            _mm512_mul_pd(face, inv),
            _mm512_set1_pd(T_ONE),
        ));
        // Uncapped, `d` exceeds the cap only when `n` is 1, where `last` does not use it.
        let d = _mm512_min_epu64(
            _mm512_cvttpd_epu64(_mm512_mul_pd(inv, _mm512_set1_pd(T_ONE))),
            _mm512_set1_epi64(T_CAP as i64),
        );
        let last = _mm512_add_epi64(
            t0,
            _mm512_mullo_epi64(d, _mm512_sub_epi64(n, _mm512_set1_epi64(1))),
        );
        let stride = _mm512_mask_sub_epi64(self.stride, !up, _mm512_setzero_si512(), self.stride);
        AxisSetup {
            t: _mm512_mask_mov_epi64(_mm512_set1_epi64(-1), some, t0),
            d,
            last: _mm512_maskz_mov_epi64(some, last),
            inc: _mm512_maskz_mov_epi64(some, stride),
            n,
        }
    }
}

/// `k * l` in lane `l`.
const fn per_lane(k: u64) -> __m512i {
    // SAFETY: __m512i and [u64; 8] are both 64 plain bytes; every bit pattern is valid.
    unsafe { std::mem::transmute([0, k, 2 * k, 3 * k, 4 * k, 5 * k, 6 * k, 7 * k]) }
}

const IOTA: __m512i = per_lane(1);
/// Each lane's first buffer.
const FIRST_BUFFERS: __m512i = per_lane(BUFFERS as u64);

#[inline(always)]
fn from_array(a: [u64; 8]) -> __m512i {
    // SAFETY: as in `to_array`.
    unsafe { std::mem::transmute(a) }
}

#[inline(always)]
fn to_array(v: __m512i) -> [u64; 8] {
    // SAFETY: __m512i and [u64; 8] are both 64 plain bytes; every bit pattern is valid.
    unsafe { std::mem::transmute(v) }
}
