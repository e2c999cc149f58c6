"""Memory one environment costs in a worker, per family: the worker's resident set (RSS) after
creating and resetting sessions of N envs, minus before, over N. The server charges these figures
against its memory budget (`server/core/src/budget.rs`) before it builds a session's envs.

    .venv/bin/python bench/env_memory.py [--envs 8]
"""

import argparse
import time
from pathlib import Path

import numpy as np

import radserve

CASES = [
    ("dmc/cheetah-run", {}, "dmc pixels 100x100"),
    ("dmc/cheetah-run", {"pixels": False}, "dmc state"),
    ("gym/HalfCheetah-v5", {}, "gym MuJoCo"),
    ("gym/CartPole-v1", {}, "gym classic control"),
    ("procgen/bigfish", {}, "procgen"),
]


def rss(pid):
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS")


def worker_pid(server_pid):
    children = {int(pid) for task in Path(f"/proc/{server_pid}/task").iterdir()
                for pid in (task / "children").read_text().split()}
    workers = [pid for pid in children if b"\0worker\0" in Path(f"/proc/{pid}/cmdline").read_bytes()]
    assert len(workers) == 1, workers
    return workers[0]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=8)
    args = parser.parse_args()
    print(f"{'family':<22} {'per env (MiB)':>14} {'per session (MiB)':>18} {'first env (MiB)':>16}")
    for env_id, options, label in CASES:
        # A fresh server per family: imports and GL contexts of one family do not count for another.
        with radserve.LocalServer(workers=1) as server:
            client = radserve.Client(server.address)
            client.list_envs()  # the catalog's transient worker is gone before the worker is measured
            time.sleep(1.0)
            pid = worker_pid(server.process.pid)
            base = rss(pid)
            one = client.make_vec(env_id, num_envs=1, seed=0, autoreset_mode="SameStep", **options)
            one.reset()
            after_one = rss(pid)
            many = client.make_vec(env_id, num_envs=args.envs, seed=1, autoreset_mode="SameStep", **options)
            many.reset()
            for _ in range(3):
                many.step(np.stack([many.single_action_space.sample() for _ in range(args.envs)]))
            after_many = rss(pid)
            per_env = (after_many - after_one) / args.envs
            # One more session of one env: what a session (a worker group) costs beside its envs.
            extra = client.make_vec(env_id, num_envs=1, seed=100, autoreset_mode="SameStep", **options)
            extra.reset()
            per_session = rss(pid) - after_many - per_env
            print(f"{label:<22} {per_env / 2**20:>14.1f} {per_session / 2**20:>18.1f} {(after_one - base) / 2**20:>16.1f}",
                  flush=True)
            for envs in (one, many, extra):
                envs.close()
            client.close()


if __name__ == "__main__":
    main()
