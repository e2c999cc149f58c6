"""Augmented minibatches delivered into numpy through radserve, against the transport ceiling and
against the reference pipeline, in one run.

    make bench-replay           (or: .venv/bin/python bench/replay_stream.py)

1. radserve over gRPC: a dm_control pixel session records transitions into its replay buffer; a Python
   learner streams batches of 512 sampled, frame-stacked and augmented on the server
   (crop 100->84, translate 100->108) with obs and next_obs, into numpy arrays.
2. transport ceiling: one batch of the same stream, recorded, sent again and again by a stand-in
   server in a process of its own (bench/transport_ceiling.py), so nothing is sampled or augmented;
   same messages, same client decoding.
3. shared memory: the same batches written by the server into memory the learner maps (delivery=
   "shared_memory"): only descriptors go through gRPC, the arrays are read in place.
4. reference pipeline: in one Python process, a numpy replay buffer that stores obs and next_obs
   stacks separately (as RAD's reference does), sampled with numpy and augmented with PyTorch
   (bench/augment_speed.py's implementation) on the same cores.
Also prints the bytes of memory per stored transition of both buffers. Each stream is measured
--rounds times (medians, with the rounds' range); the tables go to bench/results/replay_stream.json
(docs/performance.md renders them).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

import radserve  # noqa: E402
import record  # noqa: E402  (bench/record.py: the results file)
from radserve.proto import radserve_pb2 as pb  # noqa: E402
from transport_ceiling import RecordedServer, record_batch  # noqa: E402


def rate(stream, batches: int, warmup: int = 6) -> "tuple[float, int]":
    """Batches per second over `batches` batches after `warmup`, and bytes per batch. The warm-up
    covers a shared-memory ring's first pass (prefetch 4 + 2 slots), whose pages the kernel zeroes
    on first touch, once per stream."""
    iterator = iter(stream)
    for _ in range(warmup):
        next(iterator)
    size = 0
    started = time.perf_counter()
    for _ in range(batches):
        batch = next(iterator)
        size = sum(view.nbytes for view in batch.views.values())  # obs and next_obs, or the named views
    elapsed = time.perf_counter() - started
    stream.close()
    return batches / elapsed, size


def reference_rate(augment, capacity: int, batch_size: int, batches: int, threads: int) -> float:
    import torch

    torch.set_num_threads(threads)
    rng = np.random.default_rng(0)
    obs = rng.integers(0, 256, (capacity, 9, 100, 100), dtype=np.uint8)
    next_obs = rng.integers(0, 256, (capacity, 9, 100, 100), dtype=np.uint8)
    actions = rng.standard_normal((capacity, 6), dtype=np.float32)
    rewards = rng.standard_normal(capacity, dtype=np.float32)

    def one_batch():
        index = rng.integers(0, capacity, batch_size)
        sample = torch.from_numpy(obs[index]), torch.from_numpy(next_obs[index])
        return augment(sample[0]).numpy(), augment(sample[1]).numpy(), actions[index], rewards[index]

    one_batch()
    started = time.perf_counter()
    for _ in range(batches):
        one_batch()
    return batches / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--batches", type=int, default=40)
    parser.add_argument("--steps", type=int, default=250, help="acting steps to fill the replay buffer")
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--rounds", type=int, default=3, help="measurements of each stream (medians and ranges)")
    parser.add_argument("--no-reference", action="store_true", help="skip the PyTorch reference (no torch needed)")
    args = parser.parse_args()

    rows = []
    with radserve.LocalServer(workers=2) as server, radserve.Client(server.address) as client:
        envs = client.make_vec("dmc/cheetah-run", num_envs=args.envs, seed=0, autoreset_mode="SameStep",
                               replay_capacity=100_000,
                               render_profile="fast")
        envs.reset()
        for _ in range(args.steps):
            envs.step(envs.action_space.sample())
        replay = client.describe_session(envs.session_id).replay
        stored = replay.size
        print(f"replay: {stored} transitions from {args.steps} steps of {args.envs} envs; "
              f"{replay.memory_bytes / replay.capacity:.0f} bytes per transition of capacity "
              f"({replay.frames_per_transition:.4f} frames per transition)")
        for name, augment in [("crop", "crop(84)"), ("translate", "translate(108)")]:
            for next_obs in (True, False):
                common = dict(augment=augment, prefetch=4, include_next_obs=next_obs)
                recorded = record_batch(client, pb.SampleBatchesRequest(
                    session_id=envs.session_id, batch_size=args.batch, pipeline_text=augment, prefetch=4,
                    include_next_obs=next_obs))
                served, ceiling, shared = [], [], []
                with RecordedServer(recorded) as stand_in:
                    for _ in range(args.rounds):
                        rate_, size = rate(envs.sample_batches(args.batch, **common), args.batches)
                        served.append(rate_)
                        ceiling.append(rate(stand_in.stream(), args.batches)[0])
                        shared.append(rate(envs.sample_batches(args.batch, delivery="shared_memory",
                                                                 **common), args.batches)[0])
                rows.append((name, "obs+next_obs" if next_obs else "obs only", size, served, ceiling, shared))
        envs.close()

    reference = {}
    if not args.no_reference:
        from augment_speed import crop, translate

        for name, fn in [("crop", lambda x: crop(x, 84)), ("translate", lambda x: translate(x, 108))]:
            reference[name] = [reference_rate(fn, min(stored, 4000), args.batch, max(3, args.batches // 8), args.threads)
                               for _ in range(args.rounds)]

    table_rows = []
    for name, fields, size, served, ceiling, shared in rows:
        ref = reference.get(name) if fields == "obs+next_obs" else None
        table_rows.append([
            {"crop": "crop 100→84", "translate": "translate 100→108"}[name], fields, record.cell(size / 1e6, digits=1),
            record.ranged(served, digits=1), record.ranged(ceiling, digits=1),
            record.ranged([a / b for a, b in zip(served, ceiling)], digits=2),
            record.ranged(shared, digits=1), record.cell(sorted(shared)[len(shared) // 2] * size / 1e9, digits=1),
            record.ranged(ref, digits=2) if ref else "-",
        ])
    streams = {"id": "replay_stream", "rows": table_rows,
               "columns": ["augment", "fields", "MB/batch", "gRPC", "gRPC ceiling", "gRPC / ceiling", "shared memory",
                           "shared memory GB/s", "reference"],
               "align": ["l", "l", "r", "r", "r", "r", "r", "r", "r"],
               "note": f"Batches of {args.batch} per second into numpy in a Python learner, medians of {args.rounds} "
                       f"rounds (their range); the server with 2 workers and {args.envs} envs."}
    reference_bytes = 2 * 9 * 100 * 100 + 6 * 4 + 4 + 1
    memory = {"id": "replay_memory", "columns": ["buffer", "bytes per transition", "frames per transition"],
              "rows": [["radserve (frames stored once)", record.cell(replay.memory_bytes / replay.capacity),
                        record.cell(replay.frames_per_transition, digits=4)],
                       ["reference (obs and next_obs stacks stored)", record.cell(reference_bytes), record.cell(6)]],
              "note": "cheetah-run frames of 3x100x100, stacks of 3."}
    for row in table_rows:
        print(record.plain(row))
    record.write("replay_stream", [streams, memory], {"batch": args.batch, "batches": args.batches, "rounds": args.rounds,
                                                      "envs": args.envs, "threads": args.threads})


if __name__ == "__main__":
    main()
