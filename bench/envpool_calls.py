"""The worker's side of an engine="envpool" step, in one process: EnvPool called raw vs through its wrapper.

    .venv/bin/python bench/envpool_calls.py [--rounds 5] [--seconds 2]

Builds the worker's EnvpoolGroup (server/sim/python/radserve_worker/envpool_engine.py) for each workload twice with the
same seeds, one calling EnvPool's raw `_send`/`_recv` (what the worker does) and one its public
`step`/`reset` (the wrapper: action conversion, state tree, info dict), and times `Group.step` of each
in alternating rounds. No server, client or pipes: only what the worker spends per step. EnvPool runs
with 2 threads, as it does in a 2-worker server.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PROCGEN = {"num_levels": 0, "start_level": 0, "distribution_mode": "easy", "restrict_themes": False,
           "use_backgrounds": True, "use_monochrome_assets": False, "center_agent": True,
           "use_sequential_levels": False, "paint_vel_info": False, "use_generated_assets": False}
# label, family, name, options, envs
WORKLOADS = [
    ("dmc cheetah-run state, action repeat 4", "dmc", "cheetah-run", {"action_repeat": 4}, 16),
    ("gym HalfCheetah-v5", "gym", "HalfCheetah-v5", {"max_episode_steps": 0}, 16),
    ("gym HalfCheetah-v5", "gym", "HalfCheetah-v5", {"max_episode_steps": 0}, 64),
    ("procgen bigfish", "procgen", "bigfish", PROCGEN, 64),
]


def worker_module():
    """The worker's entry points, from the package the worker embeds."""
    import record

    return record.worker_module("adapters")


def group(worker, family, name, options, n, raw):
    made = worker.make_group(family, name, {"engine": "envpool", "envpool_threads": 2, **options}, list(range(n)))
    if not raw:
        made.state_index = None
    observation = made.spec()["observation"]
    made.attach(memoryview(bytearray(2 * n * int(np.prod(observation["shape"]))
                                     * np.dtype(observation["dtype"]).itemsize)))
    made.reset(None)
    return made


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=2.0)
    args = parser.parse_args()
    worker = worker_module()
    rows = []
    for label, family, name, options, n in WORKLOADS:
        groups = {raw: group(worker, family, name, options, n, raw) for raw in (True, False)}
        space = groups[True].spec()["action"]
        rng = np.random.default_rng(0)
        if space["kind"] == "discrete":
            actions = [rng.integers(0, space["n"], n) for _ in range(16)]
        else:
            actions = [rng.uniform(space["low"], space["high"], (n,) + tuple(space["shape"])) for _ in range(16)]
        actions = [a.astype(groups[True].action_dtype).tobytes() for a in actions]
        times = {True: [], False: []}
        for _ in range(args.rounds):
            for raw, made in groups.items():
                for a in actions:
                    made.step(a)
                calls, start = 0, time.perf_counter()
                while time.perf_counter() - start < args.seconds:
                    made.step(actions[calls % 16])
                    calls += 1
                times[raw].append((time.perf_counter() - start) / calls)
        for made in groups.values():
            made.close()
        ratios = [b / a for a, b in zip(times[True], times[False])]
        rows.append((label, n, statistics.median(times[False]), statistics.median(times[True]), ratios))
        print(f"{label} x{n}: wrapper {rows[-1][2] * 1e6:,.0f} us, raw {rows[-1][3] * 1e6:,.0f} us", file=sys.stderr)
    print(f"\nEnvpoolGroup.step, EnvPool 2 threads, median of {args.rounds} alternating rounds of {args.seconds:g} s\n")
    print("| workload | envs | EnvPool's wrapper, us/step | raw calls, us/step | speed-up (range) |")
    print("|---|---:|---:|---:|---:|")
    for label, n, wrapper, raw, ratios in rows:
        print(f"| {label} | {n} | {wrapper * 1e6:,.0f} | {raw * 1e6:,.0f} | {statistics.median(ratios):.2f}x "
              f"({min(ratios):.2f}-{max(ratios):.2f}) |")


if __name__ == "__main__":
    main()
