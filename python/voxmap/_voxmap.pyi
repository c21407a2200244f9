"""Type stubs of voxmap's extension module (see voxmap/__init__.py and docs/bindings.md)."""

import os
from typing import Optional, Sequence, Tuple

import numpy as np
import numpy.typing as npt

UNKNOWN: int
FREE: int
OCCUPIED: int

_Vec3 = Sequence[float]

class VoxmapError(Exception):
    """A voxmap call failed: a file that is not a valid map or snapshot, shared memory, or
    the service."""

class View:
    """A voxmap snapshot read in place: from ``open(path)``, ``View.from_bytes(b)`` or
    ``Subscriber.latest()`` (then in shared memory). Points are world metres."""

    @staticmethod
    def from_bytes(data: bytes) -> "View":
        """Open snapshot bytes in place (no copy; structure validated, not the checksum)."""
    @property
    def resolution(self) -> float: ...
    @property
    def sequence(self) -> int:
        """The last frame the snapshot holds (0: none yet, or a file made from a map)."""
    @property
    def timestamp_ns(self) -> int: ...
    @property
    def counts(self) -> Tuple[int, int]:
        """(known, occupied) voxel counts."""
    @property
    def bounds(self) -> Optional[Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]]:
        """(min, max) corners of the box holding every known voxel, or None."""
    def state_at(self, x: float, y: float, z: float) -> int:
        """UNKNOWN, FREE or OCCUPIED at a point (not finite or outside the map: UNKNOWN)."""
    def states_at(self, points: npt.ArrayLike) -> npt.NDArray[np.uint8]:
        """States at the rows of an (N, 3) float64 array, as an (N,) uint8 array; the GIL is
        released meanwhile."""
    def first_hit(
        self, a: _Vec3, b: _Vec3, unknown_is_occupied: bool = False
    ) -> Optional[npt.NDArray[np.float64]]:
        """Centre of the first occupied (or unknown) voxel on a -> b, or None when clear.
        ValueError for an end point outside the index space or a segment over 65,536 voxels."""
    def is_box_free(self, lo: _Vec3, hi: _Vec3, unknown_is_free: bool = False) -> bool:
        """No voxel the box overlaps is occupied (nor unknown unless unknown_is_free).
        ValueError for an inverted box or a corner outside the index space."""
    def probability_at(self, p: _Vec3) -> Optional[float]:
        """Occupancy probability of a known voxel, when the snapshot stores values."""
    def occupied_centres(self) -> npt.NDArray[np.float64]:
        """Every occupied voxel's centre, (M, 3)."""
    @property
    def field(self) -> Optional[Tuple[float, str]]:
        """(max distance in metres, unknown policy "free" or "occupied") of the snapshot's
        distance field, or None when it carries none (a service run with --esdf does)."""
    def distance_at(self, p: _Vec3) -> Optional[float]:
        """Distance (m) to the nearest obstacle at p, interpolated between voxel centres
        (their distances kept to the nearest 1/steps voxel) and capped at the max distance; None where the field does not reach. Raises
        VoxmapError without a field."""
    def distance_and_gradient_at(
        self, p: _Vec3
    ) -> Optional[Tuple[float, npt.NDArray[np.float64]]]:
        """(distance, gradient) at p; the gradient (per metre) points away from obstacles."""
    def nearest_obstacle(self, p: _Vec3) -> Optional[npt.NDArray[np.float64]]:
        """Centre of the obstacle voxel nearest to p's voxel; None when none is within the
        max distance or the field does not reach p."""
    def distances_at(
        self, points: npt.ArrayLike
    ) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Distances (N,) (NaN where the field does not reach) and gradients (N, 3) at the
        rows of an (N, 3) array, with the GIL released."""

def open(path: "os.PathLike[str] | str") -> View:
    """Open a map file or snapshot file (verified whole)."""

class Subscriber:
    """The newest snapshots of a map, in shared memory. Stays on its thread."""

    def __init__(self, prefix: str = "voxmap", map: str = "default") -> None: ...
    def wait(self, timeout_s: float) -> bool:
        """Wait for a newer snapshot; True if one came (GIL released, Ctrl-C honoured)."""
    def latest(self) -> Optional[View]:
        """The newest snapshot in place, or None; hold at most one old view besides it."""

class Publisher:
    """A sensor driver's frames to a map. Keep it until the service has taken its frames."""

    def __init__(self, prefix: str = "voxmap", map: str = "default") -> None: ...
    def send(
        self,
        points: npt.ArrayLike,
        translation: _Vec3,
        rotation_xyzw: Sequence[float],
        stamp_ns: int = 0,
    ) -> int:
        """Send (N, 3) float32 sensor-frame points with the sensor's pose; the sequence number."""

class Control:
    """Requests to a running service."""

    def __init__(self, prefix: str = "voxmap", map: str = "default", timeout_s: float = 30.0) -> None: ...
    def stats(self) -> dict: ...
    def save(self, path: str) -> None: ...
    def load(self, path: str) -> None: ...
    def clear(self) -> None: ...
