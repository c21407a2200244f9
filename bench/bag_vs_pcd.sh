#!/usr/bin/env bash
# Offline replay of a ROS 2 bag against the same clouds as PCD files, alternated runs.
#   bench/bag_vs_pcd.sh PYTHON [RUNS]   (PYTHON: one with rosbags, mcap and numpy)
# Writes 100 clouds of 65,536 points (Ouster layout, /tf at 100 Hz) as MCAP with zstd
# chunks, as sqlite3, and as PCD files, then times `voxmap replay --offline` and `--dry-run` (reading only).
set -euo pipefail
py=${1:?python with rosbags}; runs=${2:-8}
root=$(cd "$(dirname "$0")/.." && pwd)
# From the checkout: cargo reads .cargo/config.toml (the x86-64-v2 baseline) from the
# working directory, so a build started elsewhere makes a different, slower binary.
(cd "$root" && cargo build --release -q -p voxmap-service)
v="$root/target/release/voxmap"
d=$(mktemp -d); trap 'rm -rf "$d"' EXIT
"$py" "$root/tests/ros/make_bags.py" bench 100 65536 "$d/w"
echo "cpu: $(lscpu | sed -n 's/^Model name: *//p' | head -1), $(nproc) cores"
for k in $(seq "$runs"); do
    for src in pcd bag bag_sqlite; do
        s=$(date +%s.%N)
        "$v" replay --offline --out "$d/$src.vxm" --threads 2 --max-range 30 --resolution 0.1 "$d/w/$src" >/dev/null
        e=$(date +%s.%N)
        r=$("$v" replay --dry-run "$d/w/$src" | sed -n 's/.* in \([0-9.]*\) s.*/\1/p')
        echo "$src run $k: replay $(echo "$e - $s" | bc) s, reading alone $r s"
    done
done
for b in bag bag_sqlite; do
    cmp -s "$d/pcd.vxm" "$d/$b.vxm" && echo "maps: $b identical to pcd" || echo "maps: $b DIFFERS"
done
