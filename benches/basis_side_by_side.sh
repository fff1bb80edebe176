#!/usr/bin/env bash
# Side-by-side: `librplus bench basis` vs ../shared/bench/fem_peer.py (scikit-fem + SciPy) on the same
# TetGen meshes of ../shared/data/sofa_liver.vtk, alternating runs in one session; prints JSON lines.
# Setup once: python3 -m venv .venv-peer && .venv-peer/bin/pip install scikit-fem meshio numpy scipy tetgen
# Usage: benches/basis_side_by_side.sh [RUNS=3] [MAX_TET_VOLUME_MM3 ...=40]
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-3}; shift || true
vols=("${@:-40}")
py=${PEER_PYTHON:-../.venv-peer/bin/python}
meshdir=${MESH_DIR:-target/bench-meshes}
mkdir -p "$meshdir"
cargo build --release --quiet
for v in "${vols[@]}"; do
  "$py" ../shared/bench/make_liver_tets.py ../shared/data/sofa_liver.vtk "$meshdir/liver_v$v" "$v" >&2
  mesh=$(ls "$meshdir"/liver_v"$v"_*.vtu | head -1)
  for r in $(seq "$runs"); do
    echo "{\"tool\":\"librplus\",\"run\":$r,\"result\":$(target/release/librplus bench basis --mesh "$mesh" --rhs 300 --json)}"
    echo "{\"tool\":\"fem_peer.py\",\"run\":$r,\"result\":$("$py" ../shared/bench/fem_peer.py "$mesh" 300)}"
  done
done
