#!/usr/bin/env bash
# Point-cloud denoising benchmark (not a test): qemd against CGAL jet_smooth_point_set,
# CGAL bilateral_smooth_point_set and PCL MovingLeastSquares on the same noisy samples.
#
# Installs CGAL, Eigen, TBB and PCL with apt (Debian), builds the drivers in benches/cpp/ and qemd
# (release, in $CARGO_TARGET_DIR or target/), then runs benches/compare_cgal_pcl.py, which writes
# docs/quality/points.md (pass --out - to print it instead). Extra arguments go to the Python
# script, e.g.  benches/compare_cgal_pcl.sh --points 20000 --seeds 1 --shapes cube
#
# Environment: MESH_DIR (directory with bun_zipper.ply and fandisk.off: adds the bunny and fandisk
# shapes), WORK (data and result cache, reused by later runs with the same settings; default a
# fresh temporary directory, removed at the end), SKIP_APT=1 (do not call apt-get).
set -euo pipefail
cd "$(dirname "$0")/.."

# Installs what is missing, builds the C++ drivers and qemd; sets TARGET, BIN and QEMD.
source benches/cpp/build.sh

# --- run -------------------------------------------------------------------------------------
if [[ -z "${WORK:-}" ]]; then
  WORK=$(mktemp -d -t qemd-cgal-pcl.XXXXXX)
  trap 'rm -rf "$WORK"' EXIT
fi
ARGS=(--qemd "$QEMD" --bin "$BIN" --work "$WORK")
COMMAND="benches/compare_cgal_pcl.sh${*:+ $*}"
if [[ -n "${MESH_DIR:-}" ]]; then
  ARGS+=(--mesh-dir "$MESH_DIR")
  COMMAND="MESH_DIR=$MESH_DIR $COMMAND"
fi
COMMAND="${CARGO_TARGET_DIR:+CARGO_TARGET_DIR=$CARGO_TARGET_DIR }$COMMAND"
python3 benches/compare_cgal_pcl.py "${ARGS[@]}" --command "$COMMAND" "$@"
