#!/usr/bin/env bash
# shellcheck source-path=SCRIPTDIR
# CI's check of the image (docs/deploy.md): runs the container as Kubernetes would (read-only
# root filesystem, no capabilities, non-root), waits for grpc.health.v1 SERVING, replays the
# demo's scenarios against it from a client container, and reports the image size and the
# seconds from `docker run` to SERVING. Build the image first (deploy/build-image.sh).
# shellcheck source=test/lib.sh
source "$(dirname "$0")/test/lib.sh"

size=$(docker image inspect "$image" --format '{{.Size}}')
user=$(docker image inspect "$image" --format '{{.Config.User}}')
[ "$user" = "10001:10001" ] || { echo "the image runs as '$user', not 10001:10001" >&2; exit 1; }
echo "image $image: $(( size / 1000000 )) MB, user $user, labels:"
docker image inspect "$image" --format '{{range $k, $v := .Config.Labels}}  {{$k}}={{$v}}{{"\n"}}{{end}}'

make_demo_case
t0=$(now)
start_server librplus-server
serving=$(wait_serving librplus-server)
echo "start to SERVING: $(since "$t0") s (the health probe saw SERVING after $serving s of polling)"
# Docker's own HEALTHCHECK (the image's) reports healthy too.
for _ in $(seq 1 60); do
  h=$(docker inspect -f '{{.State.Health.Status}}' librplus-server)
  [ "$h" = healthy ] && break
  sleep 1
done
echo "docker health: $h"
[ "$h" = healthy ]

# The demo's replay, over the network, with the bearer token.
client replay --server http://librplus-server:50051 --token "$token" \
  --data /var/lib/librplus/demo --limit 10 --methods rigid,libr,libr_plus --json >"$work/replay.json"
python3 - "$work/replay.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print(f"replay against the container: {s['scenarios']} scenarios, {s['sessions']} sessions, "
      f"{s['failed']} failed, {s['updates']} updates, TRE {s.get('tre_mm')}")
assert s["sessions"] == 3 * s["scenarios"] and s["scenarios"] >= 10, "sessions missing"
assert s["failed"] == 0, "a session failed"
PY
# Without the token: refused.
client replay --server http://librplus-server:50051 --data /var/lib/librplus/demo --limit 1 \
  --json >"$work/noauth.json" 2>&1 || true
grep -q UNAUTHENTICATED "$work/noauth.json" \
  || { echo "a replay without a token was not refused UNAUTHENTICATED:" >&2; tail -5 "$work/noauth.json" >&2; exit 1; }
echo "replay without a token: UNAUTHENTICATED"
# The server wrote only to its volume (the root filesystem is read-only) and runs as 10001.
docker exec librplus-server sh -c 'id -u; ls /var/lib/librplus' | tr '\n' ' '
echo
mem=$(docker stats --no-stream --format '{{.MemUsage}}' librplus-server)
echo "server memory after the replay: $mem"
# SIGTERM drains and exits 0.
t0=$(now)
docker stop -t 30 librplus-server >/dev/null
code=$(docker inspect -f '{{.State.ExitCode}}' librplus-server)
echo "docker stop: exit code $code after $(since "$t0") s"
[ "$code" = 0 ]
echo "image test passed"
