"""Server-side acting against learner-side acting, same envs, same policy: env steps per second of a
session of 8 envs acted once by this process (ONNX Runtime in Python on the observations each Step
returns, the head drawn here, a Step per vector step over gRPC) and once by the server (SetPolicy +
StartActing: the same model in the server's ONNX Runtime, no call per step), on dm_control pixels
(the RAD actor, 12 MB; the simulator's rendering dominates a step) and ProcGen (a small categorical
policy; the simulator is cheap, so the call per step is what learner-side acting costs). Also: what
a server-side step spends in inference and in the simulators (DescribeSession's acting timings),
this process's CPU per env step, and random actions acting learner-side (the simulators' floor).
Both modes record into a replay buffer; rounds alternate the modes. Prints the table and writes
bench/results/actor_throughput.json.

    python bench/actor_throughput.py [--rounds 3] [--seconds 20] [--num-envs 8] [--address host:port]
"""

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
import record

policies = record.tests_helper("policies")

import radserve

# (env id, make_vec options, the model for the env's spaces, head): a pixel task whose simulator
# dominates a step (dm_control renders each frame), and one whose simulator is cheap (ProcGen), where
# the call per step is what a learner-side step costs.
CONFIGS = {
    "dmc": ("dmc/cartpole-swingup", {"observation_view": "center_crop(84)"}, "gaussian_tanh"),
    "procgen": ("procgen/bigfish", {}, "categorical"),
}


def model_for(envs, head: str) -> bytes:
    shape = envs.single_observation_space.shape
    if head == "gaussian_tanh":
        return policies.rad_actor(frames=shape[0], size=shape[1], action_dim=envs.single_action_space.shape[0])
    return policies.conv_categorical(shape, int(envs.single_action_space.n), value=False, uint8=True)


def make(client, config: str, num_envs: int, seed: int):
    env_id, options, _ = CONFIGS[config]
    return client.make_vec(env_id, num_envs=num_envs, seed=seed, replay_capacity=20_000, autoreset_mode="SameStep", **options)


def act_here(session, obs, envs, head: str, rng):
    """The actions this process takes: the head's draw on the model's outputs (None: random)."""
    space = envs.single_action_space
    if head == "categorical":
        if session is None:
            return rng.integers(0, space.n, size=len(obs))
        (logits,) = session.run(None, {"obs": obs})
        probabilities = np.exp(logits - logits.max(1, keepdims=True))
        probabilities /= probabilities.sum(1, keepdims=True)
        return (probabilities.cumsum(1) > rng.random((len(obs), 1))).argmax(1)
    if session is None:
        unit = rng.uniform(-1, 1, size=(len(obs), space.shape[0]))
    else:
        mean, log_std = session.run(None, {"obs": obs})
        unit = np.tanh(mean + np.exp(np.clip(log_std, -20, 2)) * rng.standard_normal(mean.shape))
    return (space.low + (unit + 1) * 0.5 * (space.high - space.low)).astype(np.float32)


def learner_side(client, config: str, with_policy: bool, num_envs: int, seconds: float, seed: int) -> dict:
    """Steps/s with this process acting (without a policy: random actions), and this process's CPU."""
    import onnxruntime

    envs = make(client, config, num_envs, seed)
    head = CONFIGS[config][2]
    try:
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = 1
        session = onnxruntime.InferenceSession(model_for(envs, head), options) if with_policy else None
        rng = np.random.default_rng(seed)
        obs, _ = envs.reset(seed=seed)
        steps, inference = 0, 0.0
        begin, cpu = time.perf_counter(), time.process_time()
        while time.perf_counter() - begin < seconds:
            started = time.perf_counter()
            actions = act_here(session, obs, envs, head, rng)
            inference += time.perf_counter() - started
            obs, *_ = envs.step(actions)
            steps += num_envs
        elapsed, cpu = time.perf_counter() - begin, time.process_time() - cpu
        return {"steps_per_second": steps / elapsed, "inference_ms": 1e3 * inference / steps if with_policy else 0.0,
                "learner_cpu_ms": 1e3 * cpu / steps}
    finally:
        envs.close()


def server_side(client, config: str, num_envs: int, seconds: float, seed: int) -> dict:
    envs = make(client, config, num_envs, seed)
    try:
        envs.set_policy(model_for(envs, CONFIGS[config][2]), head=CONFIGS[config][2])
        envs.start_acting(seed=seed)
        # The first steps include the reset and ONNX Runtime's first runs: measure after them.
        while envs.acting()[0].env_steps < 2 * num_envs:
            time.sleep(0.05)
        first = envs.acting()[0]
        begin, cpu = time.perf_counter(), time.process_time()
        time.sleep(seconds)
        last = envs.acting()[0]
        elapsed, cpu = time.perf_counter() - begin, time.process_time() - cpu
        envs.stop_acting()
        steps = last.env_steps - first.env_steps
        return {"steps_per_second": steps / elapsed,
                "inference_ms": 1e3 * (last.inference_seconds - first.inference_seconds) / steps,
                "simulator_ms": 1e3 * (last.step_seconds - first.step_seconds) / steps,
                "learner_cpu_ms": 1e3 * cpu / steps}
    finally:
        envs.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--address", default="", help="an existing server (default: one started on localhost)")
    parser.add_argument("--configs", default="dmc,procgen", help="which of " + ", ".join(CONFIGS))
    args = parser.parse_args()
    results: "dict[tuple[str, str], list[dict]]" = {}

    def run(address: str) -> None:
        with radserve.Client(address) as client:
            for round_ in range(args.rounds):
                seed = 100 * round_
                for config in args.configs.split(","):
                    measured = {
                        "learner": learner_side(client, config, True, args.num_envs, args.seconds, seed),
                        "server": server_side(client, config, args.num_envs, args.seconds, seed),
                        "random": learner_side(client, config, False, args.num_envs, args.seconds, seed),
                    }
                    for mode, figures in measured.items():
                        results.setdefault((config, mode), []).append(figures)
                    print(f"round {round_ + 1}, {config}: " + ", ".join(f"{mode} {figures['steps_per_second']:.0f} steps/s" for mode, figures in measured.items()))

    if args.address:
        run(args.address)
    else:
        with radserve.LocalServer(workers=args.workers) as server:
            run(server.address)

    def column(config: str, mode: str, key: str, digits: int = 0):
        return record.ranged([r[key] for r in results[(config, mode)]], digits)

    rows = []
    for config in args.configs.split(","):
        env_id, _, head = CONFIGS[config]
        learner = [r["steps_per_second"] for r in results[(config, "learner")]]
        ratio = lambda mode: record.ranged([r["steps_per_second"] / base for r, base in zip(results[(config, mode)], learner)], 2, suffix="x")  # noqa: E731
        rows += [
            [env_id, "learner-side (a Step per vector step)", column(config, "learner", "steps_per_second"),
             column(config, "learner", "inference_ms", 2), "", column(config, "learner", "learner_cpu_ms", 2), ratio("learner")],
            [env_id, "server-side (StartActing)", column(config, "server", "steps_per_second"),
             column(config, "server", "inference_ms", 2), column(config, "server", "simulator_ms", 2),
             column(config, "server", "learner_cpu_ms", 3), ratio("server")],
            [env_id, "learner-side, random actions", column(config, "random", "steps_per_second"), "", "",
             column(config, "random", "learner_cpu_ms", 2), ratio("random")],
        ]
    table = {
        "id": "actor_throughput",
        "columns": ["env", "acting", "env steps/s", "inference ms per env step", "simulators ms per env step",
                    "learner CPU ms per env step", "vs learner-side"],
        "rows": rows,
        "note": (f"{args.num_envs} envs, replay recorded; dm_control: 3 stacked frames through center_crop(84), the RAD "
                 f"actor (gaussian_tanh, 12 MB); ProcGen: a small MLP categorical policy on [3, 64, 64]; "
                 f"ONNX Runtime with one thread on both sides; {args.rounds} rounds of {args.seconds:.0f} s, "
                 f"{'a server on this host' if not args.address else 'the server at ' + args.address} with "
                 f"{args.workers} workers; medians (range)"),
    }
    for row in rows:
        print(record.plain(row))
    record.write("actor_throughput", [table], settings=vars(args))


if __name__ == "__main__":
    main()
