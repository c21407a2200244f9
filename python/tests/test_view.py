"""The Python view against the Rust view's answers on the same map, and its errors.

VOXMAP_FIXTURE names a directory made by tests/tests/foreign.rs: map.vxm, map.snap,
queries.bin and expected.bin (the Rust answers, laid out as c/tests/programs/queries.cpp
writes them). Without it the fixture tests are skipped; the rest run on a map of their own.
"""

import os
import pathlib

import numpy as np
import pytest

import voxmap

FIXTURE = os.environ.get("VOXMAP_FIXTURE")
INVALID = -2  # VOXMAP_ERR_INVALID, as the answers file records refused queries


class Reader:
    def __init__(self, data):
        self.data, self.at = data, 0

    def take(self, dtype, count=1):
        dtype = np.dtype(dtype).newbyteorder("<")
        a = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.at)
        self.at += dtype.itemsize * count
        return a


def read_queries(path):
    r = Reader(pathlib.Path(path).read_bytes())
    blocks = []
    for per in (3, 7, 7):
        n = int(r.take("u8")[0])
        blocks.append(r.take("f8", n * per).reshape(n, per))
    return blocks


def read_expected(path, n_points, n_rays, n_boxes):
    r = Reader(pathlib.Path(path).read_bytes())
    e = {
        "resolution": r.take("f8")[0],
        "counts": tuple(int(x) for x in r.take("u8", 2)),
        "bounds_code": int(r.take("i4")[0]),
        "bounds": r.take("f8", 6),
        "states": r.take("u1", n_points),
        "single": r.take("u1", n_points),
    }
    probs = [(int(r.take("i4")[0]), r.take("f8")[0]) for _ in range(n_points)]
    e["probs"] = probs
    e["rays"] = [(int(r.take("i4")[0]), r.take("f8", 3)) for _ in range(n_rays)]
    e["boxes"] = r.take("i4", n_boxes)
    e["occupied"] = int(r.take("u8")[0])
    e["occupied_sum"] = r.take("f8", 3)
    assert r.at == len(r.data)
    return e


@pytest.fixture(scope="module", params=["map.vxm", "map.snap", "bytes"])
def case(request):
    if not FIXTURE:
        pytest.skip("VOXMAP_FIXTURE not set (run by tests/tests/foreign.rs)")
    d = pathlib.Path(FIXTURE)
    if request.param == "bytes":
        view = voxmap.View.from_bytes((d / "map.snap").read_bytes())
    else:
        view = voxmap.open(d / request.param)
    points, rays, boxes = read_queries(d / "queries.bin")
    return view, points, rays, boxes, read_expected(d / "expected.bin", len(points), len(rays), len(boxes))


def test_header_queries(case):
    view, _, _, _, e = case
    assert view.resolution == e["resolution"]
    assert view.counts == e["counts"]
    lo_hi = view.bounds
    assert (lo_hi is not None) == (e["bounds_code"] == 1)
    np.testing.assert_array_equal(np.concatenate(lo_hi), e["bounds"])


def test_states(case):
    view, points, _, _, e = case
    got = view.states_at(points)
    assert got.dtype == np.uint8 and got.shape == (len(points),)
    np.testing.assert_array_equal(got, e["states"])
    # Not contiguous, not float64, a list: converted, same answers.
    np.testing.assert_array_equal(view.states_at(np.asfortranarray(points)), e["states"])
    np.testing.assert_array_equal(view.states_at(points[:50].tolist()), e["states"][:50])
    single = [view.state_at(*p) for p in points[:2000]]
    np.testing.assert_array_equal(single, e["single"][:2000])


def test_probabilities(case):
    view, points, _, _, e = case
    for p, (code, want) in list(zip(points, e["probs"]))[:3000]:
        got = view.probability_at(p)
        assert (got is not None) == (code == 1)
        if got is not None:
            assert got == want


def test_first_hits(case):
    view, _, rays, _, e = case
    for r, (code, centre) in zip(rays, e["rays"]):
        if code == INVALID:
            with pytest.raises(ValueError):
                view.first_hit(r[:3], r[3:6], bool(r[6]))
            continue
        hit = view.first_hit(r[:3], r[3:6], unknown_is_occupied=bool(r[6]))
        assert (hit is not None) == (code == 1)
        if hit is not None:
            np.testing.assert_array_equal(hit, centre)


def test_boxes(case):
    view, _, _, boxes, e = case
    for b, code in zip(boxes, e["boxes"]):
        if code == INVALID:
            with pytest.raises(ValueError):
                view.is_box_free(b[:3], b[3:6], bool(b[6]))
            continue
        assert view.is_box_free(b[:3], b[3:6], unknown_is_free=bool(b[6])) == (code == 1)


def test_occupied_centres(case):
    view, _, _, _, e = case
    c = view.occupied_centres()
    assert c.shape == (e["occupied"], 3)
    # Summed in the same order as the Rust view's.
    s = np.zeros(3)
    for row in c:
        s += row
    np.testing.assert_array_equal(s, e["occupied_sum"])
    # Every centre is an occupied voxel.
    assert (view.states_at(c) == voxmap.OCCUPIED).all()


def test_bad_input_is_an_error_not_a_crash(tmp_path):
    with pytest.raises(voxmap.VoxmapError):
        voxmap.open(tmp_path / "missing.vxm")
    (tmp_path / "junk").write_bytes(b"VXMSNAP\0" + bytes(300))
    with pytest.raises(voxmap.VoxmapError):
        voxmap.open(tmp_path / "junk")
    with pytest.raises(voxmap.VoxmapError):
        voxmap.View.from_bytes(b"not a snapshot")
    if not FIXTURE:
        return
    good = (pathlib.Path(FIXTURE) / "map.snap").read_bytes()
    view = voxmap.View.from_bytes(good)
    with pytest.raises(ValueError):
        view.states_at(np.zeros((4, 2)))
    with pytest.raises(ValueError):
        view.is_box_free([1, 1, 1], [0, 2, 2])
    # Mutated bytes: refused, or opened and queried without harm.
    rng = np.random.default_rng(7)
    opened = 0
    pts = rng.uniform(-4, 4, size=(64, 3))
    for _ in range(2000):
        b = bytearray(good)
        for i in rng.integers(0, len(b), size=rng.integers(1, 8)):
            b[i] = int(rng.integers(0, 256))
        try:
            v = voxmap.View.from_bytes(bytes(b))
        except voxmap.VoxmapError:
            continue
        opened += 1
        assert (v.states_at(pts) <= 2).all()
        try:
            v.first_hit([0, 0, 0], [3, 1, 0.5], True)
            v.is_box_free([-1, -1, -1], [1, 1, 1], True)
        except ValueError:
            pass
        v.occupied_centres()
    assert opened > 0
