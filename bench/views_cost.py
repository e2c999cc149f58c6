"""What named views and n-step returns cost, against the batches they extend, in one run.

    make bench-views            (or: .venv/bin/python bench/views_cost.py)

Batches of 256 frame stacks (3 RGB frames) into numpy in a Python learner, over gRPC and through
shared memory, from two dm_control sessions filled with random steps:
- RAD's crop: 100x100 renders cropped to 84, obs and next_obs (the batches radserve served before
  views);
- DrQ on 84x84 renders: one view (obs, shift(4)), two (obs and next_obs: DrQ-v2's batch), four
  (DrQ's K = M = 2) and the two views with n-step returns (n = 3, DrQ-v2's).
Targets (docs/performance.md): four views cost at most the bytes they add (4 x batches/s of four
views within 0.9x of one view's batches/s), and n-step 3 at most 1.1x of n-step 1. Each stream is
measured --rounds times, the cases interleaved (medians, with the rounds' range); the table goes to
bench/results/views_cost.json.
"""

from __future__ import annotations

import argparse
import os
import statistics

import radserve
import record  # noqa: E402  (bench/record.py: the results file)
from replay_stream import rate  # noqa: E402  (batches per second and bytes per batch of a stream)

DRQ = {"obs": "shift(4)", "obs_aug": "shift(4)", "next_obs": "shift(4)", "next_obs_aug": "shift(4)"}
CASES = [
    # (label, session, settings)
    ("RAD crop 100→84, obs + next_obs", "rad", dict(augment="crop(84)")),
    ("shift(4), 1 view", "drq", dict(views={"obs": "shift(4)"})),
    ("shift(4), 2 views (DrQ-v2)", "drq", dict(views={"obs": "shift(4)", "next_obs": "shift(4)"})),
    ("shift(4), 4 views (DrQ)", "drq", dict(views=DRQ)),
    ("shift(4), 2 views, n-step 3", "drq", dict(views={"obs": "shift(4)", "next_obs": "shift(4)"}, n_step=3,
                                                discount=0.99)),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--batches", type=int, default=30)
    parser.add_argument("--steps", type=int, default=200, help="random steps to fill each replay buffer")
    parser.add_argument("--envs", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()

    results = {(label, delivery): [] for label, _, _ in CASES for delivery in ("grpc", "shared_memory")}
    sizes = {}
    with radserve.LocalServer(workers=2) as server, radserve.Client(server.address) as client:
        sessions = {
            "rad": client.make_vec("dmc/cheetah-run", num_envs=args.envs, seed=0, replay_capacity=100_000,
                                   render_profile="fast", autoreset_mode="SameStep"),
            "drq": client.make_vec("dmc/cheetah-run", num_envs=args.envs, seed=1, replay_capacity=100_000,
                                   render_profile="fast", height=84, width=84, autoreset_mode="SameStep"),
        }
        for envs in sessions.values():
            envs.reset()
            for _ in range(args.steps):
                envs.step(envs.action_space.sample())
        for _ in range(args.rounds):
            for label, session, settings in CASES:
                for delivery in ("grpc", "shared_memory"):
                    stream = sessions[session].sample_batches(args.batch, prefetch=4, delivery=delivery, **settings)
                    batches_per_second, size = rate(stream, args.batches)
                    results[(label, delivery)].append(batches_per_second)
                    sizes[label] = size
        for envs in sessions.values():
            envs.close()

    median = statistics.median
    one_view = {delivery: median(results[("shift(4), 1 view", delivery)]) for delivery in ("grpc", "shared_memory")}
    n_step_1 = {delivery: median(results[("shift(4), 2 views (DrQ-v2)", delivery)])
                for delivery in ("grpc", "shared_memory")}
    rows = []
    for label, _, settings in CASES:
        views = len(settings.get("views", {"obs": 0, "next_obs": 0}))
        row = [label, record.cell(sizes[label] / 1e6, digits=1)]
        for delivery in ("grpc", "shared_memory"):
            rates = results[(label, delivery)]
            row.append(record.ranged(rates, digits=1))
            row.append(record.cell(median(rates) * sizes[label] / 1e9, digits=2))
            if label.startswith("shift") and "n-step" not in label:
                row.append(record.cell(median(rates) * views / one_view[delivery], digits=2))
            elif "n-step" in label:
                row.append(record.cell(n_step_1[delivery] / median(rates), digits=2, suffix=" cost"))
            else:
                row.append("-")
        rows.append(row)
        print(record.plain(row))
    table = {"id": "views_cost", "rows": rows,
             "columns": ["batch", "MB/batch", "gRPC batches/s", "gRPC GB/s", "gRPC vs 1 view",
                         "shared memory batches/s", "shared memory GB/s", "shared vs 1 view"],
             "align": ["l", "r", "r", "r", "r", "r", "r", "r"],
             "note": f"Batches of {args.batch} stacks of 3 RGB frames per second into numpy in a Python learner, "
                     f"medians of {args.rounds} interleaved rounds (their range); \"vs 1 view\": views x batches/s "
                     f"over one view's batches/s (1.0: a view costs only its bytes); for n-step 3, its cost: "
                     f"n-step 1's batches/s over its own. The server with 2 workers, {args.envs} envs per session."}
    record.write("views_cost", [table], {"batch": args.batch, "batches": args.batches, "rounds": args.rounds,
                                         "envs": args.envs, "steps": args.steps, "threads": os.cpu_count()})


if __name__ == "__main__":
    main()
