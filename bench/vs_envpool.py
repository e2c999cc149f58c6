"""radserve against EnvPool on the same tasks, in one run: steps/s and CPU per env step.

    .venv/bin/python bench/vs_envpool.py [--rounds 3] [--seconds 4] [--only TEXT] [--policy-ms M]

EnvPool (1.2.5, C++ dm_control / MuJoCo-gym / ProcGen ports with their own thread pool) is what a
researcher would use instead of radserve for fast vectorized simulation. This script runs it from a
virtualenv of its own (`.venv-envpool`, installed here, never the project's: the baseline is EnvPool
as its users install it), then measures each workload in alternating rounds: radserve with 2
workers through shared stepping and through gRPC (a Python client in this process, one
session), with its native engine (the simulators' own Python packages) and with engine="envpool"
(EnvPool's ports inside radserve's workers; state rows only), each in its synchronous mode and in
EnvPool's asynchronous one (option batch_size = half the envs: recv the first ready half, send its
actions, one call per batch; the native engine's halves are two groups, one per worker process,
each stepped whole while the other's result is read), and EnvPool in-process with 2 threads
in its synchronous mode (batch = every env) and its asynchronous one (send/recv of half the envs,
EnvPool's fast path). Same task, same physics per env step, same image size; random actions. For the
dm_control state row EnvPool is also run doing radserve's action repeat (four calls of one control
step per agent step), a last table comparing against that.

With --policy-ms M every side spends M ms choosing each call's actions (a sleep: the learner waiting on
its accelerator's forward pass), the work EnvPool's asynchronous mode overlaps with stepping.

CPU per env step adds every process's user+system time over the timed window (radserve: the client,
the server and its workers; EnvPool: its one process) and divides by the steps.

EnvPool's pixel path needs the system EGL library preloaded (LD_PRELOAD) and its ProcGen the Qt 5
GUI library (Debian's libqt5gui5, installed here when missing).

A run of every workload writes bench/results/vs_envpool.json, a --policy-ms run
bench/results/vs_envpool_policy.json (the ratio table only); docs/performance.md renders them
(`make docs-tables`).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import record  # noqa: E402  (bench/record.py: the results file)

ROOT = Path(__file__).resolve().parents[1]
VENV = ROOT / ".venv-envpool"
ENVPOOL = "envpool==1.2.5"
EGL = "/usr/lib/x86_64-linux-gnu/libEGL.so.1"
TICKS = os.sysconf("SC_CLK_TCK")

# label, radserve env id and options, EnvPool task id and make() keywords, envs
WORKLOADS = [
    ("dmc cheetah-run pixels 100x100", "dmc/cheetah-run",
     {"pixels": True, "height": 100, "width": 100, "frame_stack": 1, "action_repeat": 4},
     "CheetahRun-v1", {"from_pixels": True, "render_width": 100, "render_height": 100, "render_camera_id": 0,
                       "frame_skip": 4}, 4),
    # EnvPool's dm_control frame_skip multiplies the physics substeps of one control step (the reward
    # is the last control step's, not a sum): the same physics per env step as action repeat 4, and
    # with max_episode_steps 250 the same episode length, for less per-step work than a true repeat.
    ("dmc cheetah-run state", "dmc/cheetah-run", {"pixels": False, "action_repeat": 4},
     "CheetahRun-v1", {"frame_skip": 4, "max_episode_steps": 250}, 16),
    ("gym HalfCheetah-v5", "gym/HalfCheetah-v5", {}, "HalfCheetah-v5", {}, 16),
    # The same with 4x the envs: how much of the gap is radserve's fixed cost per step.
    ("gym HalfCheetah-v5, 64 envs", "gym/HalfCheetah-v5", {}, "HalfCheetah-v5", {}, 64),
    ("procgen bigfish", "procgen/bigfish", {"distribution_mode": "easy"}, "BigfishEasy-v0", {}, 64),
]

# EnvPool doing radserve's action repeat on the state row: one control step per call (frame_skip 1,
# episodes of 1000 control steps), `calls` calls per agent step, the rewards of all of them. This is
# the work radserve's engines do for action_repeat 4 (dm_control's reward summed over the repeat), so
# it shows how much of that row's gap is the baseline's cheaper frame_skip rather than radserve.
TRUE_REPEAT = {"dmc cheetah-run state": ({"max_episode_steps": 1000}, 4)}


# Seconds the learner spends choosing each call's actions (--policy-ms): slept before each send or step.
POLICY = {"seconds": 0.0}


def choose(actions):
    """`actions`, after the learner's time to choose them."""
    if POLICY["seconds"]:
        time.sleep(POLICY["seconds"])
    return actions


def random_actions(space, batch: int) -> "list[np.ndarray]":
    """64 batches of random actions for `space` (float32 for boxes: radserve's action dtype)."""
    rng = np.random.default_rng(0)
    if hasattr(space, "n"):
        return [rng.integers(0, space.n, batch) for _ in range(64)]
    return [rng.uniform(space.low, space.high, (batch,) + space.shape).astype(np.float32) for _ in range(64)]


def radserve_result(rate, cpu, each, mean_pixel=None) -> dict:
    """A radserve measurement: `each` is the CPU per env step of the client, the server, its workers."""
    return {"rate": rate, "cpu": cpu, "mean_pixel": mean_pixel,
            "cpu_client": each[0], "cpu_server": each[1], "cpu_workers": sum(each[2:])}


def cpu_seconds(pids) -> float:
    total = 0.0
    for pid in pids:
        try:
            fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        except FileNotFoundError:
            continue
        total += (int(fields[11]) + int(fields[12])) / TICKS  # utime + stime
    return total


def descendants(pid: int) -> "list[int]":
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        found.append(current)
        for task in os.listdir(f"/proc/{current}/task"):
            try:
                with open(f"/proc/{current}/task/{task}/children") as listing:
                    todo += [int(child) for child in listing.read().split()]
            except FileNotFoundError:
                pass
    return found


def timed(step, envs_per_call: int, seconds: float, pids) -> "tuple[float, float, list[float]]":
    """(env steps per second, CPU seconds per env step, the same per process of `pids`) of calling
    `step` for `seconds`; a `step` that returns a number says how many env steps it made (a recv may
    return fewer than its batch)."""
    for _ in range(3):
        step()
    before, steps, start = [cpu_seconds([pid]) for pid in pids], 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        made = step()
        steps += envs_per_call if made is None else made
    elapsed = time.perf_counter() - start
    each = [(cpu_seconds([pid]) - cpu) / steps for pid, cpu in zip(pids, before)]
    return steps / elapsed, sum(each), each


# --- EnvPool, run in its own virtualenv (`--envpool-worker`) -------------------------------------

def envpool_measure(task: str, options: dict, num_envs: int, mode: str, seconds: float, calls: int = 1,
                    policy_s: float = 0.0) -> dict:
    """`mode` "sync" (batch = every env; `calls` EnvPool steps per agent step, the same actions) or
    "async" (EnvPool's send/recv of half the envs)."""
    import envpool

    POLICY["seconds"] = policy_s
    batch = num_envs if mode == "sync" else num_envs // 2
    env = envpool.make(task, env_type="gymnasium", num_envs=num_envs, batch_size=batch, num_threads=2, seed=0,
                       **options)
    space = env.action_space
    rng = np.random.default_rng(0)
    if hasattr(space, "n"):
        actions = [rng.integers(0, space.n, batch) for _ in range(64)]
    else:
        actions = [rng.uniform(space.low, space.high, (batch,) + space.shape) for _ in range(64)]
    counter = iter(range(1 << 62))
    if mode == "sync":
        env.reset()

        def step():
            chosen = choose(actions[next(counter) % 64])
            for _ in range(calls):
                env.step(chosen)
    else:
        env.async_reset()

        def step():  # EnvPool's own async loop: take the first ready half, send its actions
            *_, info = env.recv()
            env.send(choose(actions[next(counter) % 64][:len(info["env_id"])]), info["env_id"])
            return len(info["env_id"])

    rate, cpu, _ = timed(step, batch, seconds, [os.getpid()])
    first = env.reset()[0] if mode == "sync" else None
    pixels = isinstance(first, np.ndarray) and first.dtype == np.uint8
    return {"rate": rate, "cpu": cpu, "mean_pixel": float(np.mean(first)) if pixels else None}


def ensure_envpool() -> None:
    """EnvPool in its own virtualenv, and the system libraries its pixel and ProcGen paths load."""
    stamp = VENV / ".installed"
    if not stamp.exists() or stamp.read_text() != ENVPOOL:
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
        subprocess.run([str(VENV / "bin" / "pip"), "install", "-q", ENVPOOL], check=True)
        stamp.write_text(ENVPOOL)
    if subprocess.run("ldconfig -p | grep -q libQt5Gui.so.5", shell=True).returncode != 0:
        sudo = [] if os.geteuid() == 0 else ["sudo"]
        subprocess.run(sudo + ["apt-get", "update", "-qq"], check=True)
        subprocess.run(sudo + ["apt-get", "install", "-y", "-qq", "--no-install-recommends", "libqt5gui5"], check=True,
                       env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"}, stdout=subprocess.DEVNULL)


def envpool_run(task: str, options: dict, num_envs: int, mode: str, seconds: float, calls: int = 1) -> dict:
    env = {**os.environ, "MUJOCO_GL": "egl", "LD_PRELOAD": EGL}
    output = subprocess.run(
        [str(VENV / "bin" / "python"), __file__, "--envpool-worker",
         json.dumps([task, options, num_envs, mode, seconds, calls, POLICY["seconds"]])],
        capture_output=True, text=True, env=env, cwd="/tmp", check=False)
    if output.returncode != 0:
        raise RuntimeError(f"EnvPool {task} {mode}: {output.stderr[-2000:]}")
    return json.loads(output.stdout.strip().splitlines()[-1])


# --- radserve -------------------------------------------------------------------------------------

def radserve_run(client, server_pids, env_id: str, options: dict, num_envs: int, delivery: str, seconds: float,
                 engine: str = "native", asynchronous: bool = False):
    """radserve's steps/s and CPU per env step; `asynchronous`: EnvPool's async loop through the
    session's send/recv (batch_size half the envs, as EnvPool's async side here), one call per batch."""
    batch = num_envs // 2 if asynchronous else num_envs
    extra = {"batch_size": batch} if asynchronous else {}
    envs = client.make_vec(env_id, num_envs=num_envs, seed=0, autoreset_mode="SameStep",
                           delivery=delivery, engine=engine, **options, **extra)
    actions = random_actions(envs.single_action_space, batch)
    counter = iter(range(1 << 62))
    if asynchronous:
        envs.async_reset()
        ready = [envs.recv()[4]["env_id"]]

        def step():  # recv the first ready half and send it its actions, in one call (step(action, env_id))
            sent = ready[0]
            ready[0] = envs.step(choose(actions[next(counter) % 64][:len(sent)]), sent)[4]["env_id"]
            return len(sent)
    else:
        envs.reset()

        def step():
            envs.step(choose(actions[next(counter) % 64]))

    # The client (this process), the server, its workers.
    rate, cpu, each = timed(step, batch, seconds, [os.getpid(), *server_pids()])
    first = None if asynchronous else envs.reset()[0]
    envs.close()
    pixels = first is not None and first.dtype == np.uint8
    return radserve_result(rate, cpu, each, float(np.mean(first)) if pixels else None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--only", default="",
                        help="only the workloads whose label contains this (several: separated by commas)")
    parser.add_argument("--results", default="",
                        help="write bench/results/NAME.json (default: vs_envpool on a run of every workload, "
                             "vs_envpool_policy with --policy-ms; any other run with --only writes none)")
    parser.add_argument("--policy-ms", type=float, default=0.0,
                        help="the learner's time to choose each call's actions (slept), overlapped by the async modes")
    parser.add_argument("--envpool-worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    POLICY["seconds"] = args.policy_ms / 1000
    if args.envpool_worker:
        print(json.dumps(envpool_measure(*json.loads(args.envpool_worker))))
        return

    os.environ.setdefault("MUJOCO_GL", "egl")
    import radserve

    ensure_envpool()
    sides = ["radserve shm", "radserve grpc", "radserve async shm", "radserve async grpc", "radserve+EnvPool shm",
             "radserve+EnvPool grpc",
             "radserve+EnvPool async shm", "radserve+EnvPool async grpc", "EnvPool sync", "EnvPool async",
             "EnvPool repeat"]
    results: "dict[str, dict[str, list[dict]]]" = {}
    workloads = [w for w in WORKLOADS if any(part in w[0] for part in args.only.split(","))]
    with radserve.LocalServer(workers=2) as server:
        client = radserve.Client(server.address)
        client.list_envs()  # the catalog is built
        pids = lambda: descendants(server.process.pid)  # noqa: E731 (workers are restarted at times)
        for round_ in range(args.rounds):
            for label, env_id, options, task, envpool_options, num_envs in workloads:
                row = results.setdefault(label, {side: [] for side in sides})
                for side in sides:
                    if side.startswith("radserve"):
                        delivery = "shared_memory" if side.endswith("shm") else "grpc"
                        engine = "envpool" if "EnvPool" in side else "native"
                        if engine == "envpool" and options.get("pixels"):
                            continue  # the envpool engine hosts state observations; radserve renders pixels
                        result = radserve_run(client, pids, env_id, options, num_envs, delivery, args.seconds, engine,
                                              asynchronous="async" in side)
                    elif side == "EnvPool repeat":
                        if label not in TRUE_REPEAT:
                            continue
                        repeat_options, calls = TRUE_REPEAT[label]
                        result = envpool_run(task, repeat_options, num_envs, "sync", args.seconds, calls)
                    else:
                        result = envpool_run(task, envpool_options, num_envs, side.split()[1], args.seconds)
                    row[side].append(result)
                    print(f"round {round_ + 1} {label} x{num_envs}: {side} {result['rate']:,.0f} steps/s, "
                          f"{result['cpu'] * 1e6:,.0f} us CPU/step", file=sys.stderr)
        client.close()

    def med(runs, key="rate"):
        return statistics.median(r[key] for r in runs)

    def best_mode(row):
        return max(("EnvPool sync", "EnvPool async"), key=lambda side: med(row[side]))

    def rates(runs):
        return record.ranged([r["rate"] for r in runs]) if runs else "-"

    def ratios(runs, baseline_runs):
        """Each round's rate over the baseline's in the same round."""
        return record.ranged([a["rate"] / b["rate"] for a, b in zip(runs, baseline_runs)], 2, "x") if runs else "-"

    # The docs' two runs: every workload without a policy, and the policy's ratio on the rows it is about.
    name = args.results or ("vs_envpool_policy" if args.policy_ms else "" if args.only else "vs_envpool")
    prefix = name or "vs_envpool"
    setting = (f"radserve with 2 workers (engine native, and engine envpool on the state rows) against EnvPool "
               f"1.2.5 with 2 threads; median (range) of {args.rounds} alternating rounds of {args.seconds:g} s"
               + (f"; every side spends {args.policy_ms:g} ms choosing each call's actions" if args.policy_ms else ""))
    radserve_sides = [side for side in sides if side.startswith("radserve")]
    heads = {"radserve shm": "shm", "radserve grpc": "gRPC", "radserve async shm": "async shm",
             "radserve async grpc": "async gRPC", "radserve+EnvPool shm": "+EnvPool shm",
             "radserve+EnvPool grpc": "+EnvPool gRPC", "radserve+EnvPool async shm": "+EnvPool async shm",
             "radserve+EnvPool async grpc": "+EnvPool async gRPC", "EnvPool sync": "EnvPool sync",
             "EnvPool async": "EnvPool async"}
    shown = [side for side in sides if side in heads]
    pixels = [label for label, *_ in workloads if "pixels" in label]
    look = "; ".join(f"{label}: mean pixel of the first observations, radserve "
                     f"{med(results[label]['radserve shm'], 'mean_pixel'):.1f}, EnvPool "
                     f"{med(results[label]['EnvPool sync'], 'mean_pixel'):.1f}" for label in pixels)
    rate_table = {"id": prefix, "columns": ["workload", "envs"] + [heads[side] for side in shown],
                  "rows": [[label, str(num_envs)] + [rates(results[label][side]) for side in shown]
                           for label, *_, num_envs in workloads],
                  "note": f"Env steps/s: {setting}. " + (look + "." if look else "")}
    ratio_rows = []
    for label, *_, num_envs in workloads:
        row = results[label]
        best = best_mode(row)
        ratio_rows.append([label] + [ratios(row[side], row[best]) for side in radserve_sides]
                          + [f"{best.split()[1]}, {med(row[best]):,.0f}"])
    ratio_table = {"id": f"{prefix}_ratio", "columns": ["workload"] + [heads[side] for side in radserve_sides]
                   + ["EnvPool's best (mode, steps/s)"], "rows": ratio_rows,
                   "note": f"Each round's rate over EnvPool's best mode in that round: {setting}."}

    def split(row, side):
        if not row[side]:
            return "-"
        return " / ".join(f"{med(row[side], key) * 1e6:,.0f}" for key in ("cpu_client", "cpu_server", "cpu_workers"))

    cpu_table = {"id": f"{prefix}_cpu", "columns": ["workload", "envs", "shm", "async shm", "+EnvPool shm",
                                                    "+EnvPool async shm", "EnvPool best"],
                 "rows": [[label, str(num_envs)] + [split(results[label], side) for side in
                          ("radserve shm", "radserve async shm", "radserve+EnvPool shm", "radserve+EnvPool async shm")]
                          + [f"{med(results[label][best_mode(results[label])], 'cpu') * 1e6:,.0f}"]
                          for label, *_, num_envs in workloads],
                 "note": "CPU per env step in us (user+system over the timed window), radserve's through shared "
                         "memory as client / server / workers, EnvPool's its one process."}
    # With a policy's time in the loop the question is only the ratio (the docs show that table alone).
    tables = [ratio_table] if args.policy_ms else [rate_table, ratio_table, cpu_table]
    repeated = [w for w in workloads if w[0] in TRUE_REPEAT]
    if repeated and not args.policy_ms:
        tables.append({
            "id": f"{prefix}_repeat",
            "columns": ["workload", "envs", "EnvPool, repeat by calls (steps/s)", "radserve shm / it",
                        "+EnvPool shm / it", "EnvPool frame_skip best / it"],
            "rows": [[label, str(num_envs), rates(results[label]["EnvPool repeat"]),
                      ratios(results[label]["radserve shm"], results[label]["EnvPool repeat"]),
                      ratios(results[label]["radserve+EnvPool shm"], results[label]["EnvPool repeat"]),
                      ratios(results[label][best_mode(results[label])], results[label]["EnvPool repeat"])]
                     for label, *_, num_envs in repeated],
            "note": "EnvPool doing radserve's action repeat: frame_skip 1, 1000-step episodes, four calls with the "
                    "same actions per agent step, sync."})
    for table in tables:
        print("\n" + " | ".join(table["columns"]))
        for row in table["rows"]:
            print(record.plain(row))
    if name:
        record.write(name, tables, {"rounds": args.rounds, "seconds": args.seconds, "policy_ms": args.policy_ms,
                                    "only": args.only, "workers": 2, "envpool": ENVPOOL})

if __name__ == "__main__":
    main()
