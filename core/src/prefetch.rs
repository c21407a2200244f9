//! A hint to load a cache line ahead of its use, for loops whose loads are independent
//! but too many for an out-of-order core to keep in flight by itself.

/// Ask for the cache line holding `items[i]`, if there is one, to be loaded.
#[inline(always)]
pub(crate) fn prefetch<T>(items: &[T], i: usize) {
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
