//! Where the integrator's worker threads run: one per CPU of the set that the thread
//! creating the integrator may run on (the process's, unless that thread was pinned).
//!
//! Left to the Linux scheduler, the two workers of a two-thread pool often shared one CPU
//! for many frames in a row while the other idled (a waker's wakee is placed on the
//! waker's CPU): such frames took as long as on one thread (structured 50k 6 m, ray phase
//! 4.1 against 2.1 ms, the CPUs read with `sched_getcpu` after each frame; `voxmap bench
//! --e2e` at 10 Hz: integration p50 3.2-3.4 ms pinned, 3.4-5.4 ms not). The cost comes
//! where another process keeps a worker's CPU busy: the worker gets only its share of it,
//! and the frame waits for the task in hand (the others steal the rest). With a busy loop
//! on one of two CPUs, random 500k 6 m on 2 threads took 60 against 52 ms unpinned, and
//! the e2e rate with the sensor process flat out fell from 57-58 to 51 frames/s.

/// The CPUs the calling thread may run on, in order; empty where unknown.
pub(crate) fn allowed() -> Vec<usize> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: `cpu_set_t` is plain bits; all zeros is the empty set.
        let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
        let size = std::mem::size_of::<libc::cpu_set_t>();
        // SAFETY: `set` is a writable `cpu_set_t` of `size` bytes; pid 0 is this thread.
        if unsafe { libc::sched_getaffinity(0, size, &mut set) } != 0 {
            return Vec::new();
        }
        // Every bit of the set (some libcs' `CPU_SETSIZE` is smaller than the set).
        (0..8 * size)
            // SAFETY: `c` indexes a bit of `set`, which `CPU_ISSET` reads in bounds.
            .filter(|&c| unsafe { libc::CPU_ISSET(c, &set) })
            .collect()
    }
    #[cfg(not(target_os = "linux"))]
    Vec::new()
}

/// Pin the calling thread to `cpu`, one of [`allowed`]. Only speed depends on it, so a
/// failure leaves the thread as it was.
pub(crate) fn pin_to(cpu: usize) {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: as in `allowed`; all zeros is the empty set.
        let mut one: libc::cpu_set_t = unsafe { std::mem::zeroed() };
        // SAFETY: `cpu` came from `allowed`, so it indexes a bit of the set.
        unsafe { libc::CPU_SET(cpu, &mut one) };
        let size = std::mem::size_of::<libc::cpu_set_t>();
        // SAFETY: `one` is a valid `cpu_set_t` of `size` bytes; pid 0 is this thread.
        unsafe { libc::sched_setaffinity(0, size, &one) };
    }
    #[cfg(not(target_os = "linux"))]
    let _ = cpu;
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use crate::{Integrator, IntegratorConfig};

    /// Pinned workers run on the CPUs of the set in turn, one each (wrapping when there
    /// are more workers than CPUs); unpinned ones keep the whole set.
    #[test]
    fn integrator_workers_are_pinned_one_per_cpu() {
        let all = super::allowed();
        assert!(!all.is_empty());
        for (threads, pin) in [(all.len().min(4), true), (all.len() + 1, true), (2, false)] {
            let integ = Integrator::new(IntegratorConfig {
                threads,
                pin_threads: pin,
                ..Default::default()
            })
            .unwrap();
            let sets = integ.install(|| rayon::broadcast(|_| super::allowed()));
            for (i, set) in sets.iter().enumerate() {
                if pin {
                    assert_eq!(set, &[all[i % all.len()]], "worker {i}");
                } else {
                    assert_eq!(set, &all, "worker {i}");
                }
            }
        }
    }
}
