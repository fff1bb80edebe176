#!/usr/bin/env bash
# Offline checks of the deploy files (CI runs it): the renderer's own tests, every overlay
# rendered and validated with `kubernetes-validate --strict` against Kubernetes 1.37 (no unknown
# fields, every required one), the Dockerfile linted with hadolint, the scripts with shellcheck. The tools come from PyPI
# (tests/reference/requirements-ci.txt); LIBRPLUS_PYTHON is the interpreter whose environment
# has them.
set -euo pipefail
cd "$(dirname "$0")/.."
py="${LIBRPLUS_PYTHON:-python3}"
bin="$(dirname "$py")"
k8s_version="${K8S_VERSION:-1.37.0}"
out=$(mktemp -d "${TMPDIR:-/tmp}/librplus-manifests.XXXXXX")
trap 'rm -rf "$out"' EXIT

"$py" deploy/k8s/test_render.py 2>&1 | tail -1
for overlay in dev prod gpu; do
  LIBRPLUS_PYTHON="$py" deploy/k8s/render.sh "$overlay" "$out/$overlay"
  "$bin/kubernetes-validate" --strict -k "$k8s_version" "$out/$overlay"/*.yaml >"$out/$overlay.log" 2>&1 \
    || { cat "$out/$overlay.log" >&2; exit 1; }
  echo "$overlay: $(grep -c ' passed ' "$out/$overlay.log") objects pass kubernetes-validate --strict (Kubernetes $k8s_version)"
done
"$bin/hadolint" deploy/Dockerfile
echo "hadolint: deploy/Dockerfile passes (ignored rules are justified in the file)"
"$bin/shellcheck" -x deploy/*.sh deploy/test/lib.sh deploy/k8s/render.sh .ci/run clients/python/ci.sh
echo "shellcheck: the deploy scripts and .ci/run pass"
