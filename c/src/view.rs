//! `voxmap_view`: a validated snapshot and the planner's queries on it, and
//! `voxmap_occupied`, a cursor over its occupied voxel centres.
//!
//! Thread safety: a view opened from a file or from bytes may be queried and freed from
//! any thread (queries concurrently; free once, after the last query). A view from a
//! subscriber may be queried from any thread while it lives, but `voxmap_view_free` and
//! `voxmap_view_occupied` on it belong to the subscriber's thread (iceoryx2's samples are
//! tied to it).

use crate::error::{
    free_handle, guard, into_handle, ref_arg, status, str_arg, xyz_arg, Failure, VOXMAP_ERR_FILE,
    VOXMAP_ERR_INVALID,
};
use std::ffi::{c_char, c_int};
use std::sync::Arc;
use voxmap_client::HeldSnapshot;
use voxmap_reader::snapshot::{InvalidBox, SnapshotView};
use voxmap_reader::{VoxelState, WorldPoint};

/// A voxel's state, as the `uint8_t` the queries return.
#[repr(u8)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum voxmap_state {
    /// Not known.
    VOXMAP_UNKNOWN = 0,
    /// Known free.
    VOXMAP_FREE = 1,
    /// Known occupied.
    VOXMAP_OCCUPIED = 2,
    /// Not a state: the call failed (a null view); see `voxmap_last_error`.
    VOXMAP_STATE_ERROR = 255,
}

/// `voxmap_state` codes are the core's `VoxelState` discriminants.
const _: () = assert!(
    VoxelState::Unknown as u8 == voxmap_state::VOXMAP_UNKNOWN as u8
        && VoxelState::Free as u8 == voxmap_state::VOXMAP_FREE as u8
        && VoxelState::Occupied as u8 == voxmap_state::VOXMAP_OCCUPIED as u8
);
const VOXMAP_STATE_ERROR: u8 = voxmap_state::VOXMAP_STATE_ERROR as u8;

/// What keeps a view's bytes alive (its fields are held, never read).
#[derive(Clone)]
#[allow(dead_code)]
enum Backing {
    /// Read from a file.
    Owned(Arc<[u8]>),
    /// The caller's bytes, which the caller keeps alive.
    Borrowed,
    /// A shared-memory sample.
    Held(Box<HeldSnapshot>),
}

/// A validated snapshot read in place: opened from a map or snapshot file, from a caller's
/// bytes, or from a subscriber's shared memory. Free with `voxmap_view_free`.
pub struct voxmap_view {
    // Field order: the view, which points into the backing, is dropped first.
    view: SnapshotView<'static>,
    backing: Backing,
}

impl voxmap_view {
    /// A view over bytes that `backing` keeps alive, as a pointer for C.
    ///
    /// # Safety
    /// `bytes` stays valid and unchanged while `backing` lives (or, for
    /// [`Backing::Borrowed`], until the caller frees the view).
    unsafe fn boxed(bytes: &'static [u8], backing: Backing) -> Result<*mut Self, Failure> {
        let view = SnapshotView::open(bytes).map_err(|e| Failure::chain(VOXMAP_ERR_FILE, &e))?;
        Ok(into_handle(Self { view, backing }))
    }

    /// A view over a subscriber's held sample.
    pub(crate) fn held(held: HeldSnapshot) -> *mut Self {
        // SAFETY (of the lifetime): the view's bytes are the held sample's, which `backing`
        // keeps alive as long as this struct; the view is dropped first.
        let view: SnapshotView<'static> = unsafe { extend(held.view()) };
        into_handle(Self {
            view,
            backing: Backing::Held(Box::new(held)),
        })
    }
}

/// A view with its lifetime erased.
///
/// # Safety
/// The bytes it reads stay valid and unchanged as long as the result is used.
unsafe fn extend(v: SnapshotView<'_>) -> SnapshotView<'static> {
    // SAFETY: the same type but for the lifetime; the caller keeps the bytes alive.
    unsafe { std::mem::transmute::<SnapshotView<'_>, SnapshotView<'static>>(v) }
}

/// Open a voxmap map file or snapshot file (told apart by their first bytes; a map file is
/// converted into a snapshot with its probabilities). The file is read and verified whole
/// (structure and checksum). Returns null on failure (see `voxmap_last_error`).
///
/// # Safety
/// `path` is null or a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_open_file(path: *const c_char) -> *mut voxmap_view {
    guard(
        |_| std::ptr::null_mut(),
        || {
            // SAFETY: the caller's promise on `path`.
            let path = unsafe { str_arg(path, "path") }?;
            let bytes: Arc<[u8]> = voxmap_reader::mapfile::read_as_snapshot(path.as_ref())
                .map_err(|e| Failure::chain(VOXMAP_ERR_FILE, &e))?
                .into();
            // SAFETY: the bytes are on the heap, owned by the `Arc` the view keeps, and
            // never written.
            let slice: &'static [u8] =
                unsafe { std::slice::from_raw_parts(bytes.as_ptr(), bytes.len()) };
            // SAFETY: as above.
            unsafe { voxmap_view::boxed(slice, Backing::Owned(bytes)) }
        },
    )
}

/// Open snapshot bytes in place, without copying them: the structure is validated (every
/// offset, length and count), not the checksum. The bytes must stay valid and unchanged
/// until `voxmap_view_free`. Returns null on failure (see `voxmap_last_error`).
///
/// # Safety
/// `bytes` is null or points to `len` readable bytes that outlive the view unchanged.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_open_bytes(bytes: *const u8, len: usize) -> *mut voxmap_view {
    guard(
        |_| std::ptr::null_mut(),
        || {
            if bytes.is_null() {
                return Err(Failure::null("bytes"));
            }
            if len > isize::MAX as usize {
                return Err(Failure::invalid("len is larger than any buffer"));
            }
            // SAFETY: the caller's promise: `len` bytes, alive and unchanged until the
            // view is freed.
            let slice: &'static [u8] = unsafe { std::slice::from_raw_parts(bytes, len) };
            // SAFETY: as above.
            unsafe { voxmap_view::boxed(slice, Backing::Borrowed) }
        },
    )
}

/// Free a view (null is ignored).
///
/// # Safety
/// `view` is null or a view from this library, not yet freed.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_free(view: *mut voxmap_view) {
    // SAFETY: the caller's promise: `view` is null or made by `into_handle`, unfreed.
    unsafe { free_handle(view) }
}

/// The view's snapshot, or the failure for a null `view`.
///
/// # Safety
/// `view` is null or a live view.
pub(crate) unsafe fn snapshot<'a>(
    view: *const voxmap_view,
) -> Result<&'a SnapshotView<'static>, Failure> {
    // SAFETY: the caller's promise.
    Ok(&unsafe { ref_arg(view, "view") }?.view)
}

/// Voxel edge length in metres (NaN for a null view).
///
/// # Safety
/// `view` is null or a live view.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_resolution(view: *const voxmap_view) -> f64 {
    // SAFETY: the caller's promise.
    guard(|_| f64::NAN, || Ok(unsafe { snapshot(view) }?.resolution()))
}

/// The snapshot's sequence number: the last frame it holds (0: none yet, or a file made
/// from a map); 0 for a null view.
///
/// # Safety
/// `view` is null or a live view.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_sequence(view: *const voxmap_view) -> u64 {
    // SAFETY: the caller's promise.
    guard(|_| 0, || Ok(unsafe { snapshot(view) }?.sequence()))
}

/// The time stamp of the last frame the snapshot holds (ns, the publisher's clock); 0 for a
/// null view.
///
/// # Safety
/// `view` is null or a live view.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_timestamp_ns(view: *const voxmap_view) -> u64 {
    // SAFETY: the caller's promise.
    guard(|_| 0, || Ok(unsafe { snapshot(view) }?.timestamp_ns()))
}

/// Known and occupied voxel counts (either pointer may be null). 0, or an error code.
///
/// # Safety
/// `view` is null or a live view; `known` and `occupied` are null or writable.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_counts(
    view: *const voxmap_view,
    known: *mut u64,
    occupied: *mut u64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        let (k, o) = unsafe { snapshot(view) }?.counts();
        // SAFETY: each is null or writable.
        unsafe {
            if let Some(p) = known.as_mut() {
                *p = k;
            }
            if let Some(p) = occupied.as_mut() {
                *p = o;
            }
        }
        Ok(0)
    })
}

/// The box (world metres, voxel faces) holding every known voxel: 1 and `min`, `max`
/// written; 0 when nothing is known; or an error code.
///
/// # Safety
/// `view` is null or a live view; `min` and `max` are null or point to 3 writable doubles.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_bounds(
    view: *const voxmap_view,
    min: *mut f64,
    max: *mut f64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        let v = unsafe { snapshot(view) }?;
        if min.is_null() || max.is_null() {
            return Err(Failure::null(if min.is_null() { "min" } else { "max" }));
        }
        let Some((lo, hi)) = v.bounds() else {
            return Ok(0);
        };
        let r = v.resolution();
        let (lo, hi) = (lo.to_array(), hi.to_array());
        for k in 0..3 {
            // SAFETY: both point to 3 writable doubles.
            unsafe {
                *min.add(k) = f64::from(lo[k]) * r;
                *max.add(k) = (f64::from(hi[k]) + 1.0) * r;
            }
        }
        Ok(1)
    })
}

/// The state of the voxel holding (x, y, z) (world metres): `VOXMAP_UNKNOWN`, `VOXMAP_FREE`
/// or `VOXMAP_OCCUPIED`; a point that is not finite or outside the index space is unknown.
/// `VOXMAP_STATE_ERROR` for a null view.
///
/// # Safety
/// `view` is null or a live view.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_state_at(
    view: *const voxmap_view,
    x: f64,
    y: f64,
    z: f64,
) -> u8 {
    guard(
        |_| VOXMAP_STATE_ERROR,
        // SAFETY: the caller's promise.
        || Ok(unsafe { snapshot(view) }?.state_at(&WorldPoint::new(x, y, z)) as u8),
    )
}

/// `out[i]` = the state at point i (`xyz[3i..3i+3]`), as `voxmap_view_state_at`, for `n`
/// points: one call for a trajectory's samples, with the memory reads of many points
/// overlapped (faster per point than single calls on a big map). On a null argument, `out`
/// (if not null) is filled with `VOXMAP_STATE_ERROR`.
///
/// # Safety
/// `view` is null or a live view; `xyz` is null or holds `3 n` doubles; `out` is null or
/// holds `n` writable bytes.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_states_at(
    view: *const voxmap_view,
    xyz: *const f64,
    n: usize,
    out: *mut u8,
) {
    guard(
        |_| (),
        || {
            if out.is_null() {
                return Err(Failure::null("out"));
            }
            if n > isize::MAX as usize / 24 {
                return Err(Failure::invalid("n is larger than any buffer"));
            }
            // SAFETY: `out` holds `n` writable bytes (the caller's promise).
            let out = unsafe { std::slice::from_raw_parts_mut(out, n) };
            let fail = |out: &mut [u8], f: Failure| {
                out.fill(VOXMAP_STATE_ERROR);
                Err(f)
            };
            // SAFETY: the caller's promise.
            let v = match unsafe { snapshot(view) } {
                Ok(v) => v,
                Err(f) => return fail(out, f),
            };
            if xyz.is_null() {
                return fail(out, Failure::null("xyz"));
            }
            // SAFETY: `xyz` holds `3 n` doubles (the caller's promise); 24 n fits isize.
            let xyz = unsafe { std::slice::from_raw_parts(xyz, 3 * n) };
            v.state_codes_at(xyz, out);
            Ok(())
        },
    )
}

/// The occupancy probability of the voxel holding (x, y, z): 1 and `*p` written when the
/// voxel is known and the snapshot stores values (files opened from map files do; the
/// service's snapshots do when configured to), 0 when not, or an error code.
///
/// # Safety
/// `view` is null or a live view; `p` is null or writable.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_probability_at(
    view: *const voxmap_view,
    x: f64,
    y: f64,
    z: f64,
    p: *mut f64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        let v = unsafe { snapshot(view) }?;
        if p.is_null() {
            return Err(Failure::null("p"));
        }
        let prob = v
            .transform()
            .voxel_of(&WorldPoint::new(x, y, z))
            .and_then(|c| v.probability(c));
        Ok(match prob {
            Some(q) => {
                // SAFETY: `p` is writable.
                unsafe { *p = q };
                1
            }
            None => 0,
        })
    })
}

/// Walk the segment `from` -> `to` (world metres) voxel by voxel: 1 when a voxel on it is
/// occupied (or unknown, when `unknown_is_occupied` is non-zero), its centre written to
/// `hit_centre` (which may be null); 0 when the line of sight is clear; or an error code
/// (an end point not finite or outside the index space, a segment over 65,536 voxels).
///
/// # Safety
/// `view` is null or a live view; `from` and `to` are null or hold 3 doubles;
/// `hit_centre` is null or holds 3 writable doubles.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_first_hit(
    view: *const voxmap_view,
    from: *const f64,
    to: *const f64,
    unknown_is_occupied: c_int,
    hit_centre: *mut f64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promises.
        let (v, a, b) = unsafe { (snapshot(view)?, xyz_arg(from, "from")?, xyz_arg(to, "to")?) };
        let hit = v
            .first_hit(
                &WorldPoint::from(a),
                &WorldPoint::from(b),
                unknown_is_occupied != 0,
            )
            .map_err(|e| Failure::new(VOXMAP_ERR_INVALID, e.to_string()))?;
        let Some(hit) = hit else { return Ok(0) };
        if !hit_centre.is_null() {
            let c = v.transform().voxel_center(hit);
            for k in 0..3 {
                // SAFETY: `hit_centre` holds 3 writable doubles.
                unsafe { *hit_centre.add(k) = c[k] };
            }
        }
        Ok(1)
    })
}

/// Whether the box [min, max] (world metres) is free: 1 when no voxel it overlaps (from
/// the voxel holding `min` to the one holding `max`, as OctoMap's bounding boxes) is
/// occupied, nor unknown unless `unknown_is_free` is non-zero; 0 when one is; or an error
/// code (a corner not finite or outside the index space, `min` above `max` on an axis).
///
/// # Safety
/// `view` is null or a live view; `min` and `max` are null or hold 3 doubles.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_is_box_free(
    view: *const voxmap_view,
    min: *const f64,
    max: *const f64,
    unknown_is_free: c_int,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promises.
        let (v, lo, hi) = unsafe { (snapshot(view)?, xyz_arg(min, "min")?, xyz_arg(max, "max")?) };
        match v.is_box_free(
            &WorldPoint::from(lo),
            &WorldPoint::from(hi),
            unknown_is_free != 0,
        ) {
            Ok(free) => Ok(c_int::from(free)),
            Err(e @ (InvalidBox::Inverted | InvalidBox::OutsideIndexSpace)) => {
                Err(Failure::invalid(e.to_string()))
            }
        }
    })
}

/// A cursor over a view's occupied voxel centres. It keeps the view's file or shared-memory
/// bytes alive, so it may outlive the view (over a caller's bytes: while those live); free
/// it with `voxmap_occupied_free`. One thread at a time (for a
/// subscriber's view: the subscriber's thread).
pub struct voxmap_occupied {
    // Field order: the iterator, which reads the backing's bytes, is dropped first.
    centres: Box<dyn Iterator<Item = WorldPoint>>,
    _backing: Backing,
}

/// Start a cursor over the occupied voxel centres (in the snapshot's leaf order). Null on
/// failure.
///
/// # Safety
/// `view` is null or a live view.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_occupied(view: *const voxmap_view) -> *mut voxmap_occupied {
    guard(
        |_| std::ptr::null_mut(),
        || {
            // SAFETY: the caller's promise.
            let v = unsafe { ref_arg(view, "view") }?;
            // The iterator reads the view's bytes, which the cloned backing keeps alive
            // (for borrowed bytes: the caller, until the view is freed).
            let centres = Box::new(v.view.occupied_centers());
            Ok(into_handle(voxmap_occupied {
                centres,
                _backing: v.backing.clone(),
            }))
        },
    )
}

/// Write up to `capacity` next occupied voxel centres into `xyz` (x, y, z after one
/// another); returns how many were written (0 at the end), or an error code.
///
/// # Safety
/// `it` is null or a live cursor; `xyz` is null or holds `3 capacity` writable doubles.
#[no_mangle]
pub unsafe extern "C" fn voxmap_occupied_next(
    it: *mut voxmap_occupied,
    xyz: *mut f64,
    capacity: usize,
) -> i64 {
    guard(i64::from, || {
        // SAFETY: the caller's promise.
        let it = unsafe { crate::error::mut_arg(it, "cursor") }?;
        if xyz.is_null() {
            return Err(Failure::null("xyz"));
        }
        if capacity > isize::MAX as usize / 24 {
            return Err(Failure::invalid("capacity is larger than any buffer"));
        }
        // SAFETY: `3 capacity` writable doubles (the caller's promise), 24 capacity
        // fits isize.
        let out = unsafe { std::slice::from_raw_parts_mut(xyz, 3 * capacity) };
        let mut n = 0;
        for (slot, c) in out.chunks_exact_mut(3).zip(it.centres.by_ref()) {
            slot.copy_from_slice(&[c.x, c.y, c.z]);
            n += 1;
        }
        Ok(n as i64)
    })
}

/// Free a cursor (null is ignored).
///
/// # Safety
/// `it` is null or a cursor from this library, not yet freed.
#[no_mangle]
pub unsafe extern "C" fn voxmap_occupied_free(it: *mut voxmap_occupied) {
    // SAFETY: the caller's promise: `it` is null or made by `into_handle`, unfreed.
    unsafe { free_handle(it) }
}
