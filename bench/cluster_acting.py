"""Server-side against learner-side acting over three server containers (issue 38): one sharded
session over three radserve containers (one worker each) on a Docker network, acted from a learner
container either learner-side (the learner runs the policy in torch on the observations each Step
returns, one Step per vector step to every server) or server-side (the same network exported to ONNX,
SetPolicy + StartActing on every server; the learner makes no call per step), on ProcGen bigfish (a
small categorical MLP: the simulator is cheap, so the call per step is what learner-side acting costs)
and dm_control cartpole-swingup from 64x64 pixels (a small conv gaussian_tanh actor: rendering
dominates a step). Both record into a replay buffer. Prints the table and writes
bench/results/cluster_acting.json (docs/performance.md renders it).

    python bench/cluster_acting.py [--rounds 2] [--seconds 15]     (make images first; tag dev)

On a 2-core machine the three servers and the learner share the same two cores: the figures show
what the call per step costs a learner against three servers, not how acting scales with servers.
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# name: (env id, make_vec options, envs over the three servers, head)
CONFIGS = {
    "procgen": ("procgen/bigfish", {}, 24, "categorical"),
    "dmc": ("dmc/cartpole-swingup", {"height": 64, "width": 64, "frame_stack": 3, "render_profile": "fast"}, 6,
            "gaussian_tanh"),
}
MODES = ("learner", "server")


def policy(obs_shape, action_space, head: str):
    """The network both sides run: a categorical MLP on the flattened frame, or a two-conv actor
    with mean and log std (the shape of RAD's, smaller). Observations arrive as uint8."""
    import torch
    import torch.nn as nn

    torch.manual_seed(0)

    class Categorical(nn.Module):
        def __init__(self):
            super().__init__()
            self.net = nn.Sequential(nn.Flatten(), nn.Linear(int(torch.tensor(obs_shape).prod()), 64), nn.Tanh(),
                                     nn.Linear(64, int(action_space.n)))

        def forward(self, obs):
            return self.net(obs.float() / 255.0)

    class Gaussian(nn.Module):
        def __init__(self):
            super().__init__()
            self.convs = nn.Sequential(nn.Conv2d(obs_shape[0], 16, 3, stride=2), nn.ReLU(), nn.Conv2d(16, 16, 3), nn.ReLU(),
                                       nn.Flatten())
            with torch.no_grad():
                features = self.convs(torch.zeros(1, *obs_shape)).shape[1]
            self.head = nn.Sequential(nn.Linear(features, 50), nn.Tanh(), nn.Linear(50, 2 * action_space.shape[0]))

        def forward(self, obs):
            mean, log_std = self.head(self.convs(obs.float() / 255.0)).chunk(2, dim=-1)
            return mean, log_std.clamp(-5.0, 2.0)

    return (Categorical() if head == "categorical" else Gaussian()).eval()


def measure(addresses: str, config: str, mode: str, seconds: float) -> dict:
    """One measurement, in the learner container: env steps/s over the sharded session."""
    import numpy as np
    import torch

    import radserve
    import radserve.actors

    torch.set_num_threads(1)
    env_id, options, num_envs, head = CONFIGS[config]
    client = radserve.Client(addresses)
    envs = client.make_vec(env_id, num_envs=num_envs, seed=0, autoreset_mode="SameStep", replay_capacity=20_000, **options)
    space = envs.single_action_space
    module = policy(envs.single_observation_space.shape, space, head)
    rng = np.random.default_rng(0)
    cpu = time.process_time()
    try:
        if mode == "learner":
            obs, _ = envs.reset(seed=0)

            @torch.no_grad()
            def act(obs):
                out = module(torch.as_tensor(obs))
                if head == "categorical":
                    return torch.distributions.Categorical(logits=out).sample().numpy()
                mean, log_std = out
                squashed = np.tanh(mean.numpy() + np.exp(log_std.numpy()) * rng.standard_normal(mean.shape))
                return (space.low + (squashed + 1) * 0.5 * (space.high - space.low)).astype(np.float32)

            for _ in range(5):
                obs, *_ = envs.step(act(obs))
            cpu, start, steps = time.process_time(), time.perf_counter(), 0
            while time.perf_counter() - start < seconds:
                obs, *_ = envs.step(act(obs))
                steps += num_envs
            elapsed = time.perf_counter() - start
        else:
            example = np.zeros((1, *envs.single_observation_space.shape), dtype=np.uint8)
            envs.set_policy(radserve.actors.export_onnx(module, example), head=head)
            envs.start_acting(seed=0)
            time.sleep(2.0)

            def acted() -> int:
                return sum(info.env_steps for info in envs.acting())

            cpu, start, first = time.process_time(), time.perf_counter(), acted()
            time.sleep(seconds)
            steps, elapsed = acted() - first, time.perf_counter() - start
            envs.stop_acting()
        learner_cpu = time.process_time() - cpu
    finally:
        envs.close()
        client.close()
    return {"steps_per_s": steps / elapsed, "learner_cpu_ms": 1e3 * learner_cpu / max(steps, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--tag", default="dev")
    parser.add_argument("--measure", nargs=3, metavar=("ADDRESSES", "CONFIG", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(*args.measure, seconds=args.seconds)))
        return

    import record
    from cluster import in_learner_container, server_containers

    results: "dict[tuple[str, str], list[dict]]" = {}
    with server_containers(args.tag, "acting") as (network, servers):
        for round_ in range(args.rounds):
            for config in CONFIGS:
                for mode in (MODES if round_ % 2 == 0 else MODES[::-1]):
                    result = in_learner_container(args.tag, network, "/bench/cluster_acting.py", "--seconds",
                                                  str(args.seconds), "--measure", ",".join(servers), config, mode)
                    results.setdefault((config, mode), []).append(result)
                    print(f"round {round_ + 1}: {config} {mode}-side: {result['steps_per_s']:,.0f} env steps/s, "
                          f"learner CPU {result['learner_cpu_ms']:.3f} ms per env step", file=sys.stderr)

    rows = []
    for config, (env_id, _, num_envs, head) in CONFIGS.items():
        base = statistics.median(r["steps_per_s"] for r in results[config, "learner"])
        for mode in MODES:
            runs = results[config, mode]
            label = "learner-side (a Step per vector step)" if mode == "learner" else "server-side (StartActing)"
            rates = [r["steps_per_s"] for r in runs]
            rows.append([f"{env_id} x{num_envs}", label, record.ranged(rates),
                         record.ranged([r["learner_cpu_ms"] for r in runs], digits=3),
                         record.cell(statistics.median(rates) / base, digits=2, suffix="x")])
            print(record.plain(rows[-1]))
    table = {"id": "cluster_acting", "rows": rows,
             "columns": ["env (envs over 3 servers)", "acting", "env steps/s", "learner CPU ms per env step",
                         "vs learner-side"],
             "note": f"One sharded session over three server containers (one worker each) from a learner container, "
                     f"{args.rounds} alternating rounds of {args.seconds:.0f} s, median (range); replay recorded; "
                     "the same network learner-side (torch, one thread) and server-side (ONNX Runtime, one thread); "
                     "every container shares this machine's cores."}
    record.write("cluster_acting", [table], {"rounds": args.rounds, "seconds": args.seconds, "tag": args.tag})


if __name__ == "__main__":
    main()
