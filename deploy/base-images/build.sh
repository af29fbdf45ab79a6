#!/usr/bin/env bash
# Builds the three base images the container test needs from Debian's packages, for machines
# that reach Debian's mirror and crates.io but no container registry (nothing is pulled):
#   posematch-local/runtime:bookworm   Debian bookworm minbase: the runtime stage's base
#                                      (stands in for debian:bookworm-slim)
#   posematch-local/rust:bookworm      the same plus gcc and this machine's Rust toolchain, with
#                                      every crate of Cargo.lock fetched and CARGO_NET_OFFLINE set
#                                      (stands in for rust:1.95-slim-bookworm)
#   posematch-local/postgres:bookworm  Debian's PostgreSQL with a small entrypoint that honours
#                                      POSTGRES_USER/PASSWORD/DB like the official image
#                                      (stands in for postgres:16-bookworm)
# Then build and run with them (deploy/README.md, "Without a registry"):
#   docker build --build-arg RUST_IMAGE=posematch-local/rust:bookworm \
#                --build-arg RUNTIME_IMAGE=posematch-local/runtime:bookworm -t posematch .
#   POSTGRES_IMAGE=posematch-local/postgres:bookworm docker-compose -f deploy/docker-compose.yml up -d
#
# Usage: deploy/base-images/build.sh [--force]   (an image that exists is kept unless --force)
# Needs: root (or sudo), docker, mmdebstrap (apt-get install mmdebstrap), cargo.
# Writes only to Docker and to target/base-images/ (the crates, the toolchain copy).
set -euo pipefail
cd "$(dirname "$0")/../.."

force=false
[ "${1:-}" = "--force" ] && force=true
suite=bookworm
mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
stage=target/base-images
as_root=""
[ "$(id -u)" = 0 ] || as_root="sudo"

if ! command -v mmdebstrap >/dev/null; then
  echo "mmdebstrap is missing: apt-get install mmdebstrap" >&2
  exit 1
fi

have() { docker image inspect "$1" >/dev/null 2>&1 && ! $force; }

# A Debian root file system as an image. $1: tag; $2: packages (comma-separated, may be empty);
# then mmdebstrap options (hooks), then `--` and `docker import --change` instructions.
debian_image() {
  local tag=$1 include=$2
  shift 2
  local options=() changes=()
  while [ $# -gt 0 ] && [ "$1" != "--" ]; do options+=("$1"); shift; done
  [ $# -gt 0 ] && shift
  for change in "$@"; do changes+=(--change "$change"); done
  local started=$SECONDS
  # Documentation and package lists only take space in an image.
  $as_root mmdebstrap --variant=minbase --quiet ${include:+--include="$include"} \
    --dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-exclude=/usr/share/man/*' \
    --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-include=/usr/share/doc/*/copyright' \
    --customize-hook='rm -rf "$1"/var/lib/apt/lists/* "$1"/var/cache/apt/*' \
    "${options[@]}" "$suite" - "$mirror" \
    | docker import "${changes[@]}" - "$tag" >/dev/null
  echo "$tag: $(docker image inspect -f '{{.Size}}' "$tag" | numfmt --to=iec) in $((SECONDS - started)) s"
}

runtime=posematch-local/runtime:$suite
if have "$runtime"; then echo "$runtime: kept"; else
  debian_image "$runtime" "" -- 'CMD ["bash"]'
fi

rust=posematch-local/rust:$suite
if have "$rust"; then echo "$rust: kept"; else
  # This machine's toolchain (rustc finds its libraries next to its binary), without its
  # 800 MB of HTML documentation, and every crate Cargo.lock names, fetched now with a
  # CARGO_HOME of its own: the image build then needs no network (CARGO_NET_OFFLINE).
  sysroot=$(rustc --print sysroot)
  echo "toolchain: $(rustc --version) from $sysroot"
  rm -rf "$stage/toolchain" "$stage/cargo-home"
  mkdir -p "$stage/toolchain" "$stage/cargo-home"
  tar -C "$sysroot" --exclude=./share/doc -cf - . | tar -C "$stage/toolchain" -xf -
  CARGO_HOME=$PWD/$stage/cargo-home cargo fetch --locked --quiet
  rm -rf "$stage/cargo-home/registry/src"
  debian_image "$rust" "gcc,libc6-dev,ca-certificates" \
    --customize-hook="copy-in $PWD/$stage/toolchain /usr/local" \
    --customize-hook="copy-in $PWD/$stage/cargo-home /usr/local" \
    --customize-hook='mv "$1"/usr/local/toolchain "$1"/usr/local/rust && mv "$1"/usr/local/cargo-home "$1"/usr/local/cargo' \
    -- \
    'ENV PATH=/usr/local/cargo/bin:/usr/local/rust/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    'ENV CARGO_HOME=/usr/local/cargo' \
    'ENV CARGO_NET_OFFLINE=true' \
    'CMD ["bash"]'
fi

postgres=posematch-local/postgres:$suite
if have "$postgres"; then echo "$postgres: kept"; else
  major=15 # bookworm's PostgreSQL
  debian_image "$postgres" "postgresql-$major" \
    --customize-hook='rm -rf "$1"/var/lib/postgresql/'$major'/main "$1"/etc/postgresql/'$major'/main' \
    --customize-hook="upload $PWD/deploy/base-images/postgres-entrypoint.sh /usr/local/bin/postgres-entrypoint" \
    --customize-hook='chmod 0755 "$1"/usr/local/bin/postgres-entrypoint' \
    -- \
    "ENV PATH=/usr/lib/postgresql/$major/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin" \
    'ENV PGDATA=/var/lib/postgresql/data' \
    'EXPOSE 5432' \
    'ENTRYPOINT ["/usr/local/bin/postgres-entrypoint"]'
fi
