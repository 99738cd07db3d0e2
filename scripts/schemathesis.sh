#!/usr/bin/env bash
# Runs schemathesis (PyPI; installed into a venv under ~/.cache/relfusion) against the
# OpenAPI document of a live relfusiond with tokens, as a tenant with one live session to
# test the `{id}` routes on. Loopback only; bounded by --max-time. The
# WebSocket (`/stream`) is left out: schemathesis speaks HTTP only (tests/service_http has it).
#   bash scripts/schemathesis.sh [MAX_SECONDS]          (after `cargo build -p relfusion-server`)
set -euo pipefail
cd "$(dirname "$0")/.."
MAX_SECONDS="${1:-300}"
VENV="${XDG_CACHE_HOME:-$HOME/.cache}/relfusion/schemathesis"
[ -x "$VENV/bin/st" ] || { python3 -m venv "$VENV" && "$VENV/bin/pip" install -q schemathesis; }
BIN="${CARGO_TARGET_DIR:-target}/debug"
WORK=$(mktemp -d)
trap 'kill "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; rm -rf "$WORK"' EXIT
RELFUSIOND_TOKENS="alice:st-token-a,bob:st-token-b" "$BIN/relfusiond" \
  --listen 127.0.0.1:0 --data-dir "$WORK/data" > "$WORK/out" 2> "$WORK/log" &
PID=$!
for _ in $(seq 100); do grep -q "listening on" "$WORK/out" 2>/dev/null && break; sleep 0.1; done
URL="http://$(sed -n 's/^listening on //p' "$WORK/out")"
AUTH="Authorization: Bearer st-token-a"
camera='{"fx":262.5,"fy":262.5,"cx":159.5,"cy":119.5,"width":320,"height":240}'
SESSION=$(curl -sf -H "$AUTH" -H 'Content-Type: application/json' \
  -d "{\"camera\":$camera,\"policy\":\"wait\"}" "$URL/v1/sessions" | python3 -c 'import json,sys;print(json.load(sys.stdin)["id"])')
cat > "$WORK/schemathesis.toml" <<TOML
headers = { Authorization = "Bearer st-token-a" }
request-timeout = 30.0
[parameters]
"path.id" = "$SESSION"
TOML
echo "schemathesis against $URL (session $SESSION, at most $MAX_SECONDS s)"
status=0
"$VENV/bin/st" --config-file "$WORK/schemathesis.toml" run "$URL/openapi.json" \
  --checks all --max-time "$MAX_SECONDS" --max-examples 100 \
  --exclude-path-regex "/stream$" || status=$?
grep -E "panicked|ERROR" "$WORK/log" && status=1
exit $status
