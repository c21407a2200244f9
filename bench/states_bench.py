"""The Python side of bench/bindings_vs_rust.sh.

    states_bench.py points SNAPSHOT OUT N   write N query points (f64 x, y, z): half near
                                            occupied voxel centres, half anywhere in bounds
    states_bench.py time SNAPSHOT POINTS BATCH REPS
                                            ns per point of View.states_at, median of REPS
"""

import sys
import time

import numpy as np

import voxmap


def make_points(snap, out, n):
    view = voxmap.open(snap)
    rng = np.random.default_rng(1)
    lo, hi = view.bounds
    occ = view.occupied_centres()
    near = occ[rng.integers(0, len(occ), n // 2)] + rng.uniform(-0.5, 0.5, (n // 2, 3)) * view.resolution * 4
    anywhere = rng.uniform(lo, hi, (n - n // 2, 3))
    pts = np.concatenate([near, anywhere])
    rng.shuffle(pts)
    pts.astype("<f8").tofile(out)


def time_states(snap, points, batch, reps):
    view = voxmap.open(snap)
    pts = np.fromfile(points, dtype="<f8").reshape(-1, 3)
    chunks = [pts[i : i + batch] for i in range(0, len(pts), batch)]
    per, occupied = [], 0
    for _ in range(reps):
        t = time.perf_counter_ns()
        for c in chunks:
            occupied += int(np.count_nonzero(view.states_at(c) == voxmap.OCCUPIED))
        per.append((time.perf_counter_ns() - t) / len(pts))
    per.sort()
    print(
        f"python View.states_at: {per[reps // 2]:.1f} ns/point (median of {reps}, batch {batch}, "
        f"{len(pts)} points; {occupied} occupied answers)"
    )


if __name__ == "__main__":
    if sys.argv[1] == "points":
        make_points(sys.argv[2], sys.argv[3], int(sys.argv[4]))
    else:
        time_states(sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))
