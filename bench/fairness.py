"""Streams sharing the augmentation threads: one learner's batches per second alone, while another
stream draws the most expensive pipeline the server accepts, and in the second after that stream is
cancelled; and one heavy stream's rate alone (what splitting batches into pool jobs costs).

    .venv/bin/python bench/fairness.py [--binary A --binary B ...] [--rounds 3] [--seconds 4]

With several binaries (e.g. a build before a change and after it), rounds alternate between them
and the table shows each one's median and range: these machines are noisy, compare in one run. A run
on the build alone writes bench/results/fairness.json (docs/reliability.md).
"""

import argparse
import os
import statistics
import sys
import threading
import time

import numpy as np

import radserve

import record  # noqa: E402  (bench/record.py: the results file)

ATTACK = "|".join(["color_jitter"] * 8)  # eight stages: the most a pipeline may have


def drain(stream, stop, counts, key):
    for _ in stream:
        counts[key] += 1
        if stop.is_set():
            break
    stream.close()


def measure(binary, seconds):
    # A binary copied out of the checkout finds no .venv above it: point it at this interpreter's.
    with radserve.LocalServer(workers=2, binary=binary, env={"RADSERVE__SIM__VENV": sys.prefix}) as server:
        client = radserve.Client(server.address)
        envs = client.make_vec("dmc/cheetah-run", num_envs=4, seed=0, autoreset_mode="SameStep",
                               replay_capacity=10_000, render_profile="fast")
        envs.reset()
        for _ in range(150):
            envs.step(np.random.default_rng(0).uniform(-1, 1, (4, 6)).astype(np.float32))
        sid = envs.session_id
        # The attacker has a session of its own (its replay buffer's lock is not the victim's).
        other = client.make_vec("dmc/cheetah-run", num_envs=4, seed=9, autoreset_mode="SameStep",
                                replay_capacity=10_000, render_profile="fast")
        other.reset()
        for _ in range(150):  # 600 transitions: one batch of 512 is there to sample
            other.step(np.random.default_rng(1).uniform(-1, 1, (4, 6)).astype(np.float32))

        # A heavy stream alone: crop obs+next_obs at the paper's batch size, through shared memory.
        heavy = client.sample_batches(sid, batch_size=512, augment="crop(84)", delivery="auto")
        it = iter(heavy)
        for _ in range(3):
            next(it)
        started, count = time.perf_counter(), 0
        while time.perf_counter() - started < seconds:
            next(it)
            count += 1
        heavy_rate = count / (time.perf_counter() - started)
        heavy.close()

        def victim_rate(duration):
            counts = {"victim": 0}
            stop = threading.Event()
            stream = client.sample_batches(sid, batch_size=32, augment="crop(84)", delivery="auto")
            thread = threading.Thread(target=drain, args=(stream, stop, counts, "victim"))
            thread.start()
            time.sleep(0.5)
            begin = counts["victim"]
            time.sleep(duration)
            rate = (counts["victim"] - begin) / duration
            stop.set()
            thread.join()
            return rate

        alone = victim_rate(seconds)
        # The attacker: 512 samples of eight colour-jitter stages per batch, read as fast as it comes.
        attack_counts = {"attack": 0}
        attack_stop = threading.Event()
        attack = other.sample_batches(batch_size=512, augment=ATTACK, delivery="auto")
        attacker = threading.Thread(target=drain, args=(attack, attack_stop, attack_counts, "attack"))
        attacker.start()
        time.sleep(1.0)
        attacked = victim_rate(seconds)
        attack_stop.set()
        attacker.join()
        after = victim_rate(1.0)  # the first second after the attacker left
        envs.close()
        other.close()
        client.close()
        return {"heavy": heavy_rate, "alone": alone, "attacked": attacked, "after": after}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--binary", action="append", help="radserve binaries to compare (default: the build)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=4.0)
    args = parser.parse_args()
    binaries = args.binary or [radserve.server.find_binary()]
    results = {binary: [] for binary in binaries}
    for round_index in range(args.rounds):
        for binary in binaries:
            results[binary].append(measure(binary, args.seconds))
            print(f"round {round_index + 1} {binary}: " + ", ".join(f"{k} {v:.1f}" for k, v in results[binary][-1].items()),
                  flush=True)
    print()
    print(f"{'binary':<40} {'heavy alone':>14} {'victim alone':>14} {'under attack':>14} {'1 s after':>14}  (batches/s, median [range])")
    table_rows = []
    for binary, rows in results.items():
        cells = []
        for key in ("heavy", "alone", "attacked", "after"):
            values = [row[key] for row in rows]
            cells.append(f"{statistics.median(values):6.1f} [{min(values):.0f}-{max(values):.0f}]")
        print(f"{binary[-40:]:<40} " + " ".join(f"{cell:>14}" for cell in cells))
        table_rows.append([os.path.relpath(binary, record.ROOT) if len(binaries) > 1 else "this build"]
                          + [record.ranged([row[key] for row in rows]) for key in ("heavy", "alone", "attacked", "after")])
    if not args.binary:
        record.write("fairness", [{
            "id": "fairness", "rows": table_rows,
            "columns": ["build", "heavy stream alone (crop 512, obs+next_obs)", "victim alone (crop, batch 32)",
                        "victim while another session draws 8x colour jitter at 512", "victim 1 s after"],
            "note": f"Batches/s, median (range) of {args.rounds} rounds of {args.seconds:g} s; 2 workers, dm_control "
                    "cheetah with the fast look."}], {"rounds": args.rounds, "seconds": args.seconds})


if __name__ == "__main__":
    main()
