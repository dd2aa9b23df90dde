#!/usr/bin/env bash
# Issue 11: wall time of the SLURM path (plan, one array job per phase chained with afterok,
# finish) against `qemd denoise` on the same input and flags, in one run; checks the bytes match.
#
#   benches/slurm.sh [POINTS] [TASKS]   (default 2000000 points; arrays of the plan's task
#                                        counts, or of at most TASKS tasks)
#
# Needs the cluster of `.ci/slurm.sh start` (or SLURM_CONF) and `cargo build --release`.
set -euo pipefail
cd "$(dirname "$0")/.."
points=${1:-2000000}
tasks=${2:-1000000000}
export SLURM_CONF=${SLURM_CONF:-$PWD/target/slurm/slurm.conf}
q=$PWD/target/release/qemd
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
flags=(--tile-points 200000 --outliers classify)
now() { date +%s.%N; }

"$q" synth step --points "$points" -o "$d/in.ply"
"$q" noise "$d/in.ply" -o "$d/noisy.ply" >/dev/null

s=$(now)
"$q" denoise "$d/noisy.ply" -o "$d/denoise.ply" -q "${flags[@]}"
denoise=$(echo "$(now) - $s" | bc)

s=$(now)
"$q" plan "$d/noisy.ply" --work "$d/work" --json "${flags[@]}" >"$d/plan.json"
dep=""
for p in partition globals tiles stitch; do
  n=$(python3 -c "import json; print(json.load(open('$d/plan.json'))['tasks']['$p'])")
  [ "$n" -gt 0 ] || continue
  ((n <= tasks)) || n=$tasks
  dep=$(sbatch --parsable --job-name="qemd-$p" --array=0-$((n - 1)) -c 1 \
    ${dep:+--dependency=afterok:$dep} --output="$d/%x-%A_%a.out" \
    --wrap "exec $q worker --work file://$d/work --phase $p --threads 1 -q")
done
start=$SECONDS
until [ "$(squeue -h -r -t all -j "$dep" -o %T | sort -u)" = COMPLETED ]; do
  ((SECONDS - start < 1800)) || { echo "slurm jobs not done after 30 min" >&2; exit 1; }
  sleep 0.5
done
"$q" finish --work "file://$d/work" -o "$d/slurm.ply" -q
slurm=$(echo "$(now) - $s" | bc)

cmp "$d/denoise.ply" "$d/slurm.ply"
tiles=$(python3 -c "import json; print(json.load(open('$d/plan.json'))['tiles'])")
echo "points $points, tiles $tiles, arrays of at most $tasks tasks (-c 1, --threads 1), $(nproc) cores"
echo "qemd denoise (all cores): $denoise s"
echo "SLURM path (plan..finish): $slurm s"
echo "bytes identical"
