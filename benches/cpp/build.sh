# Sourced (not run) by benches/compare_cgal_pcl.sh and benches/real_scans.sh, from the repository
# root: installs CGAL, Eigen, TBB and PCL with apt (Debian) when missing, builds the drivers in
# benches/cpp/ into $BIN and qemd (release) into $TARGET. Sets TARGET, BIN and QEMD.
#
# Environment: CARGO_TARGET_DIR (default target/), SKIP_APT=1 (do not call apt-get).

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
