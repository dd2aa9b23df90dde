#!/usr/bin/env bash
# Runs every fuzz target (or those named) for SECONDS each and prints one line of figures per
# target: executions, exec/s, peak RSS, corpus size, crashes/timeouts/OOMs (issue 15).
#   tests/fuzz/run.sh SECONDS [target…]        (from anywhere; ../shared/data seeds the corpus)
# Needs cargo-fuzz (`cargo install cargo-fuzz`); the stable toolchain runs it with
# RUSTC_BOOTSTRAP=1. Exits non-zero when a target finds a crash, a timeout or an OOM; the input
# is in tests/fuzz/artifacts/<target>/ and the log in tests/fuzz/artifacts/<target>.log.
set -euo pipefail
cd "$(dirname "$0")/../.."
secs=${1:-5}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  targets=(ply pcd pcd_body las obj off text raw sniff)
fi
export RUSTC_BOOTSTRAP=1
# The seed corpus is made once (a run adds what it finds; delete tests/fuzz/corpus to reseed).
if [ ! -d tests/fuzz/corpus ]; then
  python3 tests/fuzz/seeds.py "${QEMD_SHARED_DATA:-../shared/data}" > /dev/null
fi
# -O: release without debug assertions, as qemd ships (the laz codec relies on wrapping
# arithmetic, which overflow checks turn into panics; qemd's own profiles disable them for laz).
cargo fuzz build --fuzz-dir tests/fuzz -O -s none > /dev/null
status=0
for t in "${targets[@]}"; do
  mkdir -p "tests/fuzz/artifacts/$t"
  log="tests/fuzz/artifacts/$t.log"
  # -rss_limit_mb: inputs are at most 64 KiB, so a gigabyte is an unbounded allocation;
  # -timeout: a single input taking 10 s is a hang.
  if cargo fuzz run --fuzz-dir tests/fuzz -O -s none "$t" -- \
      -max_total_time="$secs" -timeout=10 -rss_limit_mb=1024 -max_len=65536 \
      -print_final_stats=1 > "$log" 2>&1; then
    verdict=ok
  else
    verdict=FOUND
    status=1
  fi
  stat() { grep -m1 "^stat::$1:" "$log" | awk '{print $2}'; }
  found=$(find "tests/fuzz/artifacts/$t" -type f | wc -l)
  corpus=$(find "tests/fuzz/corpus/$t" -type f | wc -l)
  echo "$t: $verdict, ${secs} s, $(stat number_of_executed_units) executions," \
    "$(stat average_exec_per_sec) exec/s, peak RSS $(stat peak_rss_mb) MB, corpus $corpus," \
    "artifacts $found"
  if [ "$verdict" != ok ]; then
    grep -E "ERROR|panicked|Test unit written|SUMMARY" "$log" | head -5
  fi
done
exit $status
