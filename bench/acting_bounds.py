"""How fast could a same-host server step EnvPool at best? EnvPool behind one shared-memory hop.

    .venv/bin/python bench/acting_bounds.py [--rounds 3] [--seconds 4] [--only TEXT] [--spin-us L,C] [--no-radserve]

radserve keeps simulators out of the learner's process, so every step crosses processes. The least
such a design can add to EnvPool in-process is one hop per call: the learner writes its actions into
memory both processes map and rings a Unix socket; a process holding EnvPool steps them and writes the
results beside them (numpy, in place) and rings back. This script measures exactly that, with nothing
of radserve in the way (no server, no frame stacking, no episode bookkeeping, no checks): EnvPool
1.2.5 (2 threads, its raw `_send`/`_recv`, as radserve's envpool engine calls it) in a child process of
its own virtualenv (`.venv-envpool`, installed by bench/vs_envpool.py), one byte each way on a
socketpair, against EnvPool in-process (its public API, as its users step it) in alternating rounds,
on bench/vs_envpool.py's state and ProcGen workloads:

- "one hop sync": the learner sends every env's actions and waits (gymnasium's `step`);
- "one hop async": EnvPool's async pattern across the hop (batch = half the envs: the child sends the
  ready half's actions, then recv's the next ready half and rings).

In the same rounds, radserve itself (2 workers, a synchronous session through shared stepping,
engine native and engine envpool; `--no-radserve` leaves it out). The column "one hop best /
in-process best" (each round's better mode of each) is about the most any design with the simulator
outside the learner's process can reach on this machine (the child's own work per call is a few numpy
writes); "radserve best / one hop best" is what radserve's own relay (client, server, worker loop)
costs below that bound. `--spin-us L,C` has the learner (L) and the child (C) poll the socket for
that long before sleeping on it.

First it times a pipe round trip between two processes on different CPUs and on one CPU: on a VM
whose idle vCPUs halt at once, waking a process on another CPU is what a cross-process step costs.

A run of every row with radserve and no polling writes bench/results/acting_bounds.json, which
docs/performance.md renders (`make docs-tables`).
"""

import argparse
import contextlib
import json
import mmap
import os
import socket
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np

import record  # noqa: E402  (bench/record.py: the results file)
import vs_envpool  # noqa: E402  (the same workloads, EnvPool virtualenv and timing)

# Bytes of the memory the learner and the child share (every row's arrays fit: bigfish x64 needs ~1 MB).
MEMORY = 1 << 26

# Seconds each side polls before it sleeps on the ring (--spin-us): learner, child.
SPIN = {"learner": 0.0, "child": 0.0}

ROWS = [w for w in vs_envpool.WORKLOADS if "pixels" not in w[0]]


def pipe_round_trip(cpus, count=20000) -> float:
    """Seconds per round trip of one byte between two processes pinned to `cpus` (parent, child)."""
    r1, w1 = os.pipe()
    r2, w2 = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.sched_setaffinity(0, {cpus[1]})
        for _ in range(count):
            os.read(r1, 1)
            os.write(w2, b"x")
        os._exit(0)
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {cpus[0]})
    start = time.perf_counter()
    for _ in range(count):
        os.write(w1, b"x")
        os.read(r2, 1)
    elapsed = time.perf_counter() - start
    os.waitpid(pid, 0)
    os.sched_setaffinity(0, before)
    for fd in (r1, w1, r2, w2):
        os.close(fd)
    return elapsed / count


def layout(num_envs: int, batch: int, obs_shape, obs_dtype, act_shape, act_dtype):
    """Offsets of actions, env ids, obs, reward, terminated, truncated in the shared memory."""
    sizes = [("actions", batch * int(np.prod(act_shape)) * np.dtype(act_dtype).itemsize),
             ("ids", num_envs * 4),
             ("obs", num_envs * int(np.prod(obs_shape)) * np.dtype(obs_dtype).itemsize),
             ("reward", num_envs * 8), ("terminated", num_envs), ("truncated", num_envs)]
    offsets, end = {}, 0
    for name, size in sizes:
        offsets[name] = end
        end += (size + 63) // 64 * 64
    if end > MEMORY:
        raise ValueError(f"the arrays need {end} bytes, the shared memory holds {MEMORY}")
    return offsets


def views(buffer, offsets, num_envs, batch, obs_shape, obs_dtype, act_shape, act_dtype):
    def at(name, dtype, shape):
        return np.frombuffer(buffer, dtype=dtype, count=int(np.prod(shape)), offset=offsets[name]).reshape(shape)

    return {"actions": at("actions", act_dtype, (batch,) + tuple(act_shape)),
            "ids": at("ids", np.int32, (num_envs,)),
            "obs": at("obs", obs_dtype, (num_envs,) + tuple(obs_shape)),
            "reward": at("reward", np.float64, (num_envs,)),
            "terminated": at("terminated", np.bool_, (num_envs,)),
            "truncated": at("truncated", np.bool_, (num_envs,))}


def wait(sock, ring, spin_s: float) -> int:
    """Receives the ring: polling without sleeping for up to `spin_s` first (--spin-us), then blocking."""
    if spin_s:
        until = time.perf_counter() + spin_s
        while time.perf_counter() < until:
            try:
                return sock.recv_into(ring, 1, socket.MSG_DONTWAIT)
            except BlockingIOError:
                pass
    return sock.recv_into(ring)


def child(spec: str) -> None:
    """EnvPool behind the doorbell (runs in EnvPool's virtualenv), on the socket and memory passed."""
    import envpool

    task, options, num_envs, mode, socket_fd, memory_fd, spin = json.loads(spec)
    batch = num_envs if mode == "sync" else num_envs // 2
    env = envpool.make(task, env_type="gymnasium", num_envs=num_envs, batch_size=batch, num_threads=2, seed=0,
                       **options)
    obs_space, act_space = env.observation_space, env.action_space
    act_shape, act_dtype = (act_space.shape, act_space.dtype)
    # dm_control's observations are a dict: one float32 vector per env, the keys' arrays side by side (the
    # flattening a server does).
    keys = list(obs_space.spaces) if hasattr(obs_space, "spaces") else None
    if keys is not None:
        widths = [int(np.prod(obs_space.spaces[key].shape)) for key in keys]
        obs_space = type("Flat", (), {"shape": (sum(widths),), "dtype": np.dtype(np.float32)})
    doorbell = socket.socket(fileno=socket_fd)
    memory = mmap.mmap(memory_fd, os.fstat(memory_fd).st_size)
    offsets = layout(num_envs, batch, obs_space.shape, obs_space.dtype, act_shape, act_dtype)
    shared = views(memory, offsets, num_envs, batch, obs_space.shape, obs_space.dtype, act_shape, act_dtype)
    doorbell.sendall(json.dumps({"obs_shape": obs_space.shape, "obs_dtype": str(obs_space.dtype),
                                 "act_shape": act_shape, "act_dtype": str(act_dtype),
                                 "discrete": hasattr(act_space, "n"),
                                 "n": int(act_space.n) if hasattr(act_space, "n") else None,
                                 "low": None if hasattr(act_space, "n") else act_space.low.tolist(),
                                 "high": None if hasattr(act_space, "n") else act_space.high.tolist()}
                                ).encode().ljust(4096))

    # EnvPool's raw calls (what radserve's envpool engine steps with): no action conversion, state tree or
    # info dict, 60-70 us less per call than its public step/recv.
    names = list(env._state_keys)
    obs_names = ["obs"] if keys is None else [f"obs:{key}" for key in keys]
    index = [names.index(name) for name in ["info:env_id", "reward", "done", "trunc"] + obs_names]
    all_ids = np.arange(num_envs, dtype=np.int32)
    flat_obs = shared["obs"].reshape(num_envs, -1)  # a view: each env's observation parts side by side

    def receive():
        """EnvPool's next results, written into the shared memory (rows in its order, ids beside)."""
        state = env._recv()
        ids, done, trunc = state[index[0]], state[index[2]], state[index[3]]
        n = len(ids)
        shared["ids"][:n] = ids
        start = 0
        for part in (state[i].reshape(n, -1) for i in index[4:]):
            flat_obs[:n, start:start + part.shape[1]] = part
            start += part.shape[1]
        shared["reward"][:n] = state[index[1]]
        shared["terminated"][:n] = done & ~trunc
        shared["truncated"][:n] = trunc

    ring = bytearray(1)
    if mode == "sync":
        env.reset()
    else:
        env.async_reset()
        receive()
    while wait(doorbell, ring, spin) == 1:
        ids = all_ids if mode == "sync" else shared["ids"][:batch].copy()
        env._send([ids, ids, shared["actions"]])
        receive()
        doorbell.send(b"d")


def one_hop(task: str, options: dict, num_envs: int, mode: str, seconds: float) -> dict:
    """Steps/s and CPU per env step (learner + child) of EnvPool behind the doorbell."""
    ours, theirs = socket.socketpair()
    memory_fd = os.memfd_create("acting-bounds")
    os.ftruncate(memory_fd, MEMORY)
    env = {**os.environ, "MUJOCO_GL": "egl", "LD_PRELOAD": vs_envpool.EGL}
    env.pop("PYTHONPATH", None)
    process = subprocess.Popen(
        [str(vs_envpool.VENV / "bin" / "python"), __file__, "--child",
         json.dumps([task, options, num_envs, mode, theirs.fileno(), memory_fd, SPIN["child"]])],
        pass_fds=(theirs.fileno(), memory_fd), env=env, cwd="/tmp")
    theirs.close()
    try:
        hello = b""
        while len(hello) < 4096:
            part = ours.recv(4096 - len(hello))
            if not part:
                raise RuntimeError(f"EnvPool child for {task} exited")
            hello += part
        spec = json.loads(hello.decode().strip())
        batch = num_envs if mode == "sync" else num_envs // 2
        memory = mmap.mmap(memory_fd, MEMORY)
        offsets = layout(num_envs, batch, spec["obs_shape"], spec["obs_dtype"], spec["act_shape"], spec["act_dtype"])
        shared = views(memory, offsets, num_envs, batch, spec["obs_shape"], spec["obs_dtype"], spec["act_shape"],
                       spec["act_dtype"])
        space = (SimpleNamespace(n=spec["n"]) if spec["discrete"] else
                 SimpleNamespace(low=np.array(spec["low"]), high=np.array(spec["high"]), shape=tuple(spec["act_shape"])))
        actions = vs_envpool.random_actions(space, batch)
        counter = iter(range(1 << 62))
        ring = bytearray(1)
        spin = SPIN["learner"]

        def step():
            shared["actions"][:] = actions[next(counter) % 64]  # the ready envs' actions (async: their ids stay)
            ours.send(b"s")
            wait(ours, ring, spin)

        rate, cpu, _ = vs_envpool.timed(step, batch, seconds, [os.getpid(), process.pid])
        return {"rate": rate, "cpu": cpu}
    finally:
        ours.close()
        process.wait(timeout=30)
        os.close(memory_fd)


def best_of(row, sides, rounds: int) -> "list[float]":
    """Round by round, the best rate of `sides` (those run)."""
    return [max(row[side][i]["rate"] for side in sides if row[side]) for i in range(rounds)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--only", default="")
    parser.add_argument("--spin-us", default="0,0",
                        help="learner,child: microseconds each side polls the ring before it sleeps")
    parser.add_argument("--no-radserve", action="store_true",
                        help="leave out radserve's synchronous shared-memory sessions (both engines)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    SPIN["learner"], SPIN["child"] = (float(us) / 1e6 for us in args.spin_us.split(","))
    if args.child:
        child(args.child)
        return
    vs_envpool.ensure_envpool()
    cpus = sorted(os.sched_getaffinity(0))
    pipe_rows = []
    if len(cpus) > 1:
        pipe_rows.append(["two CPUs", record.ranged([pipe_round_trip(cpus[:2]) * 1e6 for _ in range(5)], 1)])
    pipe_rows.append(["one CPU", record.ranged([pipe_round_trip([cpus[0]] * 2) * 1e6 for _ in range(5)], 1)])
    pipe_table = {"id": "acting_bounds_pipe", "columns": ["processes on", "pipe round trip (us)"], "rows": pipe_rows,
                  "note": "One byte each way between two processes, median (range) of 5 runs of 20,000."}
    sides = ["in-process sync", "in-process async", "one hop sync", "one hop async"]
    if not args.no_radserve:
        sides += ["radserve native", "radserve envpool"]
    rows = [w for w in ROWS if args.only in w[0]]
    results = {}
    with contextlib.ExitStack() as stack:
        if not args.no_radserve:
            os.environ.setdefault("MUJOCO_GL", "egl")
            import radserve

            server = stack.enter_context(radserve.LocalServer(workers=2))
            client = radserve.Client(server.address)
            stack.callback(client.close)
            client.list_envs()  # the catalog is built
            pids = lambda: vs_envpool.descendants(server.process.pid)  # noqa: E731
        for round_ in range(args.rounds):
            for label, env_id, radserve_options, task, options, num_envs in rows:
                row = results.setdefault(label, {side: [] for side in sides})
                for side in sides:
                    mode = side.split()[-1]
                    if side.startswith("in-process"):
                        result = vs_envpool.envpool_run(task, options, num_envs, mode, args.seconds)
                    elif side.startswith("one hop"):
                        result = one_hop(task, options, num_envs, mode, args.seconds)
                    else:  # radserve, synchronous, through shared stepping
                        result = vs_envpool.radserve_run(client, pids, env_id, radserve_options, num_envs,
                                                         "shared_memory", args.seconds, engine=mode)
                    row[side].append(result)
                    print(f"round {round_ + 1} {label} x{num_envs}: {side} {result['rate']:,.0f} steps/s, "
                          f"{result['cpu'] * 1e6:,.0f} us CPU/step", file=sys.stderr)
    heads = {"in-process sync": "EnvPool sync", "in-process async": "EnvPool async", "one hop sync": "one hop sync",
             "one hop async": "one hop async", "radserve native": "radserve native",
             "radserve envpool": "radserve envpool engine"}
    columns = ["workload", "envs"] + [heads[side] for side in sides] + ["one hop best / in-process best"]
    if not args.no_radserve:
        columns.append("radserve best / one hop best")
    table_rows = []
    for label, *_, num_envs in rows:
        row = results[label]
        best = best_of(row, ["in-process sync", "in-process async"], args.rounds)
        hop = best_of(row, ["one hop sync", "one hop async"], args.rounds)
        cells = [label, str(num_envs)] + [record.ranged([r["rate"] for r in row[side]]) for side in sides]
        cells.append(record.ranged([h / b for h, b in zip(hop, best)], 2, "x"))
        if not args.no_radserve:
            ours = best_of(row, ["radserve native", "radserve envpool"], args.rounds)
            cells.append(record.ranged([r / h for r, h in zip(ours, hop)], 2, "x"))
        table_rows.append(cells)
    table = {"id": "acting_bounds", "columns": columns, "rows": table_rows,
             "note": f"Env steps/s: EnvPool 1.2.5 (2 threads) in-process and behind one shared-memory hop"
                     + ("" if args.no_radserve else ", and radserve (2 workers, synchronous session, shared memory)")
                     + f"; median (range) of {args.rounds} alternating rounds of {args.seconds:g} s; the ratios "
                       "take each round's better mode."}
    for each in (pipe_table, table):
        print("\n" + " | ".join(each["columns"]))
        for cells in each["rows"]:
            print(record.plain(cells))
    if not args.only and not args.no_radserve and args.spin_us == "0,0":
        record.write("acting_bounds", [pipe_table, table], {"rounds": args.rounds, "seconds": args.seconds,
                                                            "workers": 2, "envpool": vs_envpool.ENVPOOL})


if __name__ == "__main__":
    main()
