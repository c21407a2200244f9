//! Operating-system facilities the service and tools share: the wall clock used for frame
//! and snapshot time stamps, and real-time scheduling.

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
