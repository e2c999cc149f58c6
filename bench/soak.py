"""Soak: N client processes, each with M sessions acting and sampling, for T minutes; every few
seconds one client is killed (SIGKILL: it closes nothing) and a fresh one takes its place. The server
must stay flat: its RSS, open file descriptors, worker processes and sessions over time, with the
clients' errors and throughput.

    .venv/bin/python bench/soak.py [--clients 4] [--sessions 2] [--minutes 10] [--kill-every 20]

Sessions of killed clients are left behind on purpose and closed by the server's lease
(`limits.session_idle_timeout_s`, set short here). Each client's sessions rotate through the kinds a
learner opens: CartPole through gRPC, Pendulum through shared stepping, a ProcGen game with a
replay buffer sampled with `crop(56)`, a Pendulum with a replay buffer sampled with `ras_m`, and a
CartPole rollout sampled in epochs. Prints a table every `--report-every` seconds and a summary; a
run of at least 10 minutes on the build writes bench/results/soak.json (docs/reliability.md).
"""

import argparse
import multiprocessing as mp
import os
import random
import signal
import statistics
import sys
import time
from pathlib import Path

import radserve
import record  # bench/record.py: the results file

worker_pids = record.tests_helper("_procs").worker_pids

KINDS = ["grpc-acting", "shm-acting", "procgen-replay", "state-replay", "rollout"]
# Counters per client slot: env steps, batches, errors, refusals (RESOURCE_EXHAUSTED while the
# sessions of killed clients wait for their lease to run out).
STEPS, BATCHES, ERRORS, REFUSED = range(4)


def client_main(address, slot, sessions, counters, seed):
    """One learner process: `sessions` sessions, acting and sampling round-robin until killed."""
    rng = random.Random(seed)
    client = radserve.Client(address)
    work = []

    def count(index, amount=1):
        with counters.get_lock():
            counters[slot * 4 + index] += amount

    def open_session(kind):
        if kind == "grpc-acting":
            envs = client.make_vec("gym/CartPole-v1", num_envs=8, seed=rng.randrange(1 << 30),
                                   autoreset_mode="SameStep")
        elif kind == "shm-acting":
            envs = client.make_vec("gym/Pendulum-v1", num_envs=8, seed=rng.randrange(1 << 30),
                                   autoreset_mode="SameStep", delivery="shared_memory")
        elif kind == "procgen-replay":
            envs = client.make_vec("procgen/bigfish", num_envs=4, seed=rng.randrange(1 << 30),
                                   autoreset_mode="SameStep", replay_capacity=2000)
        elif kind == "state-replay":
            envs = client.make_vec("gym/Pendulum-v1", num_envs=4, seed=rng.randrange(1 << 30),
                                   autoreset_mode="SameStep", replay_capacity=5000)
        else:
            envs = client.make_vec("gym/CartPole-v1", num_envs=4, seed=rng.randrange(1 << 30),
                                   autoreset_mode="SameStep", rollout_steps=32)
        envs.reset()
        return kind, envs

    def act(envs, steps):
        for _ in range(steps):
            envs.step(envs.action_space.sample())
        count(STEPS, steps * envs.num_envs)

    def sample(kind, envs):
        if kind == "procgen-replay":
            stream = envs.sample_batches(batch_size=32, augment="crop(56)", max_batches=8)
        elif kind == "state-replay":
            stream = envs.sample_batches(batch_size=64, augment="ras_m", max_batches=8)
        else:
            stream = envs.sample_batches(batch_size=32, source="rollout", epochs=1)
        count(BATCHES, sum(1 for _ in stream))

    kinds = [KINDS[(slot + i) % len(KINDS)] for i in range(sessions)]
    while True:
        try:
            while len(work) < sessions:
                work.append(open_session(kinds[len(work)]))
            for kind, envs in work:
                if kind in ("grpc-acting", "shm-acting"):
                    act(envs, 20)
                elif kind == "rollout":
                    act(envs, 32)
                    sample(kind, envs)
                else:
                    act(envs, 8)
                    sample(kind, envs)
            # Now and then a learner finishes a run and starts another.
            if rng.random() < 0.05:
                kind, envs = work.pop(rng.randrange(len(work)))
                envs.close()
        except radserve.ResourceExhaustedError:
            count(REFUSED)
            time.sleep(1.0)
        except radserve.RadServeError as error:
            count(ERRORS)
            print(f"client {slot}: {type(error).__name__}: {str(error)[:200]}", file=sys.stderr, flush=True)
            time.sleep(0.5)


def rss_mib(pid):
    """Resident memory of a process in MiB (0 when it is gone)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        return int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:"))) / 1024
    except (FileNotFoundError, StopIteration):
        return 0.0


def server_figures(server, client):
    pid = server.process.pid
    workers = worker_pids(pid)
    sessions = client.list_sessions()
    return {"rss": rss_mib(pid), "fds": len(os.listdir(f"/proc/{pid}/fd")), "workers": len(workers),
            "worker_rss": sum(rss_mib(worker) for worker in workers), "sessions": len(sessions),
            "streams": sum(s.open_streams for s in sessions)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--sessions", type=int, default=2, help="sessions per client")
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--kill-every", type=float, default=20.0, help="seconds between client kills")
    parser.add_argument("--report-every", type=float, default=30.0)
    parser.add_argument("--idle-timeout", type=int, default=10, help="the server's session lease, seconds")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--binary", default=None)
    args = parser.parse_args()

    env = {"RADSERVE__LIMITS__SESSION_IDLE_TIMEOUT_S": str(args.idle_timeout), "RADSERVE__SIM__VENV": sys.prefix}
    context = mp.get_context("spawn")
    counters = context.Array("d", 4 * args.clients)
    rng = random.Random(0)
    with radserve.LocalServer(workers=args.workers, binary=args.binary, env=env) as server:
        client = radserve.Client(server.address)
        client.list_envs()  # the catalog is built before the clock starts

        def spawn(slot):
            process = context.Process(target=client_main, args=(server.address, slot, args.sessions, counters, rng.randrange(1 << 30)),
                                      daemon=True)
            process.start()
            return process

        processes = [spawn(slot) for slot in range(args.clients)]
        start = time.monotonic()
        end = start + args.minutes * 60
        next_kill = start + args.kill_every
        next_report = start + args.report_every
        kills = 0
        rows = []
        last = (start, [0.0] * 4)
        print(f"{'min':>5} {'RSS MiB':>8} {'fds':>5} {'workers':>7} {'worker RSS':>10} {'sessions':>8} {'streams':>7} "
              f"{'steps/s':>8} {'batches/s':>9} {'errors':>6} {'refused':>7} {'kills':>5}", flush=True)
        while time.monotonic() < end:
            time.sleep(0.5)
            now = time.monotonic()
            if now >= next_kill:
                slot = rng.randrange(args.clients)
                os.kill(processes[slot].pid, signal.SIGKILL)
                processes[slot].join()
                processes[slot] = spawn(slot)
                kills += 1
                next_kill += args.kill_every
            if now >= next_report:
                with counters.get_lock():
                    totals = [sum(counters[slot * 4 + i] for slot in range(args.clients)) for i in range(4)]
                elapsed = now - last[0]
                figures = server_figures(server, client)
                row = {**figures, "minute": (now - start) / 60, "steps_per_s": (totals[STEPS] - last[1][STEPS]) / elapsed,
                       "batches_per_s": (totals[BATCHES] - last[1][BATCHES]) / elapsed, "errors": totals[ERRORS],
                       "refused": totals[REFUSED], "kills": kills}
                rows.append(row)
                last = (now, totals)
                print(f"{row['minute']:5.1f} {row['rss']:8.0f} {row['fds']:5d} {row['workers']:7d} {row['worker_rss']:10.0f} "
                      f"{row['sessions']:8d} {row['streams']:7d} {row['steps_per_s']:8.0f} {row['batches_per_s']:9.1f} "
                      f"{row['errors']:6.0f} {row['refused']:7.0f} {row['kills']:5d}", flush=True)
                next_report += args.report_every
        for process in processes:
            os.kill(process.pid, signal.SIGKILL)
            process.join()
        # Every client is gone: after one lease the server holds nothing.
        time.sleep(args.idle_timeout + 5)
        after = server_figures(server, client)
        code = server.process.poll()

    warm = rows[len(rows) // 4:] or rows
    print("\nsummary")
    print(f"  clients {args.clients} x sessions {args.sessions}, {args.minutes:g} min, {kills} clients killed, "
          f"server {'alive' if code is None else f'exited {code}'}")
    for key, label in [("rss", "server RSS MiB"), ("fds", "server fds"), ("workers", "workers"),
                       ("worker_rss", "workers' RSS MiB"), ("sessions", "sessions")]:
        values = [row[key] for row in warm]
        print(f"  {label:18} first quarter skipped: min {min(values):.0f} median {statistics.median(values):.0f} "
              f"max {max(values):.0f}; last {values[-1]:.0f}; after all clients left {after[key]:.0f}")
    print(f"  throughput median: {statistics.median(r['steps_per_s'] for r in warm):.0f} env steps/s, "
          f"{statistics.median(r['batches_per_s'] for r in warm):.1f} batches/s")
    print(f"  errors {rows[-1]['errors']:.0f}, refusals (RESOURCE_EXHAUSTED) {rows[-1]['refused']:.0f}")

    # The docs' table: a row at about each quarter of the run, and the server after every client left.
    shown = sorted({rows[min(len(rows) - 1, round(i * (len(rows) - 1) / 4))]["minute"] for i in range(5)})
    table_rows = [[f"{row['minute']:.1f}", round(row["rss"]), row["fds"], row["workers"], round(row["worker_rss"]),
                   row["sessions"], round(row["steps_per_s"]), round(row["batches_per_s"]), round(row["errors"])]
                  for row in rows if row["minute"] in shown]
    table_rows.append(["all clients gone, one lease later", round(after["rss"]), after["fds"], after["workers"],
                       round(after["worker_rss"]), after["sessions"], "", "", ""])
    table = {"id": "soak", "columns": ["minute", "server RSS MiB", "server fds", "workers", "workers' RSS MiB",
                                        "sessions", "env steps/s", "batches/s", "errors"], "rows": table_rows,
             "note": f"{args.clients} clients of {args.sessions} sessions, one SIGKILLed every {args.kill_every:g} s "
                     f"({kills} in all), lease {args.idle_timeout} s, {args.workers} workers; server "
                     f"{'alive at the end' if code is None else f'exited {code}'}."}
    if args.binary is None and args.minutes >= 10:
        record.write("soak", [table], {"clients": args.clients, "sessions": args.sessions, "minutes": args.minutes,
                                       "kill_every": args.kill_every, "idle_timeout": args.idle_timeout,
                                       "workers": args.workers})


if __name__ == "__main__":
    main()
