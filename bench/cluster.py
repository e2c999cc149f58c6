"""Sharding over server containers: steps/s of one sharded session and batches/s of sharded
crop(84) 512x9x84x84 obs+next_obs batches over 1, 2 and 3 server containers, with one local
radserve process (no containers) beside them, in alternating rounds; prints the table and writes it
to bench/results/cluster.json (docs/performance.md renders it).

    python bench/cluster.py [--rounds 3]        (make bench-cluster builds the images first)

The learner runs in a learner container on the servers' private network (so the figures include
Docker's bridge, not a port proxy); the local baseline runs the same measurement on this host
against a server started here. Every server has one worker process. On a 2-core machine all the
servers and the learner share the same two cores: the figures show what sharding costs, not how
it scales (on a cluster each server has its own cores).
"""

import argparse
import contextlib
import json
import statistics
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STATE_ENV, STATE_ENVS, STEPS = "gym/HalfCheetah-v5", 12, 1500
PIXEL_ENV = "dmc/cartpole-balance"
PIXEL_OPTIONS = {"height": 100, "width": 100, "frame_stack": 3, "render_profile": "fast"}
BATCH, BATCHES = 512, 20


def measure(addresses: str, delivery: str = "grpc") -> dict:
    """One measurement against `addresses` (comma-separated): acting steps/s and batches/s."""
    import radserve

    client = radserve.Client(addresses)
    envs = client.make_vec(STATE_ENV, num_envs=STATE_ENVS, seed=0, autoreset_mode="SameStep", delivery=delivery)
    envs.reset(seed=0)
    actions = np.zeros((STATE_ENVS,) + envs.single_action_space.shape, dtype=np.float32)
    for _ in range(50):
        envs.step(actions)
    start = time.perf_counter()
    for _ in range(STEPS):
        envs.step(actions)
    steps_per_s = STEPS * STATE_ENVS / (time.perf_counter() - start)
    envs.close()

    pixels = client.make_vec(PIXEL_ENV, num_envs=6, seed=0, autoreset_mode="SameStep",
                             replay_capacity=3000, delivery=delivery, **PIXEL_OPTIONS)
    pixels.reset(seed=0)
    for _ in range(120):
        pixels.step(pixels.action_space.sample())
    with pixels.sample_batches(BATCH, augment="crop(84)", min_size=BATCH, prefetch=2,
                               delivery=delivery) as stream:
        batch = next(stream)
        assert batch.obs.shape == (BATCH, 9, 84, 84) and batch.next_obs.shape == (BATCH, 9, 84, 84)
        start = time.perf_counter()
        for _ in range(BATCHES):
            next(stream)
        batches_per_s = BATCHES / (time.perf_counter() - start)
    pixels.close()
    client.close()
    return {"steps_per_s": steps_per_s, "batches_per_s": batches_per_s, "delivery": envs.delivery}


def docker(*args: str, check: bool = True) -> str:
    result = subprocess.run(["docker", *args], capture_output=True, text=True)
    if check and result.returncode != 0:
        raise SystemExit(f"docker {' '.join(args)}: {result.stderr.strip()}")
    return result.stdout.strip()


def wait_healthy(name: str, timeout: float = 240) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if docker("inspect", "-f", "{{.State.Health.Status}}", name) == "healthy":
            return
        time.sleep(1)
    raise SystemExit(f"{name} not healthy within {timeout} s")


@contextlib.contextmanager
def server_containers(tag: str, label: str, count: int = 3):
    """`count` server containers (one worker each) on a private network of their own, aliased
    radserve-0, radserve-1, ...: yields (network, their addresses); removed on the way out."""
    prefix = f"radserve-{label}-{uuid.uuid4().hex[:6]}"
    network = f"{prefix}-net"
    names = [f"radserve-{i}" for i in range(count)]
    docker("network", "create", "--internal", network)
    try:
        for name in names:
            docker("run", "-d", "--name", f"{prefix}-{name}", "--network", network, "--network-alias", name,
                   "-e", "RADSERVE__SIM__WORKERS=1", f"radserve:{tag}", "serve", "--insecure")
        for name in names:
            wait_healthy(f"{prefix}-{name}")
        yield network, [f"{name}:50051" for name in names]
    finally:
        containers = docker("ps", "-aq", "--filter", f"name={prefix}", check=False).split()
        if containers:
            docker("rm", "-f", *containers, check=False)
        docker("network", "rm", network, check=False)


def in_learner_container(tag: str, network: str, *args: str) -> dict:
    """Runs a bench script (its path under /bench) in a learner container on `network`: the JSON of
    its last line."""
    output = docker("run", "--rm", "--network", network, "-v", f"{ROOT / 'bench'}:/bench:ro",
                    f"radserve-learner:{tag}", *args)
    return json.loads(output.splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--tag", default="dev")
    parser.add_argument("--measure", help=argparse.SUPPRESS)  # inside the learner container
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure)))
        return

    import radserve

    results: "dict[str, list[dict]]" = {}
    with server_containers(args.tag, "bench") as (network, servers), radserve.LocalServer(workers=1) as local:
        for round_ in range(args.rounds):
            for count in ("shm", 0, 1, 2, 3):
                if count == "shm":
                    label, result = "one local process, shared memory", measure(local.address, "shared_memory")
                elif count == 0:
                    label, result = "one local process (no container)", measure(local.address)
                else:
                    label = f"{count} server container{'s' if count > 1 else ''}"
                    result = in_learner_container(args.tag, network, "/bench/cluster.py", "--measure",
                                                  ",".join(servers[:count]))
                results.setdefault(label, []).append(result)
                print(f"round {round_ + 1}: {label}: {result['steps_per_s']:,.0f} steps/s, "
                      f"{result['batches_per_s']:.1f} batches/s ({result['delivery']})", file=sys.stderr)

    import record  # bench/record.py: the results file (imported here: the learner container needs none of it)

    baseline = results["one local process (no container)"]
    base_steps = statistics.median(r["steps_per_s"] for r in baseline)
    base_batches = statistics.median(r["batches_per_s"] for r in baseline)
    rows = []
    for label, runs in results.items():
        steps = [r["steps_per_s"] for r in runs]
        batches = [r["batches_per_s"] for r in runs]
        rows.append([label, record.ranged(steps), record.cell(statistics.median(steps) / base_steps, digits=2),
                     record.ranged(batches, digits=1), record.cell(statistics.median(batches) / base_batches, digits=2)])
        print(record.plain(rows[-1]))
    table = {"id": "cluster", "rows": rows,
             "columns": ["servers (gRPC unless said)", f"{STATE_ENV} x{STATE_ENVS} steps/s", "vs local",
                         f"crop(84) {BATCH}x9x84x84 obs+next_obs batches/s", "vs local"],
             "note": f"Median (range) of {args.rounds} alternating rounds, one worker per server; every server and the "
                     f"learner share this machine's cores."}
    record.write("cluster", [table], {"rounds": args.rounds, "tag": args.tag})


if __name__ == "__main__":
    main()
