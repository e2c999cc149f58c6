"""Where the time of one gRPC Step goes, from a Python client's `envs.step`: the client's own Python
(building the request, decoding the response, batching infos), grpcio's blocking call, and inside
that the server's core (the session's step, simulators included, from radserve_step_seconds); what is
left of the call is transport and conversion on both sides (grpcio's and tonic's framing, the
server's message building, loopback).

    .venv/bin/python bench/acting_per_call.py [--steps 2000] [--rounds 3] [--no-results]

Each row steps one session of 2 workers with fixed actions over gRPC, SameStep autoreset. The
client's split comes from cProfile (the cumulative time of grpcio's `_blocking` is the call, the
rest of `step` is the client's own); cProfile slows Python code, so the client's share is an upper
bound. The core's time is the histogram's sum over the same steps, scraped before and after. The
table goes to bench/results/acting_per_call.json (docs/performance.md renders it) unless --no-results.
"""

import argparse
import cProfile
import pstats
import socket
import sys
import time
import urllib.request

import numpy as np

import radserve

import record  # noqa: E402  (bench/record.py: the results file)

WORKLOADS = [
    ("gym HalfCheetah-v5 x16", "gym/HalfCheetah-v5", 16, {}),
    ("procgen bigfish x64", "procgen/bigfish", 64, {}),
    ("gym CartPole-v1 x1", "gym/CartPole-v1", 1, {}),
]


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def core_step_seconds(port: int) -> "tuple[float, int]":
    """radserve_step_seconds' sum and count from the server's Prometheus endpoint."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as answer:
        text = answer.read().decode()
    total = count = 0.0
    for line in text.splitlines():
        if line.startswith("radserve_step_seconds_sum"):
            total = float(line.split()[-1])
        elif line.startswith("radserve_step_seconds_count"):
            count = float(line.split()[-1])
    return total, int(count)


def measure(env_id, num_envs, options, steps, port, address):
    with radserve.Client(address) as client:
        envs = client.make_vec(env_id, num_envs=num_envs, seed=0, autoreset_mode="SameStep", **options)
        envs.action_space.seed(0)
        actions = [envs.action_space.sample() for _ in range(8)]
        envs.reset(seed=0)
        for index in range(100):  # warm: first calls, caches
            envs.step(actions[index % len(actions)])
        before = core_step_seconds(port)
        profile = cProfile.Profile()
        started = time.perf_counter()
        profile.enable()
        for index in range(steps):
            envs.step(actions[index % len(actions)])
        profile.disable()
        wall = time.perf_counter() - started
        after = core_step_seconds(port)
        envs.close()
    stats = pstats.Stats(profile).stats
    call = sum(cumulative for (path, _, name), (_, _, _, cumulative, _) in stats.items()
               if name == "_blocking" and path.endswith("grpc/_channel.py"))
    core = after[0] - before[0]
    if after[1] - before[1] != steps:
        raise SystemExit(f"{after[1] - before[1]} core steps counted for {steps} client steps")
    per_step = lambda seconds: seconds / steps * 1000  # noqa: E731
    return {"wall": per_step(wall), "client": per_step(wall - call), "call": per_step(call), "core": per_step(core),
            "rest": per_step(call - core)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--no-results", action="store_true", help="print only; leave bench/results/ as it is")
    args = parser.parse_args()
    port = free_port()
    env = {"RADSERVE__SIM__VENV": sys.prefix, "RADSERVE__METRICS__ADDRESS": f"127.0.0.1:{port}"}
    results = {label: [] for label, *_ in WORKLOADS}
    with radserve.LocalServer(workers=2, env=env) as server:
        for round_index in range(args.rounds):
            for label, env_id, num_envs, options in WORKLOADS:
                steps = args.steps if num_envs > 1 else args.steps * 4
                results[label].append(measure(env_id, num_envs, options, steps, port, server.address))
            print(f"round {round_index + 1}/{args.rounds} done", file=sys.stderr, flush=True)
    rows = []
    for label, runs in results.items():
        cell = lambda key: record.ranged([run[key] for run in runs], digits=3)  # noqa: E731
        shares = [run["client"] / run["wall"] * 100 for run in runs]
        rest_shares = [run["rest"] / run["wall"] * 100 for run in runs]
        rows.append([label, cell("wall"), cell("client"), cell("call"), cell("core"), cell("rest"),
                     record.ranged(shares, suffix="%"), record.ranged(rest_shares, suffix="%")])
        print(record.plain(rows[-1]))
    if not args.no_results:
        table = {"id": "acting_per_call", "rows": rows, "align": ["l"] + ["r"] * 7,
                 "columns": ["workload", "ms per step", "client Python", "gRPC call", "of which the core",
                             "of which transport", "client share", "transport share"],
                 "note": f"Milliseconds per `envs.step` over gRPC on loopback, {args.steps} steps per round "
                         f"({args.steps * 4} for one env), median (range) of {args.rounds} rounds; the client's "
                         "Python measured under cProfile (an upper bound); the core from radserve_step_seconds."}
        record.write("acting_per_call", [table], {"steps": args.steps, "rounds": args.rounds})


if __name__ == "__main__":
    main()
