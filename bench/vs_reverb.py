"""radserve's replay against DeepMind Reverb's on the same items, in one run.

    make bench-reverb        (makes the Reverb venv, .venv-reverb, from bench/reverb-requirements.txt)

Items: 84x84x3 uint8 frames (dm_control cheetah-run rendered by radserve), frame_stack 3 for single
transitions (obs and next_obs stacks, action, reward), frame_stack 1 for sequences of 80 steps (a
recurrent learner's input). Both replays hold `--items` transitions, frames stored once (radserve's
ring; Reverb's chunks, referenced by each item). Rows: uniform and prioritized (alpha 0.6, no
priority updates) sampling, batch 256 transitions or 32 sequences (a batch of 256 sequences of 80
stacks is 1.3 GB, above radserve's 1 GiB bound), into numpy in a Python learner:

- samples/s: transitions (or sequences) per second delivered; bytes/s of their arrays;
- inserts/s while sampling: radserve records env steps, so its figure is the session's step rate
  while a stream samples (the simulator's cost included), beside its rate without sampling;
  Reverb's is a writer appending pre-rendered frames while its table is sampled;
- memory per stored transition: the server process's RSS growth over the fill, per transition
  (Reverb's server runs in its bench process; its chunks are zstd-compressed).

radserve's rows also run with `crop(76)` on (its target: within 0.8x of its row without). The
Reverb side runs in its own venv (TensorFlow 2.15 and dm-reverb 0.14: bench/reverb_side.py) on
the same frames, after radserve's server has stopped. Results: bench/results/vs_reverb.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

import radserve
import record  # noqa: E402  (bench/record.py: the results file)

ROOT = Path(__file__).resolve().parents[1]


def rss(pid: int) -> int:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


def fill(envs, transitions: int) -> float:
    """Steps `envs` until `transitions` were recorded (the replay then holds its capacity, less the
    episodes' first frames); returns transitions recorded per second."""
    envs.reset(seed=0)
    began = time.perf_counter()
    steps = 0
    while steps < transitions:
        envs.step(envs.action_space.sample())
        steps += envs.num_envs
    return steps / (time.perf_counter() - began)


def sample_rate(envs, batch: int, batches: int, **settings) -> "tuple[float, int]":
    """Samples (transitions or sequences) per second into numpy, and bytes per batch."""
    with envs.sample_batches(batch, prefetch=4, seed=1, **settings) as stream:
        iterator = iter(stream)
        for _ in range(3):
            next(iterator)
        began = time.perf_counter()
        size = 0
        for _ in range(batches):
            sample = next(iterator)
            size = sum(value.nbytes for value in vars(sample).values() if isinstance(value, np.ndarray))
            size += sum(view.nbytes for name, view in sample.views.items() if name not in ("obs", "next_obs"))
        return batches * batch / (time.perf_counter() - began), size


def steps_while_sampling(envs, seconds: float, batch: int, **settings) -> float:
    """The session's step rate while a stream samples it continuously in another thread."""
    stop = threading.Event()

    def learner():
        with envs.sample_batches(batch, prefetch=4, seed=2, **settings) as stream:
            for _ in stream:
                if stop.is_set():
                    return

    thread = threading.Thread(target=learner)
    thread.start()
    time.sleep(0.5)
    steps = 0
    began = time.perf_counter()
    while time.perf_counter() - began < seconds:
        envs.step(envs.action_space.sample())
        steps += envs.num_envs
    rate = steps / (time.perf_counter() - began)
    stop.set()
    thread.join()
    return rate


def radserve_side(args, frames_path: Path) -> dict:
    results = {"rows": {}}
    common = dict(num_envs=args.envs, seed=0, autoreset_mode="SameStep", height=84, width=84, render_profile="fast")
    with radserve.LocalServer(workers=2) as server, radserve.Client(server.address) as client:
        pid = server.process.pid
        before = rss(pid)
        envs = client.make_vec("dmc/cheetah-run", frame_stack=3, replay_capacity=args.items, **common)
        results["fill_steps_per_s"] = fill(envs, args.items)
        results["rss_per_transition"] = (rss(pid) - before) / args.items
        # The frames Reverb stores: the newest frame of each stack, as rendered.
        obs = np.concatenate([envs.step(envs.action_space.sample())[0] for _ in range(64)])
        np.save(frames_path, np.ascontiguousarray(obs[:, 6:9].transpose(0, 2, 3, 1)))
        def measure(name, batch, **settings):
            row = {"batch": batch}
            row["grpc_samples_per_s"], row["bytes_per_batch"] = sample_rate(envs, batch, args.batches, **settings)
            shared = dict(settings, delivery="shared_memory")
            row["samples_per_s"], _ = sample_rate(envs, batch, args.batches, **shared)
            row["crop_samples_per_s"], _ = sample_rate(envs, batch, args.batches, augment="crop(76)", **shared)
            row["inserts_per_s_while_sampling"] = steps_while_sampling(envs, args.seconds, batch, **shared)
            results["rows"][name] = row
            print(name, row, file=sys.stderr, flush=True)

        measure("uniform", args.batch)
        measure("prioritized", args.batch, sampler="prioritized")
        envs.close()
        envs = client.make_vec("dmc/cheetah-run", frame_stack=1, replay_capacity=args.items, **common)
        fill(envs, args.items)
        measure("sequence", args.sequence_batch, sequence=radserve.Sequence(args.length, boundary="across_episodes"))
        envs.close()
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--items", type=int, default=50_000, help="transitions each replay holds")
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--sequence-batch", type=int, default=32)
    parser.add_argument("--length", type=int, default=80)
    parser.add_argument("--batches", type=int, default=30)
    parser.add_argument("--seconds", type=float, default=5.0, help="of stepping while a stream samples")
    parser.add_argument("--reverb-python", default=str(ROOT / ".venv-reverb" / "bin" / "python"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        frames = Path(scratch) / "frames.npy"
        ours = radserve_side(args, frames)
        command = [args.reverb_python, str(ROOT / "bench" / "reverb_side.py"), "--frames", str(frames), "--items",
                   str(args.items), "--batch", str(args.batch), "--sequence-batch", str(args.sequence_batch),
                   "--length", str(args.length), "--batches", str(args.batches)]
        theirs = json.loads(subprocess.run(command, check=True, stdout=subprocess.PIPE, text=True).stdout)
    rows = []
    for name, label in [("uniform", "transitions, uniform"), ("prioritized", "transitions, prioritized"),
                        ("sequence", f"sequences of {args.length}, uniform"),
                        ("sequence_prioritized", f"sequences of {args.length}, prioritized")]:
        mine, reverb = ours["rows"].get(name), theirs["rows"][name]
        unit = "sequences" if name.startswith("sequence") else "transitions"
        rows.append([
            label, f"{reverb['batch']} {unit}",
            record.cell(mine["grpc_samples_per_s"]) if mine else "refused",
            record.cell(mine["samples_per_s"]) if mine else "refused", record.cell(reverb["samples_per_s"]),
            record.cell(mine["grpc_samples_per_s"] / reverb["samples_per_s"], digits=2) if mine else "-",
            record.cell(mine["samples_per_s"] / reverb["samples_per_s"], digits=2) if mine else "-",
            record.cell(mine["crop_samples_per_s"] / mine["samples_per_s"], digits=2) if mine else "-",
            record.cell(mine["samples_per_s"] * mine["bytes_per_batch"] / mine["batch"] / 1e9, digits=2) if mine else "-",
            record.cell(reverb["samples_per_s"] * reverb["bytes_per_batch"] / reverb["batch"] / 1e9, digits=2),
            record.cell(mine["inserts_per_s_while_sampling"]) if mine else "-",
            record.cell(reverb["inserts_per_s_while_sampling"]),
        ])
    table = {"id": "vs_reverb", "rows": rows,
             "columns": ["items", "batch", "radserve gRPC samples/s", "radserve shared memory samples/s",
                         "Reverb samples/s", "gRPC / Reverb", "shared memory / Reverb", "crop(76) / none",
                         "radserve GB/s", "Reverb GB/s", "radserve inserts/s while sampling",
                         "Reverb inserts/s while sampling"],
             "align": ["l", "l", "r", "r", "r", "r", "r", "r", "r", "r", "r", "r"],
             "note": f"{args.items} transitions of 84x84x3 frames held by each; radserve's inserts are its "
                     f"{args.envs} cheetah-run envs' steps (rendering included; {ours['fill_steps_per_s']:.0f} steps/s "
                     f"without sampling), Reverb's a writer's appends of rendered frames "
                     f"({theirs['fill_steps_per_s']:.0f}/s while filling its four tables). Reverb samples in its "
                     f"server's process (a TrajectoryDataset beside the server: no gRPC, its fastest path); radserve "
                     f"into a learner process over gRPC and over shared memory (crop and GB/s: shared memory). "
                     f"Reverb's sequence items are made every {theirs['period']} steps (R2D2's period)."}
    memory = {"id": "vs_reverb_memory", "columns": ["replay", "server RSS per stored transition (bytes)"],
              "rows": [["radserve (frame_stack 3)", record.cell(ours["rss_per_transition"])],
                       ["Reverb (four tables over the same chunks)", record.cell(theirs["rss_per_transition"])]],
              "note": "RSS growth of the server process over the fill, per transition held; one 84x84x3 frame is "
                      "21168 bytes."}
    for row in rows:
        print(record.plain(row))
    record.write("vs_reverb", [table, memory], vars(args) | {"reverb_python": "(.venv-reverb)"})


if __name__ == "__main__":
    main()
