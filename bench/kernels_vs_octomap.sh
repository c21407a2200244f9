#!/usr/bin/env bash
# Every kernel this CPU runs, alternated, and OctoMap (Debian's liboctomap, built against
# here) on the same workload files, in one run.
#   bench/kernels_vs_octomap.sh WORKLOAD_DIR [ROUNDS] [FILTER]
# Needs g++ and liboctomap-dev. Prints `voxmap bench` rows (2 threads, --no-snapshot) per
# kernel and round, then OctoMap's insertPointCloud time for each file the filter matches.
set -euo pipefail
wl=${1:?workload dir (python3 ../shared/bench/gen_workloads.py DIR)}; rounds=${2:-2}; filter=${3:-6m}
root=$(cd "$(dirname "$0")/.." && pwd)
# From the checkout: cargo reads .cargo/config.toml (the x86-64-v2 baseline) from the
# working directory, so a build started elsewhere makes a different, slower binary.
(cd "$root" && cargo build --release -q -p voxmap-service)
v="$root/target/release/voxmap"
ob=$(mktemp -d)/octomap_bench; trap 'rm -rf "$(dirname "$ob")"' EXIT
g++ -O2 -o "$ob" "$root/bench/octomap_bench.cpp" -loctomap -loctomath
echo "cpu: $(lscpu | sed -n 's/^Model name: *//p' | head -1), $(nproc) cores; $(date -u +%FT%TZ)"
# `if`, not `&&`: a kernel the CPU lacks must not end the script under `set -e`.
kernels=$(for k in scalar avx2 avx512; do
    if VOXMAP_KERNEL=$k "$v" bench --workloads "$wl" --modes exact --runs 1 --threads 1 --no-snapshot --filter random_50000_6m >/dev/null 2>&1; then echo $k; fi
done)
for r in $(seq "$rounds"); do
    for k in $kernels; do
        echo "== round $r, kernel $k"
        VOXMAP_KERNEL=$k "$v" bench --workloads "$wl" --modes exact --runs 5 --threads 2 --no-snapshot --filter "$filter" | grep -E '^(workload|random|structured)'
    done
done
echo "== OctoMap $(dpkg-query -W -f='${Version}' liboctomap-dev 2>/dev/null || echo '?'), OMP_NUM_THREADS=2, 3 runs"
for f in "$wl"/*"$filter"*.pcd; do
    range=$(basename "$f" .pcd); range=${range##*_}; range=${range%m}
    OMP_NUM_THREADS=2 "$ob" 0.1 "$range" 3 "$f"
done
