//! Fixed-size bitmasks: which voxels of a leaf (or children of a node) are active.

/// 512 bits: one per voxel of an 8x8x8 leaf, bit `x | y << 3 | z << 6` (so word `z`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Zeroable, bytemuck::Pod)]
#[repr(transparent)]
pub struct Mask512 {
    pub words: [u64; 8],
}

impl Mask512 {
    pub const EMPTY: Self = Self { words: [0; 8] };
    pub const FULL: Self = Self { words: [!0; 8] };

    #[inline]
    pub fn get(&self, i: usize) -> bool {
        self.words[i >> 6] >> (i & 63) & 1 != 0
    }

    #[inline]
    pub fn set(&mut self, i: usize) {
        self.words[i >> 6] |= 1 << (i & 63);
    }

    #[inline]
    pub fn clear(&mut self, i: usize) {
        self.words[i >> 6] &= !(1 << (i & 63));
    }

    /// The bits set in both.
    #[inline]
    pub fn and(&self, other: &Self) -> Self {
        Self {
            words: std::array::from_fn(|w| self.words[w] & other.words[w]),
        }
    }

    pub fn count(&self) -> u32 {
        self.words.iter().map(|w| w.count_ones()).sum()
    }

    /// The bits set below bit `i`: the place of bit `i` among the set bits.
    #[inline]
    pub fn rank(&self, i: usize) -> u32 {
        let (w, b) = (i >> 6 & 7, i & 63);
        let below: u32 = self.words[..w].iter().map(|x| x.count_ones()).sum();
        below + (self.words[w] & ((1u64 << b) - 1)).count_ones()
    }

    pub fn is_empty(&self) -> bool {
        self.words.iter().all(|&w| w == 0)
    }

    /// The in-leaf coordinates (0..8 per axis) of the smallest box holding every set bit,
    /// as (min, max) inclusive; `None` when empty. Read from the words and rows, not bit by
    /// bit.
    #[inline(always)]
    pub fn extent(&self) -> Option<([i32; 3], [i32; 3])> {
        // Bit x|y<<3 of a word; word index z.
        let (mut xs, mut ys, mut zs) = (0u8, 0u8, 0u8);
        for (z, &w) in self.words.iter().enumerate() {
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
            return None;
        }
        let lo = [xs, ys, zs].map(|m| m.trailing_zeros() as i32);
        let hi = [xs, ys, zs].map(|m| 7 - m.leading_zeros() as i32);
        Some((lo, hi))
    }

    /// Indices of the set bits, ascending.
    pub fn iter_ones(&self) -> impl Iterator<Item = usize> + '_ {
        self.words
            .iter()
            .enumerate()
            .flat_map(|(wi, &w)| BitIter(w).map(move |b| wi * 64 + b))
    }
}

/// The set bits of one word, ascending, popping the lowest with `w &= w - 1`.
#[derive(Clone, Copy)]
pub struct BitIter(pub u64);

impl Iterator for BitIter {
    type Item = usize;
    #[inline]
    fn next(&mut self) -> Option<usize> {
        if self.0 == 0 {
            return None;
        }
        let b = self.0.trailing_zeros() as usize;
        self.0 &= self.0 - 1;
        Some(b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_get_iterate() {
        let mut m = Mask512::EMPTY;
        for i in [0, 63, 64, 200, 511] {
            m.set(i);
        }
        assert!(m.get(200) && !m.get(201));
        assert_eq!(m.count(), 5);
        assert_eq!(m.iter_ones().collect::<Vec<_>>(), vec![0, 63, 64, 200, 511]);
        m.clear(63);
        assert!(!m.get(63));
        assert_eq!(m.count(), 4);
    }
}
