"""radserve as containers: three server containers on a private Docker network and a learner
container acting in one sharded session over them (`make test-cluster`; needs a Docker engine and
the images docker/build.sh makes).

The host never talks to a container's address: it drives the learner container through its stdin
(tests/cluster/learner.py answers each command with a JSON line) and stops, kills and starts the
server containers between commands. Everything created here (containers, network, Compose project)
is removed at the end, passed or failed.
"""

import json
import os
import subprocess
import time
import uuid
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TAG = os.environ.get("RADSERVE_TAG", "dev")
SERVER_IMAGE, LEARNER_IMAGE = f"radserve:{TAG}", f"radserve-learner:{TAG}"
PREFIX = f"radserve-test-{uuid.uuid4().hex[:8]}"
NETWORK = f"{PREFIX}-net"
NAMES = [f"radserve-{i}" for i in range(3)]
ADDRESSES = ",".join(f"{name}:50051" for name in NAMES)
# What the servers run under, as docker/compose.yaml and docker/k8s run them.
HARDENED = ["--read-only", "--tmpfs", "/tmp:exec", "--cap-drop", "ALL", "--security-opt", "no-new-privileges:true"]
GRACE_S = 40


def docker(*args, check=True, timeout=300) -> str:
    result = subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout)
    if check and result.returncode != 0:
        raise AssertionError(f"docker {' '.join(args)} failed ({result.returncode}): {result.stderr.strip()}")
    return result.stdout.strip()


def container(name: str) -> str:
    return f"{PREFIX}-{name}"


def wait_healthy(name: str, timeout: float = 240) -> float:
    """Seconds until the container's HEALTHCHECK (radserve healthcheck) reports healthy."""
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        status = docker("inspect", "-f", "{{.State.Health.Status}} {{.State.Status}}", container(name))
        if status.startswith("healthy"):
            return time.monotonic() - start
        assert "exited" not in status, f"{name} exited: {docker('logs', '--tail', '30', container(name), check=False)}"
        time.sleep(1)
    raise AssertionError(f"{name} not healthy within {timeout} s: {docker('logs', '--tail', '30', container(name))}")


def start_server(name: str) -> None:
    # Replay snapshots of named sessions go to a volume of the container's own (kept across `docker
    # start`, removed with it), every second.
    docker("run", "-d", "--name", container(name), "--network", NETWORK, "--network-alias", name,
           "-e", "RADSERVE__SIM__WORKERS=1", "-v", "/var/lib/radserve/snapshots",
           "-e", "RADSERVE__REPLAY__SNAPSHOT_DIR=/var/lib/radserve/snapshots", "-e", "RADSERVE__REPLAY__SNAPSHOT_INTERVAL_S=1",
           "--stop-timeout", str(GRACE_S), *HARDENED, SERVER_IMAGE, "serve", "--insecure")


class LearnerContainer:
    """The learner image running tests/cluster/learner.py, one JSON answer per command."""

    def __init__(self, *network_args: str, addresses: str = ADDRESSES, name: str = "learner"):
        self.process = subprocess.Popen(
            ["docker", "run", "-i", "--rm", "--name", container(name), *network_args, *HARDENED,
             "-v", f"{ROOT / 'tests' / 'cluster'}:/scenario:ro", LEARNER_IMAGE, "/scenario/learner.py", addresses],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def ask(self, command: str) -> dict:
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()
        line = self.process.stdout.readline()
        assert line, f"the learner container ended (status {self.process.poll()}) on {command!r}"
        answer = json.loads(line)
        assert "exception" not in answer, f"{command}: {answer['exception']}\n{answer.get('traceback')}"
        return answer

    def close(self) -> None:
        if self.process.poll() is None:
            try:
                self.process.stdin.write("quit\n")
                self.process.stdin.close()
                self.process.wait(30)
            except (OSError, subprocess.TimeoutExpired):
                self.process.kill()


@pytest.fixture(scope="module")
def cluster():
    for image in (SERVER_IMAGE, LEARNER_IMAGE):
        if not docker("image", "ls", "-q", image):
            pytest.fail(f"no image {image}: run docker/build.sh first (make test-cluster does)")
    docker("network", "create", "--internal", NETWORK)
    try:
        for name in NAMES:
            start_server(name)
        yield {name: wait_healthy(name) for name in NAMES}
    finally:
        names = docker("ps", "-aq", "--filter", f"name={PREFIX}", check=False).split()
        if names:
            docker("rm", "-f", "-v", *names, check=False)
        docker("network", "rm", NETWORK, check=False)


def test_the_image_runs_as_a_user_with_its_healthcheck():
    config = json.loads(docker("image", "inspect", SERVER_IMAGE))[0]["Config"]
    assert config["User"] == "10001:10001"
    assert config["Entrypoint"] == ["radserve"] and config["Cmd"] == ["serve"]
    assert config["Healthcheck"]["Test"] == ["CMD", "radserve", "healthcheck"]
    assert "RADSERVE__SERVER__ADDRESS=0.0.0.0:50051" in config["Env"]
    # The host's package configuration reached the build stages only.
    listing = docker("run", "--rm", "--entrypoint", "sh", SERVER_IMAGE, "-c",
                     "ls /build-config 2>&1; pip config list 2>&1; echo PIP_CERT=$PIP_CERT")
    assert "No such file" in listing and "PIP_CERT=\n" in listing + "\n"


def test_a_learner_container_over_three_server_containers(cluster):
    learner = LearnerContainer("--network", NETWORK)
    try:
        # One sharded session, envs on all three; batches of 32 drawn from every server.
        opened = learner.ask("open")
        assert opened["servers"] == ADDRESSES.split(",")
        assert opened["sizes"] == [2, 2, 2]
        assert opened["delivery"] == "grpc"  # "auto" across containers: no shared memory, gRPC
        assert opened["batch_sizes"] == [32, 32, 32] and opened["obs_shape"] == [32, 9, 56, 56]
        assert all(counts == [11, 11, 10] for counts in opened["batch_servers"])
        usage = docker("stats", "--no-stream", "--format", "{{.Name}} {{.MemUsage}}",
                       *[container(name) for name in NAMES])
        print(f"\nserver containers with 2 dm_control pixel envs each and 1,000 transitions of replay:\n{usage}")

        # The learner's session is named: each server snapshots its share of the replay. Once the
        # snapshot holds everything recorded so far, a server is killed (SIGKILL): the default
        # raises naming it; "continue" goes on with the other two.
        saved = learner.ask("wait_snapshot 1")
        assert saved["size"] > 0, saved
        docker("kill", container("radserve-1"))
        strict = learner.ask("step_strict")
        assert strict["error"] == "UnavailableError" and strict["server"] == "radserve-1:50051", strict
        assert "radserve-1:50051" in strict["message"]
        survived = learner.ask("step_lenient 5")
        assert survived["active"] == [True, True, False, False, True, True]
        assert survived["truncated_lost"] == [False, False, True, True, False, False]
        assert survived["inactive"] == [False, False, True, True, False, False]
        assert survived["batch_size"] == 32 and survived["batch_servers"] == [0, 2]
        assert any("radserve-1:50051 lost" in warning for warning in survived["warnings"])

        # It comes back (same name, maybe another address): a new session there under the same
        # session name, with the replay of its last snapshot restored, and its share again.
        docker("start", container("radserve-1"))
        wait_healthy("radserve-1")
        back = learner.ask("until_active")
        assert back["active"] == [True] * 6 and back["batch_servers"] == [0, 1, 2], back
        assert any("is back" in warning for warning in back["warnings"])
        assert back["restored"][1] >= saved["size"], (back, saved)
        print(f"\nreplay of radserve-1: {saved['size']} transitions at its last snapshot, {back['restored'][1]} restored")

        # `docker stop` (SIGTERM) of a server the learner is acting and sampling on: NOT_SERVING at
        # once, its batch stream ends with the shutdown status (the learner goes on over the other
        # two), the process exits 0 within the grace period.
        learner.ask("watch_drain radserve-2:50051")
        time.sleep(1)
        start = time.monotonic()
        docker("stop", "-t", str(GRACE_S), container("radserve-2"), timeout=GRACE_S + 30)
        stopped_in = time.monotonic() - start
        report = learner.ask("drain_report")
        statuses = [status for _, status in report["statuses"]]
        print(f"\nstop took {stopped_in:.1f} s; drain {report}")
        assert statuses[0] == "SERVING" and statuses[1] == "NOT_SERVING", report
        assert report["loss"] is not None and "shutting down" in report["loss"], report
        assert report["batch_sizes"] == [32], report
        assert docker("inspect", "-f", "{{.State.ExitCode}}", container("radserve-2")) == "0"
        assert stopped_in < GRACE_S, f"radserve took {stopped_in:.1f} s to stop"
        print(f"\nhealthy after {cluster} s; stop took {stopped_in:.1f} s; drain {report}")
    finally:
        learner.close()


def test_the_same_host_variant_shares_memory(cluster):
    """A learner in a server's network namespace (as in one pod) acts and samples through shared memory."""
    if docker("inspect", "-f", "{{.State.Running}}", container("radserve-0")) != "true":
        start_server("radserve-0")
    wait_healthy("radserve-0")
    learner = LearnerContainer("--network", f"container:{container('radserve-0')}", addresses="127.0.0.1:50051",
                               name="learner-same-host")
    try:
        answer = learner.ask("same_host")
        assert answer == {"acting": "shared_memory", "batches": "SharedBatchStream", "obs_shape": [16, 9, 56, 56]}
    finally:
        learner.close()


def test_every_simulator_family_runs_in_the_server_image(cluster):
    """dm_control, gymnasium MuJoCo and ProcGen each create, reset and step in a server container
    (ProcGen's libenv.so needs the system's GLib, which the image once lacked)."""
    if docker("inspect", "-f", "{{.State.Running}}", container("radserve-0")) != "true":
        start_server("radserve-0")
    wait_healthy("radserve-0")
    learner = LearnerContainer("--network", NETWORK, addresses="radserve-0:50051", name="learner-families")
    try:
        assert learner.ask("families") == {"dmc/cartpole-balance": [2, 9, 64, 64], "gym/HalfCheetah-v5": [2, 17],
                                           "procgen/bigfish": [2, 3, 64, 64]}
    finally:
        learner.close()


def test_compose_brings_up_healthy_servers_and_a_learner():
    """docker/compose.yaml: the servers become healthy, the learner (random actions, the torch-less
    learner image) runs against all three, and `down -v` leaves nothing."""
    project = f"{PREFIX}-compose"
    compose = ["docker-compose", "-p", project, "-f", str(ROOT / "docker" / "compose.yaml")]
    env = {**os.environ, "RADSERVE_TAG": TAG}
    try:
        subprocess.run([*compose, "config", "-q"], check=True, env=env, timeout=60)
        run = subprocess.run(
            [*compose, "run", "--rm", "learner", "examples/random_agent.py", f"--address={ADDRESSES}",
             "--env=dmc/cartpole-balance", "--num-envs=3", "--steps=300", "--render-profile=fast"],
            capture_output=True, text=True, env=env, timeout=600)
        assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
        for name in NAMES:
            health = docker("inspect", "-f", "{{.State.Health.Status}}", f"{project}_{name}_1")
            assert health == "healthy", f"{name}: {health}"
    finally:
        subprocess.run([*compose, "down", "-v", "--remove-orphans", "-t", "5"], env=env, timeout=120,
                       capture_output=True)
    assert not docker("ps", "-aq", "--filter", f"name={project}")


def metric_total(text: str, name: str) -> float:
    """The sum of a counter's samples (every label set) in a Prometheus text exposition."""
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
               if line.startswith(name) and (line[len(name)] in " {"))


def test_a_compose_learner_trains_with_the_servers_acting():
    """Server-side actors as Compose runs them: the learner container trains RAD-SAC over the three
    servers with --actor server (the policy exported to ONNX and sent, the servers acting and
    evaluating with it), and every env step the servers took was their actors' (no Step call)."""
    project = f"{PREFIX}-actors"
    compose = ["docker-compose", "-p", project, "-f", str(ROOT / "docker" / "compose.yaml")]
    env = {**os.environ, "RADSERVE_TAG": TAG}
    try:
        run = subprocess.run(
            [*compose, "run", "--rm", "learner", "examples/sac_pixels.py", "--actor=server", f"--address={ADDRESSES}",
             "--env=dmc/cartpole-swingup", "--num-envs=3", "--image-size=64", "--aug=translate(72)", "--num-filters=16",
             "--hidden-dim=64", "--total-env-steps=960", "--init-steps=20", "--batch-size=16", "--eval-every=960",
             "--eval-episodes=3", "--render-profile=fast", "--policy-every=10", "--log-every=10", "--runs-dir=/tmp/runs"],
            capture_output=True, text=True, env=env, timeout=900)
        assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
        assert "evaluation return" in run.stdout, run.stdout[-2000:]
        for name in NAMES:
            text = docker("exec", f"{project}_{name}_1", "/opt/radserve/venv/bin/python", "-c",
                          "import urllib.request; print(urllib.request.urlopen('http://127.0.0.1:9090/metrics').read().decode())")
            steps, acted = metric_total(text, "radserve_env_steps_total"), metric_total(text, "radserve_actor_env_steps_total")
            assert steps > 0 and steps == acted, f"{name}: {steps} env steps, {acted} by its actors"
            assert metric_total(text, "radserve_actor_policies_total") >= 2
    finally:
        subprocess.run([*compose, "down", "-v", "--remove-orphans", "-t", "5"], env=env, timeout=120,
                       capture_output=True)
    assert not docker("ps", "-aq", "--filter", f"name={project}")
