#!/usr/bin/env bash
# The service table of BENCHMARKS.md rerun three ways in one run, alternating: plain; TLS (mTLS)
# + auth; TLS (mTLS) + auth + audit log. Release build; the server and the load client share the
# machine. Usage: server/bench/secure-service.sh [DATA_DIR] (default: the demo's case; run
# `cargo run --release -p librplus-server -- demo` once first). DUR, CONC, ROUNDS, BUDGET set the
# load (defaults 30 s, 8 streams, 2 rounds, the server's 250 ms).
set -euo pipefail
cd "$(dirname "$0")/../.."
bin="${CARGO_TARGET_DIR:-$HOME/.cache/librplus-target}/release"
data="${1:-${XDG_CACHE_HOME:-$HOME/.cache}/librplus/demo-v1}"
dur="${DUR:-30}"; conc="${CONC:-8}"; rounds="${ROUNDS:-2}"
work="$(mktemp -d)"
trap 'kill "${server:-0}" 2>/dev/null || true; rm -rf "$work"' EXIT
"$bin/librplus-server" dev-certs --out "$work/certs" --client bench 2>/dev/null
token="bench-$(date +%s%N)"
hash="$(printf %s "$token" | sha256sum | cut -d' ' -f1)"
cat > "$work/auth.json" <<JSON
{"format": 1, "principals": [{"principal": "bench", "token_sha256": ["$hash"], "cases": ["*"], "roles": ["register"]}]}
JSON
port=50077
run() { # name, server flags..., --, client flags...
  local name="$1"; shift
  local sflags=() cflags=()
  while [ "$1" != "--" ]; do sflags+=("$1"); shift; done; shift
  cflags=("$@")
  rm -f "$work/audit.db"*
  "$bin/librplus-server" --cases "$data" --listen "127.0.0.1:$port" "${sflags[@]}" 2> "$work/server.log" &
  server=$!
  for _ in $(seq 600); do grep -q "^preloaded" "$work/server.log" && break; sleep 0.1; done
  "$bin/librplus-client" load --server "http://127.0.0.1:$port" --data "$data" --limit 40 \
    --duration "$dur" --concurrency "$conc" ${BUDGET:+--time-budget-ms $BUDGET} --json "${cflags[@]}" \
    > "$work/$name.json"
  local audited=""
  if curl -sf "http://127.0.0.1:9478/metrics" > "$work/metrics.txt" 2>/dev/null; then
    python3 - "$work/metrics.txt" >&2 <<'PY'
import sys
m = {}
for line in open(sys.argv[1]):
    if line.startswith("librplus_audit_commit_seconds_") and "{" not in line.split()[0]:
        k, v = line.split()
        m[k] = float(v)
n = m.get("librplus_audit_commit_seconds_count", 0)
if n:
    print(f"audit commits: {int(n)}, mean {1e3 * m['librplus_audit_commit_seconds_sum'] / n:.2f} ms", file=sys.stderr)
PY
  fi
  if [ -f "$work/audit.db" ]; then
    audited="$(python3 -c "import sqlite3,sys; c=sqlite3.connect(sys.argv[1]); print(c.execute('select count(*) from registrations').fetchone()[0])" "$work/audit.db")"
  fi
  kill -TERM "$server"; wait "$server" || true
  python3 - "$name" "$work/$name.json" "$audited" <<'PY'
import json, sys
name, path, audited = sys.argv[1], sys.argv[2], sys.argv[3]
s = json.load(open(path))
l = s["latency_ms"]
err = sum(s["errors"].values()) + sum(s["session_errors"].values())
q = s["quality"]; m = s["method_used"]
full = q.get("QUALITY_OK", 0) + q.get("QUALITY_NOT_CONVERGED", 0)
deg = q.get("QUALITY_DEGRADED", 0)
print(f"| {name} | {s['registrations_per_s']:.1f} | {l['p50']:.1f} | {l['p95']:.1f} | {l['p99']:.1f} | {l['max']:.1f} | {err} | {full} / {deg} | {audited or '-'} |")
PY
}
echo "| configuration | updates/s | p50 ms | p95 ms | p99 ms | max ms | errors | full / degraded | audited registrations |"
echo "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"
c="$work/certs"
for r in $(seq "$rounds"); do
  run "plain (round $r)" --
  run "mTLS + auth (round $r)" --tls-cert "$c/localhost.pem" --tls-key "$c/localhost.key" --client-ca "$c/ca.pem" --auth "$work/auth.json" -- \
    --ca "$c/ca.pem" --cert "$c/bench.pem" --key "$c/bench.key" --tls-domain localhost --token "$token"
  run "mTLS + auth + audit (round $r)" --tls-cert "$c/localhost.pem" --tls-key "$c/localhost.key" --client-ca "$c/ca.pem" --auth "$work/auth.json" --audit "$work/audit.db" --metrics-listen 127.0.0.1:9478 -- \
    --ca "$c/ca.pem" --cert "$c/bench.pem" --key "$c/bench.key" --tls-domain localhost --token "$token"
done
