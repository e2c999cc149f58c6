"""The release's wheels (`make dist`) where there is no repository and no Rust: a container of the
Dockerfile's `runtime` stage (radserve-runtime, docker/build.sh: Debian bookworm's CPython 3.11 and
Mesa, nothing of radserve) gets only
dist/ and one example file. In it, `pip install "radserve[server,examples]"` resolves the server wheel through
the client's extra and everything else from the package registry; then `radserve serve` from the
activated venv serves a learner (client-py/examples/random_agent.py with --address), and
`radserve.LocalServer()` from the venv's python, not activated, finds the binary by itself.

The host's package configuration (CA bundle, pip's index settings) reaches the container at run time,
read-only, as docker/build.sh hands it to the image builds; nothing is baked into an image.
"""

import os
import subprocess
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DIST = ROOT / "dist"
TAG = os.environ.get("RADSERVE_TAG", "dev")
RUNTIME_IMAGE = f"radserve-runtime:{TAG}"
VERSION = tomllib.loads((ROOT / "Cargo.toml").read_text())["workspace"]["package"]["version"]

INSIDE = r"""
set -euo pipefail
if command -v cargo || command -v rustc || [ -e /src ]; then echo "this container has Rust or sources" >&2; exit 1; fi
python3 -m venv /tmp/venv
/tmp/venv/bin/pip install -q --find-links /wheels "radserve[server,examples]==$VERSION"
. /tmp/venv/bin/activate
echo "binary: $(command -v radserve)"
radserve --version
radserve serve --address 127.0.0.1:50051 --workers 1 > /tmp/serve.out 2> /tmp/serve.err &
server=$!
for _ in $(seq 240); do grep -q "radserve listening on" /tmp/serve.out && break; sleep 0.5; done
grep "radserve listening on" /tmp/serve.out || { cat /tmp/serve.err; exit 1; }
python /example/random_agent.py --address 127.0.0.1:50051 --env dmc/cheetah-run --num-envs 2 --steps 40 \
    --render-profile fast 2>/dev/null
kill -TERM $server
wait $server
deactivate
env -i HOME=/tmp MUJOCO_GL=egl PATH=/usr/bin:/bin /tmp/venv/bin/python - <<'PY'
import numpy as np
import radserve
with radserve.LocalServer(workers=1) as server, radserve.Client(server.address) as client:
    (info,) = client.server_info()
    envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=3)
    envs.reset()
    envs.step(np.zeros(2, np.int64))
    envs.close()
    print(f"local server {radserve.server.find_binary()} {info.version} stepped CartPole")
PY
"""


def docker(*args, timeout=900) -> subprocess.CompletedProcess:
    return subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout)


def package_configuration() -> "list[str]":
    """docker run arguments that hand this host's CA bundle and pip index settings to the container."""
    args = []
    bundle = os.environ.get("SSL_CERT_FILE", "/etc/ssl/certs/ca-certificates.crt")
    if os.path.exists(bundle) and os.path.getsize(bundle):
        args += ["-v", f"{bundle}:/run/host-ca.crt:ro", "-e", "PIP_CERT=/run/host-ca.crt"]
    for name in ("PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL", "PIP_TRUSTED_HOST", "PIP_DEFAULT_TIMEOUT"):
        if os.environ.get(name):
            args += ["-e", f"{name}={os.environ[name]}"]
    listed = subprocess.run(["python3", "-m", "pip", "config", "list"], capture_output=True, text=True).stdout
    for line in listed.splitlines():
        key, _, value = line.partition("=")
        setting = key.split(".", 1)[-1]
        if key.split(".", 1)[0] in ("global", "install") and setting in ("index-url", "extra-index-url", "trusted-host"):
            args += ["-e", f"PIP_{setting.upper().replace('-', '_')}={value.strip(chr(39))}"]
    return args


def test_the_wheels_install_and_serve_without_the_repository():
    wheels = sorted(path.name for path in DIST.glob("*.whl"))
    assert any(name.startswith(f"radserve-{VERSION}-py3-none-any") for name in wheels), f"no client wheel in dist/: {wheels}"
    assert any(name.startswith(f"radserve_server-{VERSION}-cp311-cp311-") for name in wheels), f"no server wheel in dist/: {wheels}"
    # The Dockerfile's runtime stage, which docker/build.sh tags (make images-local, before this test).
    assert docker("image", "inspect", RUNTIME_IMAGE).returncode == 0, f"no {RUNTIME_IMAGE}: run docker/build.sh"
    ran = docker("run", "--rm", "--user", "10001:10001", "-e", f"VERSION={VERSION}", *package_configuration(),
                 "-v", f"{DIST}:/wheels:ro", "-v", f"{ROOT / 'client-py/examples/random_agent.py'}:/example/random_agent.py:ro",
                 RUNTIME_IMAGE, "bash", "-c", INSIDE)
    assert ran.returncode == 0, f"stdout:\n{ran.stdout[-3000:]}\nstderr:\n{ran.stderr[-3000:]}"
    out = ran.stdout
    assert "binary: /tmp/venv/bin/radserve" in out, out
    assert f"radserve {VERSION}" in out, out
    assert "dmc/cheetah-run: 2 envs" in out and "steps/s" in out, out
    assert f"local server /tmp/venv/bin/radserve {VERSION} stepped CartPole" in out, out
