#!/usr/bin/env bash
# Builds the LIBR+ image from deploy/Dockerfile (docs/deploy.md).
#
#   deploy/build-image.sh [--gpu] [--tag NAME:TAG] [--prebuilt DIR]
#
# Where no container registry can be reached, the Debian base the Dockerfile names
# (debian:trixie-slim) is first made locally from Debian's packages: debootstrap (minbase) into a
# folder, trimmed as Debian's own slim images are (no docs, man pages or locales), then
# `docker import`ed under that name. Where the base exists already (pulled, or made before) it is
# used as it is. `--gpu` builds the training image: cargo feature `librplus/gpu` and the Vulkan
# loader (`libvulkan1`), tagged `librplus:VERSION-gpu`. `--prebuilt DIR` skips the build stage:
# the run stage of the same Dockerfile takes `librplus`, `librplus-server` and `librplus-client`
# from DIR (release binaries built on this host, as CI does: docs/deploy.md); where they do not
# run inside the image (a host newer than Debian trixie), the in-Docker build is used instead.
set -euo pipefail
cd "$(dirname "$0")/.."

gpu=0
tag=""
prebuilt=""
while [ $# -gt 0 ]; do
  case "$1" in
    --gpu) gpu=1 ;;
    --tag) tag="$2"; shift ;;
    --prebuilt) prebuilt="$2"; shift ;;
    -h|--help) sed -n '2,16p' "$0"; exit 0 ;;
    *) echo "build-image.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
  shift
done

base="debian:trixie-slim"
suite="trixie"
mirror="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
version=$(sed -n 's/^version = "\(.*\)"/\1/p' Cargo.toml | head -1)
commit=$(git rev-parse HEAD 2>/dev/null || echo unknown)
if [ "$commit" != unknown ] && [ -n "$(git status --porcelain --untracked-files=no 2>/dev/null)" ]; then
  commit="$commit-dirty"
fi

if ! docker image inspect "$base" >/dev/null 2>&1; then
  echo "== making the base $base from Debian's packages (debootstrap --variant=minbase $suite)"
  if ! command -v debootstrap >/dev/null; then
    if [ "$(id -u)" = 0 ]; then
      apt-get install -y -q debootstrap >/dev/null 2>&1 \
        || { apt-get update -q >/dev/null && apt-get install -y -q debootstrap >/dev/null; }
    else
      echo "build-image.sh: debootstrap is needed to make $base (apt-get install debootstrap)" >&2
      exit 1
    fi
  fi
  rootfs=$(mktemp -d "${TMPDIR:-/tmp}/librplus-rootfs.XXXXXX")
  trap 'rm -rf "$rootfs"' EXIT
  debootstrap --variant=minbase "$suite" "$rootfs" "$mirror" >"$rootfs.log" 2>&1 \
    || { tail -20 "$rootfs.log" >&2; exit 1; }
  rm -f "$rootfs.log"
  # As Debian's slim images: no documentation but the copyright files, no man pages or locales.
  rm -rf "$rootfs"/usr/share/doc/* "$rootfs"/usr/share/man/* "$rootfs"/usr/share/info/* \
    "$rootfs"/var/cache/apt/*.bin "$rootfs"/var/lib/apt/lists/*
  mkdir -p "$rootfs/etc/dpkg/dpkg.cfg.d"
  cat >"$rootfs/etc/dpkg/dpkg.cfg.d/docker-slim" <<'CFG'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
CFG
  tar --numeric-owner -C "$rootfs" -c . | docker import \
    --change 'CMD ["bash"]' \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change "LABEL org.opencontainers.image.description=\"Debian $suite minbase, made locally by debootstrap\"" \
    - "$base" >/dev/null
  rm -rf "$rootfs"
  trap - EXIT
fi

# The host's locally added CAs (a TLS-inspecting proxy's), for the build stage's downloads.
rm -f deploy/build-ca/*.crt
for c in /usr/local/share/ca-certificates/*.crt; do
  [ -f "$c" ] && cp "$c" deploy/build-ca/
done

args=(--build-arg "VERSION=$version" --build-arg "COMMIT=$commit")
if [ "$gpu" = 1 ]; then
  args+=(--build-arg "CARGO_FEATURES=librplus/gpu" --build-arg "RUNTIME_PACKAGES=libvulkan1")
  tag="${tag:-librplus:$version-gpu}"
else
  tag="${tag:-librplus:$version}"
fi
# The classic builder: this machine's Docker client has no buildx, and the Dockerfile needs
# nothing BuildKit-only (its dependency layer is cached by the classic builder too).
build() {
  DOCKER_BUILDKIT=0 docker build -t "$tag" "${args[@]}" "$@" 2>&1 \
    | grep --line-buffered -v -e "DEPRECATED: The legacy builder" -e "BuildKit is currently disabled" \
        -e "Install the buildx component" -e "https://docs.docker.com/go/buildx/" -e '^ *$'
}
start=$(date +%s)
built=0
if [ -n "$prebuilt" ]; then
  [ "$gpu" = 0 ] || { echo "build-image.sh: --prebuilt makes the CPU image only" >&2; exit 2; }
  echo "== docker build: the run stage of deploy/Dockerfile over the binaries in $prebuilt (commit $commit)"
  rm -rf deploy/prebuilt
  mkdir -p deploy/prebuilt
  for b in librplus librplus-server librplus-client; do
    [ -x "$prebuilt/$b" ] || { echo "build-image.sh: no executable $prebuilt/$b" >&2; exit 1; }
    cp "$prebuilt/$b" deploy/prebuilt/
  done
  # One source for the run stage: the Dockerfile without its build stage, the binaries copied in.
  awk '/^# ---- build/ {skip = 1} /^# ---- run/ {skip = 0} !skip' deploy/Dockerfile \
    | sed 's|^COPY --from=build /out/ /usr/local/bin/$|COPY deploy/prebuilt/ /usr/local/bin/|' \
    >deploy/prebuilt/Dockerfile
  grep -q '^COPY deploy/prebuilt/ /usr/local/bin/$' deploy/prebuilt/Dockerfile \
    || { echo "build-image.sh: deploy/Dockerfile has no 'COPY --from=build /out/ /usr/local/bin/'" >&2; exit 1; }
  build -f deploy/prebuilt/Dockerfile .
  rm -rf deploy/prebuilt
  if docker run --rm --entrypoint librplus-server "$tag" --version >/dev/null 2>&1 \
     && docker run --rm --entrypoint librplus "$tag" --version >/dev/null 2>&1; then
    built=1
  else
    echo "== the binaries from $prebuilt do not run in $base (built against a newer C library?): building inside Docker"
  fi
fi
if [ "$built" = 0 ]; then
  echo "== docker build -f deploy/Dockerfile -t $tag (commit $commit)"
  build -f deploy/Dockerfile .
fi
size=$(docker image inspect "$tag" --format '{{.Size}}')
echo "== built $tag in $(( $(date +%s) - start )) s: $(( size / 1000000 )) MB"
