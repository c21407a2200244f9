//! `Subscriber`, `Publisher` and `Control`: a running service over iceoryx2 shared memory.
//! Each stays on the thread that made it (iceoryx2's `ipc` ports are not `Send`).

use crate::view::{points, View};
use crate::voxmap_error;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::time::{Duration, Instant};
use voxmap_client::{FramePublisher, MapControl, SnapshotSubscriber};

/// Longest stretch `Subscriber.wait` blocks without looking for Ctrl-C.
const SIGNAL_CHECK: Duration = Duration::from_millis(100);

/// The newest snapshots of a map, read in place in shared memory.
#[pyclass(unsendable, module = "voxmap")]
pub struct Subscriber {
    sub: SnapshotSubscriber,
}

/// A `&mut` to move into `Python::detach`.
struct OnThisThread<'a, T>(&'a mut T);
// SAFETY: `Python::detach` runs its closure on the calling thread, so the `!Send` value
// never leaves it; the object is `unsendable`, so no other thread can reach it meanwhile.
unsafe impl<T> Send for OnThisThread<'_, T> {}

#[pymethods]
impl Subscriber {
    /// Connect to map ``map`` of the service under ``prefix`` (it need not be running yet).
    #[new]
    #[pyo3(signature = (prefix = "voxmap", map = "default"))]
    fn new(prefix: &str, map: &str) -> PyResult<Self> {
        let sub = SnapshotSubscriber::connect(prefix, map).map_err(|e| voxmap_error(&e))?;
        Ok(Self { sub })
    }

    /// Wait up to ``timeout_s`` for a snapshot newer than the last received; True if one
    /// came. The GIL is released while waiting.
    fn wait(&mut self, py: Python<'_>, timeout_s: f64) -> PyResult<bool> {
        if !(timeout_s.is_finite() && timeout_s >= 0.0) {
            return Err(PyValueError::new_err("timeout_s must be finite and >= 0"));
        }
        let deadline = Instant::now() + Duration::from_secs_f64(timeout_s.min(1e9));
        loop {
            let slice = deadline
                .saturating_duration_since(Instant::now())
                .min(SIGNAL_CHECK);
            let sub = OnThisThread(&mut self.sub);
            let got = py
                .detach(move || {
                    let s = sub;
                    s.0.wait_for_update(slice)
                })
                .map_err(|e| voxmap_error(&e))?;
            if got {
                return Ok(true);
            }
            py.check_signals()?;
            if Instant::now() >= deadline {
                return Ok(false);
            }
        }
    }

    /// The newest snapshot as a View over the shared-memory sample (no copy), or None when
    /// none has arrived. Keep at most one older view besides it: views of two older
    /// snapshots use up the subscriber's samples and newer ones wait (an error).
    fn latest(&mut self) -> PyResult<Option<View>> {
        let held = self.sub.latest_held().map_err(|e| voxmap_error(&e))?;
        Ok(held.map(View::held))
    }
}

/// A sensor driver's frames to a map. A frame lives in the publisher's shared memory until
/// the service takes it: keep the publisher until then (a script that sends and exits at
/// once can lose its last frame; wait for a snapshot with its sequence).
#[pyclass(unsendable, module = "voxmap")]
pub struct Publisher {
    publisher: FramePublisher,
}

#[pymethods]
impl Publisher {
    #[new]
    #[pyo3(signature = (prefix = "voxmap", map = "default"))]
    fn new(prefix: &str, map: &str) -> PyResult<Self> {
        let publisher = FramePublisher::connect(prefix, map).map_err(|e| voxmap_error(&e))?;
        Ok(Self { publisher })
    }

    /// Send points (an (N, 3) float32 array, sensor frame, metres) with the sensor's pose
    /// in the map frame (``translation`` x, y, z; ``rotation_xyzw`` a unit quaternion) and
    /// time stamp; returns the frame's sequence number. The points are copied once, into
    /// the shared-memory loan.
    #[pyo3(signature = (points, translation, rotation_xyzw, stamp_ns = 0))]
    fn send(
        &mut self,
        points: &Bound<'_, PyAny>,
        translation: [f64; 3],
        rotation_xyzw: [f64; 4],
        stamp_ns: u64,
    ) -> PyResult<u64> {
        let pose = voxmap_client::frame_pose(translation, rotation_xyzw)
            .map_err(|e| PyValueError::new_err(format!("bad pose: {e}")))?;
        let arr = self::points::<f32>(points, "float32")?;
        let src = arr.as_slice()?;
        self.publisher
            .publish(&pose, stamp_ns, src.as_chunks::<3>().0)
            .map_err(|e| voxmap_error(&e))
    }
}

/// Requests to a running service: stats, save, load, clear.
#[pyclass(unsendable, module = "voxmap")]
pub struct Control {
    control: MapControl,
}

#[pymethods]
impl Control {
    #[new]
    #[pyo3(signature = (prefix = "voxmap", map = "default", timeout_s = 30.0))]
    fn new(prefix: &str, map: &str, timeout_s: f64) -> PyResult<Self> {
        if !(timeout_s.is_finite() && timeout_s > 0.0) {
            return Err(PyValueError::new_err("timeout_s must be finite and > 0"));
        }
        let mut control = MapControl::connect(prefix, map).map_err(|e| voxmap_error(&e))?;
        control.set_timeout(Duration::from_secs_f64(timeout_s.min(1e9)));
        Ok(Self { control })
    }

    /// The service's counters, as a dict.
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let s = self.control.stats().map_err(|e| voxmap_error(&e))?;
        let d = PyDict::new(py);
        d.set_item("frames_received", s.frames_received)?;
        d.set_item("frames_integrated", s.frames_integrated)?;
        d.set_item("frames_dropped", s.frames_dropped)?;
        d.set_item("frames_rejected", s.frames_rejected)?;
        d.set_item("points_integrated", s.points_integrated)?;
        d.set_item("points_skipped", s.points_skipped)?;
        d.set_item("map_leaves", s.map_leaves)?;
        d.set_item("map_memory_bytes", s.map_memory_bytes)?;
        d.set_item("snapshot_bytes", s.snapshot_bytes)?;
        d.set_item("snapshot_sequence", s.snapshot_sequence)?;
        d.set_item("integrate_ms_p50", s.integrate_ms_p50)?;
        d.set_item("integrate_ms_p99", s.integrate_ms_p99)?;
        d.set_item("integrate_ms_max", s.integrate_ms_max)?;
        d.set_item("encode_ms_last", s.encode_ms_last)?;
        d.set_item("intake_us_p50", s.intake_us_p50)?;
        d.set_item("intake_us_p99", s.intake_us_p99)?;
        d.set_item("kernel", s.kernel())?;
        d.set_item("memory_budget_bytes", s.memory_budget_bytes)?;
        d.set_item("resident_bytes", s.resident_bytes)?;
        d.set_item("tiles_resident", s.tiles_resident)?;
        d.set_item("tiles_stored", s.tiles_stored)?;
        d.set_item("tile_evictions", s.tile_evictions)?;
        d.set_item("tile_loads", s.tile_loads)?;
        d.set_item("tiles_refused", s.tiles_refused)?;
        d.set_item("tile_wait_ms_max", s.tile_wait_ms_max)?;
        Ok(d)
    }

    /// Save the map to ``path`` on the service's machine (atomically).
    fn save(&self, path: &str) -> PyResult<()> {
        self.control.save(path).map_err(|e| voxmap_error(&e))
    }

    /// Replace the service's map with the map file at ``path``, or with the tile store in
    /// the directory ``path`` (continued lazily).
    fn load(&self, path: &str) -> PyResult<()> {
        self.control.load(path).map_err(|e| voxmap_error(&e))
    }

    /// Clear the service's map.
    fn clear(&self) -> PyResult<()> {
        self.control.clear().map_err(|e| voxmap_error(&e))
    }
}
