#!/usr/bin/env bash
# schemathesis against the real `qemd serve` (issue 15): starts the server on 127.0.0.1:0 with a
# bearer token and a fresh data directory, runs every check of schemathesis on every operation
# of proto/openapi.yaml, stops the server. Outside the cargo suite.
#
#   tests/schemathesis.sh [QEMD_BINARY] [MAX_EXAMPLES]      (default target/debug/qemd, 30)
#
# Needs `schemathesis` on PATH, or SCHEMATHESIS=/path/to/schemathesis; e.g.
#   python3 -m venv /tmp/st && /tmp/st/bin/pip install schemathesis
#   SCHEMATHESIS=/tmp/st/bin/schemathesis tests/schemathesis.sh target/release/qemd
# Exit status: schemathesis's (0 when every check passed).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
repo=$(dirname "$here")
bin=${1:-$repo/target/debug/qemd}
examples=${2:-30}
st=${SCHEMATHESIS:-schemathesis}
work=$(mktemp -d)
token=schemathesis-token-1
cat > "$work/qemd.toml" <<TOML
auth_tokens = "$token:st"
max_sync_size = "4 MiB"
max_upload_size = "16 MiB"
TOML
QEMD_LISTEN=127.0.0.1:0 QEMD_DATA_DIR="$work/data" "$bin" serve --config "$work/qemd.toml" \
  > "$work/out" 2> "$work/server.log" &
pid=$!
trap 'kill "$pid" 2>/dev/null; wait "$pid" 2>/dev/null; rm -rf "$work"' EXIT
for _ in $(seq 1 600); do
  grep -q "listening on" "$work/out" 2>/dev/null && break
  kill -0 "$pid" 2>/dev/null || { cat "$work/server.log"; exit 1; }
  sleep 0.1
done
url=$(sed -n 's/^qemd: listening on //p' "$work/out")
[ -n "$url" ] || { echo "qemd serve did not start"; cat "$work/server.log"; exit 1; }
cd "$here/schemathesis"
status=0
SCHEMATHESIS_HOOKS=hooks "$st" --no-color --config-file schemathesis.toml run "$repo/proto/openapi.yaml" \
  --url "$url" -H "Authorization: Bearer $token" --checks all --max-examples "$examples" \
  --workers 2 --request-timeout 60 --seed "${SEED:-15}" || status=$?
if [ "$status" != 0 ]; then
  echo "--- server log, errors and warnings:"
  grep -E " (ERROR|WARN) " "$work/server.log" | tail -20 || true
fi
exit "$status"
