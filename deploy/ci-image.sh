#!/usr/bin/env bash
# CI's image (docs/deploy.md#the-image-in-ci). The in-Docker build (deploy/Dockerfile: Rust from
# Debian, every crate compiled inside the build stage) is run when what it depends on changed
# since it last passed: deploy/Dockerfile, Cargo.lock and the workspace's manifests, whose
# SHA-256 are recorded in deploy/in-docker-build.sha256. Otherwise the image is the same
# Dockerfile's run stage over release binaries built here, which saves the in-Docker build
# (about 16 minutes on 2 cores).
#
#   deploy/ci-image.sh           # build librplus:VERSION the way CI does
#   deploy/ci-image.sh --stamp   # after the in-Docker build passed: record what it was built from
set -euo pipefail
cd "$(dirname "$0")/.."
stamp=deploy/in-docker-build.sha256
inputs=(deploy/Dockerfile Cargo.lock Cargo.toml proto/Cargo.toml server/Cargo.toml client/Cargo.toml igtl/Cargo.toml)

if [ "${1:-}" = --stamp ]; then
  sha256sum "${inputs[@]}" >"$stamp"
  echo "recorded in $stamp:"
  cat "$stamp"
  exit 0
fi
[ $# = 0 ] || { echo "ci-image.sh: unknown argument $1 (see the comment at its top)" >&2; exit 2; }

if [ "$(sha256sum "${inputs[@]}")" = "$(cat "$stamp" 2>/dev/null)" ]; then
  echo "the Dockerfile, Cargo.lock and the manifests are as when the in-Docker build last passed ($stamp):"
  echo "the image is the run stage over release binaries built here"
  target="${CARGO_TARGET_DIR:-target}"
  CARGO_PROFILE_RELEASE_DEBUG=0 cargo build --release --locked --bins \
    -p librplus -p librplus-server -p librplus-client
  deploy/build-image.sh --prebuilt "$target/release"
else
  echo "changed since the in-Docker build last passed ($stamp):"
  sha256sum --check "$stamp" 2>&1 | grep -v ': OK$' || true
  echo "so the image is built inside Docker; once it passes, record it with deploy/ci-image.sh --stamp"
  deploy/build-image.sh
fi
