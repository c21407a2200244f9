"""The Python distance field queries against the Rust field's answers on the same snapshot.

VOXMAP_FIXTURE names a directory made by tests/tests/foreign.rs: field.snap (a snapshot
with a distance field), field_points.bin (a count, then x y z doubles) and
field_expected.bin (the Rust answers, laid out as c/tests/programs/field.cpp writes them).
Without it the tests are skipped.
"""

import os
import pathlib

import numpy as np
import pytest

import voxmap

FIXTURE = os.environ.get("VOXMAP_FIXTURE")


def read(dirname):
    d = pathlib.Path(dirname)
    raw = (d / "field_points.bin").read_bytes()
    n = int(np.frombuffer(raw, "<u8", 1)[0])
    points = np.frombuffer(raw, "<f8", 3 * n, 8).reshape(n, 3)
    e = (d / "field_expected.bin").read_bytes()
    rec = np.dtype([("dcode", "<i4"), ("d", "<f8"), ("g", "<f8", 3),
                    ("ncode", "<i4"), ("c", "<f8", 3), ("nd", "<f8")])
    max_distance = np.frombuffer(e, "<f8", 1)[0]
    per = np.frombuffer(e, rec, n, 8)
    batched = np.frombuffer(e, "<f8", 4 * n, 8 + rec.itemsize * n).reshape(n, 4)
    return points, max_distance, per, batched


@pytest.mark.skipif(not FIXTURE, reason="VOXMAP_FIXTURE not set (run by tests/tests/foreign.rs)")
def test_field_answers_as_the_rust_view():
    points, max_distance, per, batched = read(FIXTURE)
    view = voxmap.open(os.path.join(FIXTURE, "field.snap"))
    assert view.field == (max_distance, "free")
    for p, e in zip(points, per):
        d = view.distance_at(p)
        dg = view.distance_and_gradient_at(p)
        if e["dcode"] == 1:
            assert d == e["d"] and dg[0] == e["d"]
            assert np.array_equal(dg[1], e["g"])
        else:
            assert d is None and dg is None
        near = view.nearest_obstacle(p)
        if e["ncode"] == 1:
            assert np.array_equal(near, e["c"])
        else:
            assert near is None
    d, g = view.distances_at(points)
    assert np.array_equal(d, batched[:, 0], equal_nan=True)
    assert np.array_equal(g, batched[:, 1:], equal_nan=True)
    # Any array-like, converted.
    d2, _ = view.distances_at(points.astype(np.float32).tolist())
    assert d2.shape == d.shape


@pytest.mark.skipif(not FIXTURE, reason="VOXMAP_FIXTURE not set (run by tests/tests/foreign.rs)")
def test_a_snapshot_without_a_field_says_so():
    view = voxmap.open(os.path.join(FIXTURE, "map.snap"))
    assert view.field is None
    with pytest.raises(voxmap.VoxmapError, match="no distance field"):
        view.distance_at([0.0, 0.0, 0.0])
    with pytest.raises(voxmap.VoxmapError, match="no distance field"):
        view.distances_at(np.zeros((2, 3)))
