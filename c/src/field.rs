//! The distance field of a `voxmap_view` (when its snapshot carries one: a service run
//! with `--esdf`, or `voxmap export --snapshot --esdf-max-distance`): distances to the
//! nearest obstacle, their gradient, and the obstacle, read in place. Thread safety is the
//! view's.

use crate::error::{guard, status, xyz_arg, Failure, VOXMAP_ERR_INVALID};
use crate::view::{snapshot, voxmap_view};
use std::ffi::c_int;
use voxmap_reader::field::UnknownPolicy;
use voxmap_reader::snapshot::{FieldView, Nearest};
use voxmap_reader::WorldPoint;

/// The view's field, or a failure saying it has none.
///
/// # Safety
/// `view` is null or a live view.
unsafe fn field<'a>(view: *const voxmap_view) -> Result<FieldView<'a>, Failure> {
    // SAFETY: the caller's promise.
    let v = unsafe { snapshot(view) }?;
    v.distance_field().ok_or_else(|| {
        Failure::new(
            VOXMAP_ERR_INVALID,
            "the snapshot carries no distance field (run the service with --esdf)",
        )
    })
}

/// Write `v` to `out[..3]` when `out` is not null.
///
/// # Safety
/// `out` is null or holds 3 writable doubles.
unsafe fn put3(out: *mut f64, v: [f64; 3]) {
    if !out.is_null() {
        for (k, x) in v.into_iter().enumerate() {
            // SAFETY: the caller's promise.
            unsafe { *out.add(k) = x };
        }
    }
}

/// Whether the view carries a distance field: 1 (its max distance in metres and whether
/// unknown voxels count as obstacles written where not null), 0 when not, or an error code.
///
/// # Safety
/// `view` is null or a live view; `max_distance` and `unknown_is_occupied` are null or
/// writable.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_field(
    view: *const voxmap_view,
    max_distance: *mut f64,
    unknown_is_occupied: *mut c_int,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promise.
        let Some(f) = unsafe { snapshot(view) }?.distance_field() else {
            return Ok(0);
        };
        if !max_distance.is_null() {
            // SAFETY: writable (the caller's promise).
            unsafe { *max_distance = f.max_distance() };
        }
        if !unknown_is_occupied.is_null() {
            // SAFETY: writable (the caller's promise).
            unsafe { *unknown_is_occupied = c_int::from(f.unknown() == UnknownPolicy::Occupied) };
        }
        Ok(1)
    })
}

/// The distance (metres) at `p`, interpolated between the voxel centres around it (their
/// distances kept to the nearest 1/steps voxel, docs/distance-field.md) and capped at the
/// field's max distance, and its gradient (per metre, pointing away from the
/// nearest obstacles; `gradient` may be null): 1 when written, 0 where the field does not
/// reach (unknown space, outside its window), or an error code (no field).
///
/// # Safety
/// `view` is null or a live view; `p` is null or holds 3 doubles; `distance` is null or
/// writable; `gradient` is null or holds 3 writable doubles.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_distance_at(
    view: *const voxmap_view,
    p: *const f64,
    distance: *mut f64,
    gradient: *mut f64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promises.
        let (f, p) = unsafe { (field(view)?, xyz_arg(p, "p")?) };
        if distance.is_null() {
            return Err(Failure::null("distance"));
        }
        let Some((d, g)) = f.distance_and_gradient_at(&WorldPoint::from(p)) else {
            return Ok(0);
        };
        // SAFETY: checked non-null above; writable (the caller's promise).
        unsafe {
            *distance = d;
            put3(gradient, [g.x, g.y, g.z]);
        }
        Ok(1)
    })
}

/// The obstacle voxel nearest to the voxel holding `p`: 1 with its centre (and the
/// distance between the two voxels' centres, where not null) written; 2 when none lies
/// within the max distance; 0 where the field does not reach; or an error code.
///
/// # Safety
/// `view` is null or a live view; `p` is null or holds 3 doubles; `centre` is null or holds
/// 3 writable doubles; `distance` is null or writable.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_nearest_obstacle(
    view: *const voxmap_view,
    p: *const f64,
    centre: *mut f64,
    distance: *mut f64,
) -> c_int {
    status(|| {
        // SAFETY: the caller's promises.
        let (f, p) = unsafe { (field(view)?, xyz_arg(p, "p")?) };
        Ok(match f.nearest_obstacle(&WorldPoint::from(p)) {
            Nearest::Unknown => 0,
            Nearest::NoneWithin => 2,
            Nearest::At {
                centre: c,
                distance: d,
                ..
            } => {
                // SAFETY: the caller's promises.
                unsafe {
                    put3(centre, [c.x, c.y, c.z]);
                    if !distance.is_null() {
                        *distance = d;
                    }
                }
                1
            }
        })
    })
}

/// `voxmap_view_distance_at` at `n` points (`xyz`: x, y, z per point): `distance[i]` (NaN
/// where the field does not reach) and, when `gradient` is not null, `gradient[3i..3i+3]`.
/// Returns 0, or an error code with every output NaN.
///
/// # Safety
/// `view` is null or a live view; `xyz` is null or holds `3 n` doubles; `distance` is null
/// or holds `n` writable doubles; `gradient` is null or holds `3 n` writable doubles.
#[no_mangle]
pub unsafe extern "C" fn voxmap_view_distances_at(
    view: *const voxmap_view,
    xyz: *const f64,
    n: usize,
    distance: *mut f64,
    gradient: *mut f64,
) -> c_int {
    guard(
        |code| code,
        || {
            if distance.is_null() {
                return Err(Failure::null("distance"));
            }
            if n > isize::MAX as usize / 24 {
                return Err(Failure::invalid("n is larger than any buffer"));
            }
            // SAFETY: `distance` holds `n` writable doubles, `gradient` (if not null) 3 n.
            let d = unsafe { std::slice::from_raw_parts_mut(distance, n) };
            let mut g = (!gradient.is_null())
                // SAFETY: as above.
                .then(|| unsafe { std::slice::from_raw_parts_mut(gradient, 3 * n) });
            d.fill(f64::NAN);
            if let Some(g) = g.as_deref_mut() {
                g.fill(f64::NAN);
            }
            // SAFETY: the caller's promise.
            let f = unsafe { field(view) }?;
            if xyz.is_null() {
                return Err(Failure::null("xyz"));
            }
            // SAFETY: `xyz` holds `3 n` doubles (the caller's promise); 24 n fits isize.
            let xyz = unsafe { std::slice::from_raw_parts(xyz, 3 * n) };
            for (i, p) in xyz.chunks_exact(3).enumerate() {
                if let Some((dist, grad)) =
                    f.distance_and_gradient_at(&WorldPoint::new(p[0], p[1], p[2]))
                {
                    d[i] = dist;
                    if let Some(g) = g.as_deref_mut() {
                        g[3 * i..3 * i + 3].copy_from_slice(&[grad.x, grad.y, grad.z]);
                    }
                }
            }
            Ok(0)
        },
    )
}
