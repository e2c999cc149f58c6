"""DeepMind Reverb's half of bench/vs_reverb.py, run by the Python of a venv that holds dm-reverb and
its TensorFlow (`make bench-reverb` makes it: bench/reverb-requirements.txt). Prints one JSON object.

The items are what radserve serves: frames of 84x84x3 uint8 (cycled from the frames radserve's env
rendered, `--frames`, so both compress alike), stored once per step in Reverb's chunks; a transition
item references obs = frames [t-3, t-1] and next_obs = frames [t-2, t] (frame_stack 3) with the
action and reward; a sequence item the last `--length` frames, actions and rewards. One writer
inserts (Reverb's TrajectoryWriter, as Acme's adders do); a `TrajectoryDataset` (Reverb's fastest
sampler: C++ workers into TensorFlow) batches items into numpy arrays.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time

import numpy as np
import reverb
import tensorflow as tf


def rss_bytes() -> int:
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", required=True, help=".npy of [K, 84, 84, 3] uint8 frames to cycle through")
    parser.add_argument("--items", type=int, required=True, help="transitions held (the tables' max_size)")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--sequence-batch", type=int, default=32)
    parser.add_argument("--length", type=int, default=80)
    parser.add_argument("--batches", type=int, default=30)
    parser.add_argument("--period", type=int, default=40, help="steps between two sequence items (R2D2's 40)")
    args = parser.parse_args()
    tf.config.threading.set_inter_op_parallelism_threads(os.cpu_count())
    frames = np.load(args.frames)
    action = np.zeros(6, dtype=np.float32)
    step_spec = {"frame": tf.TensorSpec([84, 84, 3], tf.uint8), "action": tf.TensorSpec([6], tf.float32),
                 "reward": tf.TensorSpec([], tf.float32)}
    transition = {"obs": tf.TensorSpec([3, 84, 84, 3], tf.uint8), "next_obs": tf.TensorSpec([3, 84, 84, 3], tf.uint8),
                  "action": step_spec["action"], "reward": step_spec["reward"]}
    sequence = {name: tf.TensorSpec([args.length, *spec.shape], spec.dtype) for name, spec in step_spec.items()}
    def table(name, sampler, signature, size):
        return reverb.Table(name, sampler=sampler, remover=reverb.selectors.Fifo(), max_size=size,
                            rate_limiter=reverb.rate_limiters.MinSize(1), signature=signature)

    before = rss_bytes()
    server = reverb.Server([
        table("uniform", reverb.selectors.Uniform(), transition, args.items),
        table("prioritized", reverb.selectors.Prioritized(0.6), transition, args.items),
        # A sequence every `period` steps (Acme's SequenceAdder), each referencing `length` frames.
        table("sequence", reverb.selectors.Uniform(), sequence, args.items // args.period),
        table("sequence_prioritized", reverb.selectors.Prioritized(0.6), sequence, args.items // args.period),
    ])
    address = f"localhost:{server.port}"
    client = reverb.Client(address)
    empty = rss_bytes()

    def insert(count: int, start: int, tables: "tuple[str, ...]", stop=None) -> "tuple[int, float]":
        """Appends `count` steps, creating each step's items; returns the steps and their rate."""
        done = 0
        began = time.perf_counter()
        with client.trajectory_writer(num_keep_alive_refs=args.length) as writer:
            for step in range(start, start + count):
                if stop is not None and stop.is_set():
                    break
                writer.append({"frame": frames[step % len(frames)], "action": action, "reward": np.float32(step)})
                done += 1
                seen = step - start + 1
                if seen >= 4:
                    item = {"obs": writer.history["frame"][-4:-1], "next_obs": writer.history["frame"][-3:],
                            "action": writer.history["action"][-2], "reward": writer.history["reward"][-2]}
                    for name in tables:
                        if not name.startswith("sequence"):
                            writer.create_item(name, priority=1.0, trajectory=item)
                if seen >= args.length and (seen - args.length) % args.period == 0:
                    item = {name: writer.history[name][-args.length:] for name in step_spec}
                    for name in tables:
                        if name.startswith("sequence"):
                            writer.create_item(name, priority=1.0, trajectory=item)
            writer.flush()
        return done, done / (time.perf_counter() - began)

    # Filling: every table at once (frames stored once, referenced by each table's items).
    tables = ("uniform", "prioritized", "sequence", "sequence_prioritized")
    filled, fill_rate = insert(args.items + args.length, 0, tables)
    full = rss_bytes()

    def sample_rate(name: str, batch: int, batches: int) -> "tuple[float, int]":
        dataset = reverb.TrajectoryDataset.from_table_signature(address, name, max_in_flight_samples_per_worker=2 * batch)
        iterator = iter(dataset.batch(batch, drop_remainder=True).prefetch(2))
        for _ in range(3):
            next(iterator)
        began = time.perf_counter()
        size = 0
        for _ in range(batches):
            sample = next(iterator)
            size = sum(tensor.numpy().nbytes for tensor in tf.nest.flatten(sample.data))
        return batches * batch / (time.perf_counter() - began), size

    results = {"fill_steps_per_s": fill_rate, "period": args.period, "rss_empty": empty - before, "rss_full": full - before,
               "rss_per_transition": (full - empty) / args.items, "rows": {}}
    for name, batch in [("uniform", args.batch), ("prioritized", args.batch), ("sequence", args.sequence_batch),
                        ("sequence_prioritized", args.sequence_batch)]:
        rate, size = sample_rate(name, batch, args.batches)
        # Inserts while this table is sampled: a writer thread for a fixed time.
        stop = threading.Event()
        counted = {}

        def writer_thread():
            counted["done"], counted["rate"] = insert(10 ** 9, filled, (name,), stop)

        thread = threading.Thread(target=writer_thread)
        thread.start()
        time.sleep(0.5)
        during, _ = sample_rate(name, batch, max(5, args.batches // 2))
        stop.set()
        thread.join()
        results["rows"][name] = {"samples_per_s": rate, "bytes_per_batch": size, "samples_per_s_while_inserting": during,
                                 "inserts_per_s_while_sampling": counted["rate"], "batch": batch}
        print(name, results["rows"][name], flush=True, file=__import__("sys").stderr)
    server.stop()
    print(json.dumps(results))


if __name__ == "__main__":
    main()
