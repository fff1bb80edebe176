#!/usr/bin/env bash
# CI of the Python client package: a fresh venv in a temporary folder, `pip install
# ./clients/python` (the stubs generated from the proto at build), the unit tests (an in-process
# fake server), then, given a running server and the dataset it serves, the example against it.
#
# usage: clients/python/ci.sh [SERVER_URL DATASET_DIR]
# Environment (arguments win): LIBRPLUS_SERVER (URL), LIBRPLUS_DATA (dataset directory, e.g. the
# demo's default case from `librplus-server demo --only-data --data DIR`), LIBRPLUS_TOKEN (read by
# the example from the environment), LIBRPLUS_CA / LIBRPLUS_CERT / LIBRPLUS_KEY / LIBRPLUS_DOMAIN
# (TLS), LIBRPLUS_METHOD (libr), LIBRPLUS_MAX_TRE (fail above this final TRE, mm),
# LIBRPLUS_WAIT_S (300: how long to wait for the server to preload), PYTHON (python3).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
python="${PYTHON:-python3}"
server="${1:-${LIBRPLUS_SERVER:-}}"
data="${2:-${LIBRPLUS_DATA:-}}"
if [ -n "$server" ] && [ -z "$data" ]; then
  echo "ci.sh: a server ($server) but no dataset directory (second argument or LIBRPLUS_DATA)" >&2
  exit 2
fi

work="$(mktemp -d "${TMPDIR:-/tmp}/librplus-python-client.XXXXXX")"
trap 'rm -rf "$work"' EXIT
venv="$work/venv"

echo "-- fresh venv: $("$python" --version), pip install $here"
"$python" -m venv "$venv"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check "$here"
"$venv/bin/python" -m pip list --disable-pip-version-check 2>/dev/null \
  | grep -iE '^(librplus-client|grpcio|protobuf|numpy) ' | tr -s ' ' | paste -sd ',' -

echo "-- unit tests (a fake server in-process)"
# From the temporary folder, so that the installed package is the one imported.
(cd "$work" && "$venv/bin/python" -m unittest discover -s "$here/tests" -v)

if [ -z "$server" ]; then
  echo "-- no server given (SERVER_URL DATASET_DIR or LIBRPLUS_SERVER, LIBRPLUS_DATA): the example did not run"
  exit 0
fi
echo "-- the example against $server (dataset $data)"
args=(--server "$server" --data "$data" --method "${LIBRPLUS_METHOD:-libr}"
      --wait "${LIBRPLUS_WAIT_S:-300}")
[ -n "${LIBRPLUS_CA:-}" ] && args+=(--ca "$LIBRPLUS_CA")
[ -n "${LIBRPLUS_CERT:-}" ] && args+=(--cert "$LIBRPLUS_CERT")
[ -n "${LIBRPLUS_KEY:-}" ] && args+=(--key "$LIBRPLUS_KEY")
[ -n "${LIBRPLUS_DOMAIN:-}" ] && args+=(--domain "$LIBRPLUS_DOMAIN")
[ -n "${LIBRPLUS_MAX_TRE:-}" ] && args+=(--max-tre "$LIBRPLUS_MAX_TRE")
(cd "$work" && "$venv/bin/python" "$here/examples/replay_case.py" "${args[@]}")
echo "-- python client: passed"
