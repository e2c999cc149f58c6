#!/usr/bin/env bash
# Packs what a GPU machine without registries needs to run radserve and the learners (bench/gpu/README.md):
#   .dev/a/pack.a, .dev/b/pack.b  the server's Python 3.11 (trimmed) and a virtualenv holding only what the
#                                 workers import (dm_control, mujoco, procgen, gymnasium, scipy...), xz'd and
#                                 split so that each part travels in one call (64 MiB per call)
#   .dev/b/radserve               the stripped release binary (its RUNPATH names the same Python path)
#   .dev/b/*.whl                  cp312 wheels the learner side lacks there (grpcio, protobuf, gymnasium)
#   .dev/glib/                    shared libraries procgen's libenv.so needs that such an image lacks
#   .gl/                          glvnd's EGL/GL loaders, unpacked there (.library/device/README.md)
# Run from the repository root after `make setup`; .dev/ and .gl/ must be in .git/info/exclude.
set -euo pipefail
ROOT=$(pwd)
PY=$(readlink -f .venv/bin/python); BASE=$(dirname "$(dirname "$PY")"); VER=$(basename "$PY" | sed 's/python//')
SITE=.venv/lib/python$VER/site-packages
STAGE=$(mktemp -d); trap 'rm -rf "$STAGE"' EXIT
B=$STAGE/base$BASE; V=$STAGE/sv; T=$V/lib/python$VER/site-packages
mkdir -p "$B/bin" "$B/lib/extra" "$T" "$V/bin"

# The interpreter at the same absolute path (the binary's RUNPATH and pyvenv.cfg name it), minus what no
# worker imports; plus the few system libraries its extension modules link against, used only if missing.
cp -a "$BASE/bin/python$VER" "$B/bin/"
cp -a "$BASE"/lib/libpython"$VER".so* "$B/lib/"
(cd "$BASE/lib" && tar cf - --exclude=site-packages --exclude=test --exclude=idlelib --exclude=tkinter \
    --exclude=turtledemo --exclude=ensurepip --exclude=lib2to3 --exclude='config-*' --exclude=__pycache__ \
    "python$VER") | (cd "$B/lib" && tar xf -)
mkdir -p "$B/lib/python$VER/site-packages"
for l in libffi.so.8 libbz2.so.1.0 liblzma.so.5 libz.so.1 libexpat.so.1 libcrypt.so.1 libuuid.so.1 libsqlite3.so.0; do
    cp -L "/lib/x86_64-linux-gnu/$l" "$B/lib/extra/"
done

# The packages the worker imports (found by importing each family's simulator and listing sys.modules).
for m in OpenGL _cffi_backend* absl cffi cloudpickle dm_control dm_env farama_notifications glfw gym gym3 \
         gym_notices gymnasium imageio lxml mujoco numpy numpy.libs packaging procgen procgen_mirror.libs \
         pycparser scipy scipy.libs tree typing_extensions.py; do
    cp -a "$SITE"/$m "$T/"
done
(cd "$SITE" && ls -d *.dist-info | grep -iE '^(pyopengl|absl|cffi|cloudpickle|dm_control|dm_env|farama|glfw|gym|gymnasium|imageio|lxml|mujoco|numpy|packaging|procgen|pycparser|scipy|typing_extensions)' \
    | xargs -I{} cp -a {} "$T/")
rm -rf "$T/dm_control/locomotion" "$T/mujoco/experimental"   # not imported by the suite; 124 MB
find "$STAGE" \( -name tests -o -name __pycache__ \) -type d -prune -exec rm -rf {} +
printf 'home = %s/bin\ninclude-system-site-packages = false\nversion = %s\n' "$BASE" "$("$PY" -c 'import platform;print(platform.python_version())')" > "$V/pyvenv.cfg"
ln -s "$BASE/bin/python$VER" "$V/bin/python"

rm -rf .dev && mkdir -p .dev/a .dev/b .dev/glib
# Members are named from the top directory down (root/..., sv/): never "." (unpacking at / would chmod /).
TOP=$(echo "$BASE" | cut -d/ -f2)
tar cf - -C "$STAGE/base" "$TOP" -C "$STAGE" sv | xz -T0 -6 > "$STAGE/pack.tar.xz"
head -c 60000000 "$STAGE/pack.tar.xz" > .dev/a/pack.a
tail -c +60000001 "$STAGE/pack.tar.xz" > .dev/b/pack.b
cp target/release/radserve .dev/b/radserve && strip .dev/b/radserve
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d .dev/b "grpcio==$(.venv/bin/python -c 'import grpc;print(grpc.__version__)')" \
    "protobuf==$(.venv/bin/python -c 'import google.protobuf as p;print(p.__version__)')" \
    "gymnasium==$(.venv/bin/python -c 'import gymnasium;print(gymnasium.__version__)')" farama-notifications
for l in libgthread-2.0.so.0 libglib-2.0.so.0 libpcre2-8.so.0 libX11.so.6 libxcb.so.1 libXau.so.6 libXdmcp.so.6 libbsd.so.0 libmd.so.0; do
    cp -L "/lib/x86_64-linux-gnu/$l" .dev/glib/
done
mkdir -p .gl /tmp/amd64/partial
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
apt-get $o update >/dev/null && (cd .gl && apt-get $o download libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 2>/dev/null)
du -sh .dev/a .dev/b .dev/glib .gl
