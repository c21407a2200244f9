//! Cache lines asked for ahead of their use: a hint to load one, for loops whose loads are
//! independent but too many for an out-of-order core to keep in flight by itself; and
//! lines made this core's by a store each, for loops whose stores would wait on them.

/// Ask for the cache line holding `items[i]`, if there is one, to be loaded.
#[inline(always)]
pub fn prefetch<T>(items: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(item) = items.get(i) {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: `_mm_prefetch` needs SSE, which every x86_64 CPU has. A prefetch is a
        // hint: it reads nothing into the program and cannot fault, and the address is
        // inside `items` anyway.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(item).cast()) };
    }
    // Elsewhere no prefetch (Arm's is not stable Rust): the loads are still independent,
    // so an out-of-order core overlaps some of them.
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (items, i);
}

/// Store a zero element in each cache line of `items` (64-byte lines), so
/// that the lines are this core's, modified, before a loop stores to them among other
/// work. A buffer another core read or wrote last (a frame's rays, read by every thread of
/// the walk) has each line's ownership fetched from that core by the first store to it;
/// from a loop with several stores a line, few of those fetches overlap, where one store a
/// line keeps many in flight. Overwrites what `items` held, so only for a buffer that is
/// about to be written anyway.
pub fn own_lines<T: bytemuck::Zeroable>(items: &mut [T]) {
    const LINE: usize = 64;
    let size = std::mem::size_of::<T>();
    if size == 0 || items.is_empty() {
        return;
    }
    // The first element, then the element holding each later line's first byte.
    let base = items.as_ptr() as usize;
    let end = base + std::mem::size_of_val(items);
    let starts = (base / LINE + 1..)
        .map(|l| l * LINE)
        .take_while(|&b| b < end);
    for i in std::iter::once(0).chain(starts.map(|b| (b - base) / size)) {
        // SAFETY: the pointer comes from a live `&mut` element (indexing checks `i`),
        // valid and aligned; an all-zero `T` is a valid value (`Zeroable`). Volatile: the
        // compiler must not drop a store that a later one overwrites, as the store is
        // the point.
        unsafe { std::ptr::write_volatile(&raw mut items[i], T::zeroed()) }
    }
}

#[cfg(test)]
mod tests {
    use super::own_lines;

    /// Every 64-byte line of the slice gets a zero, and nothing outside it changes, for
    /// elements of several sizes and a slice starting anywhere in a line.
    #[test]
    fn own_lines_writes_each_line_of_the_slice_only() {
        fn check<T: bytemuck::Pod + PartialEq + std::fmt::Debug>(one: T) {
            let size = std::mem::size_of::<T>();
            for start in 0..8 {
                for len in [0, 1, 2, 15, 16, 17, 100] {
                    let mut v = [one; 120];
                    own_lines(&mut v[start..start + len]);
                    let zero = T::zeroed();
                    assert!(v[..start]
                        .iter()
                        .chain(&v[start + len..])
                        .all(|x| *x == one));
                    // Each line the slice's bytes cover overlaps a zero element of it.
                    let lines = |i: usize| {
                        let b = v.as_ptr() as usize + i * size;
                        b / 64..=(b + size - 1) / 64
                    };
                    for i in start..start + len {
                        for line in lines(i) {
                            let zeroed = (start..start + len)
                                .any(|j| lines(j).contains(&line) && v[j] == zero);
                            assert!(zeroed, "a line of {size}-byte elements not written");
                        }
                    }
                }
            }
        }
        check(1u8);
        check(1u32);
        check([1u64; 3]);
        check([1u64; 4]);
        check([1u8; 100]);
    }
}
