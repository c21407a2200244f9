//! `voxmap_publisher`: a sensor driver's frames, written in place in shared memory and sent
//! with their pose and time stamp.
//!
//! Thread safety: a publisher belongs to the thread that connected it; its loaned points may
//! be written from any thread until they are sent or discarded.

use crate::error::{connect_handle, free_handle, guard, mut_arg, status, xyz_arg, Failure};
use std::ffi::{c_char, c_int};
use voxmap_client::{ClientError, FramePublisher, Isometry3, PendingFrame};

/// A driver's connection to the frames of one map. Free with `voxmap_publisher_free`. Sent
/// frames live in the publisher's shared memory until the service takes them: a publisher
/// freed (or a process ending) right after a send can lose that frame, so a one-shot
/// driver waits for a snapshot whose sequence reaches its frame's.
pub struct voxmap_publisher {
    // Field order: a pending loan goes back before its publisher closes.
    loan: Option<PendingFrame>,
    publisher: FramePublisher,
}

/// Connect to map `map` of the service under `prefix`. Null on failure.
///
/// # Safety
/// `prefix` and `map` are null or NUL-terminated strings.
#[no_mangle]
pub unsafe extern "C" fn voxmap_publisher_connect(
    prefix: *const c_char,
    map: *const c_char,
) -> *mut voxmap_publisher {
    // SAFETY: the caller's promises.
    unsafe {
        connect_handle(prefix, map, |prefix, map| {
            FramePublisher::connect(prefix, map).map(|publisher| voxmap_publisher {
                loan: None,
                publisher,
            })
        })
    }
}

/// Loan shared memory for `n` points: returns `3 n` zeroed floats (x, y, z of each point
/// in the sensor frame, metres) to write in place, then `voxmap_publisher_send` or
/// `voxmap_publisher_discard`. One loan at a time per publisher. Null on failure.
///
/// # Safety
/// `publisher` is null or a live publisher.
#[no_mangle]
pub unsafe extern "C" fn voxmap_publisher_loan(
    publisher: *mut voxmap_publisher,
    n: usize,
) -> *mut f32 {
    guard(
        |_| std::ptr::null_mut(),
        || {
            // SAFETY: the caller's promise.
            let p = unsafe { mut_arg(publisher, "publisher") }?;
            if p.loan.is_some() {
                return Err(Failure::invalid(
                    "a frame is already loaned: send or discard it first",
                ));
            }
            let mut frame = p
                .publisher
                .loan_pending(n)
                .map_err(|e| Failure::client(&e))?;
            let ptr = frame.points_mut().as_mut_ptr().cast::<f32>();
            p.loan = Some(frame);
            Ok(ptr)
        },
    )
}

/// The pose of a frame from C arrays, checked as the service checks it.
///
/// # Safety
/// Each pointer is null or holds 3 (translation) or 4 (rotation) doubles.
unsafe fn pose_arg(
    translation: *const f64,
    rotation_xyzw: *const f64,
) -> Result<Isometry3<f64>, Failure> {
    // SAFETY: the caller's promise.
    let t = unsafe { xyz_arg(translation, "translation") }?;
    if rotation_xyzw.is_null() {
        return Err(Failure::null("rotation_xyzw"));
    }
    // SAFETY: 4 readable doubles (the caller's promise).
    let q = unsafe { std::slice::from_raw_parts(rotation_xyzw, 4) };
    voxmap_client::frame_pose(t, [q[0], q[1], q[2], q[3]])
        .map_err(|e| Failure::invalid(format!("bad pose: {e}")))
}

/// Send the loaned frame with the sensor's pose in the map frame (`translation` x, y, z in
/// metres; `rotation_xyzw` a unit quaternion) and its time stamp (ns); `*sequence` (if not
/// null) gets the frame's sequence number. 0, or an error code (a bad pose keeps the loan:
/// fix it and send again, or discard).
///
/// # Safety
/// `publisher` is null or a live publisher; `translation` null or 3 doubles;
/// `rotation_xyzw` null or 4 doubles; `sequence` null or writable.
#[no_mangle]
pub unsafe extern "C" fn voxmap_publisher_send(
    publisher: *mut voxmap_publisher,
    translation: *const f64,
    rotation_xyzw: *const f64,
    stamp_ns: u64,
    sequence: *mut u64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        let p = unsafe { mut_arg(publisher, "publisher") }?;
        let Some(frame) = p.loan.take() else {
            return Err(Failure::invalid("no frame is loaned"));
        };
        // SAFETY: the caller's promises.
        let pose = match unsafe { pose_arg(translation, rotation_xyzw) } {
            Ok(pose) => pose,
            Err(f) => {
                p.loan = Some(frame);
                return Err(f);
            }
        };
        let seq = p.publisher.send_pending(frame, &pose, stamp_ns);
        // SAFETY: null or writable (the caller's promise).
        unsafe { sent(seq, sequence) }
    })
}

/// A send's outcome for C: 0 and `*sequence` (if not null) written, or the error code.
///
/// # Safety
/// `sequence` is null or writable.
unsafe fn sent(seq: Result<u64, ClientError>, sequence: *mut u64) -> Result<c_int, Failure> {
    let seq = seq.map_err(|e| Failure::client(&e))?;
    // SAFETY: null or writable (the caller's promise).
    if let Some(s) = unsafe { sequence.as_mut() } {
        *s = seq;
    }
    Ok(0)
}

/// Return the loaned frame unsent (nothing loaned: nothing happens). 0, or an error code.
///
/// # Safety
/// `publisher` is null or a live publisher.
#[no_mangle]
pub unsafe extern "C" fn voxmap_publisher_discard(publisher: *mut voxmap_publisher) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        unsafe { mut_arg(publisher, "publisher") }?.loan = None;
        Ok(0)
    })
}

/// Copy `n` points (`xyz`, x, y, z after one another) into a loan and send it, for a driver
/// that already holds them in a buffer. As `voxmap_publisher_send` otherwise.
///
/// # Safety
/// As `voxmap_publisher_send`; `xyz` is null or holds `3 n` floats.
#[no_mangle]
pub unsafe extern "C" fn voxmap_publisher_publish(
    publisher: *mut voxmap_publisher,
    xyz: *const f32,
    n: usize,
    translation: *const f64,
    rotation_xyzw: *const f64,
    stamp_ns: u64,
    sequence: *mut u64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        let p = unsafe { mut_arg(publisher, "publisher") }?;
        if xyz.is_null() {
            return Err(Failure::null("xyz"));
        }
        if n > isize::MAX as usize / 12 {
            return Err(Failure::invalid("n is larger than any buffer"));
        }
        if p.loan.is_some() {
            return Err(Failure::invalid(
                "a frame is loaned: send or discard it first",
            ));
        }
        // SAFETY: the caller's promises.
        let pose = unsafe { pose_arg(translation, rotation_xyzw) }?;
        // SAFETY: `3 n` readable floats, 12 n fits isize.
        let src = unsafe { std::slice::from_raw_parts(xyz, 3 * n) };
        let seq = p.publisher.publish(&pose, stamp_ns, src.as_chunks::<3>().0);
        // SAFETY: null or writable (the caller's promise).
        unsafe { sent(seq, sequence) }
    })
}

/// Free a publisher (null is ignored); a loaned frame is returned unsent.
///
/// # Safety
/// `publisher` is null or a publisher from this library, not yet freed.
#[no_mangle]
pub unsafe extern "C" fn voxmap_publisher_free(publisher: *mut voxmap_publisher) {
    // SAFETY: the caller's promise: `publisher` is null or made by `into_handle`, unfreed.
    unsafe { free_handle(publisher) }
}
