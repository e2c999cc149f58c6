"""Where a synchronous step's CPU goes: client, server and each worker process, read from
/proc/<pid>/stat around a timed loop of one session (Linux only).

    .venv/bin/python bench/cpu_per_step.py procgen/bigfish 64 [--delivery shared_memory|grpc]
                                           [--seconds 5] [--option pixels=false ...]

Prints steps per second, wall time per vector step and CPU time per vector step for each process.
"""

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import radserve  # noqa: E402
from sim_throughput import random_actions  # noqa: E402  (bench/ is the script's directory)

TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid):
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS  # utime + stime


def children(pid):
    found = []
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as listing:
            found += [int(child) for child in listing.read().split()]
    return found


def option(text):
    key, _, value = text.partition("=")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("env_id")
    parser.add_argument("num_envs", type=int)
    parser.add_argument("--delivery", default="shared_memory", choices=("shared_memory", "grpc"))
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--workers", type=int, default=os.cpu_count())
    parser.add_argument("--option", action="append", type=option, default=[], help="session option KEY=VALUE")
    args = parser.parse_args()
    with radserve.LocalServer(workers=args.workers) as server:
        client = radserve.Client(server.address)
        client.list_envs()  # the catalog worker is gone once this answers
        envs = client.make_vec(args.env_id, num_envs=args.num_envs, seed=0, autoreset_mode="SameStep",
                               delivery=args.delivery,
                               **dict(args.option))
        envs.reset()
        actions = random_actions(envs.single_action_space, args.num_envs)
        for i in range(20):
            envs.step(actions[i % 64])
        processes = {"client": os.getpid(), "server": server.process.pid}
        processes.update({f"worker {i}": pid for i, pid in enumerate(children(server.process.pid))})
        before = {name: cpu_seconds(pid) for name, pid in processes.items()}
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < args.seconds:
            envs.step(actions[steps % 64])
            steps += 1
        elapsed = time.perf_counter() - start
        after = {name: cpu_seconds(pid) for name, pid in processes.items()}
        envs.close()
    per_step = {name: (after[name] - before[name]) / steps * 1e3 for name in processes}
    print(f"{args.env_id} x {args.num_envs} through {args.delivery}: {steps * args.num_envs / elapsed:.0f} steps/s, "
          f"{elapsed / steps * 1e3:.2f} ms per step; CPU per step: "
          + ", ".join(f"{name} {ms:.2f} ms" for name, ms in per_step.items())
          + f"; total {sum(per_step.values()):.2f} ms")


if __name__ == "__main__":
    main()
