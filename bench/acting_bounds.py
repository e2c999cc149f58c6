"""How fast could a same-host server step EnvPool at best? Bounds of two designs, on this machine.

    .venv/bin/python bench/acting_bounds.py [--rounds 4] [--seconds 2]

radserve keeps simulators out of the learner's process, so every step crosses processes. This script
measures what that costs at the very least, with nothing of radserve in the way: a simulator process
holding EnvPool (2 threads, raw calls) and the caller sharing memory, one one-byte pipe message each
way per step, against EnvPool in the caller's own process (its sync and async modes), alternating
rounds, same task and threads:

- "2 processes, sync": the caller sends a whole batch and waits for it (gymnasium's `step`, radserve's
  contract today);
- "2 processes, async": EnvPool's own async pattern across the two processes (batch = half the envs:
  the caller takes the first half that is ready and sends its actions while the other half steps).

First it times a pipe round trip between two processes on different CPUs and on one CPU: on a VM
whose idle vCPUs halt at once, waking a process on another CPU is what a cross-process step costs.
"""

import argparse
import mmap
import os
import statistics
import time

import numpy as np

TASK = "HalfCheetah-v5"
HEADER = 64  # obs_dim, action_dim, action itemsize (int64 each), written by the simulator process


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


def make(num_envs: int, batch: int):
    import envpool  # after any fork: EnvPool's threads do not survive one

    return envpool.make(TASK, env_type="gymnasium", num_envs=num_envs, batch_size=batch, num_threads=2, seed=0)


def doorbells(memory):
    """The polled design's request and answer counters, in the header after its three sizes."""
    return np.ndarray((1,), np.int64, memory, 24), np.ndarray((1,), np.int64, memory, 32)


def spin_until(counter, past: int) -> int:
    """Waits, yielding the CPU at each look, for shared `counter[0]` to move past `past`."""
    while True:
        value = int(counter[0])
        if value != past:
            return value
        os.sched_yield()


def simulator(memory, n: int, mode: str, requests: int, answers: int) -> None:
    """The simulator process: steps what the caller asks, results into the shared memory."""
    pool = make(n, n // 2 if mode == "async" else n)
    obs_dim, act_dim = pool.observation_space.shape[0], pool.action_space.shape[0]
    header = np.ndarray((3,), np.int64, memory, 0)
    header[:] = (obs_dim, act_dim, pool.action_space.dtype.itemsize)
    actions, obs, reward, ready = views(memory, n, obs_dim, act_dim, pool.action_space.dtype)
    keys = pool._state_keys
    at_obs, at_reward, at_id = keys.index("obs"), keys.index("reward"), keys.index("info:env_id")
    os.write(answers, b"r")
    if mode in ("sync", "spin"):
        pool.reset()
        ids = np.arange(n, dtype=np.int32)
        if mode == "spin":  # doorbells as counters in the shared memory, polled instead of slept on
            request, answer = doorbells(memory)

            def wait(seen):
                return spin_until(request, seen)

            def done(seen):
                answer[0] = seen
        else:  # one byte through a pipe each way, slept on
            def wait(seen):
                os.read(requests, 1)
                return seen

            def done(seen):
                os.write(answers, b"k")
        seen = 0
        while True:
            seen = wait(seen)
            pool._send([ids, ids, actions.copy()])
            state = pool._recv()
            env = state[at_id]
            obs[env], reward[env] = state[at_obs], state[at_reward]
            done(seen)
    else:
        pool.async_reset()
        while True:
            state = pool._recv()
            env = state[at_id]
            obs[env], reward[env] = state[at_obs], state[at_reward]
            ready[: len(env)] = env
            os.write(answers, b"k")
            os.read(requests, 1)
            pool._send([env, env, actions[env]])


def views(memory, n, obs_dim, act_dim, action_dtype):
    at = HEADER
    actions = np.ndarray((n, act_dim), action_dtype, memory, at)
    at += 8 * n * act_dim
    obs = np.ndarray((n, obs_dim), np.float32, memory, at)
    at += 4 * n * obs_dim
    reward = np.ndarray((n,), np.float64, memory, at)
    at += 8 * n
    ready = np.ndarray((n,), np.int32, memory, at)
    return actions, obs, reward, ready


def two_processes(n: int, mode: str):
    """(step function, envs per call, cleanup) for the two-process design."""
    memory = mmap.mmap(-1, 1 << 20)
    r1, w1 = os.pipe()
    r2, w2 = os.pipe()
    pid = os.fork()
    if pid == 0:
        simulator(memory, n, mode, r1, w2)
    os.read(r2, 1)
    obs_dim, act_dim, itemsize = np.ndarray((3,), np.int64, memory, 0)
    actions, obs, reward, ready = views(memory, n, int(obs_dim), int(act_dim), np.dtype(f"f{itemsize}"))
    sent = np.random.default_rng(0).uniform(-1, 1, actions.shape)

    if mode == "sync":
        def step():
            np.copyto(actions, sent)
            os.write(w1, b"s")
            os.read(r2, 1)
            return obs.copy(), reward.copy()
        per = n
    elif mode == "spin":
        request, answer = doorbells(memory)

        def step():
            np.copyto(actions, sent)
            target = int(request[0]) + 1
            request[0] = target
            spin_until(answer, target - 1)
            return obs.copy(), reward.copy()
        per = n
    else:
        half = n // 2

        def step():
            os.read(r2, 1)
            env = ready[:half].copy()
            result = obs[env], reward[env]
            actions[env] = sent[:half]
            os.write(w1, b"s")
            return result
        per = half

    def close():
        os.kill(pid, 9)  # every forked process holds the pipes' ends: no end-of-file would reach it
        os.waitpid(pid, 0)
        for fd in (r1, w1, r2, w2):
            os.close(fd)
    return step, per, close


def in_process(n: int, mode: str):
    pool = make(n, n if mode == "sync" else n // 2)
    sent = np.random.default_rng(0).uniform(-1, 1, (n,) + pool.action_space.shape)
    if mode == "sync":
        pool.reset()
        ids = np.arange(n, dtype=np.int32)
        return (lambda: pool.step(sent, ids)), n, pool.close
    pool.async_reset()

    def step():
        *_, info = pool.recv()
        pool.send(sent[: n // 2], info["env_id"])
    return step, n // 2, pool.close


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=2.0)
    args = parser.parse_args()
    cpus = sorted(os.sched_getaffinity(0))
    print("\npipe round trip between two processes, median of 5:\n")
    print("| processes on | us |")
    print("|---|---:|")
    if len(cpus) > 1:
        print(f"| two CPUs | {statistics.median(pipe_round_trip(cpus[:2]) for _ in range(5)) * 1e6:.1f} |")
    print(f"| one CPU | {statistics.median(pipe_round_trip([cpus[0]] * 2) for _ in range(5)) * 1e6:.1f} |")

    designs = [("2 processes, sync", two_processes, "sync"), ("2 processes, async", two_processes, "async"),
               ("2 processes, sync, polled doorbells", two_processes, "spin"),
               ("EnvPool in-process, sync", in_process, "sync"), ("EnvPool in-process, async", in_process, "async")]
    table = []
    # Every simulator process is forked before this process loads EnvPool (its threads do not fork).
    built = {n: [(label, *build(n, mode)) for label, build, mode in designs if build is two_processes]
             for n in (16, 64)}
    for n in (16, 64):
        steps = built[n] + [(label, *build(n, mode)) for label, build, mode in designs if build is in_process]
        rates = {label: [] for label, *_ in steps}
        for _ in range(args.rounds):
            for label, step, per, _ in steps:
                for _ in range(10):
                    step()
                calls, start = 0, time.perf_counter()
                while time.perf_counter() - start < args.seconds:
                    step()
                    calls += 1
                rates[label].append(calls * per / (time.perf_counter() - start))
        for *_, close in steps:
            close()
        best = max(("EnvPool in-process, sync", "EnvPool in-process, async"), key=lambda k: statistics.median(rates[k]))
        for label in rates:
            ratios = [a / b for a, b in zip(rates[label], rates[best])]
            table.append((n, label, statistics.median(rates[label]), statistics.median(ratios)))
    print(f"\n{TASK}, EnvPool 2 threads, median of {args.rounds} alternating rounds of {args.seconds:g} s:\n")
    print("| envs | design | steps/s | vs EnvPool's best |")
    print("|---:|---|---:|---:|")
    for n, label, rate, ratio in table:
        print(f"| {n} | {label} | {rate:,.0f} | {ratio:.2f}x |")


if __name__ == "__main__":
    main()
