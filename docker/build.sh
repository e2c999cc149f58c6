#!/usr/bin/env bash
# Builds radserve's images from the repository: the server (radserve:$TAG), the learner
# (radserve-learner:$TAG), and the bare runtime both stand on (radserve-runtime:$TAG: the base image
# with Mesa and the user, nothing of radserve; tests/cluster/test_wheels.py installs the wheels in
# it). Usage: docker/build.sh [--local-bases] [--with-torch] [--tag TAG]
#
#   --local-bases   make the base images from Debian packages first (docker/base/make-bases.sh) and
#                   build on them: nothing is pulled from a container registry
#   --with-torch    the learner image with PyTorch (WITH_TORCH=1)
#
# This host's package configuration (its CA bundle and pip's settings) is handed to the build stages
# through docker/build-config/ and never reaches the images that run (docker/build-config/README.md).
set -euo pipefail
cd "$(dirname "$0")/.."
tag=dev local_bases=0 with_torch=0
while [[ $# -gt 0 ]]; do
    case $1 in
        --local-bases) local_bases=1 ;;
        --with-torch) with_torch=1 ;;
        --tag) tag=$2; shift ;;
        *) echo "build.sh: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done

config=docker/build-config
find "$config" -mindepth 1 ! -name README.md -delete
bundle=${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}
[[ -s $bundle ]] && cp "$bundle" "$config/ca-certificates.crt"
# pip's index settings, when this host has any (the certificate is passed as above).
python3 -m pip config list 2>/dev/null | grep -E '^(global|install)\.(index-url|extra-index-url|trusted-host)=' \
    | sed -E "s/^[a-z]+\.([a-z-]+)='?([^']*)'?$/\1 = \2/" > "$config/pip.body" || true
if [[ -s $config/pip.body ]]; then { echo "[global]"; cat "$config/pip.body"; } > "$config/pip.conf"; fi
rm -f "$config/pip.body"

args=()
if [[ $local_bases == 1 ]]; then
    bash docker/base/make-bases.sh
    args+=(--build-arg BASE_IMAGE=radserve-base:bookworm --build-arg RUST_IMAGE=radserve-rust:1.95.0)
fi
log=$(mktemp /tmp/radserve-docker-build.XXXXXX)
build() {  # image, then docker build's arguments
    local image=$1 start
    shift
    start=$(date +%s)
    if ! docker build "${args[@]}" -f docker/Dockerfile -t "$image" "$@" . > "$log" 2>&1; then
        tail -40 "$log"
        echo "build.sh: building $image failed (whole log: $log)" >&2
        exit 1
    fi
    echo "build.sh: $image ($(( $(date +%s) - start )) s)"
}
build "radserve:$tag"
build "radserve-learner:$tag" --build-arg WITH_TORCH=$with_torch --target learner
build "radserve-runtime:$tag" --target runtime
rm -f "$log"
find "$config" -mindepth 1 ! -name README.md -delete
docker image ls --format '{{.Repository}}:{{.Tag}} {{.Size}}' | grep -E "^radserve(-learner|-runtime)?:$tag " || true
