//! Big zeroed arrays mapped straight from the kernel and advised onto 2 MiB pages.
//!
//! The map's leaf pool and the frame marks' pools hold hundreds of MiB at 60 m and are
//! read in no cache-friendly order. On 4 KiB pages nearly every such access also misses
//! the TLB, and a fresh map's first writes fault once per 4 KiB. Each [`Zeroed`] is its own
//! anonymous mapping, aligned to 2 MiB and advised `MADV_HUGEPAGE`, so that where the
//! kernel has transparent huge pages set to `madvise` (the usual default) or `always`, it
//! backs the array with 2 MiB pages. Where it has not, this is an ordinary zeroed array.
//! An array that may stay mostly unused comes from the global allocator instead
//! ([`Zeroed::from_allocator`]).

use std::ptr::NonNull;

/// Bytes of a huge page.
pub(crate) const HUGE_PAGE: usize = 2 << 20;

/// A fixed-length array of all-zero `T`, owned like a `Box<[T]>`.
pub(crate) struct Zeroed<T> {
    ptr: NonNull<T>,
    len: usize,
    /// The whole mapping (start, bytes), or (null, 0) when the array is a `Box<[T]>` from
    /// the global allocator (leaked into `ptr`, `len`).
    map: (*mut libc::c_void, usize),
}

// SAFETY: a `Zeroed<T>` owns its elements exclusively, as a `Box<[T]>` does; the raw
// pointers are only the address of that memory.
unsafe impl<T: Send> Send for Zeroed<T> {}
// SAFETY: as above; shared access hands out only `&[T]`.
unsafe impl<T: Sync> Sync for Zeroed<T> {}

impl<T: bytemuck::Zeroable> Zeroed<T> {
    /// `len` zeroed elements on huge pages where the kernel grants them. Aborts like any
    /// allocation when the memory is not there.
    pub(crate) fn new(len: usize) -> Self {
        Self::alloc(len, true)
    }

    /// `len` zeroed elements from the global allocator: for an array that may stay mostly
    /// unused, where a huge page would fault in (and zero) 2 MiB on its first write, and
    /// where memory a freed array held may be handed back at once (unless the process's
    /// allocator keeps freed memory, as the service's does).
    pub(crate) fn from_allocator(len: usize) -> Self {
        Self::alloc(len, false)
    }

    fn alloc(len: usize, huge: bool) -> Self {
        if huge {
            Self::new_many(len, 1).pop().expect("one array")
        } else {
            Self::boxed(len)
        }
    }

    fn boxed(len: usize) -> Self {
        let heap: Box<[T]> = bytemuck::allocation::zeroed_slice_box(len);
        Zeroed {
            ptr: NonNull::new(Box::into_raw(heap).cast()).expect("a box is non-null"),
            len,
            map: (std::ptr::null_mut(), 0),
        }
    }

    /// `count` arrays of `len` zeroed elements, as [`Self::new`] makes one, from one
    /// mapping and one advice for all: two system calls, not two per array. Each array
    /// owns its part of the mapping (the first one also the slack before, the last one
    /// the slack after), which it unmaps alone.
    pub(crate) fn new_many(len: usize, count: usize) -> Vec<Self> {
        const {
            assert!(!std::mem::needs_drop::<T>());
            assert!(std::mem::align_of::<T>() <= 4096);
        }
        let layout = std::alloc::Layout::array::<T>(len).expect("array size overflows");
        if layout.size() == 0 || count == 0 {
            return (0..count).map(|_| Self::boxed(len)).collect();
        }
        let used = layout.size().next_multiple_of(HUGE_PAGE);
        let all = used.checked_mul(count).expect("arrays' size overflows");
        // One huge page more than needed, so that an aligned run of `all` bytes fits.
        let map_len = all + HUGE_PAGE;
        // SAFETY: a new private anonymous mapping, which touches no existing memory.
        let p = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                map_len,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                -1,
                0,
            )
        };
        if p == libc::MAP_FAILED {
            std::alloc::handle_alloc_error(layout);
        }
        let skip = (p as usize).next_multiple_of(HUGE_PAGE) - p as usize;
        // SAFETY: skip < HUGE_PAGE, so the run [p + skip, p + skip + all) lies inside the
        // mapping of all + HUGE_PAGE bytes.
        let start = unsafe { p.cast::<u8>().add(skip) };
        #[cfg(target_os = "linux")]
        // SAFETY: advice on part of our own mapping; it never changes contents, and a
        // refusal (no transparent huge pages) leaves ordinary pages, so the result is
        // ignored.
        unsafe {
            libc::madvise(start.cast(), all, libc::MADV_HUGEPAGE);
        }
        let end = p as usize + map_len;
        (0..count)
            .map(|i| {
                // SAFETY: i * used < all: the array's run lies inside the aligned run.
                let at = unsafe { start.add(i * used) };
                let from = if i == 0 { p as usize } else { at as usize };
                let to = if i + 1 == count {
                    end
                } else {
                    at as usize + used
                };
                Zeroed {
                    ptr: NonNull::new(at.cast()).expect("mmap returned a non-null address"),
                    len,
                    map: (from as *mut libc::c_void, to - from),
                }
            })
            .collect()
    }
}

impl<T> std::ops::Deref for Zeroed<T> {
    type Target = [T];

    #[inline]
    fn deref(&self) -> &[T] {
        // SAFETY: `ptr` and `len` are those of a `Box<[T]>` we own, or `ptr` is page-aligned
        // (enough for T, checked in `alloc`) and the `len` elements lie in our mapping, whose
        // fresh pages read as zero, a valid T (T: Zeroable); `&self` guarantees no `&mut`
        // to them is live.
        unsafe { std::slice::from_raw_parts(self.ptr.as_ptr(), self.len) }
    }
}

impl<T> std::ops::DerefMut for Zeroed<T> {
    #[inline]
    fn deref_mut(&mut self) -> &mut [T] {
        // SAFETY: as in `deref`, and `&mut self` makes this the only access.
        unsafe { std::slice::from_raw_parts_mut(self.ptr.as_ptr(), self.len) }
    }
}

impl<T> Drop for Zeroed<T> {
    fn drop(&mut self) {
        if self.map.1 != 0 {
            // SAFETY: unmaps exactly this array's part of the mapping `new_many` made, once
            // (page-aligned: the mapping's start, or a multiple of a huge page from it); T
            // has no drop glue, and no reference into it outlives `self`.
            unsafe {
                libc::munmap(self.map.0, self.map.1);
            }
        } else {
            let slice = std::ptr::slice_from_raw_parts_mut(self.ptr.as_ptr(), self.len);
            // SAFETY: `ptr` and `len` came from `Box::into_raw` in `alloc` and are given
            // back once, here.
            drop(unsafe { Box::from_raw(slice) });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_mapped_together_are_apart_zeroed_and_freed_one_by_one() {
        let mut many = Zeroed::<u64>::new_many(HUGE_PAGE / 8 + 3, 3);
        assert_eq!(many.len(), 3);
        for (i, a) in many.iter_mut().enumerate() {
            assert_eq!(a.as_ptr() as usize % HUGE_PAGE, 0);
            assert!(a.iter().all(|&x| x == 0));
            let n = a.len();
            a[0] = i as u64 + 1;
            a[n - 1] = i as u64 + 10;
        }
        // Freed out of order, the others stay whole.
        drop(many.remove(1));
        assert_eq!((many[0][0], many[1][0]), (1, 3));
        assert_eq!(
            (many[0][HUGE_PAGE / 8 + 2], many[1][HUGE_PAGE / 8 + 2]),
            (10, 12)
        );
        assert!(Zeroed::<u64>::new_many(0, 2).iter().all(|a| a.is_empty()));
    }

    #[test]
    fn zeroed_arrays_are_zero_aligned_and_writable() {
        for (len, huge) in [
            (0usize, true),
            (1, true),
            (1000, false),
            (HUGE_PAGE / 8 + 1, true),
        ] {
            let mut a = Zeroed::<u64>::alloc(len, huge);
            assert_eq!(a.len(), len);
            assert!(a.iter().all(|&x| x == 0));
            if len > 0 {
                if huge {
                    assert_eq!(a.as_ptr() as usize % HUGE_PAGE, 0);
                }
                a[len - 1] = 7;
                a[0] += 1;
                assert_eq!(a[len - 1], if len == 1 { 8 } else { 7 });
                assert_eq!(a.iter().sum::<u64>(), 8);
            }
        }
    }
}
