"""What a replay snapshot costs while a learner works, and how long a restore takes, in one run.

    .venv/bin/python bench/snapshot_cost.py [--rounds 2] [--capacity 100000] [--rates 268435456,0]
        [--binary target/release/radserve] [--dir DIR] [--no-results]

Per round and per pacing (`replay.snapshot_bytes_per_second`; 0: unpaced):
1. `dd` writes 1 GiB into the snapshot directory's disk (conv=fdatasync): the disk's rate, same run.
2. A server with `[replay] snapshot_dir` and a long `snapshot_interval_s`; a named ProcGen bigfish
   session (64 envs, 64x64 pixels) with a replay buffer of `--capacity` transitions, filled by
   stepping. Then the learner works: this process steps the session (one gRPC Step of 64 envs at a
   time, recording into the buffer being snapshotted) while a learner process drains crop batches
   of 128 from it. The first snapshot comes while they work: a full one (every frame the buffer
   holds; later ones write only what was recorded since, so this is the costliest kind).
   Step p99 and batches/s are compared between the quiet seconds before it and the seconds it ran
   (when it ran: DescribeSession's snapshot age and radserve_snapshot_duration_seconds).
3. The server is killed (SIGKILL); the page cache is dropped when this process may (root); a new
   server over the same directory restores the session: transitions, bytes, the server's restore
   time (radserve_snapshot_restore_duration_seconds), against creating the same session unnamed.

The table goes to bench/results/snapshot_cost.json (docs/performance.md renders it) unless --no-results.
"""

import argparse
import multiprocessing
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

import radserve

import record  # noqa: E402  (bench/record.py: the results file)

ENV, NUM_ENVS = "procgen/bigfish", 64
DRAIN = dict(batch_size=128, augment="crop(56)", prefetch=2)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def dd_rate(directory: Path) -> float:
    """MiB/s of `dd` writing 1 GiB (synced) into `directory`."""
    target = directory / "dd.bin"
    done = subprocess.run(["dd", "if=/dev/zero", f"of={target}", "bs=4M", "count=256", "conv=fdatasync"],
                          capture_output=True, text=True, check=True)
    target.unlink()
    seconds = float(re.search(r"copied, ([\d.]+) s", done.stderr).group(1))
    return 1024 / seconds


def metric(address: str, name: str) -> float:
    text = urllib.request.urlopen(f"http://{address}/metrics", timeout=10).read().decode()
    match = re.search(rf"^{name}(?:_total)? ([\d.e+-]+)$", text, re.MULTILINE)
    return float(match.group(1)) if match else 0.0


def drain_process(address, session_id, stop, times):
    """A learner in a process of its own: takes batches as fast as they come, sends their times."""
    client = radserve.Client(address)
    seen = []
    with client.sample_batches(session_id, **DRAIN) as stream:
        for _ in stream:
            seen.append(time.time())
            if stop.is_set():
                break
    times.put(seen)


def server(binary, directory, rate, interval, metrics_address):
    env = {"RADSERVE__SIM__VENV": sys.prefix, "RADSERVE__REPLAY__SNAPSHOT_DIR": str(directory),
           "RADSERVE__REPLAY__SNAPSHOT_INTERVAL_S": str(interval),
           "RADSERVE__REPLAY__SNAPSHOT_BYTES_PER_SECOND": str(rate),
           "RADSERVE__METRICS__ADDRESS": metrics_address}
    running = radserve.LocalServer(workers=2, binary=binary, env=env)
    running.start()
    return running


def session(client, capacity, name):
    return client.make_vec(ENV, num_envs=NUM_ENVS, seed=0, replay_capacity=capacity, autoreset_mode="SameStep",
                           name=name)


def measure(binary, directory, rate, capacity, interval):
    metrics_address = f"127.0.0.1:{free_port()}"
    running = server(binary, directory, rate, interval, metrics_address)
    started = time.time()
    client = radserve.Client(running.address)
    client.list_envs()  # the catalog's transient worker renders every spec: not beside the timing
    envs = session(client, capacity, "bench")
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 15, size=(64, NUM_ENVS))
    envs.reset(seed=0)
    for index in range(capacity // NUM_ENVS + 64):
        envs.step(actions[index % 64])
    context = multiprocessing.get_context("spawn")
    stop, batch_times = context.Event(), context.Queue()
    learner = context.Process(target=drain_process, args=(running.address, envs.session_id, stop, batch_times))
    learner.start()
    steps = []  # (start time, ms)
    snapshot_end = None
    deadline = started + interval + 600
    last_check = 0.0
    while time.time() < deadline:
        begin = time.time()
        tick = time.perf_counter()
        envs.step(actions[len(steps) % 64])
        steps.append((begin, (time.perf_counter() - tick) * 1000))
        if begin - last_check > 0.2:
            last_check = begin
            if snapshot_end is None:
                age = client.describe_session(envs.session_id).replay.snapshot.age_seconds
                if age is not None:
                    snapshot_end = time.time() - age
            elif begin > snapshot_end + 3:
                break
    stop.set()
    seen = batch_times.get(timeout=60)
    learner.join()
    duration = metric(metrics_address, "radserve_snapshot_duration_seconds")
    written = metric(metrics_address, "radserve_snapshot_bytes")
    snapshot_start = snapshot_end - duration
    filled = steps[0][0] + 3.0  # the learner's first seconds (process start, first batches) are not quiet
    quiet = [ms for at, ms in steps if filled <= at < snapshot_start - 0.5]
    during = [ms for at, ms in steps if snapshot_start <= at <= snapshot_end]
    quiet_seconds = max(1e-9, snapshot_start - 0.5 - filled)
    quiet_batches = sum(1 for at in seen if filled <= at < snapshot_start - 0.5) / quiet_seconds
    during_batches = sum(1 for at in seen if snapshot_start <= at <= snapshot_end) / max(1e-9, duration)
    size = client.describe_session(envs.session_id).replay.size
    client.close()
    running.process.send_signal(signal.SIGKILL)
    running.process.wait()

    dropped = True
    try:
        subprocess.run(["sync"], check=True)
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
    except OSError:
        dropped = False
    metrics_address = f"127.0.0.1:{free_port()}"
    running = server(binary, directory, rate, 3600, metrics_address)
    client = radserve.Client(running.address)
    client.list_envs()
    tick = time.perf_counter()
    unnamed = client.make_vec(ENV, num_envs=NUM_ENVS, seed=0, replay_capacity=capacity, autoreset_mode="SameStep")
    create_seconds = time.perf_counter() - tick
    unnamed.close()
    tick = time.perf_counter()
    restored = session(client, capacity, "bench")
    restore_wall = time.perf_counter() - tick
    restored_transitions = restored.info.replay.snapshot.restored_transitions
    disk_bytes = restored.info.replay.snapshot.disk_bytes
    restore_seconds = metric(metrics_address, "radserve_snapshot_restore_duration_seconds")
    restored.close(discard_snapshot=True)
    client.close()
    running.stop()
    return {
        "quiet_p99": float(np.percentile(quiet, 99)), "during_p99": float(np.percentile(during, 99)),
        "quiet_p50": float(np.percentile(quiet, 50)), "during_p50": float(np.percentile(during, 50)),
        "quiet_batches": quiet_batches, "during_batches": during_batches, "snapshot_seconds": duration,
        "written_mib": written / 2**20, "write_mib_s": written / 2**20 / max(duration, 1e-9), "size": size,
        "restored": restored_transitions, "disk_gib": disk_bytes / 2**30, "restore_seconds": restore_seconds,
        "restore_wall": restore_wall, "create_seconds": create_seconds, "dropped_cache": dropped,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--binary", default="target/release/radserve")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--capacity", type=int, default=100_000)
    parser.add_argument("--rates", default=f"{256 << 20},0", help="snapshot_bytes_per_second values, comma-separated")
    parser.add_argument("--interval", type=float, default=60.0,
                        help="snapshot_interval_s: the first snapshot comes this long after the server starts")
    parser.add_argument("--dir", default=None, help="where snapshots go (default: a temporary directory in /var/tmp)")
    parser.add_argument("--no-results", action="store_true", help="print only; leave bench/results/ as it is")
    args = parser.parse_args()
    rates = [int(rate) for rate in args.rates.split(",")]
    base = Path(args.dir or tempfile.mkdtemp(prefix="radserve-snapshots-", dir="/var/tmp"))
    base.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    try:
        for round_index in range(args.rounds):
            for rate in rates:
                directory = base / f"round{round_index}-rate{rate}"
                disk = dd_rate(base)
                row = measure(args.binary, directory, rate, args.capacity, args.interval)
                row["dd_mib_s"] = disk
                results.setdefault(rate, []).append(row)
                print(f"round {round_index + 1}/{args.rounds} rate {rate}: {row}", file=sys.stderr, flush=True)
                shutil.rmtree(directory, ignore_errors=True)
    finally:
        if args.dir is None:
            shutil.rmtree(base, ignore_errors=True)

    def ranged(rows, key, digits=0, suffix=""):
        return record.ranged([row[key] for row in rows], digits=digits, suffix=suffix)

    cost_rows, restore_rows = [], []
    for rate, rows in results.items():
        pacing = f"{rate / 2**20:.0f} MiB/s" if rate else "unpaced"
        for row in rows:
            row["p99_ratio"] = row["during_p99"] / row["quiet_p99"]
            row["batch_ratio"] = row["during_batches"] / max(row["quiet_batches"], 1e-9)
            row["disk_share"] = row["write_mib_s"] / row["dd_mib_s"]
        cost_rows.append([pacing, ranged(rows, "written_mib"), ranged(rows, "snapshot_seconds", 1),
                          ranged(rows, "write_mib_s"), ranged(rows, "dd_mib_s"),
                          f"{np.median([r['quiet_p99'] for r in rows]):.1f} / {np.median([r['during_p99'] for r in rows]):.1f}",
                          ranged(rows, "p99_ratio", 2, "x"),
                          f"{np.median([r['quiet_batches'] for r in rows]):.1f} / {np.median([r['during_batches'] for r in rows]):.1f}",
                          ranged(rows, "batch_ratio", 2, "x")])
        restore_rows.append([pacing, ranged(rows, "restored"), ranged(rows, "disk_gib", 2),
                             ranged(rows, "restore_seconds", 2), ranged(rows, "create_seconds", 2),
                             "yes" if all(row["dropped_cache"] for row in rows) else "no"])
        print(record.plain(cost_rows[-1]))
        print(record.plain(restore_rows[-1]))
    if not args.no_results:
        frame = "64x64x3"
        cost = {"id": "snapshot_cost", "rows": cost_rows, "align": ["l"] + ["r"] * 8,
                "columns": ["pacing", "MiB written", "seconds", "MiB/s", "dd MiB/s", "Step p99 ms quiet / during",
                            "p99 ratio", "batches/s quiet / during", "batches/s ratio"],
                "note": f"A full snapshot (every frame held) of a {args.capacity}-transition replay of {ENV} x{NUM_ENVS} "
                        f"({frame} frames) while this process steps the session and a learner process drains "
                        f"{DRAIN['augment']} batches of {DRAIN['batch_size']}; dd: 1 GiB with fdatasync to the same "
                        f"disk in the same round. Median (range) of {args.rounds} rounds."}
        restore = {"id": "snapshot_restore", "rows": restore_rows, "align": ["l", "r", "r", "r", "r", "l"],
                   "columns": ["pacing of the snapshot", "transitions restored", "GiB on disk", "restore s",
                               "creating it unnamed s", "page cache dropped"],
                   "note": "After SIGKILL, a new server creates the session under its name: the server's restore time "
                           "(radserve_snapshot_restore_duration_seconds), beside creating the same session without a "
                           "name (building its 64 envs and buffer). Median (range) of the rounds."}
        record.write("snapshot_cost", [cost, restore], {"rounds": args.rounds, "capacity": args.capacity,
                                                         "rates": rates, "interval": args.interval})


if __name__ == "__main__":
    main()
