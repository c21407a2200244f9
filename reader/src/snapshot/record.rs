//! A leaf's mask record: its known and occupied masks, each in the smallest of a few
//! encodings, all readable one voxel at a time in O(1).
//!
//! A mask's *kind* (kept in its leaf's entry, see `layout::LeafEntry`) says how it is
//! stored:
//!
//! | kind | known mask                           | occupied mask      | data           |
//! |------|--------------------------------------|--------------------|----------------|
//! | 0    | all 512 voxels known                 | none occupied      | none           |
//! | 1    | dense                                | dense              | 64 bytes       |
//! | 2-4  | rows along x, y, z                   | rows along x, y, z | presence, rows |
//! | 5-7  | unknown voxels as rows along x, y, z | (invalid)          | presence, rows |
//!
//! A *row* is the 8 voxels of a leaf along one axis; rows along axis `a` are numbered by
//! the other two coordinates, lower axis first (`y | z << 3` for x). A row mask has a
//! `u64` presence word, bit `r` set when row `r` has a set voxel, and one byte per present
//! row in ascending order, bit = the voxel's coordinate along `a`. Dense data is the
//! 512-bit mask itself: rows along x with every row present.
//!
//! ```text
//! record = [known presence] [occupied presence] known bytes, occupied bytes
//! ```
//!
//! The presence words come first, at offsets the kinds give, so neither mask's data waits
//! on the other's length being read.
//!
//! Why rows, and along any axis: a partly known leaf far from the sensor is crossed by a
//! few nearly parallel rays, and a ray's voxels share rows along its main axis. On the
//! 500k-point 60 m random frame this cuts the masks by 42%, and the snapshot from 0.78 to
//! 0.53 bytes per known voxel. The price is a dependent load per query (presence word,
//! then row byte, where a dense mask needs one load): a point query on the cache-resident
//! 6 m map went from 20-26 to 28-36 ns.

use crate::mask::Mask512;

/// The largest kind an occupied mask may have (a known mask may have any of 0-7).
pub const MAX_OCCUPIED_KIND: u8 = 4;

/// Transpose an 8x8 bit matrix held as byte `i` = row `i`, bit `j` = column `j`.
#[inline(always)]
fn transpose8(mut x: u64) -> u64 {
    let t = (x ^ (x >> 7)) & 0x00AA_00AA_00AA_00AA;
    x ^= t ^ (t << 7);
    let t = (x ^ (x >> 14)) & 0x0000_CCCC_0000_CCCC;
    x ^= t ^ (t << 14);
    let t = (x ^ (x >> 28)) & 0x0000_0000_F0F0_F0F0;
    x ^ t ^ (t << 28)
}

/// Byte `y` of each word, gathered into one word (byte `z` from word `z`).
#[inline(always)]
fn gather_bytes(words: &[u64; 8], y: usize) -> u64 {
    words
        .iter()
        .enumerate()
        .fold(0, |acc, (z, w)| acc | (w >> (8 * y) & 0xff) << (8 * z))
}

/// The mask's rows along `axis` (0, 1, 2), as 64 bytes held in 8 words (row `r` is byte
/// `r & 7` of word `r >> 3`).
#[inline(always)]
fn to_rows(m: &Mask512, axis: u8) -> [u64; 8] {
    match axis {
        0 => m.words,
        // Plane z, transposed: byte x holds bits y.
        1 => m.words.map(transpose8),
        // For each y, the (z, x) matrix transposed: byte x holds bits z.
        _ => std::array::from_fn(|y| transpose8(gather_bytes(&m.words, y))),
    }
}

/// Inverse of [`to_rows`].
fn from_rows(rows: &[u64; 8], axis: u8) -> Mask512 {
    let words = match axis {
        0 => *rows,
        1 => rows.map(transpose8),
        _ => {
            let planes = rows.map(transpose8); // planes[y]: byte z holds bits x
            std::array::from_fn(|z| gather_bytes(&planes, z))
        }
    };
    Mask512 { words }
}

/// Bit `i` of a word per non-zero byte of `v`.
#[inline(always)]
fn nonzero_bytes(v: u64) -> u8 {
    const LOW7: u64 = 0x7F7F_7F7F_7F7F_7F7F;
    let high = (v | ((v & LOW7) + LOW7)) & !LOW7;
    ((high >> 7).wrapping_mul(0x0102_0408_1020_4080) >> 56) as u8
}

/// The presence word of `rows`.
#[inline(always)]
fn presence(rows: &[u64; 8]) -> u64 {
    rows.iter()
        .enumerate()
        .fold(0, |p, (i, &w)| p | u64::from(nonzero_bytes(w)) << (8 * i))
}

#[cfg(test)]
/// The presence word of the mask's rows along `axis`, without building the rows: a row
/// along y is present when its column bit is set in any byte of its plane's word, a row
/// along z when its bit is set in any word.
pub fn presence_of(m: &Mask512, axis: u8) -> u64 {
    match axis {
        0 => presence(&m.words),
        1 => m.words.iter().enumerate().fold(0, |p, (z, &w)| {
            let w = w | w >> 32;
            let w = w | w >> 16;
            p | ((w | w >> 8) & 0xff) << (8 * z)
        }),
        _ => m.words.iter().fold(0, |p, &w| p | w),
    }
}

/// Where a voxel index's coordinates go for rows along one axis: the row is the two
/// other coordinates (shifted out of `i` by `lo` and `hi`), the bit the axis's own.
#[derive(Clone, Copy, Debug)]
struct Shifts {
    lo: u8,
    hi: u8,
    bit: u8,
}

impl Shifts {
    #[inline]
    fn of(axis: u8) -> Self {
        // x, y, z sit at bits 0, 3 and 6 of a voxel index. Arithmetic rather than a table:
        // a table load would add its latency to every query.
        Shifts {
            lo: if axis == 0 { 3 } else { 0 },
            hi: if axis == 2 { 3 } else { 6 },
            bit: 3 * (axis % 3),
        }
    }

    #[inline]
    fn row_bit(self, i: usize) -> (u32, u32) {
        let i = i as u32;
        (
            (i >> self.lo & 7) | (i >> self.hi & 7) << 3,
            i >> self.bit & 7,
        )
    }
}

/// Axis and complement of a kind >= 2.
#[inline]
fn rows_kind(kind: u8) -> (u8, bool) {
    (axis_of(kind), kind >= 5)
}

/// The axis of a row kind; 0 (rows along x) for dense and empty masks.
#[inline]
fn axis_of(kind: u8) -> u8 {
    kind.wrapping_sub(2) % 3 * u8::from(kind >= 2)
}

/// The presence word of a kind without one stored: kind 0 has no rows, dense all 64.
#[inline]
fn fixed_presence(kind: u8) -> u64 {
    0u64.wrapping_sub(u64::from(kind == 1))
}

/// A mask chosen for a record: its kind and data length.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Choice {
    pub kind: u8,
    pub len: u32,
}

/// Rows present along x, y and z, in the mask (`[0..3]`) and in its complement
/// (`[3..6]`), in one pass: a row of the complement is present where the mask's row is
/// not full, so AND-folds count those as OR-folds count the mask's.
#[inline(always)]
fn row_counts(m: &Mask512) -> [u32; 6] {
    let (mut x, mut y, mut ix, mut iy) = (0, 0, 0, 0);
    let (mut any, mut all) = (0u64, !0u64);
    for &w in &m.words {
        x += nonzero_bytes(w).count_ones();
        ix += nonzero_bytes(!w).count_ones();
        let (o, a) = (w | w >> 32, w & w >> 32);
        let (o, a) = (o | o >> 16, a & a >> 16);
        y += ((o | o >> 8) & 0xff).count_ones();
        iy += 8 - ((a & a >> 8) & 0xff).count_ones();
        any |= w;
        all &= w;
    }
    [x, y, any.count_ones(), ix, iy, 64 - all.count_ones()]
}

/// The smallest encoding of a known mask.
#[inline(always)]
pub fn choose_known(m: &Mask512) -> Choice {
    if m.words.iter().all(|&w| w == !0) {
        return Choice { kind: 0, len: 0 };
    }
    smallest(&row_counts(m))
}

/// The smallest encoding of an occupied mask.
#[inline(always)]
pub fn choose_occupied(m: &Mask512) -> Choice {
    if m.is_empty() {
        return Choice { kind: 0, len: 0 };
    }
    // Kinds 5-7 (complemented rows) are for known masks only.
    let c = row_counts(m);
    smallest(&[c[0], c[1], c[2], 64, 64, 64])
}

/// Dense, or the rows (kinds 2 + i for `rows[i]`) that take fewer bytes.
#[inline(always)]
fn smallest(rows: &[u32; 6]) -> Choice {
    let mut best = Choice { kind: 1, len: 64 };
    for (i, &n) in rows.iter().enumerate() {
        if 8 + n < best.len {
            best = Choice {
                kind: 2 + i as u8,
                len: 8 + n,
            };
        }
    }
    best
}

/// The record's bytes for masks of the given kinds (the kinds chosen for them); returns
/// the length written at the start of `out`. With `avx512`, rows are compressed with one
/// VBMI2 store.
#[inline(always)]
pub fn encode(
    known: &Mask512,
    known_kind: u8,
    occupied: &Mask512,
    occupied_kind: u8,
    out: &mut [u8],
    avx512: Option<Avx512Encode>,
) -> usize {
    let rows_of = |m: &Mask512, kind: u8| -> [u64; 8] {
        match kind {
            0 => [0; 8],
            1 => m.words,
            _ => {
                let (axis, complement) = rows_kind(kind);
                let src = if complement {
                    Mask512 {
                        words: m.words.map(|w| !w),
                    }
                } else {
                    *m
                };
                to_rows(&src, axis)
            }
        }
    };
    let masks = [
        (rows_of(known, known_kind), known_kind),
        (rows_of(occupied, occupied_kind), occupied_kind),
    ];
    let presences = masks.map(|(rows, _)| presence(&rows));
    let mut at = 0;
    for ((_, kind), p) in masks.iter().zip(presences) {
        if *kind >= 2 {
            out[at..at + 8].copy_from_slice(&p.to_le_bytes());
            at += 8;
        }
    }
    for ((rows, kind), p) in masks.iter().zip(presences) {
        let bytes: &[u8] = bytemuck::cast_slice(rows);
        match kind {
            0 => {}
            1 => {
                out[at..at + 64].copy_from_slice(bytes);
                at += 64;
            }
            _ => at += compress_rows(rows, p, &mut out[at..], avx512),
        }
    }
    at
}

/// Write the bytes of `rows` whose bit is set in `present`, in order, at the start of
/// `out`; returns how many. With AVX-512 VBMI2 one compressing store: the whole-map encode
/// of the random 500k 60 m map took 277-305 ms against 314-389 (minimum of 12 encodes,
/// three alternated probe runs).
#[inline(always)]
fn compress_rows(
    rows: &[u64; 8],
    present: u64,
    out: &mut [u8],
    avx512: Option<Avx512Encode>,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    if avx512.is_some() {
        let n = present.count_ones() as usize;
        assert!(n <= out.len(), "record shorter than its rows");
        // SAFETY: an `Avx512Encode` exists only where the CPU has AVX-512F and VBMI2
        // (`Avx512Encode::new`), and n <= out.len() (checked above).
        return unsafe { compress_rows_vbmi2(rows, present, out) };
    }
    let _ = avx512;
    let bytes: &[u8] = bytemuck::cast_slice(rows);
    let mut at = 0;
    for r in crate::mask::BitIter(present) {
        out[at] = bytes[r];
        at += 1;
    }
    at
}

/// Proof that the CPU has AVX-512F and VBMI2, so that the record encoder may compress rows
/// with one store. Made by the map crate's AVX-512 snapshot encoder, which enables those
/// features, and by the tests after checking the CPU.
#[derive(Clone, Copy, Debug)]
pub struct Avx512Encode(());

impl Avx512Encode {
    /// # Safety
    /// The CPU must have AVX-512F and VBMI2.
    pub unsafe fn new() -> Avx512Encode {
        Avx512Encode(())
    }
}

/// # Safety
/// The CPU must have AVX-512F and VBMI2, and `out` must hold `present.count_ones()` bytes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vbmi2")]
unsafe fn compress_rows_vbmi2(rows: &[u64; 8], present: u64, out: &mut [u8]) -> usize {
    use std::arch::x86_64::*;
    // SAFETY: the load reads the 64 bytes of `rows`; the compressing store writes
    // `present.count_ones()` bytes from `out`'s start, which the caller guarantees fit.
    unsafe {
        let v = _mm512_loadu_si512(rows.as_ptr().cast());
        _mm512_mask_compressstoreu_epi8(out.as_mut_ptr().cast(), present, v);
    }
    present.count_ones() as usize
}

/// A mask inside a record, ready to answer per-voxel reads from `bytes` (the masks
/// section). Reads outside `bytes` see zeros, so corrupt data gives wrong bits, never a
/// panic.
#[derive(Clone, Copy, Debug)]
pub struct MaskRef {
    axis: u8,
    complement: bool,
    presence: u64,
    /// Offset of the first row byte.
    data: u64,
    /// Offset just past this mask's data.
    end: u64,
}

#[inline]
fn byte_at(bytes: &[u8], at: u64) -> u8 {
    usize::try_from(at)
        .ok()
        .and_then(|a| bytes.get(a))
        .copied()
        .unwrap_or(0)
}

#[inline]
fn u64_at(bytes: &[u8], at: u64) -> u64 {
    usize::try_from(at)
        .ok()
        .and_then(|a| bytes.get(a..a.checked_add(8)?))
        .map_or(0, |b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
}

impl MaskRef {
    /// A mask of `kind`, given the presence word loaded for it (used for row kinds only)
    /// and its data offset.
    #[inline]
    fn new(kind: u8, loaded: u64, data: u64) -> Self {
        let presence = if kind >= 2 {
            loaded
        } else {
            fixed_presence(kind)
        };
        MaskRef {
            axis: axis_of(kind),
            complement: kind >= 5,
            presence,
            data,
            end: data + u64::from(presence.count_ones()),
        }
    }

    /// The whole mask.
    pub fn decode(&self, bytes: &[u8]) -> Mask512 {
        let mut rows = [0u64; 8];
        for (k, r) in crate::mask::BitIter(self.presence).enumerate() {
            rows[r >> 3] |= u64::from(byte_at(bytes, self.data + k as u64)) << (8 * (r & 7));
        }
        let m = from_rows(&rows, self.axis);
        if self.complement {
            Mask512 {
                words: m.words.map(|w| !w),
            }
        } else {
            m
        }
    }
}

/// The known and occupied masks of the record at `at` with these kinds.
#[inline]
pub fn masks_at(bytes: &[u8], at: u64, known_kind: u8, occupied_kind: u8) -> (MaskRef, MaskRef) {
    let known_rows = u64::from(known_kind >= 2);
    let occupied_rows = u64::from(occupied_kind >= 2);
    let known_presence = u64_at(bytes, at);
    let occupied_presence = u64_at(bytes, at + 8 * known_rows);
    let data = at + 8 * (known_rows + occupied_rows);
    let mut known = MaskRef::new(known_kind, known_presence, data);
    // Kind 0 of a known mask: all known, the complement of nothing stored.
    known.complement |= known_kind == 0;
    let occupied = MaskRef::new(occupied_kind, occupied_presence, known.end);
    (known, occupied)
}

/// (known, occupied) of voxel `i` in the record at `at`: [`masks_at`] and
/// [`MaskRef::get`] with only the work a point query needs.
#[inline]
pub fn voxel_bits(
    bytes: &[u8],
    at: u64,
    known_kind: u8,
    occupied_kind: u8,
    i: usize,
) -> (bool, bool) {
    let (known_rows, occupied_rows) = (known_kind >= 2, occupied_kind >= 2);
    let known_presence = if known_rows {
        u64_at(bytes, at)
    } else {
        fixed_presence(known_kind)
    };
    let data = at + 8 * (u64::from(known_rows) + u64::from(occupied_rows));
    let known =
        bit(bytes, known_kind, known_presence, data, i) != (known_kind == 0 || known_kind >= 5);
    if !known || occupied_kind == 0 {
        return (known, false);
    }
    let occupied_presence = if occupied_rows {
        u64_at(bytes, at + 8 * u64::from(known_rows))
    } else {
        !0
    };
    let occupied_data = data + u64::from(known_presence.count_ones());
    (
        known,
        bit(bytes, occupied_kind, occupied_presence, occupied_data, i),
    )
}

/// Voxel `i` of a mask of `kind` with this presence word and data.
#[inline]
fn bit(bytes: &[u8], kind: u8, presence: u64, data: u64, i: usize) -> bool {
    let (r, b) = Shifts::of(axis_of(kind)).row_bit(i);
    let below = (presence & ((1u64 << r) - 1)).count_ones();
    presence >> r & 1 != 0 && byte_at(bytes, data + u64::from(below)) >> b & 1 != 0
}

/// Length of the record at `at` with these kinds, if the kinds are valid and the record
/// lies within `bytes`.
pub fn checked_len(bytes: &[u8], at: u64, known_kind: u8, occupied_kind: u8) -> Option<u64> {
    if known_kind > 7 || occupied_kind > MAX_OCCUPIED_KIND {
        return None;
    }
    let words = 8 * u64::from(known_kind >= 2) + 8 * u64::from(occupied_kind >= 2);
    // The presence words themselves must be inside before they are read.
    if at.checked_add(words)? > bytes.len() as u64 {
        return None;
    }
    let end = masks_at(bytes, at, known_kind, occupied_kind).1.end;
    (end <= bytes.len() as u64).then_some(end - at)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::Rng;

    fn random_mask(r: &mut Rng, density: f64) -> Mask512 {
        let mut m = Mask512::EMPTY;
        for i in 0..512 {
            if r.f() < density {
                m.set(i);
            }
        }
        m
    }

    #[test]
    fn rows_round_trip_and_match_row_bit() {
        let mut r = Rng(5);
        for _ in 0..200 {
            let d = r.f();
            let m = random_mask(&mut r, d);
            for axis in 0..3 {
                let rows = to_rows(&m, axis);
                assert_eq!(from_rows(&rows, axis), m);
                let bytes: &[u8] = bytemuck::cast_slice(&rows);
                for i in 0..512 {
                    let (row, bit) = Shifts::of(axis).row_bit(i);
                    assert_eq!(bytes[row as usize] >> bit & 1 != 0, m.get(i));
                }
                let p = presence(&rows);
                assert_eq!(presence_of(&m, axis), p);
                let inv = Mask512 {
                    words: m.words.map(|w| !w),
                };
                let counts = row_counts(&m);
                assert_eq!(counts[axis as usize], p.count_ones());
                assert_eq!(
                    counts[3 + axis as usize],
                    presence_of(&inv, axis).count_ones()
                );
                for (row, &b) in bytes.iter().enumerate() {
                    assert_eq!(p >> row & 1 != 0, b != 0);
                }
            }
        }
    }

    #[test]
    fn records_read_back_every_voxel_and_choose_the_smallest() {
        let mut r = Rng(8);
        let mut kinds = [0usize; 8];
        let mut masks = vec![
            (Mask512 { words: [!0; 8] }, Mask512::EMPTY),
            (Mask512 { words: [!0; 8] }, random_mask(&mut r, 0.5)),
        ];
        for _ in 0..600 {
            let mut known = Mask512::EMPTY;
            // Lines along a random axis, like rays through a leaf.
            let axis = (r.f() * 3.0) as usize;
            for _ in 0..(r.f() * 20.0) as usize {
                let (a, b) = ((r.f() * 8.0) as usize, (r.f() * 8.0) as usize);
                for t in 0..8 {
                    let c = match axis {
                        0 => [t, a, b],
                        1 => [a, t, b],
                        _ => [a, b, t],
                    };
                    known.set(c[0] | c[1] << 3 | c[2] << 6);
                }
            }
            if r.f() < 0.3 {
                known = Mask512 {
                    words: known.words.map(|w| !w),
                };
            }
            if r.f() < 0.2 {
                let d = r.f();
                known = random_mask(&mut r, d);
            }
            let d = r.f() * 0.05;
            let mut occ = random_mask(&mut r, d);
            occ.words
                .iter_mut()
                .zip(known.words)
                .for_each(|(o, k)| *o &= k);
            masks.push((known, occ));
        }
        #[cfg(target_arch = "x86_64")]
        let vbmi2 = std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512vbmi2");
        #[cfg(not(target_arch = "x86_64"))]
        let vbmi2 = false;
        let avx512 = if vbmi2 {
            // SAFETY: the CPU has AVX-512F and VBMI2 (checked above).
            Some(unsafe { Avx512Encode::new() })
        } else {
            use std::io::Write;
            let _ = writeln!(
                std::io::stderr(),
                "NOTICE: the AVX-512 record encoder is skipped: this CPU lacks AVX-512 VBMI2"
            );
            None
        };
        for (known, occ) in masks {
            let (ck, co) = (choose_known(&known), choose_occupied(&occ));
            kinds[ck.kind as usize] += 1;
            let at = 3usize;
            let mut rec = vec![0xAAu8; at + (ck.len + co.len) as usize];
            let len = encode(&known, ck.kind, &occ, co.kind, &mut rec[at..], None);
            assert_eq!(len, (ck.len + co.len) as usize);
            // The AVX-512 encoder, where this CPU has it, writes the same bytes.
            if let Some(t) = avx512 {
                let mut vec_rec = vec![0xAAu8; rec.len()];
                let n = encode(&known, ck.kind, &occ, co.kind, &mut vec_rec[at..], Some(t));
                assert_eq!((n, &vec_rec), (len, &rec));
            }
            let len = Some(len as u64);
            assert_eq!(checked_len(&rec, at as u64, ck.kind, co.kind), len);
            let (k, o) = masks_at(&rec, at as u64, ck.kind, co.kind);
            assert_eq!(k.decode(&rec), known);
            assert_eq!(o.decode(&rec), occ);
            for i in 0..512 {
                let (kb, ob) = voxel_bits(&rec, at as u64, ck.kind, co.kind, i);
                assert_eq!((kb, ob), (known.get(i), occ.get(i) && known.get(i)));
            }
            // Every other encoding is at least as long.
            assert!(ck.len <= 64 && co.len <= 64);
            for axis in 0..3 {
                assert!(ck.len == 0 || ck.len <= 8 + presence_of(&known, axis).count_ones());
                assert!(co.len == 0 || co.len <= 8 + presence_of(&occ, axis).count_ones());
            }
        }
        // Lines along each axis, full leaves and dense random masks all occur.
        assert!(kinds[0] > 0 && kinds[1] > 0);
        assert!(kinds[2..5].iter().all(|&n| n > 0), "{kinds:?}");
        assert!(kinds[5..8].iter().any(|&n| n > 0), "{kinds:?}");
    }

    #[test]
    fn bad_kinds_and_short_records_are_refused() {
        assert_eq!(checked_len(&[], 0, 0, 0), Some(0));
        assert_eq!(checked_len(&[], 1, 0, 0), None);
        assert_eq!(checked_len(&[0; 64], 0, 0, 5), None); // occupied kind 5
        assert_eq!(checked_len(&[0; 64], 0, 8, 0), None);
        assert_eq!(checked_len(&[0; 63], 0, 1, 0), None); // dense known mask cut short
        assert_eq!(checked_len(&[1, 0, 0, 0, 0, 0, 0], 0, 2, 0), None); // presence cut short
        let mut rec = vec![3u8, 0, 0, 0, 0, 0, 0, 0, 0xff];
        assert_eq!(checked_len(&rec, 0, 2, 0), None); // two rows present, one stored
        rec.push(1);
        assert_eq!(checked_len(&rec, 0, 2, 0), Some(10));
        assert_eq!(checked_len(&rec, 0, 2, 2), None);
    }
}
