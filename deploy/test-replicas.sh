#!/usr/bin/env bash
# shellcheck source-path=SCRIPTDIR
# Replicas that take over (docs/deploy.md, "Replicas"). Three server containers on one Docker
# network share a volume (the case, its LIBR basis cache, the session journal; each replica keeps
# its own audit log there); a client container streams 8 sessions spread over the three
# (`replay --server A,B,C --resume`):
#   1. the reference: no faults;
#   2. failover: 10 times, `docker kill` (SIGKILL) of the replica serving the most sessions
#      (read from its metrics), restarted and SERVING again before the next kill;
#   3. rolling restart: each replica in turn stopped (SIGTERM: it drains, its sessions resume on
#      the others), started, SERVING, under 8 streams.
# Runs 2 and 3 must complete every session with the reference's last answers and lose no
# acknowledged registration (deploy/test/check_replicas.py). Figures go to stdout.
# shellcheck source=test/lib.sh
source "$(dirname "$0")/test/lib.sh"
kills="${KILLS:-10}"
replicas=(r1 r2 r3)

make_demo_case
for r in "${replicas[@]}"; do start_server "$r" --max-sessions 8; done
for r in "${replicas[@]}"; do echo "$r SERVING after $(wait_serving "$r") s"; done
servers="http://r1:50051,http://r2:50051,http://r3:50051"
common=(--server "$servers" --token "$token" --data /var/lib/librplus/demo --concurrency 8
        --methods libr --time-budget-ms 10000 --resume --resume-attempts 60 --timeout-s 120 --json)

# 1. The reference: 30 scenarios without faults; the faulted runs replay the 8 longest.
t0=$(now)
client replay "${common[@]}" --limit 30 >"$work/reference.json" 2>"$work/reference.log"
read -r rate chosen <<<"$(python3 - "$work/reference.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
assert s["failed"] == 0, "the reference run failed"
longest = sorted(s["results"], key=lambda r: (-r["messages"], r["scenario"]))[:8]
m = [r["messages"] for r in longest]
# Paced so that the longest session lasts ~70 s (the shortest of the 8 ~70 * min/max s): the
# faults land mid-stream.
print(f"{max(m) / 70.0:.3f}", ",".join(r["scenario"] for r in longest))
PY
)"
echo "reference: 30 sessions in $(since "$t0") s; the faulted runs replay 8 of them ($chosen) at $rate messages/s per session"
common+=(--scenarios "$chosen")

ip_of() { docker inspect -f "{{(index .NetworkSettings.Networks \"$net\").IPAddress}}" "$1"; }
# The replica with the most open sessions (librplus_sessions_active on its metrics port).
busiest() {
  local best="-" most=0 n r
  for r in "${replicas[@]}"; do
    n=$(python3 - "$(ip_of "$r")" <<'PY' 2>/dev/null || echo 0
import sys, urllib.request
text = urllib.request.urlopen(f"http://{sys.argv[1]}:9090/metrics", timeout=2).read().decode()
print(int(sum(float(l.split()[-1]) for l in text.splitlines()
              if l.startswith("librplus_sessions_active"))))
PY
)
    if [ "${n:-0}" -gt "$most" ]; then most=$n; best=$r; fi
  done
  echo "$best $most"
}

start_client() {
  containers+=("$1")
  docker run -d --name "$1" --network "$net" -v "$vol:/var/lib/librplus:ro" \
    --entrypoint librplus-client "$image" replay "${common[@]}" --rate "$rate" >/dev/null
}
finish_client() {
  local code
  code=$(docker wait "$1")
  docker logs "$1" >"$work/$1.json" 2>"$work/$1.log"
  [ "$code" = 0 ] || { echo "$1 exited $code:" >&2; tail -20 "$work/$1.log" >&2; return 1; }
}
copy_audit() {
  rm -rf "$work/audit"
  docker cp "r1:/var/lib/librplus/audit" "$work/audit"
}

# 2. Failover: kill -9 the busiest replica, 10 times.
start_client failover
sleep 5
t0=$(now)
done_kills=0
restart_s=()
while [ "$done_kills" -lt "$kills" ]; do
  [ "$(docker inspect -f '{{.State.Running}}' failover)" = true ] \
    || { echo "the sessions ended after $done_kills kills: slow them down (messages/s $rate)" >&2; exit 1; }
  read -r victim open <<<"$(busiest)"
  if [ "$victim" = - ]; then sleep 0.5; continue; fi
  docker kill "$victim" >/dev/null
  done_kills=$((done_kills + 1))
  t1=$(now)
  docker start "$victim" >/dev/null
  wait_serving "$victim" >/dev/null
  restart_s+=("$(since "$t1")")
  echo "kill $done_kills: $victim (serving $open sessions) killed at $(since "$t0") s; SERVING again after ${restart_s[-1]} s"
  sleep 1
done
finish_client failover
copy_audit
python3 "$(dirname "$0")/test/check_replicas.py" "$work/reference.json" "$work/failover.json" \
  "$work/audit" "failover: $kills kill -9"

# 3. Rolling restart under 8 streams.
start_client rolling
sleep 5
for r in "${replicas[@]}"; do
  t1=$(now)
  docker stop -t 60 "$r" >/dev/null
  stopped=$(since "$t1")
  docker start "$r" >/dev/null
  s=$(wait_serving "$r")
  echo "rolling restart: $r drained and stopped in $stopped s (exit $(docker inspect -f '{{.State.ExitCode}}' "$r") before restart), SERVING again after $s s"
  sleep 3
done
[ "$(docker inspect -f '{{.State.Running}}' rolling)" = true ] \
  || echo "note: the sessions ended before the last replica restarted" >&2
finish_client rolling
copy_audit
python3 "$(dirname "$0")/test/check_replicas.py" "$work/reference.json" "$work/rolling.json" \
  "$work/audit" "rolling restart"
python3 - "$work/rolling.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
bad = sum(1 for r in s["results"] for st in r["steps"] if st.get("error")) + s["rejections"]
print(json.dumps({"run": "rolling restart", "failed_registrations": bad + s["failed"]}))
assert bad + s["failed"] == 0
PY
echo "memory after the runs: $(docker stats --no-stream --format '{{.Name}} {{.MemUsage}}' "${replicas[@]}" | tr '\n' ';')"
echo "replica test passed"
