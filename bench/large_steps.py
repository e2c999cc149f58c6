"""A small session's Step latency while a large pixel session steps in the same server: p50/p99 of
one CartPole Step over gRPC, quiet and while another process steps a large session (by default
ProcGen bigfish, 64 envs of 4 stacked 64x64 frames with a replay buffer: 3 MiB of stacks, recorded
and copied every step) as fast as it can, in one run; and the large session's own steps/s.

    .venv/bin/python bench/large_steps.py [--binary A --binary B ...] [--rounds 3] [--steps 2000]
        [--load-env procgen/bigfish] [--load-envs 64] [--frame-stack 4]

What it measures is whether a large step's copies (stacking, replay recording, the view: memcpy on
the server's tokio threads) hold up other sessions' calls. With several binaries (a build before a
change and after it) rounds alternate between them: these machines are noisy, compare ratios within
one run. The table goes to bench/results/large_steps.json (docs/performance.md renders it) unless
--no-results.
"""

import argparse
import multiprocessing
import sys
import time

import numpy as np

import radserve

import record  # noqa: E402  (bench/record.py: the results file)
from acting_latency import latencies, percentile  # one Step timed the same way in both benches


def load(address, args, ready, stop, steps):
    """Makes the large session and steps it with random actions until `stop` (a process of its own,
    spawned: no grpc state crosses a fork)."""
    with radserve.Client(address) as client:
        envs = client.make_vec(args.load_env, num_envs=args.load_envs, seed=0, autoreset_mode="SameStep",
                               replay_capacity=args.replay_capacity, frame_stack=args.frame_stack)
        envs.action_space.seed(0)
        actions = [envs.action_space.sample() for _ in range(16)]
        envs.reset(seed=0)
        ready.set()
        while not stop.is_set():
            envs.step(actions[steps.value % len(actions)])
            steps.value += 1
        envs.close()


def measure(binary, args):
    env = {"RADSERVE__SIM__VENV": sys.prefix}
    with radserve.LocalServer(workers=2, binary=binary, env=env) as server:
        client = radserve.Client(server.address)
        small = client.make_vec("gym/CartPole-v1", num_envs=1, seed=0, autoreset_mode="SameStep")
        actions = np.random.default_rng(0).integers(0, 2, (64, 1))
        quiet = latencies(small, args.steps, actions)
        context = multiprocessing.get_context("spawn")
        ready, stop, steps = context.Event(), context.Event(), context.Value("q", 0)
        stepper = context.Process(target=load, args=(server.address, args, ready, stop, steps))
        stepper.start()
        if not ready.wait(120):
            raise SystemExit("the large session did not start within 120 s")
        time.sleep(1.0)
        started_steps, started = steps.value, time.perf_counter()
        busy = latencies(small, args.steps, actions)
        rate = (steps.value - started_steps) * args.load_envs / (time.perf_counter() - started)
        stop.set()
        stepper.join()
        small.close()
    return quiet, busy, rate


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--binary", action="append", default=None, help="a server binary to measure")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=2000, help="CartPole steps per case")
    parser.add_argument("--load-env", default="procgen/bigfish")
    parser.add_argument("--load-envs", type=int, default=64)
    parser.add_argument("--frame-stack", type=int, default=4)
    parser.add_argument("--replay-capacity", type=int, default=20000)
    parser.add_argument("--no-results", action="store_true", help="print only; leave bench/results/ as it is")
    args = parser.parse_args()
    binaries = args.binary or ["target/release/radserve"]
    results = {}
    for round_index in range(args.rounds):
        for binary in binaries:
            results.setdefault(binary, []).append(measure(binary, args))
            print(f"round {round_index + 1}/{args.rounds} {binary} done", file=sys.stderr, flush=True)
    rows = []
    for binary, runs in results.items():
        quiet = [t for run in runs for t in run[0]]
        busy = [t for run in runs for t in run[1]]
        ratios = [percentile(run[1], 99) / percentile(run[0], 99) for run in runs]
        rows.append([binary, f"{percentile(quiet, 50):.2f} / {percentile(quiet, 99):.2f}",
                     f"{percentile(busy, 50):.2f} / {percentile(busy, 99):.2f}",
                     record.ranged(ratios, digits=1, suffix="x"), record.ranged([run[2] for run in runs])])
        print(record.plain(rows[-1]))
    if not args.no_results:
        table = {"id": "large_steps", "rows": rows, "align": ["l", "r", "r", "r", "r"],
                 "columns": ["server", "CartPole quiet p50 / p99 ms", "beside the large session p50 / p99 ms",
                             "p99 ratio", "large session env steps/s"],
                 "note": f"One CartPole Step over gRPC, {args.steps} steps per case, quiet and while another process "
                         f"steps {args.load_env} x{args.load_envs} (frame_stack {args.frame_stack}, replay "
                         f"{args.replay_capacity}) over gRPC; percentiles over all {args.rounds} rounds, ratio and rate: "
                         f"median (range) of the rounds."}
        record.write("large_steps", [table], {"rounds": args.rounds, "steps": args.steps, "load_env": args.load_env,
                                              "load_envs": args.load_envs, "frame_stack": args.frame_stack})


if __name__ == "__main__":
    main()
