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

TARGET="${CARGO_TARGET_DIR:-target}"
PKGS=(libcgal-dev libeigen3-dev libtbb-dev libpcl-dev g++ python3)

need_install() {
  [[ -f /usr/include/CGAL/jet_smooth_point_set.h ]] || return 0
  [[ -d /usr/include/eigen3 ]] || return 0
  [[ -f /usr/include/tbb/parallel_for.h || -f /usr/include/oneapi/tbb/parallel_for.h ]] || return 0
  compgen -G "/usr/include/pcl-*/pcl/surface/mls.h" >/dev/null || return 0
  command -v g++ >/dev/null || return 0
  command -v python3 >/dev/null || return 0
  return 1
}

if [[ "${SKIP_APT:-0}" != 1 ]] && need_install; then
  echo "installing ${PKGS[*]} with apt-get" >&2
  export DEBIAN_FRONTEND=noninteractive
  apt_install() { apt-get install -y --no-install-recommends "${PKGS[@]}" >/dev/null; }
  apt_install || { apt-get update >/dev/null && apt_install; }
fi

# --- C++ drivers -----------------------------------------------------------------------------
BIN="$TARGET/bench-cpp"
mkdir -p "$BIN"
PCL_INC=$(compgen -G "/usr/include/pcl-*" | sort -V | tail -1)
CXXFLAGS=(-O2 -std=c++17 -DNDEBUG -I/usr/include/eigen3)
if [[ ! -x "$BIN/cgal_smooth" || benches/cpp/cgal_smooth.cpp -nt "$BIN/cgal_smooth" \
      || benches/cpp/xyz_io.h -nt "$BIN/cgal_smooth" ]]; then
  echo "building cgal_smooth" >&2
  # CGAL 5.x is header-only; Eigen for the jet fitting, TBB for Parallel_tag.
  g++ "${CXXFLAGS[@]}" -DCGAL_EIGEN3_ENABLED -DCGAL_LINKED_WITH_TBB \
    benches/cpp/cgal_smooth.cpp -o "$BIN/cgal_smooth" -ltbb -ltbbmalloc -lgmp -lmpfr
fi
if [[ ! -x "$BIN/pcl_mls" || benches/cpp/pcl_mls.cpp -nt "$BIN/pcl_mls" \
      || benches/cpp/xyz_io.h -nt "$BIN/pcl_mls" ]]; then
  echo "building pcl_mls" >&2
  # MovingLeastSquares<PointXYZ, PointXYZ> is precompiled in libpcl_surface (with OpenMP).
  g++ "${CXXFLAGS[@]}" -I"$PCL_INC" benches/cpp/pcl_mls.cpp -o "$BIN/pcl_mls" \
    -lpcl_surface -lpcl_search -lpcl_kdtree -lpcl_common -lflann_cpp -llz4
fi

# --- qemd ------------------------------------------------------------------------------------
cargo build --release --quiet
QEMD="$TARGET/release/qemd"

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
