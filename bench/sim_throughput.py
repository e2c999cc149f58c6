"""Steps per second through radserve (a Python client, one session) against the same simulator driven
directly in one Python process, measured in the same run; prints a markdown table with the ratio.

    .venv/bin/python bench/sim_throughput.py [--seconds 4] [--rounds 3] [--workers 2] [--stream]
        [--only TEXT] [--delivery both|grpc|shared_memory] [--server-env NAME=VALUE]

Each row is measured in rounds: through gRPC and through shared stepping
(`delivery="shared_memory"`, the client on the server's host), then the baseline. The table gives
median rates and the median of the rounds' ratios with its range.

The dmc pixel baselines render with `physics.render()`, as dm_control's pixels wrapper and RAD's
dmc2gym do; the row "baseline with cached Camera" gives the baseline the server's own way of rendering
(one Camera per env), to show how much of the ratio is that and how much the worker processes.

Rows marked "pipelined" split the envs into two sessions stepped with step_async/step_wait.

A full run (every row, both transports) writes bench/results/sim_throughput.json, which
docs/performance.md renders (`make docs-tables`); a partial one (--only, --delivery, --stream) only prints.
"""

import argparse
import contextlib
import functools
import logging
import os
import tempfile
import time

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
# dm_control's cheetah warns through absl on every load ("settotalmass is deprecated").
logging.getLogger("absl").setLevel(logging.ERROR)

import radserve  # noqa: E402

import record  # noqa: E402  (bench/record.py: the results file)


def timed(step_fn, steps_per_call, seconds, warmup=2):
    for _ in range(warmup):
        step_fn()
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        step_fn()
        calls += 1
    return calls * steps_per_call / (time.perf_counter() - start)


def in_scratch_dir(baseline):
    """Runs a MuJoCo baseline in a temporary working directory: MuJoCo writes its warnings to
    MUJOCO_LOG.TXT there, not into the checkout (the server's workers do the same, worker.rs)."""

    @functools.wraps(baseline)
    def run(*args):
        with tempfile.TemporaryDirectory(prefix="radserve-bench-") as scratch, contextlib.chdir(scratch):
            return baseline(*args)

    return run


@in_scratch_dir
def dmc_direct(name, num_envs, fast, pixels, seconds, cached_camera=False):
    from dm_control import suite

    domain, task = name.split("-", 1)
    envs = [suite.load(domain, task, task_kwargs={"random": i}) for i in range(num_envs)]
    for env in envs:
        if fast:
            model = env.physics.model
            model.vis.quality.shadowsize = 0
            model.vis.quality.offsamples = 0
            model.mat_reflectance[:] = 0
            model.light_castshadow[:] = 0
        env.reset()
    shape = envs[0].action_spec().shape
    rng = np.random.default_rng(0)
    repeat = 4
    # physics.render() is how dm_control's pixels wrapper (and RAD's dmc2gym) render; the server's
    # workers keep one Camera per env instead. cached_camera gives the baseline the same trick.
    if pixels and cached_camera:
        from dm_control.mujoco.engine import Camera

        cameras = [Camera(env.physics, height=100, width=100, camera_id=0) for env in envs]
        render = {id(env): camera.render for env, camera in zip(envs, cameras)}
    else:
        render = {id(env): functools.partial(env.physics.render, height=100, width=100, camera_id=0) for env in envs}

    def step():
        for env in envs:
            action = rng.uniform(-1, 1, shape)
            for _ in range(repeat):
                time_step = env.step(action)
            if time_step.last():
                env.reset()
            if pixels:
                render[id(env)]()
            else:
                np.concatenate([np.asarray(v, np.float32).reshape(-1) for v in time_step.observation.values()])

    return timed(step, num_envs, seconds)


@in_scratch_dir
def gym_direct(name, num_envs, seconds):
    import gymnasium

    envs = [gymnasium.make(name) for _ in range(num_envs)]
    for i, env in enumerate(envs):
        env.reset(seed=i)
    rng = np.random.default_rng(0)
    space = envs[0].action_space

    def step():
        for env in envs:
            _, _, terminated, truncated, _ = env.step(rng.uniform(space.low, space.high).astype(np.float32))
            if terminated or truncated:
                env.reset()

    return timed(step, num_envs, seconds)


def procgen_direct(name, num_envs, seconds):
    from procgen import ProcgenGym3Env

    env = ProcgenGym3Env(num=num_envs, env_name=name, rand_seed=0)
    rng = np.random.default_rng(0)

    def step():
        env.act(rng.integers(0, 15, num_envs).astype(np.int32))
        env.observe()

    return timed(step, num_envs, seconds)


def random_actions(space, num_envs, count=64):
    """`count` batches of random actions for `num_envs` envs, cycled through while timing."""
    rng = np.random.default_rng(0)
    if hasattr(space, "n"):
        return [rng.integers(0, space.n, num_envs) for _ in range(count)]
    return [rng.uniform(space.low, space.high, (num_envs,) + space.shape).astype(np.float32) for _ in range(count)]


def served(client, env_id, num_envs, seconds, stream, delivery, **options):
    envs = client.make_vec(env_id, num_envs=num_envs, seed=0, autoreset_mode="SameStep",
                           stream=stream, delivery=delivery, **options)
    envs.reset()
    actions = random_actions(envs.single_action_space, num_envs)
    counter = iter(range(1 << 62))

    def step():
        envs.step(actions[next(counter) % 64])

    rate = timed(step, num_envs, seconds)
    envs.close()
    return rate


def served_pipelined(client, env_id, num_envs, seconds, stream, delivery, **options):
    """num_envs split into two sessions, stepped EnvPool-style: one half's step is in flight while the
    other half's reply is read and its next actions are made (step_async / step_wait)."""
    half = num_envs // 2
    pair = [client.make_vec(env_id, num_envs=half, seed=0, autoreset_mode="SameStep",
                            stream=stream, delivery=delivery, **options)
            for _ in range(2)]
    for envs in pair:
        envs.reset()
    actions = random_actions(pair[0].single_action_space, half)
    counter = iter(range(1 << 62))
    pair[0].step_async(actions[0])

    def step():  # one call steps both halves: num_envs env steps
        pair[1].step_async(actions[next(counter) % 64])
        pair[0].step_wait()
        pair[0].step_async(actions[next(counter) % 64])
        pair[1].step_wait()

    rate = timed(step, 2 * half, seconds)
    pair[0].step_wait()
    for envs in pair:
        envs.close()
    return rate


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=4.0, help="measuring time per round, row and side")
    parser.add_argument("--rounds", type=int, default=3, help="rounds per row, server and baseline alternating")
    parser.add_argument("--workers", type=int, default=os.cpu_count())
    parser.add_argument("--delivery", default="both", choices=("both", "grpc", "shared_memory"),
                        help="act through gRPC, through memory shared with the server (same host), or both")
    parser.add_argument("--stream", action="store_true", help="with gRPC, act over the bidirectional stream")
    parser.add_argument("--only", default="", help="run only the rows whose label contains this text")
    parser.add_argument("--server-env", action="append", default=[], metavar="NAME=VALUE",
                        help="set in the server's (and its workers') environment only, e.g. LP_NUM_THREADS=1")
    args = parser.parse_args()
    s = args.seconds
    rows = [
        # (label, env id, envs, server options, direct baseline)
        ("dmc pixels cheetah-run (default look)", "dmc/cheetah-run", 4, {"frame_stack": 1},
         lambda: dmc_direct("cheetah-run", 4, False, True, s)),
        ("dmc pixels cheetah-run (default look), baseline with cached Camera", "dmc/cheetah-run", 4,
         {"frame_stack": 1}, lambda: dmc_direct("cheetah-run", 4, False, True, s, True)),
        ("dmc pixels cheetah-run (fast look)", "dmc/cheetah-run", 4, {"frame_stack": 1, "render_profile": "fast"},
         lambda: dmc_direct("cheetah-run", 4, True, True, s)),
        ("dmc pixels cheetah-run (fast look), baseline with cached Camera", "dmc/cheetah-run", 4,
         {"frame_stack": 1, "render_profile": "fast"}, lambda: dmc_direct("cheetah-run", 4, True, True, s, True)),
        ("dmc state cheetah-run", "dmc/cheetah-run", 16, {"pixels": False},
         lambda: dmc_direct("cheetah-run", 16, False, False, s)),
        ("dmc state cheetah-run, pipelined 2 x 8", "dmc/cheetah-run", 16, {"pixels": False},
         lambda: dmc_direct("cheetah-run", 16, False, False, s)),
        ("gym HalfCheetah-v5", "gym/HalfCheetah-v5", 16, {},
         lambda: gym_direct("HalfCheetah-v5", 16, s)),
        ("gym HalfCheetah-v5, pipelined 2 x 8", "gym/HalfCheetah-v5", 16, {},
         lambda: gym_direct("HalfCheetah-v5", 16, s)),
        ("procgen bigfish", "procgen/bigfish", 64, {},
         lambda: procgen_direct("bigfish", 64, s)),
        ("procgen bigfish, pipelined 2 x 32", "procgen/bigfish", 64, {},
         lambda: procgen_direct("bigfish", 64, s)),
        # procgen's own pool of 4 threads stepping each worker's vector of games, for comparison
        ("procgen bigfish (num_threads=4)", "procgen/bigfish", 64, {"num_threads": 4},
         lambda: procgen_direct("bigfish", 64, s)),
    ]
    rows = [row for row in rows if args.only in row[0]]
    deliveries = ["grpc", "shared_memory"] if args.delivery == "both" else [args.delivery]
    results = []
    server_env = dict(item.split("=", 1) for item in args.server_env)
    with radserve.LocalServer(workers=args.workers, env=server_env) as server:
        client = radserve.Client(server.address)
        # The server builds its catalog in a background worker for ~15 s after starting; measuring
        # during that time would give the first rows less CPU than the others.
        client.list_envs()
        for label, env_id, num_envs, options, direct in rows:
            acting = served_pipelined if "pipelined" in label else served
            # Rounds alternate server and baseline, so that a slow spell of this noisy machine lands on
            # both sides of a round's ratio rather than on one side of the whole row.
            rates, direct_rates = {d: [] for d in deliveries}, []
            for round_ in range(args.rounds):
                for d in deliveries:
                    rates[d].append(acting(client, env_id, num_envs, s, args.stream, d, **options))
                direct_rates.append(direct())
                served_text = ", ".join(f"{r[-1]:.0f} ({d})" for d, r in rates.items())
                print(f"{label}, round {round_ + 1}: {served_text} vs {direct_rates[-1]:.0f} steps/s", flush=True)
            results.append((label, num_envs, rates, direct_rates))
    names = {"grpc": "gRPC" + (" stream" if args.stream else ""), "shared_memory": "shared memory"}
    columns = (["workload", "envs"] + [f"{names[d]} steps/s" for d in deliveries] + ["one process steps/s"]
               + [f"{names[d]} / one process" for d in deliveries])
    table_rows = []
    for label, num_envs, rates, direct_rates in results:
        ratios = [record.ranged([a / b for a, b in zip(rates[d], direct_rates)], digits=2, suffix="x") for d in deliveries]
        table_rows.append([label, str(num_envs)] + [record.ranged(rates[d]) for d in deliveries]
                          + [record.ranged(direct_rates)] + ratios)
    table = {"id": "sim_throughput", "columns": columns, "rows": table_rows,
             "note": f"radserve with {args.workers} workers, synchronous acting unless pipelined; medians of "
                     f"{args.rounds} rounds of {args.seconds:g} s per side (their range), server and baseline alternating."}
    print("\n" + " | ".join(columns))
    for row in table_rows:
        print(record.plain(row))
    if not args.only and args.delivery == "both" and not args.stream and not args.server_env:
        record.write("sim_throughput", [table], {"seconds": args.seconds, "rounds": args.rounds, "workers": args.workers})


if __name__ == "__main__":
    main()
