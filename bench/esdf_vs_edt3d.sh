#!/usr/bin/env bash
# voxmap's distance field and OctoMap's dynamicEDT3D (Debian's, through bench/esdf_edt3d.cpp)
# on the same maps and frames, alternated, in one run:
#   bench/esdf_vs_edt3d.sh WORKLOAD_DIR [ROUNDS]
# Bulk builds: the maps of the workload PCDs (6 m ones) and of OctoMap's scan.dat, each
# exported to .bt for dynamicEDT3D. Per-frame updates: the ten TUM fr2 frames (voxmap's
# own integration and field against OctoMap's insertPointCloud and dynamicEDT3D update).
# Needs g++, liboctomap-dev and libdynamicedt3d-dev.
set -euo pipefail
wl=${1:?workload dir (python3 ../shared/bench/gen_workloads.py DIR)}; rounds=${2:-2}
root=$(cd "$(dirname "$0")/.." && pwd)
# From the checkout: cargo reads .cargo/config.toml (the x86-64-v2 baseline) from the
# working directory, so a build started elsewhere makes a different, slower binary.
(cd "$root" && cargo build --release -q -p voxmap-service)
v="$root/target/release/voxmap"
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
g++ -O2 -o "$tmp/esdf_edt3d" "$root/bench/esdf_edt3d.cpp" -ldynamicedt3d -loctomap -loctomath
echo "cpu: $(lscpu | sed -n 's/^Model name: *//p' | head -1), $(nproc) cores; $(date -u +%FT%TZ); dynamicEDT3D $(dpkg-query -W -f='${Version}' libdynamicedt3d-dev 2>/dev/null || echo '?')"
# The frames and scan.dat as PCD, and the maps as .bt.
"$v" bench --esdf --workloads "$wl" --filter 6m --threads 2 --runs 1 --esdf-write-pcd "$tmp" >/dev/null
printf '0 0 0\n' > "$tmp/q.txt"
maps=()
for f in "$wl"/*_6m.pcd "$tmp/scan_dat.pcd"; do
    name=$(basename "$f" .pcd); range=30
    [[ $name == *_6m ]] && range=6
    "$v" replay --offline --threads 2 --max-range "$range" --out "$tmp/$name.vxm" "$f" >/dev/null
    "$v" export "$tmp/$name.vxm" --bt "$tmp/$name.bt" >/dev/null
    maps+=("$name")
done
for r in $(seq "$rounds"); do
    echo "== round $r: voxmap (2 threads)"
    "$v" bench --esdf --workloads "$wl" --filter 6m --threads 2 --runs 5 | grep -vE '^(tum frame|build =)'
    echo "== round $r: dynamicEDT3D bulk builds (1 thread), ms"
    for m in "${maps[@]}"; do
        echo "$m $("$tmp/esdf_edt3d" query "$tmp/$m.bt" 2.0 free "$tmp/q.txt" 2>&1 >/dev/null | sed -n 's/^bulk_ms //p')"
    done
    echo "== round $r: dynamicEDT3D over the TUM frames (OctoMap insertPointCloud, max range 8 m)"
    "$tmp/esdf_edt3d" frames 0.1 8 2.0 free "$tmp"/tum/*.pcd 2>/dev/null | grep -E 'edt_ms'
done
