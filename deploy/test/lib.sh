# Shared by the deploy tests (sourced): the image tag, a private network and volume per run,
# an auth file with a fresh token, waiting for SERVING, and clean-up of everything a run made.
# shellcheck shell=bash
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
version=$(sed -n 's/^version = "\(.*\)"/\1/p' "$root/Cargo.toml" | head -1)
image="${LIBRPLUS_IMAGE:-librplus:$version}"
run_id="librplus-test-$$"
net="$run_id"
vol="$run_id-data"
work=$(mktemp -d "${TMPDIR:-/tmp}/$run_id.XXXXXX")
containers=()

cleanup() {
  local rc=$?
  for c in "${containers[@]}"; do docker rm -f "$c" >/dev/null 2>&1 || true; done
  docker network rm "$net" >/dev/null 2>&1 || true
  docker volume rm "$vol" >/dev/null 2>&1 || true
  rm -rf "$work"
  exit $rc
}
trap cleanup EXIT

if ! docker image inspect "$image" >/dev/null 2>&1; then
  echo "no image $image: build it with deploy/build-image.sh" >&2
  exit 1
fi
docker network create "$net" >/dev/null
docker volume create "$vol" >/dev/null

now() { date +%s.%N; }
since() { python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.1f}')" "$1" "$(now)"; }

# A bearer token for the tests and an auth file that holds only its SHA-256 (docs/service.md).
# Its principal is the one client of the tests, streaming 8 sessions: its own session limit is
# the servers' 8 (a principal's default is half of max_sessions when an auth file names them).
token=$(head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n')
mkdir -p "$work/auth"
cat >"$work/auth/auth.json" <<JSON
{"format": 1, "open_health": true, "open_reflection": true, "principals": [
  {"principal": "deploy-test", "token_sha256": ["$(printf %s "$token" | sha256sum | cut -d' ' -f1)"],
   "cases": ["*"], "roles": ["read", "register", "manage"], "max_sessions": 8}]}
JSON
chmod 755 "$work/auth"
chmod 644 "$work/auth/auth.json"

# The default case (the demo's) made inside the volume by the image itself.
make_demo_case() {
  local t0
  t0=$(now)
  docker run --rm -v "$vol:/var/lib/librplus" "$image" demo --only-data --data /var/lib/librplus/demo
  echo "default case made in the volume in $(since "$t0") s"
}

# Starts server container NAME (hostname NAME) on the network, as Kubernetes runs it: read-only
# root filesystem, /tmp in memory, the shared volume, the auth file; extra args go to `serve`.
start_server() {
  local name=$1
  shift
  containers+=("$name")
  docker run -d --name "$name" --hostname "$name" --network "$net" \
    --read-only --tmpfs /tmp --cap-drop ALL --security-opt no-new-privileges \
    -v "$vol:/var/lib/librplus" -v "$work/auth:/etc/librplus/auth:ro" \
    "$image" serve --config /etc/librplus/server.json --cases /var/lib/librplus/demo "$@" >/dev/null
}

# Waits (up to $2 s, default 300) until NAME answers SERVING; prints the seconds it took.
wait_serving() {
  local name=$1 limit=${2:-300} t0
  t0=$(now)
  while ! docker exec "$name" librplus-server health --timeout-s 2 >/dev/null 2>&1; do
    if [ "$(docker inspect -f '{{.State.Running}}' "$name")" != true ]; then
      echo "$name stopped before SERVING:" >&2
      docker logs --tail 30 "$name" >&2
      return 1
    fi
    if python3 -c "import sys; sys.exit(0 if float(sys.argv[1]) > float(sys.argv[2]) else 1)" "$(since "$t0")" "$limit"; then
      echo "$name not SERVING after $limit s" >&2
      docker logs --tail 30 "$name" >&2
      return 1
    fi
    sleep 0.2
  done
  since "$t0"
}

# Runs librplus-client in a container on the network (the dataset read-only from the volume).
client() {
  docker run --rm --network "$net" -v "$vol:/var/lib/librplus:ro" --entrypoint librplus-client \
    "$image" "$@"
}
