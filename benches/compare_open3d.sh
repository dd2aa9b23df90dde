#!/usr/bin/env bash
# Installs Open3D (pip) and its system libraries, then runs compare_open3d.py.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! python3 -c "import open3d" 2>/dev/null; then
  (apt-get install -y libusb-1.0-0 libgomp1 || (apt-get update && apt-get install -y libusb-1.0-0 libgomp1)) >/dev/null
  pip install --quiet open3d
fi
cargo build --release --quiet
python3 benches/compare_open3d.py "$@"
