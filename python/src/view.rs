//! `View`: a validated snapshot read in place (from a file, a `bytes` object, or a
//! subscriber's shared memory), with NumPy-batched queries.

use crate::voxmap_error;
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use std::sync::Arc;
use voxmap_client::HeldSnapshot;
use voxmap_reader::snapshot::{FieldView, Nearest, SnapshotView};
use voxmap_reader::WorldPoint;

/// What keeps a view's bytes alive (held, never read).
#[allow(dead_code)]
enum Backing {
    File(Arc<[u8]>),
    Bytes(Py<PyBytes>),
    Held(Box<HeldSnapshot>),
}

/// A voxmap snapshot read in place: from ``voxmap.open(path)``, ``View.from_bytes(b)``, or
/// ``Subscriber.latest()`` (then in shared memory). States are ``voxmap.UNKNOWN`` (0),
/// ``FREE`` (1) and ``OCCUPIED`` (2); points are world metres.
#[pyclass(unsendable, module = "voxmap")]
pub struct View {
    // Field order: the view, which points into the backing, is dropped first.
    view: SnapshotView<'static>,
    _backing: Backing,
}

/// `bytes` as a `'static` slice.
///
/// # Safety
/// The bytes stay valid and unchanged while the result is used.
unsafe fn forever(bytes: &[u8]) -> &'static [u8] {
    // SAFETY: the caller keeps the bytes alive and unchanged.
    unsafe { std::slice::from_raw_parts(bytes.as_ptr(), bytes.len()) }
}

impl View {
    pub(crate) fn held(held: HeldSnapshot) -> Self {
        let view = held.view();
        // SAFETY: the same type but for the lifetime. The view's bytes are the held
        // sample's shared memory, kept mapped by `_backing` as long as this object, and the
        // view is dropped first.
        let view: SnapshotView<'static> =
            unsafe { std::mem::transmute::<SnapshotView<'_>, SnapshotView<'static>>(view) };
        Self {
            view,
            _backing: Backing::Held(Box::new(held)),
        }
    }

    /// The snapshot's distance field, or VoxmapError when it carries none.
    fn field_view(&self) -> PyResult<FieldView<'static>> {
        self.view.distance_field().ok_or_else(|| {
            crate::VoxmapError::new_err(
                "the snapshot carries no distance field (run the service with --esdf)",
            )
        })
    }
}

/// An (N, 3) array of `T` from any array-like, converted (and copied) only if it is not
/// one already.
pub(crate) fn points<'py, T: numpy::Element>(
    obj: &Bound<'py, PyAny>,
    dtype: &str,
) -> PyResult<PyReadonlyArray2<'py, T>> {
    let arr = match obj.extract::<PyReadonlyArray2<'py, T>>() {
        Ok(a) if a.is_c_contiguous() => a,
        _ => {
            let np = obj.py().import("numpy")?;
            np.call_method1("ascontiguousarray", (obj, dtype))?
                .extract::<PyReadonlyArray2<'py, T>>()
                .map_err(|_| PyValueError::new_err("points must be an (N, 3) array"))?
        }
    };
    if arr.shape()[1] != 3 {
        return Err(PyValueError::new_err(format!(
            "points must be an (N, 3) array, not {:?}",
            arr.shape()
        )));
    }
    Ok(arr)
}

/// A (min, max) pair of 3-vectors.
/// Distances (N,) and gradients (N, 3).
type DistancesGradients<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray2<f64>>);
type Corners<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>);

fn array3<'py>(py: Python<'py>, p: WorldPoint) -> Bound<'py, PyArray1<f64>> {
    vec![p.x, p.y, p.z].into_pyarray(py)
}

#[pymethods]
impl View {
    /// Open snapshot bytes in place (no copy; the structure is validated, not the checksum).
    #[staticmethod]
    fn from_bytes(data: Bound<'_, PyBytes>) -> PyResult<Self> {
        // SAFETY: a `bytes` object is immutable and its buffer does not move; `_backing`
        // holds a reference to it as long as the view.
        let bytes = unsafe { forever(data.as_bytes()) };
        let view = SnapshotView::open(bytes).map_err(|e| voxmap_error(&e))?;
        Ok(Self {
            view,
            _backing: Backing::Bytes(data.unbind()),
        })
    }

    /// Voxel edge length in metres.
    #[getter]
    fn resolution(&self) -> f64 {
        self.view.resolution()
    }

    /// The last frame the snapshot holds (0: none yet, or a file made from a map).
    #[getter]
    fn sequence(&self) -> u64 {
        self.view.sequence()
    }

    /// The time stamp (ns) of the last frame the snapshot holds.
    #[getter]
    fn timestamp_ns(&self) -> u64 {
        self.view.timestamp_ns()
    }

    /// (known, occupied) voxel counts.
    #[getter]
    fn counts(&self) -> (u64, u64) {
        self.view.counts()
    }

    /// (min, max) corners in metres of the box holding every known voxel, or None.
    #[getter]
    fn bounds<'py>(&self, py: Python<'py>) -> Option<Corners<'py>> {
        let (lo, hi) = self.view.bounds()?;
        let r = self.view.resolution();
        let (lo, hi) = (lo.to_array(), hi.to_array());
        let corner = |v: [i32; 3], d: f64| v.map(|c| (f64::from(c) + d) * r).to_vec();
        Some((
            corner(lo, 0.0).into_pyarray(py),
            corner(hi, 1.0).into_pyarray(py),
        ))
    }

    /// The state of the voxel holding (x, y, z); not finite or outside the index space:
    /// unknown.
    fn state_at(&self, x: f64, y: f64, z: f64) -> u8 {
        self.view.state_at(&WorldPoint::new(x, y, z)) as u8
    }

    /// States at the rows of an (N, 3) float64 array, as an (N,) uint8 array; the GIL is
    /// released while they are looked up.
    fn states_at<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<u8>>> {
        let arr = self::points::<f64>(points, "float64")?;
        let xyz = arr.as_slice()?;
        let view = self.view;
        let codes = py.detach(move || {
            let mut out = vec![0u8; xyz.len() / 3];
            view.state_codes_at(xyz, &mut out);
            out
        });
        Ok(codes.into_pyarray(py))
    }

    /// The centre of the first occupied voxel on the segment a -> b (or unknown, with
    /// unknown_is_occupied) as an array, or None when the line of sight is clear. Raises
    /// ValueError for an end point outside the index space or a segment over 65,536
    /// voxels.
    #[pyo3(signature = (a, b, unknown_is_occupied = false))]
    fn first_hit<'py>(
        &self,
        py: Python<'py>,
        a: [f64; 3],
        b: [f64; 3],
        unknown_is_occupied: bool,
    ) -> PyResult<Option<Bound<'py, PyArray1<f64>>>> {
        let hit = self
            .view
            .first_hit(
                &WorldPoint::from(a),
                &WorldPoint::from(b),
                unknown_is_occupied,
            )
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(hit.map(|v| array3(py, self.view.transform().voxel_center(v))))
    }

    /// Whether no voxel the box [lo, hi] overlaps (from the voxel holding lo to the one
    /// holding hi, as OctoMap's bounding boxes) is occupied, nor unknown unless
    /// unknown_is_free. Raises ValueError for an inverted box or a corner outside the
    /// index space.
    #[pyo3(signature = (lo, hi, unknown_is_free = false))]
    fn is_box_free(&self, lo: [f64; 3], hi: [f64; 3], unknown_is_free: bool) -> PyResult<bool> {
        self.view
            .is_box_free(
                &WorldPoint::from(lo),
                &WorldPoint::from(hi),
                unknown_is_free,
            )
            .map_err(|e| PyValueError::new_err(e.to_string()))
    }

    /// The occupancy probability of the voxel holding p, or None when it is unknown or the
    /// snapshot stores no values (files opened from map files store them).
    fn probability_at(&self, p: [f64; 3]) -> Option<f64> {
        let v = self.view.transform().voxel_of(&WorldPoint::from(p))?;
        self.view.probability(v)
    }

    /// The distance field's (max distance in metres, unknown policy "free" or "occupied"),
    /// or None when the snapshot carries none (a service run with --esdf carries one).
    #[getter]
    fn field(&self) -> Option<(f64, &'static str)> {
        let f = self.view.distance_field()?;
        Some((f.max_distance(), f.unknown().name()))
    }

    /// The distance (metres) to the nearest obstacle at p, interpolated between the voxel
    /// centres around it (their distances kept to the nearest 1/steps voxel) and capped at
    /// the max distance, or None where the field does not
    /// reach (unknown space, outside its window). Raises VoxmapError without a field.
    fn distance_at(&self, p: [f64; 3]) -> PyResult<Option<f64>> {
        Ok(self.field_view()?.distance_at(&WorldPoint::from(p)))
    }

    /// (distance, gradient as an array) at p, or None where the field does not reach; the
    /// gradient (per metre) points away from the nearest obstacles.
    fn distance_and_gradient_at<'py>(
        &self,
        py: Python<'py>,
        p: [f64; 3],
    ) -> PyResult<Option<(f64, Bound<'py, PyArray1<f64>>)>> {
        let f = self.field_view()?;
        Ok(f.distance_and_gradient_at(&WorldPoint::from(p))
            .map(|(d, g)| (d, vec![g.x, g.y, g.z].into_pyarray(py))))
    }

    /// The centre of the obstacle voxel nearest to the voxel holding p, as an array; None
    /// when none lies within the max distance or the field does not reach p.
    fn nearest_obstacle<'py>(
        &self,
        py: Python<'py>,
        p: [f64; 3],
    ) -> PyResult<Option<Bound<'py, PyArray1<f64>>>> {
        Ok(
            match self.field_view()?.nearest_obstacle(&WorldPoint::from(p)) {
                Nearest::At { centre, .. } => Some(array3(py, centre)),
                _ => None,
            },
        )
    }

    /// Distances and gradients at the rows of an (N, 3) float64 array: an (N,) array of
    /// distances (NaN where the field does not reach) and an (N, 3) array of gradients;
    /// the GIL is released while they are computed.
    fn distances_at<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<DistancesGradients<'py>> {
        let f = self.field_view()?;
        let arr = self::points::<f64>(points, "float64")?;
        let xyz = arr.as_slice()?;
        let (d, g) = py.detach(move || {
            let pts: Vec<WorldPoint> = xyz
                .chunks_exact(3)
                .map(|p| WorldPoint::new(p[0], p[1], p[2]))
                .collect();
            let mut out = Vec::with_capacity(pts.len());
            f.distances_and_gradients_at(&pts, &mut out);
            let d: Vec<f64> = out.iter().map(|o| o[0]).collect();
            let g: Vec<f64> = out.iter().flat_map(|o| [o[1], o[2], o[3]]).collect();
            (d, g)
        });
        let n = d.len();
        Ok((d.into_pyarray(py), g.into_pyarray(py).reshape([n, 3])?))
    }

    /// Every occupied voxel's centre, as an (M, 3) float64 array.
    fn occupied_centres<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let view = self.view;
        let flat: Vec<f64> = py.detach(move || {
            view.occupied_centers()
                .flat_map(|c| [c.x, c.y, c.z])
                .collect()
        });
        let n = flat.len() / 3;
        flat.into_pyarray(py).reshape([n, 3])
    }

    fn __repr__(&self) -> String {
        let (known, occupied) = self.view.counts();
        let field = self.view.distance_field().map_or(String::new(), |f| {
            format!(", distance field to {} m", f.max_distance())
        });
        format!(
            "<voxmap.View sequence {} resolution {} m, {known} known, {occupied} occupied{field}>",
            self.view.sequence(),
            self.view.resolution()
        )
    }
}

/// Open a voxmap map file or snapshot file (verified whole; a map file becomes a snapshot
/// with its probabilities).
#[pyfunction]
pub fn open(path: std::path::PathBuf) -> PyResult<View> {
    let bytes: Arc<[u8]> = voxmap_reader::mapfile::read_as_snapshot(&path)
        .map_err(|e| voxmap_error(&e))?
        .into();
    // SAFETY: the bytes are on the heap, owned by the `Arc` the view keeps, never written.
    let slice = unsafe { forever(&bytes) };
    let view = SnapshotView::open(slice).map_err(|e| voxmap_error(&e))?;
    Ok(View {
        view,
        _backing: Backing::File(bytes),
    })
}
