//! `voxmap_subscriber`: the newest snapshot of a running service, as views read in place in
//! shared memory.
//!
//! Thread safety: a subscriber belongs to the thread that connected it (iceoryx2's `ipc`
//! ports are not `Send`): every call on it, and the freeing of its views, on that thread.

use crate::error::{connect_handle, free_handle, mut_arg, status, Failure};
use crate::view::voxmap_view;
use std::ffi::{c_char, c_int};
use std::time::Duration;
use voxmap_client::SnapshotSubscriber;

/// A planner's connection to the snapshots of one map. Free with `voxmap_subscriber_free`.
pub struct voxmap_subscriber {
    sub: SnapshotSubscriber,
}

/// Connect to map `map` of the service under `prefix` (the service's defaults: "voxmap",
/// "default"). The service need not be running yet. Null on failure.
///
/// # Safety
/// `prefix` and `map` are null or NUL-terminated strings.
#[no_mangle]
pub unsafe extern "C" fn voxmap_subscriber_connect(
    prefix: *const c_char,
    map: *const c_char,
) -> *mut voxmap_subscriber {
    // SAFETY: the caller's promises.
    unsafe {
        connect_handle(prefix, map, |prefix, map| {
            SnapshotSubscriber::connect(prefix, map).map(|sub| voxmap_subscriber { sub })
        })
    }
}

/// Wait up to `timeout_ms` for a snapshot newer than the last one received: 1 when one
/// came, 0 on timeout, or an error code. It blocks on an event, not a busy loop.
///
/// # Safety
/// `sub` is null or a live subscriber.
#[no_mangle]
pub unsafe extern "C" fn voxmap_subscriber_wait(
    sub: *mut voxmap_subscriber,
    timeout_ms: u64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        let s = unsafe { mut_arg(sub, "subscriber") }?;
        let got = s
            .sub
            .wait_for_update(Duration::from_millis(timeout_ms))
            .map_err(|e| Failure::client(&e))?;
        Ok(c_int::from(got))
    })
}

/// The newest snapshot received, as a view over the shared-memory sample itself (no copy):
/// 1 and `*out` set to a new view, which stays valid (whatever arrives later) until
/// `voxmap_view_free`; 0 and `*out` null when no snapshot has arrived yet; or an error
/// code (a snapshot that does not validate). Views of two different older snapshots held
/// at once use up the subscriber's samples: newer ones wait (an error) until one is freed.
///
/// # Safety
/// `sub` is null or a live subscriber; `out` is null or writable.
#[no_mangle]
pub unsafe extern "C" fn voxmap_subscriber_latest(
    sub: *mut voxmap_subscriber,
    out: *mut *mut voxmap_view,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promises.
        let (s, out) = unsafe { (mut_arg(sub, "subscriber")?, mut_arg(out, "out")?) };
        *out = std::ptr::null_mut();
        match s.sub.latest_held().map_err(|e| Failure::client(&e))? {
            Some(held) => {
                *out = voxmap_view::held(held);
                Ok(1)
            }
            None => Ok(0),
        }
    })
}

/// Free a subscriber (null is ignored). Its views stay valid until freed themselves.
///
/// # Safety
/// `sub` is null or a subscriber from this library, not yet freed.
#[no_mangle]
pub unsafe extern "C" fn voxmap_subscriber_free(sub: *mut voxmap_subscriber) {
    // SAFETY: the caller's promise: `sub` is null or made by `into_handle`, unfreed.
    unsafe { free_handle(sub) }
}
