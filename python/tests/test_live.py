"""A frame published from Python reaches a running service, and Python reads both it and
the C++ driver's frame back from shared memory. VOXMAP_LIVE_PREFIX names the service's
prefix (tests/tests/foreign.rs starts it and runs the C++ driver first)."""

import os
import time

import numpy as np
import pytest

import voxmap

PREFIX = os.environ.get("VOXMAP_LIVE_PREFIX")
pytestmark = pytest.mark.skipif(not PREFIX, reason="VOXMAP_LIVE_PREFIX not set")


def wall_y(distance, n=40):
    """A wall `distance` metres away on +y, n x n points."""
    u, w = np.meshgrid(np.linspace(-1.5, 1.5, n), np.linspace(-0.5, 0.5, n))
    return np.stack([u.ravel(), np.full(n * n, distance), w.ravel()], axis=1).astype(np.float32)


def test_python_frame_and_cpp_frame_come_back():
    sub = voxmap.Subscriber(PREFIX, "default")
    pub = voxmap.Publisher(PREFIX, "default")
    stamp = time.time_ns()
    seq = pub.send(wall_y(2.0), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], stamp)
    assert seq == 1
    deadline = time.monotonic() + 20
    view = None
    while time.monotonic() < deadline:
        sub.wait(0.2)
        v = sub.latest()
        if v is not None and v.timestamp_ns == stamp:
            view = v
            break
    assert view is not None, "no snapshot holds the Python frame"
    # Both walls: the C++ driver's on +x, Python's on +y; the other way is clear.
    np.testing.assert_allclose(view.first_hit([0, 0, 0], [3, 0, 0]), [2.05, 0.05, 0.05])
    np.testing.assert_allclose(view.first_hit([0, 0, 0], [0, 3, 0]), [0.05, 2.05, 0.05])
    assert view.first_hit([0, 0, 0], [-1, 0, 0]) is None
    states = view.states_at(np.array([[2.05, 0.05, 0.05], [0.05, 2.05, 0.05], [1.0, 0.05, 0.05]]))
    np.testing.assert_array_equal(states, [voxmap.OCCUPIED, voxmap.OCCUPIED, voxmap.FREE])
    # The view is over the shared-memory sample and stays valid after later receives.
    assert sub.latest().sequence == view.sequence
    with pytest.raises(ValueError):
        pub.send(wall_y(2.0), [0, 0, 0], [0, 0, 0, 0], 0)  # zero quaternion
    stats = voxmap.Control(PREFIX, "default").stats()
    assert stats["frames_integrated"] >= 2 and stats["frames_rejected"] == 0
