#!/usr/bin/env bash
# Real-scan benchmark (not a test): the do-no-harm and known-noise protocol (`qemd harm`) on every
# real scan in ../shared/data, for qemd (default, --paper, --method bilateral), CGAL
# jet_smooth_point_set, CGAL bilateral_smooth_point_set and PCL MovingLeastSquares.
#
# Installs CGAL, Eigen, TBB and PCL with apt (Debian) if missing, builds the drivers in
# benches/cpp/ and qemd (release, in $CARGO_TARGET_DIR or target/), then runs
# benches/real_scans.py, which writes docs/quality/real-scans.md (pass --out - to print it
# instead). Extra arguments go to the Python script, e.g.
#   benches/real_scans.sh --scans lidar/ --methods qemd-default cgal-jet --out -
#
# Environment: DATA (the data directory, default ../shared/data), WORK (inputs, outputs and the
# result cache, kept between runs so that a rerun only redoes what changed; default
# $TARGET/real-scans), SKIP_APT=1 (do not call apt-get).
set -euo pipefail
cd "$(dirname "$0")/.."

# Installs what is missing, builds the C++ drivers and qemd; sets TARGET, BIN and QEMD.
source benches/cpp/build.sh

DATA="${DATA:-../shared/data}"
WORK="${WORK:-$TARGET/real-scans}"
COMMAND="benches/real_scans.sh${*:+ $*}"
[[ "$DATA" == ../shared/data ]] || COMMAND="DATA=$DATA $COMMAND"
COMMAND="${CARGO_TARGET_DIR:+CARGO_TARGET_DIR=$CARGO_TARGET_DIR }$COMMAND"
python3 benches/real_scans.py --qemd "$QEMD" --bin "$BIN" --work "$WORK" --data "$DATA" \
  --command "$COMMAND" "$@"
