"""voxmap: read voxmap occupancy snapshots in place, from files or from a running
``voxmap serve`` over shared memory, and publish point-cloud frames to it.

    import numpy as np, voxmap
    sub = voxmap.Subscriber("voxmap", "default")
    sub.wait(1.0)
    view = sub.latest()                       # in place in shared memory, or None
    states = view.states_at(np.array([[1.0, 0.0, 0.5]]))   # uint8: 0 unknown, 1 free, 2 occupied
    hit = view.first_hit([0, 0, 0.5], [5, 0, 0.5])          # hit voxel's centre, or None
    free = view.is_box_free([-0.3, -0.3, 0.2], [0.3, 0.3, 1.5])

Views of a subscriber, and subscribers, publishers and controls, stay on the thread that
made them (iceoryx2's shared-memory samples are tied to it).
"""

from ._voxmap import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    Control,
    Publisher,
    Subscriber,
    View,
    VoxmapError,
    open,
)

__all__ = [
    "UNKNOWN",
    "FREE",
    "OCCUPIED",
    "Control",
    "Publisher",
    "Subscriber",
    "View",
    "VoxmapError",
    "open",
]
