#!/usr/bin/env bash
# The reliability figures of docs/reliability.md, in one command, from the repository root:
#
#     bash tests/reliability/run.sh [RUNS]
#
# RUNS: libFuzzer executions per fuzz target (default 10,000,000), each target also cut at
# FUZZ_SECONDS (default 1800; bag_file, which writes and opens a file per input, reaches
# far fewer). Prints one table row per campaign. Needs cargo-fuzz
# (`cargo install cargo-fuzz`); RUSTC_BOOTSTRAP=1 lets the stable toolchain take the
# sanitizer flags. Fuzzing starts from the checked-in corpora and does not add to them.
set -euo pipefail
cd "$(dirname "$0")/../.."
runs=${1:-10000000}
seconds=${FUZZ_SECONDS:-1800}
export RUSTC_BOOTSTRAP=1
commit=$(git rev-parse --short HEAD)
cpu=$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)
echo "reliability figures: commit $commit, $cpu, $(nproc) CPUs, $(date -u +%F)"
echo "| campaign | inputs | result |"
echo "|---|---|---|"

fuzz() { # target
    local target=$1 log
    log=$(mktemp)
    local corpus="fuzz/corpus/$target" work
    work=$(mktemp -d)
    # A scratch corpus: the checked-in seeds stay as they are.
    [ -d "$corpus" ] && cp -r "$corpus"/. "$work"/
    if (cd fuzz && cargo fuzz run -O -a "$target" "$work" -- -runs="$runs" -max_total_time="$seconds" -print_final_stats=1) >"$log" 2>&1; then
        local n
        n=$(grep -o 'Done [0-9]* runs in [0-9]* second' "$log" | tail -1)
        echo "| fuzz $target | ${n#Done } | 0 crashes |"
    else
        echo "| fuzz $target | see $log | FAILED |"
        tail -30 "$log" >&2
        return 1
    fi
    rm -rf "$work"
}

for t in snapshot_open map_file scan_files frame control_request ros_messages bag_file; do
    fuzz "$t"
done

frames=${VOXMAP_HOSTILE_FRAMES:-1000000}
log=$(mktemp)
if VOXMAP_HOSTILE_FRAMES=$frames cargo test --release -p voxmap-tests --test reliability -- --nocapture >"$log" 2>&1; then
    line=$(grep '^hostile publisher:' "$log")
    echo "| hostile publisher | $frames frames | ${line#hostile publisher: } |"
else
    echo "| hostile publisher | $frames frames | FAILED (see $log) |"
    exit 1
fi
