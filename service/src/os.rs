//! Operating-system facilities the service and tools share: the wall clock used for frame
//! and snapshot time stamps, real-time scheduling, and the allocator's hold on freed
//! memory.

use anyhow::{bail, Result};

/// Nanoseconds since the Unix epoch (the time base of frame and snapshot stamps).
pub fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// Run the calling thread under SCHED_FIFO at `priority` (1..=99), so that it wakes
/// promptly for frames and snapshots on a loaded machine. Threads it creates afterwards
/// inherit the policy: call it after starting worker pools that should not.
pub fn set_realtime(priority: i32) -> Result<()> {
    if !(1..=99).contains(&priority) {
        bail!("real-time priority must be 1..=99, not {priority}");
    }
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: sched_setscheduler reads `param` (a valid, initialised struct on our stack)
    // and changes only the scheduling of thread 0 = the caller; no memory is retained.
    let rc = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
    if rc != 0 {
        bail!(
            "SCHED_FIFO priority {priority}: {} (needs CAP_SYS_NICE or an rtprio limit)",
            std::io::Error::last_os_error()
        );
    }
    Ok(())
}

/// Have glibc's allocator keep the heap memory the process frees for its next
/// allocations, rather than hand it back to the kernel.
///
/// Every frame and every snapshot allocates and frees the same large temporaries (a whole
/// map snapshot's plan is about 200 MB at 60 m). By default glibc returns such memory on
/// free, and the next frame pays a page fault and a zeroed page per 4 KiB again, which on
/// the VMs measured costs 1-5 us a page. Kept, the process's resident memory stays at its
/// peak, as with allocators that cache freed memory. Settings: no trimming of the heap's
/// top; blocks up to 32 MiB from the heap (the ceiling of glibc's own adaptive
/// threshold, which stops adapting once set); heaps grown 256 MiB of address space at a
/// time. Whole-map encode, random 500k 60 m, in a probe with these settings given as
/// glibc's environment variables: 29 thousand page faults per encode -> 2 thousand,
/// 162 -> 136 ms (median of 10).
///
/// The answers are not checked: glibc 2.36 took even a 1 GiB threshold and an unknown
/// parameter, and a refusal would only leave the default. Call it first thing in `main`:
/// glibc documents `mallopt` as unsafe to call while other threads allocate.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    for (param, value) in [
        (libc::M_TRIM_THRESHOLD, i32::MAX),
        (libc::M_MMAP_THRESHOLD, 32 << 20),
        (libc::M_TOP_PAD, 256 << 20),
    ] {
        // SAFETY: mallopt only changes the allocator's tuning and touches no memory of
        // ours; `main` calls this before it starts any thread, so no allocation runs
        // alongside it.
        unsafe {
            libc::mallopt(param, value);
        }
    }
}

/// The process's peak resident set (bytes), from `/proc/self/status` (`VmHWM`); `None`
/// where the system does not say.
pub fn peak_rss() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb: u64 = s
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb << 10)
}
