//! `voxmap_control`: requests to a running service (stats, save, load, clear).
//!
//! Thread safety: a control connection belongs to the thread that connected it.

use crate::error::{connect_handle, free_handle, mut_arg, ref_arg, status, str_arg, Failure};
use std::ffi::{c_char, c_int};
use std::time::Duration;
use voxmap_client::MapControl;

/// A connection to a service's control requests. Free with `voxmap_control_free`.
pub struct voxmap_control {
    control: MapControl,
}

/// The service's counters (`voxmap_control_stats`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct voxmap_stats {
    pub frames_received: u64,
    pub frames_integrated: u64,
    /// Frames dropped by the intake policy (the service was busy).
    pub frames_dropped: u64,
    /// Frames refused by validation (bad header, pose or points).
    pub frames_rejected: u64,
    pub points_integrated: u64,
    /// Points skipped: not finite, or beyond the maximum range.
    pub points_skipped: u64,
    pub map_leaves: u64,
    pub map_memory_bytes: u64,
    pub snapshot_bytes: u64,
    pub snapshot_sequence: u64,
    pub integrate_ms_p50: f64,
    pub integrate_ms_p99: f64,
    pub integrate_ms_max: f64,
    pub encode_ms_last: f64,
    /// Frame send (its time stamp) to receipt by the service, microseconds.
    pub intake_us_p50: f64,
    pub intake_us_p99: f64,
    /// The integrator's kernel (`scalar`, `avx2`, `avx512`), NUL-terminated.
    pub kernel: [c_char; 17],
    /// The memory budget (bytes; 0 = unlimited).
    pub memory_budget_bytes: u64,
    /// The map's resident bytes (with a tile store: leaves, nodes, records waiting to be written).
    pub resident_bytes: u64,
    /// Tiles (128^3 voxels) in memory, with a tile store.
    pub tiles_resident: u64,
    /// Tiles only in the tile store.
    pub tiles_stored: u64,
    /// Tiles evicted to the store and loaded back from it since the start.
    pub tile_evictions: u64,
    pub tile_loads: u64,
    /// Tiles whose store record was refused (damaged); their regions read as unknown.
    pub tiles_refused: u64,
    /// The longest a frame waited for its tiles to load, ms.
    pub tile_wait_ms_max: f64,
}

/// Connect to the control requests of map `map` under `prefix`. Requests wait up to 30 s
/// for an answer (`voxmap_control_set_timeout_ms`). Null on failure.
///
/// # Safety
/// `prefix` and `map` are null or NUL-terminated strings.
#[no_mangle]
pub unsafe extern "C" fn voxmap_control_connect(
    prefix: *const c_char,
    map: *const c_char,
) -> *mut voxmap_control {
    // SAFETY: the caller's promises.
    unsafe {
        connect_handle(prefix, map, |prefix, map| {
            MapControl::connect(prefix, map).map(|control| voxmap_control { control })
        })
    }
}

/// How long each request waits for its answer. 0, or an error code.
///
/// # Safety
/// `control` is null or a live connection.
#[no_mangle]
pub unsafe extern "C" fn voxmap_control_set_timeout_ms(
    control: *mut voxmap_control,
    ms: u64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        unsafe { mut_arg(control, "control") }?
            .control
            .set_timeout(Duration::from_millis(ms));
        Ok(0)
    })
}

/// The service's counters into `*out`. 0, or an error code.
///
/// # Safety
/// `control` is null or a live connection; `out` is null or writable.
#[no_mangle]
pub unsafe extern "C" fn voxmap_control_stats(
    control: *const voxmap_control,
    out: *mut voxmap_stats,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promises.
        let (c, out) = unsafe { (ref_arg(control, "control")?, mut_arg(out, "out")?) };
        let s = c.control.stats().map_err(|e| Failure::client(&e))?;
        let mut kernel = [0 as c_char; 17];
        for (d, b) in kernel.iter_mut().zip(s.kernel().bytes()) {
            *d = b as c_char;
        }
        *out = voxmap_stats {
            frames_received: s.frames_received,
            frames_integrated: s.frames_integrated,
            frames_dropped: s.frames_dropped,
            frames_rejected: s.frames_rejected,
            points_integrated: s.points_integrated,
            points_skipped: s.points_skipped,
            map_leaves: s.map_leaves,
            map_memory_bytes: s.map_memory_bytes,
            snapshot_bytes: s.snapshot_bytes,
            snapshot_sequence: s.snapshot_sequence,
            integrate_ms_p50: s.integrate_ms_p50,
            integrate_ms_p99: s.integrate_ms_p99,
            integrate_ms_max: s.integrate_ms_max,
            encode_ms_last: s.encode_ms_last,
            intake_us_p50: s.intake_us_p50,
            intake_us_p99: s.intake_us_p99,
            kernel,
            memory_budget_bytes: s.memory_budget_bytes,
            resident_bytes: s.resident_bytes,
            tiles_resident: s.tiles_resident,
            tiles_stored: s.tiles_stored,
            tile_evictions: s.tile_evictions,
            tile_loads: s.tile_loads,
            tiles_refused: s.tiles_refused,
            tile_wait_ms_max: s.tile_wait_ms_max,
        };
        Ok(0)
    })
}

/// Save the map to `path` on the service's machine (atomically). 0, or an error code.
///
/// # Safety
/// `control` is null or a live connection; `path` null or a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn voxmap_control_save(
    control: *const voxmap_control,
    path: *const c_char,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promises.
        let (c, path) = unsafe { (ref_arg(control, "control")?, str_arg(path, "path")?) };
        c.control.save(path).map_err(|e| Failure::client(&e))?;
        Ok(0)
    })
}

/// Replace the service's map with the map file at `path` (on the service's machine), or
/// with the tile store in the directory `path` (continued lazily). 0, or an error code (the
/// map is unchanged on failure).
///
/// # Safety
/// `control` is null or a live connection; `path` null or a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn voxmap_control_load(
    control: *const voxmap_control,
    path: *const c_char,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promises.
        let (c, path) = unsafe { (ref_arg(control, "control")?, str_arg(path, "path")?) };
        c.control.load(path).map_err(|e| Failure::client(&e))?;
        Ok(0)
    })
}

/// Clear the service's map. 0, or an error code.
///
/// # Safety
/// `control` is null or a live connection.
#[no_mangle]
pub unsafe extern "C" fn voxmap_control_clear(control: *const voxmap_control) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        unsafe { ref_arg(control, "control") }?
            .control
            .clear()
            .map_err(|e| Failure::client(&e))?;
        Ok(0)
    })
}

/// Free a control connection (null is ignored).
///
/// # Safety
/// `control` is null or a connection from this library, not yet freed.
#[no_mangle]
pub unsafe extern "C" fn voxmap_control_free(control: *mut voxmap_control) {
    // SAFETY: the caller's promise: `control` is null or made by `into_handle`, unfreed.
    unsafe { free_handle(control) }
}
