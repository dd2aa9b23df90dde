#!/usr/bin/env bash
# Simulated LiDAR with exact truth: qemd against CGAL jet, CGAL bilateral and PCL MLS on every
# sensor of `qemd synth lidar` (a benchmark, not a test). Builds the drivers in benches/cpp/ and
# qemd (release), then runs benches/lidar_sim.py, which prints a Markdown table per sensor (pass
# --out FILE to write it). Extra arguments go to the Python script, e.g.
#   benches/lidar_sim.sh --seed 2 --density 0.5 --sensors spinning,airborne
#
# Environment: WORK (keep the scans and outputs there; default a temporary directory),
# SKIP_APT=1 (do not call apt-get), CARGO_TARGET_DIR (default target/).
set -euo pipefail
cd "$(dirname "$0")/.."

# Installs what is missing, builds the C++ drivers and qemd; sets TARGET, BIN and QEMD.
source benches/cpp/build.sh

ARGS=(--qemd "$QEMD" --bin "$BIN")
[[ -n "${WORK:-}" ]] && ARGS+=(--work "$WORK")
python3 benches/lidar_sim.py "${ARGS[@]}" --command "benches/lidar_sim.sh${*:+ $*}" "$@"
