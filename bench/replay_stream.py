"""Augmented minibatches delivered into numpy through radserve, against the transport ceiling and
against the reference pipeline, in one run.

    make bench-replay           (or: .venv/bin/python bench/replay_stream.py)

1. radserve over gRPC: a dm_control pixel session records transitions into its replay buffer; a Python
   learner streams batches of 512 sampled, frame-stacked and augmented on the server
   (crop 100->84, translate 100->108) with obs and next_obs, into numpy arrays.
2. transport ceiling: the same stream with `repeat_first_batch`: the server sends one batch's bytes
   again and again, so nothing is sampled or augmented; same message sizes, same client decoding.
3. shared memory: the same batches written by the server into memory the learner maps (delivery=
   "shared_memory"): only descriptors go through gRPC, the arrays are read in place.
4. reference pipeline: in one Python process, a numpy replay buffer that stores obs and next_obs
   stacks separately (as RAD's reference does), sampled with numpy and augmented with PyTorch
   (bench/augment_speed.py's implementation) on the same cores.
Also prints the bytes of memory per stored transition of both buffers.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import radserve  # noqa: E402


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
        size = batch.obs.nbytes + (batch.next_obs.nbytes if batch.next_obs is not None else 0)
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
    parser.add_argument("--no-reference", action="store_true", help="skip the PyTorch reference (no torch needed)")
    args = parser.parse_args()

    rows = []
    with radserve.LocalServer(workers=2) as server, radserve.Client(server.address) as client:
        envs = client.make_vec("dmc/cheetah-run", num_envs=args.envs, seed=0, replay_capacity=100_000,
                               render_profile="fast")
        envs.reset()
        for _ in range(args.steps):
            envs.step(envs.action_space.sample())
        replay = client.describe_session(envs.session_id).replay
        stored = replay["size"]
        print(f"replay: {stored} transitions from {args.steps} steps of {args.envs} envs; "
              f"{replay['memory_bytes'] / replay['capacity']:.0f} bytes per transition of capacity "
              f"({replay['frames_per_transition']:.4f} frames per transition)")
        for name, augment in [("crop", "crop(84)"), ("translate", "translate(108)")]:
            for next_obs in (True, False):
                common = dict(augment=augment, prefetch=4, include_next_obs=next_obs)
                served, size = rate(client.sample_batches(envs.session_id, args.batch, **common), args.batches)
                ceiling, _ = rate(client.sample_batches(envs.session_id, args.batch, repeat_first_batch=True, **common),
                                  args.batches)
                shared, _ = rate(client.sample_batches(envs.session_id, args.batch, delivery="shared_memory", **common),
                                 args.batches)
                rows.append((name, "obs+next_obs" if next_obs else "obs only", size, served, ceiling, shared))
        envs.close()

    reference = {}
    if not args.no_reference:
        from augment_speed import crop, translate

        for name, fn in [("crop", lambda x: crop(x, 84)), ("translate", lambda x: translate(x, 108))]:
            reference[name] = reference_rate(fn, min(stored, 4000), args.batch, max(3, args.batches // 8), args.threads)

    print(f"\nbatch {args.batch}, {args.threads} cores, batches per second into numpy (median of one run)")
    header = (f"{'augment':<10} {'fields':<13} {'MB/batch':>9} {'grpc':>7} {'ceiling':>8} {'of ceiling':>10} "
              f"{'GB/s':>6} {'shm':>7} {'GB/s':>6} {'shm/ceiling':>11} {'reference':>10}")
    print(header)
    print("-" * len(header))
    for name, fields, size, served, ceiling, shared in rows:
        ref = reference.get(name) if fields == "obs+next_obs" else None
        print(f"{name:<10} {fields:<13} {size / 1e6:>9.1f} {served:>7.1f} {ceiling:>8.1f} {served / ceiling:>10.2f} "
              f"{served * size / 1e9:>6.2f} {shared:>7.1f} {shared * size / 1e9:>6.2f} {shared / ceiling:>11.2f} "
              f"{f'{ref:.2f}' if ref else '-':>10}")
    reference_bytes = 2 * 9 * 100 * 100 + 6 * 4 + 4 + 1
    print(f"\nmemory per transition: radserve {replay['memory_bytes'] / replay['capacity']:.0f} B "
          f"({replay['frames_per_transition']:.4f} frames), reference {reference_bytes} B (6 frames)")


if __name__ == "__main__":
    main()
