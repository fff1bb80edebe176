#!/usr/bin/env bash
# shellcheck source-path=SCRIPTDIR
# Sharded dataset generation in containers (docs/deploy.md, "Datasets at scale"): the command of
# the Kubernetes Indexed Job (`librplus generate --shard i/N`, then once without --shard for the
# manifest) run as N containers on this machine, for N = 1, 2, 4, into one volume. Every file of
# the N = 2 and N = 4 datasets must be byte-identical to the N = 1 run's (SHA-256 of each file,
# the manifest among them); the wall times go to stdout. SHARDS="1 2 4" and GENERATE_ARGS
# override the defaults; SHARD_CPUS=C gives each container C cores (`docker run --cpus`), as a
# pod's CPU limit would.
# shellcheck source=test/lib.sh
source "$(dirname "$0")/test/lib.sh"
read -r -a gen <<<"${GENERATE_ARGS:---preset small --seed 11 --edge-mm 9 --deformations 4}"
shards="${SHARDS:-1 2 4}"

generate() { # NAME OUT [--shard i/N]
  local name=$1 out=$2
  shift 2
  containers+=("$name")
  docker run -d --name "$name" ${SHARD_CPUS:+--cpus "$SHARD_CPUS"} --read-only --tmpfs /tmp \
    -v "$vol:/var/lib/librplus" \
    --entrypoint librplus "$image" generate "${gen[@]}" --out "$out" "$@" >/dev/null
}
wait_ok() {
  local code
  code=$(docker wait "$1")
  [ "$code" = 0 ] || { echo "$1 exited $code:" >&2; docker logs --tail 20 "$1" >&2; return 1; }
  # The container's own run time (start to exit).
  python3 - "$1" "$(docker inspect -f '{{.State.StartedAt}} {{.State.FinishedAt}}' "$1")" <<'PY'
import sys
from datetime import datetime
def t(s):
    s = s.rstrip("Z")
    head, _, frac = s.partition(".")
    return datetime.fromisoformat(head).timestamp() + float("0." + (frac or "0"))
a, b = sys.argv[2].split()
print(f"  {sys.argv[1]}: {t(b) - t(a):.1f} s")
PY
  docker rm "$1" >/dev/null
}
hashes() {
  docker run --rm -v "$vol:/var/lib/librplus:ro" --entrypoint sh "$image" -c \
    "cd /var/lib/librplus/shards/$1 && find . -type f | LC_ALL=C sort | xargs sha256sum"
}

declare -A wall
for n in $shards; do
  out="/var/lib/librplus/shards/n$n"
  t0=$(now)
  if [ "$n" = 1 ]; then
    generate "gen-n1" "$out"
    wait_ok "gen-n1"
  else
    for ((i = 0; i < n; i++)); do generate "gen-n$n-$i" "$out" --shard "$i/$n"; done
    for ((i = 0; i < n; i++)); do wait_ok "gen-n$n-$i"; done
    t_shards=$(since "$t0")
    generate "gen-n$n-manifest" "$out"
    wait_ok "gen-n$n-manifest"
    echo "N = $n: shards done after $t_shards s"
  fi
  wall[$n]=$(since "$t0")
  hashes "n$n" >"$work/n$n.sha256"
  echo "N = $n: $(wc -l <"$work/n$n.sha256") files, wall $(printf %s "${wall[$n]}") s, manifest $(grep ' ./manifest.json$' "$work/n$n.sha256" | cut -c1-16)"
done
first=$(echo "$shards" | awk '{print $1}')
for n in $shards; do
  if ! diff -q "$work/n$first.sha256" "$work/n$n.sha256" >/dev/null; then
    echo "N = $n differs from N = $first:" >&2
    diff "$work/n$first.sha256" "$work/n$n.sha256" | head -20 >&2
    exit 1
  fi
done
python3 - "$work/n$first.sha256" <<'PY'
import sys
print(f"byte-identical: every one of {sum(1 for _ in open(sys.argv[1]))} files, manifest included")
PY
echo "shard test passed"
