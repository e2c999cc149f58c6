"""What the envs' info dicts cost a step: steps/s and CPU per env step of the same sessions with infos
(typed columns) and with `send_infos=False`, in one run; optionally an earlier build's (JSON infos)
beside them.

    .venv/bin/python bench/infos_cost.py [--rounds 3] [--chunks 10] [--steps 200] [--before DIR] [--no-results]

Each variant runs in a process of its own with its own server (2 workers): this tree's client and
`target/release/radserve`, and with `--before DIR` the client in DIR/client-py and the binary
DIR/target/release/radserve (a checkout of an earlier commit, built), so that a build whose infos
travelled as JSON is measured by its own client. "infos off" is this tree's server with the session
option send_infos=False. Every variant holds its session open; within a round they take turns
`--chunks` times, `--steps` steps each (random actions, autoreset SameStep as bench/vs_envpool.py
steps it), so that the machine's drift (large on these VMs) falls on every variant alike. CPU per env
step adds the client's process and the server's with its workers. Writes bench/results/infos_cost.json
(docs/performance.md renders it).
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
import record  # noqa: E402  (bench/record.py: the results file)

# label, env id, envs, options
WORKLOADS = [
    ("gym HalfCheetah-v5 x16", "gym/HalfCheetah-v5", 16, {}),
    ("gym Hopper-v5 x16", "gym/Hopper-v5", 16, {}),
]
DELIVERIES = ("shared_memory", "grpc")


def serve_measurements(client_dir: str, binary: str) -> None:
    """A variant's process: one server; then per line of stdin (JSON) either ["open", env_id,
    num_envs, options, delivery] (a session, reset and warmed up; the previous one closed) or
    ["run", steps] (answered with the seconds and CPU seconds they took)."""
    # The variant's client: its package loaded from its directory, not the installed one.
    import numpy as np
    import record

    radserve = record.load(Path(client_dir) / "radserve", "radserve", package=True)
    from vs_envpool import cpu_seconds, descendants

    with radserve.LocalServer(workers=2, binary=binary, env={"RADSERVE__SIM__VENV": sys.prefix}) as server:
        client = radserve.Client(server.address)
        # The catalog is built before anything is timed: its transient worker renders every task's
        # spec (software GL here), which would otherwise run beside the first workload's turns.
        client.list_envs()
        print(json.dumps({"ready": True}), flush=True)
        envs, actions, count = None, [], 0
        for line in sys.stdin:
            command = json.loads(line)
            if command[0] == "open":
                _, env_id, num_envs, options, delivery = command
                if envs is not None:
                    envs.close()
                envs = client.make_vec(env_id, num_envs=num_envs, seed=0, delivery=delivery,
                                       autoreset_mode="SameStep", **options)
                rng = np.random.default_rng(0)
                space = envs.single_action_space
                actions = [rng.uniform(space.low, space.high, (num_envs,) + space.shape).astype(np.float32)
                           for _ in range(64)]
                envs.reset(seed=0)
                for count in range(20):
                    envs.step(actions[count % 64])
                print(json.dumps({"ok": True}), flush=True)
                continue
            pids = [os.getpid(), *descendants(server.process.pid)]
            cpu, start = {pid: cpu_seconds([pid]) for pid in pids}, time.perf_counter()
            for _ in range(command[1]):
                count += 1
                envs.step(actions[count % 64])
            seconds = time.perf_counter() - start
            # A process that left meanwhile (the catalog's transient worker) is not counted.
            used = sum(cpu_seconds([pid]) - before for pid, before in cpu.items() if os.path.exists(f"/proc/{pid}"))
            print(json.dumps({"seconds": seconds, "cpu": used}), flush=True)


class Variant:
    def __init__(self, label: str, client_dir: Path, binary: Path, options: dict):
        self.label, self.options = label, options
        self.process = subprocess.Popen(
            [sys.executable, __file__, "--serve", str(client_dir), str(binary)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)
        assert self.ask().get("ready"), f"{self.label}: no server"

    def ask(self, command=None) -> dict:
        if command is not None:
            self.process.stdin.write(json.dumps(command) + "\n")
            self.process.stdin.flush()
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"{self.label}: the measuring process ended")
        return json.loads(line)

    def open(self, env_id, num_envs, options, delivery) -> None:
        self.ask(["open", env_id, num_envs, {**options, **self.options}, delivery])

    def run(self, steps: int) -> "tuple[float, float]":
        answer = self.ask(["run", steps])
        return answer["seconds"], answer["cpu"]

    def close(self):
        self.process.stdin.close()
        self.process.wait(timeout=60)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--chunks", type=int, default=10, help="turns of each variant per round")
    parser.add_argument("--steps", type=int, default=200, help="steps per turn")
    parser.add_argument("--before", default="", help="a built checkout of an earlier commit, measured beside")
    parser.add_argument("--no-results", action="store_true", help="print only; leave bench/results/ as it is")
    parser.add_argument("--serve", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve_measurements(*args.serve)
        return
    binary = ROOT / "target" / "release" / "radserve"
    variants = [Variant("infos off", ROOT / "client-py", binary, {"send_infos": False}),
                Variant("typed columns", ROOT / "client-py", binary, {})]
    if args.before:
        before = Path(args.before).resolve()
        variants.append(Variant("JSON (before)", before / "client-py", before / "target" / "release" / "radserve", {}))
    # (workload, delivery, variant) -> per round: (env steps/s, CPU us per env step)
    results = {}
    try:
        for label, env_id, num_envs, options in WORKLOADS:
            for delivery in DELIVERIES:
                for variant in variants:
                    variant.open(env_id, num_envs, options, delivery)
                for round_index in range(args.rounds):
                    spent = {variant.label: [0.0, 0.0] for variant in variants}
                    for chunk in range(args.chunks):
                        order = variants[chunk % len(variants):] + variants[:chunk % len(variants)]
                        for variant in order:
                            seconds, cpu = variant.run(args.steps)
                            spent[variant.label][0] += seconds
                            spent[variant.label][1] += cpu
                    env_steps = args.chunks * args.steps * num_envs
                    for name, (seconds, cpu) in spent.items():
                        results.setdefault((label, delivery, name), []).append((env_steps / seconds, cpu / env_steps * 1e6))
                print(f"{label} {delivery} done", file=sys.stderr, flush=True)
    finally:
        for variant in variants:
            variant.close()
    rows = []
    names = [variant.label for variant in variants]
    for label, *_ in WORKLOADS:
        for delivery in DELIVERIES:
            got = {name: results[label, delivery, name] for name in names}
            off = got["infos off"]
            row = [label, delivery.replace("_", " ")]
            row += [record.ranged([rate for rate, _ in got[name]]) for name in names]
            row += [record.ranged([on[0] / base[0] for on, base in zip(got[name], off)], digits=2, suffix="x")
                    for name in names[1:]]
            row += [record.ranged([cpu for _, cpu in got[name]], digits=1) for name in names]
            rows.append(row)
            print(record.plain(row))
    if not args.no_results:
        before = ""
        if args.before:
            head = subprocess.run(["git", "-C", args.before, "rev-parse", "--short=12", "HEAD"], capture_output=True,
                                  text=True).stdout.strip()
            before = f" JSON (before): commit {head or 'unknown'}, its client and its binary."
        table = {"id": "infos_cost", "rows": rows, "align": ["l", "l"] + ["r"] * (3 * len(names) - 1),
                 "columns": ["workload", "delivery", *(f"{name}: env steps/s" for name in names),
                             *(f"{name} / off" for name in names[1:]),
                             *(f"{name}: CPU us per env step" for name in names)],
                 "note": f"One session per variant (2 workers, SameStep, random actions), the variants taking "
                         f"{args.chunks} turns of {args.steps} steps per round; median (range) of {args.rounds} "
                         "rounds, ratios per round; CPU: the client's process, the server and its workers." + before}
        record.write("infos_cost", [table], {"rounds": args.rounds, "chunks": args.chunks, "steps": args.steps,
                                             "before": os.path.basename(args.before.rstrip("/")) if args.before else ""})


if __name__ == "__main__":
    main()
