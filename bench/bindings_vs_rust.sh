#!/usr/bin/env bash
# Batched state queries through C and Python against Rust's SnapshotView::states_at, on
# the same snapshot and points, alternated rounds in one run:
#   bench/bindings_vs_rust.sh WLDIR PYTHON [ROUNDS]
# WLDIR: the paper's workloads (python3 ../shared/bench/gen_workloads.py WLDIR); PYTHON: a
# Python with `voxmap` installed (pip install ./python); needs g++ and the C package in
# target/c-prefix (cmake -S c -B target/c-build && cmake --build target/c-build &&
# cmake --install target/c-build --prefix target/c-prefix).
set -euo pipefail
cd "$(dirname "$0")/.."
wl=$1 py=$2 rounds=${3:-3}
out=target/bench-bindings
mkdir -p "$out"
prefix=target/c-prefix
cargo build --release -q -p voxmap-service -p voxmap-c --example states_bench
g++ -O2 -std=c++17 bench/states_bench.cpp -I"$prefix/include" -L"$prefix/lib" -lvoxmap \
    -Wl,-rpath,"$PWD/$prefix/lib" -o "$out/states_bench_c"
grep -m1 "model name" /proc/cpuinfo
for w in random_500000_60m structured_500000_6m; do
    [ -f "$out/$w.snap" ] || {
        target/release/voxmap replay --offline --out "$out/$w.vxm" "$wl/$w.pcd" >/dev/null
        target/release/voxmap export "$out/$w.vxm" --snapshot "$out/$w.snap"
        "$py" bench/states_bench.py points "$out/$w.snap" "$out/$w.pts" 200000
    }
    for batch in 1000 100000; do
        echo "== $w, batch $batch"
        for r in $(seq "$rounds"); do
            target/release/examples/states_bench "$out/$w.snap" "$out/$w.pts" "$batch" 7
            "$out/states_bench_c" "$out/$w.snap" "$out/$w.pts" "$batch" 7
            "$py" bench/states_bench.py time "$out/$w.snap" "$out/$w.pts" "$batch" 7
        done
    done
done
