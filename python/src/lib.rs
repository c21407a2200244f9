//! `voxmap._voxmap`: the Python API (PyO3). [`view`] holds `View` and `open`; [`ipc`] the
//! shared-memory `Subscriber`, `Publisher` and `Control`. Batched queries take NumPy arrays
//! and release the GIL while they run.

use pyo3::prelude::*;

mod ipc;
mod view;

pyo3::create_exception!(
    voxmap,
    VoxmapError,
    pyo3::exceptions::PyException,
    "A voxmap call failed: a file that is not a valid map or snapshot, shared memory, or the service."
);

pub(crate) fn voxmap_error(e: &dyn std::error::Error) -> PyErr {
    VoxmapError::new_err(voxmap_client::error_chain(e))
}

#[pymodule]
fn _voxmap(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("VoxmapError", m.py().get_type::<VoxmapError>())?;
    m.add("UNKNOWN", voxmap_reader::VoxelState::Unknown as u8)?;
    m.add("FREE", voxmap_reader::VoxelState::Free as u8)?;
    m.add("OCCUPIED", voxmap_reader::VoxelState::Occupied as u8)?;
    m.add_class::<view::View>()?;
    m.add_function(wrap_pyfunction!(view::open, m)?)?;
    m.add_class::<ipc::Subscriber>()?;
    m.add_class::<ipc::Publisher>()?;
    m.add_class::<ipc::Control>()?;
    Ok(())
}
