#!/usr/bin/env bash
# On the GPU machine, from the repository root (bench/gpu/README.md):
#   device.sh stage               keep part a of the pack (first call; carry .dev/a .dev/glib)
#   device.sh setup               unpack everything (second call; carry .dev/b .gl)
#   device.sh start               start radserve and the learning checks in their own process sessions
#   device.sh wait SECONDS        wait while a learner runs, then copy runs and log tails into $OUT
set -euo pipefail
RES=/tmp/res
case "${1:-}" in
stage)
    mkdir -p /tmp/stage /tmp/glib && cp .dev/a/pack.a /tmp/stage/ && cp .dev/glib/* /tmp/glib/ ;;
setup)
    for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
    cat /tmp/stage/pack.a .dev/b/pack.b | xz -d -T0 | tar xf - -C /
    install -m 755 .dev/b/radserve /usr/local/bin/radserve
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .dev/b/*.whl
    # Libraries the image lacks: procgen's (always carried) and, only when missing, the interpreter's.
    base=$(sed -n 's/^home = \(.*\)\/bin$/\1/p' /sv/pyvenv.cfg)
    path=/tmp/glib
    if for f in "$base"/lib/libpython3*.so.1.0 "$base"/lib/python3*/lib-dynload/_ctypes*.so; do ldd "$f"; done | grep -q "not found"; then
        path=$path:$base/lib/extra
    fi
    echo "export LD_LIBRARY_PATH=$path" > /tmp/server-env ;;
start)
    mkdir -p $RES
    export MUJOCO_GL=egl RADSERVE__SIM__VENV=/sv
    ( . /tmp/server-env; setsid radserve serve --address 127.0.0.1:50051 --workers 14 > $RES/server.log 2>&1 < /dev/null & )
    sleep 5
    export PYTHONPATH=/tmp/site:$PWD/client-py PYTHONUNBUFFERED=1
    setsid python3 client-py/examples/sac_pixels.py --address 127.0.0.1:50051 --env dmc/cartpole-swingup \
        --torch-threads 4 --runs-dir $RES/runs > $RES/sac.log 2>&1 < /dev/null &
    setsid python3 client-py/examples/ppo_procgen.py --address 127.0.0.1:50051 --env procgen/bigfish \
        --total-timesteps 8000000 --eval-every 500000 --torch-threads 4 --runs-dir $RES/runs > $RES/ppo.log 2>&1 < /dev/null &
    sleep 60
    for f in sac ppo; do echo "== $f"; tr '\r' '\n' < $RES/$f.log | grep -v '^\s*$' | tail -n 3; done ;;
wait)
    end=$((SECONDS + ${2:?seconds}))
    while [ $SECONDS -lt $end ]; do
        pgrep -f "examples/(sac_pixels|ppo_procgen).py" > /dev/null || { echo "no learner running"; break; }
        sleep 20
    done
    for f in sac ppo; do echo "== $f"; tr '\r' '\n' < $RES/$f.log | grep -v '^\s*$' | tail -n 3; done
    (cd $RES && tar czf "$OUT/res.tgz" --exclude='*.pt' runs server.log) ;;
*)
    sed -n 2,7p "$0"; exit 2 ;;
esac
