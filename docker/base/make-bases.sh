#!/usr/bin/env bash
# The base images of docker/Dockerfile made on this host, so that building radserve's images pulls
# nothing from a container registry (the project's tests and CI run where none is reachable):
#
#   radserve-base:bookworm   Debian bookworm (debootstrap, minbase) with CPython 3.11 (python3,
#                            venv, its shared library and headers): BASE_IMAGE
#   radserve-rust:1.95.0     the Rust toolchain this host builds with, at the path of the official
#                            rust images (/usr/local/rustup/toolchains/...): RUST_IMAGE
#
# Anywhere a registry is reachable, the Dockerfile's defaults (python:3.11-slim-bookworm and
# rust:1.95.0-slim-bookworm) do the same job and this script is not needed.
# An image that exists already is kept (`--force` makes both again). Needs root (debootstrap).
set -euo pipefail

BASE_TAG=${BASE_TAG:-radserve-base:bookworm}
RUST_VERSION=${RUST_VERSION:-1.95.0}
RUST_TAG=${RUST_TAG:-radserve-rust:$RUST_VERSION}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
force=0
[[ ${1:-} == --force ]] && force=1

exists() { docker image inspect "$1" > /dev/null 2>&1; }

if [[ $force == 1 ]] || ! exists "$BASE_TAG"; then
    command -v debootstrap > /dev/null || { apt-get update -q && apt-get install -y -q debootstrap; }
    root=$(mktemp -d /var/tmp/radserve-rootfs.XXXXXX)
    trap 'rm -rf "$root"' EXIT
    echo "make-bases: debootstrap bookworm into $root (a few minutes)"
    debootstrap --variant=minbase \
        --include=ca-certificates,python3,python3-venv,python3-dev,libpython3.11 \
        bookworm "$root" "$MIRROR" > "$root.log" 2>&1 || { tail -20 "$root.log"; exit 1; }
    rm -f "$root.log"
    cat > "$root/etc/apt/sources.list" <<SOURCES
deb $MIRROR bookworm main
deb $MIRROR bookworm-updates main
deb http://deb.debian.org/debian-security bookworm-security main
SOURCES
    # As Debian's own container images: no recommends, no caches kept in layers.
    printf 'APT::Install-Recommends "false";\nAPT::Install-Suggests "false";\n' > "$root/etc/apt/apt.conf.d/90radserve-slim"
    rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/archives/*.deb
    tar -C "$root" --numeric-owner -c . | docker import \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' \
        --change 'CMD ["bash"]' - "$BASE_TAG" > /dev/null
    rm -rf "$root"
    trap - EXIT
    echo "make-bases: $BASE_TAG"
fi

if [[ $force == 1 ]] || ! exists "$RUST_TAG"; then
    toolchain=$(rustc --print sysroot)
    [[ $(rustc --version) == "rustc $RUST_VERSION "* ]] || { echo "make-bases: this host's rustc is $(rustc --version), not $RUST_VERSION" >&2; exit 1; }
    echo "make-bases: $RUST_TAG from $toolchain"
    # The toolchain alone (no documentation), where the official images keep it.
    tar -C "$toolchain" --exclude=./share/doc --numeric-owner \
        --transform "s,^\.,./usr/local/rustup/toolchains/$RUST_VERSION-x86_64-unknown-linux-gnu," -c . \
        | docker import --change 'CMD ["/bin/false"]' - "$RUST_TAG" > /dev/null
fi
