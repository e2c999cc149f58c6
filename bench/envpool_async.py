"""The worker's EnvPool group in EnvPool's asynchronous mode against its synchronous one, in one process.

    .venv/bin/python bench/envpool_async.py [--rounds 5] [--seconds 2]

For each workload, alternating rounds of: the worker's EnvpoolGroup stepped synchronously (`step` of
every env, what a session does today), the same group with batch_size = envs/2 driven as EnvPool's
users drive its async mode (`recv` the first half ready, `send` it its next actions), and EnvPool itself
in-process (public `step`, and `send`/`recv` with batch envs/2) as the reference. No server, client or
pipes: what the worker's own stepping can reach, in env steps per second (agent steps: with action
repeat 4 the group's rows do 4 EnvPool steps per env step; EnvPool's reference rows are left out there).
EnvPool runs with 2 threads, as in a 2-worker server.
"""

import argparse
import statistics
import sys
import time

import numpy as np

from envpool_calls import PROCGEN, worker_module  # the worker's module and ProcGen's option defaults

# label, family, name, options, envs
WORKLOADS = [
    ("dmc cheetah-run state, action repeat 4", "dmc", "cheetah-run", {"action_repeat": 4}, 16),
    ("gym HalfCheetah-v5", "gym", "HalfCheetah-v5", {"max_episode_steps": 0}, 16),
    ("gym HalfCheetah-v5", "gym", "HalfCheetah-v5", {"max_episode_steps": 0}, 64),
    ("procgen bigfish", "procgen", "bigfish", PROCGEN, 64),
]


def group(worker, family, name, options, n, batch):
    made = worker.make_group(family, name, {"engine": "envpool", "envpool_threads": 2, "batch_size": batch,
                                            **options}, list(range(n)))
    observation = made.spec()["observation"]
    made.attach(memoryview(bytearray(2 * n * int(np.prod(observation["shape"]))
                                     * np.dtype(observation["dtype"]).itemsize)))
    return made


def timed(seconds, step):
    """Env steps per second of `step` (returns the env steps it took) over `seconds`."""
    for _ in range(8):
        step()
    done, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        done += step()
    return done / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=2.0)
    args = parser.parse_args()
    worker = worker_module()
    envpool = worker._import_envpool()
    rows = []
    for label, family, name, options, n in WORKLOADS:
        half = n // 2
        sync, asyn = group(worker, family, name, options, n, 0), group(worker, family, name, options, n, half)
        space = sync.spec()["action"]
        rng = np.random.default_rng(0)
        if space["kind"] == "discrete":
            table = rng.integers(0, space["n"], (16, n))
        else:
            table = rng.uniform(space["low"], space["high"], (16, n) + tuple(space["shape"]))
        table = table.astype(sync.action_dtype)
        full = [row.tobytes() for row in table]
        halves = [row[:half].tobytes() for row in table]
        counter = [0]

        def sync_step():
            counter[0] += 1
            sync.step(full[counter[0] % 16])
            return n

        def async_step():
            counter[0] += 1
            env_ids, *_ = asyn.recv()
            asyn.send(halves[counter[0] % 16], env_ids)
            return half

        sync.reset(None)
        asyn.async_reset()
        modes = {"group sync": sync_step, "group async": async_step}
        pools = []
        if options.get("action_repeat", 1) == 1:  # EnvPool's own reference, the same task and keywords
            task, kwargs = worker.envpool_task(family, name, options)
            ref_sync = envpool.make(task, env_type="gymnasium", num_envs=n, batch_size=n, num_threads=2, **kwargs)
            ref_async = envpool.make(task, env_type="gymnasium", num_envs=n, batch_size=half, num_threads=2,
                                     **kwargs)
            pools = [ref_sync, ref_async]
            ref_sync.reset()
            ref_async.async_reset()
            raw = table.astype(ref_sync.action_space.dtype)

            def envpool_sync():
                counter[0] += 1
                ref_sync.step(raw[counter[0] % 16])
                return n

            def envpool_async():
                counter[0] += 1
                *_, info = ref_async.recv()
                ref_async.send(raw[counter[0] % 16][:half], info["env_id"])
                return half

            modes.update({"EnvPool sync": envpool_sync, "EnvPool async": envpool_async})
        rates = {mode: [] for mode in modes}
        for _ in range(args.rounds):
            for mode, step in modes.items():
                rates[mode].append(timed(args.seconds, step))
        for made in (sync, asyn):
            made.close()
        for pool in pools:
            pool.close()
        ratios = [b / a for a, b in zip(rates["group sync"], rates["group async"])]
        rows.append((label, n, {mode: statistics.median(r) for mode, r in rates.items()}, ratios))
        print(f"{label} x{n}: " + ", ".join(f"{mode} {statistics.median(r):,.0f}/s" for mode, r in rates.items()),
              file=sys.stderr)
    print(f"\nEnvpoolGroup, EnvPool 2 threads, env steps/s, median of {args.rounds} alternating rounds of "
          f"{args.seconds:g} s\n")
    print("| workload | envs | group sync | group async (batch envs/2) | async / sync (range) | EnvPool sync | "
          "EnvPool async |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for label, n, rate, ratios in rows:
        reference = " | ".join(f"{rate[mode]:,.0f}" if mode in rate else "-" for mode in ("EnvPool sync", "EnvPool async"))
        print(f"| {label} | {n} | {rate['group sync']:,.0f} | {rate['group async']:,.0f} | "
              f"{statistics.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f}) | {reference} |")


if __name__ == "__main__":
    main()
