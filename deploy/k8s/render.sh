#!/usr/bin/env bash
# Writes an overlay's final manifests: deploy/k8s/render.sh OVERLAY OUT_DIR
# (OVERLAY: dev, prod or gpu, or a folder with a kustomization.yaml). Needs Python 3 with PyYAML
# (`pip install pyyaml`); LIBRPLUS_PYTHON picks the interpreter. See render.py for what it does.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
if [ $# -ne 2 ]; then
  echo "usage: deploy/k8s/render.sh OVERLAY OUT_DIR   (OVERLAY: dev, prod, gpu)" >&2
  exit 2
fi
overlay="$1"
[ -d "$overlay" ] || overlay="$here/overlays/$1"
[ -d "$overlay" ] || { echo "render.sh: no overlay $1 (dev, prod, gpu)" >&2; exit 2; }
py="${LIBRPLUS_PYTHON:-python3}"
"$py" -c "import yaml" 2>/dev/null \
  || { echo "render.sh: $py has no PyYAML (pip install pyyaml)" >&2; exit 1; }
exec "$py" "$here/render.py" "$overlay" "$2"
