"""Acting latency while a learner drains augmented batches: p50/p99 of one Step over gRPC, quiet and
while another thread streams colour-jitter batches as fast as it reads them, in one run.

    .venv/bin/python bench/acting_latency.py [--binary A --binary B@NAME=VALUE,NAME=VALUE ...] [--rounds 3]
        [--steps 2000] [--drain-in-process]

Two cases, each measured quiet and while draining:
- own buffer: a dm_control cartpole-balance session (1 env, pixels, `fast` look) with a replay
  buffer; the learner samples that same buffer, so every Step records into the buffer the stream
  reads (the replay lock is on the path).
- other session: gym/CartPole-v1 (1 env, states, no buffer) acting while the learner drains another
  session's buffer (the augmentation threads and the acting calls share the cores).

The learner drains from a process of its own (as a learner whose sampling runs apart from its
acting would), so that the acting thread's latency is the server's, not the client's GIL;
`--drain-in-process` drains from a thread of the acting process instead.

With several binaries (a build before a change and after it), or one binary with and without settings
(`--binary target/release/radserve --binary target/release/radserve@RADSERVE__AUGMENT__NICE=10`: the
variables after `@` are set for that server only), rounds alternate between them: these machines are
noisy, compare ratios within one run. The table goes to bench/results/acting_latency.json
(docs/performance.md renders it) unless --no-results.
"""

import argparse
import multiprocessing
import statistics
import sys
import threading
import time

import numpy as np

import radserve

import record  # noqa: E402  (bench/record.py: the results file)

DRAIN = dict(batch_size=128, augment="color_jitter", prefetch=4)


def latencies(envs, steps, actions):
    envs.reset(seed=0)
    times = []
    for index in range(steps):
        started = time.perf_counter()
        envs.step(actions[index % len(actions)])
        times.append((time.perf_counter() - started) * 1000)
    return times


def drain(client, session_id, stop, counted):
    stream = client.sample_batches(session_id, **DRAIN)
    for _ in stream:
        counted[0] += 1
        if stop.is_set():
            break
    stream.close()


def drain_process(address, session_id, stop, counted):
    """`drain` in a process of its own (multiprocessing, spawned: no grpc state crosses a fork)."""
    client = radserve.Client(address)
    shared = [0]
    thread = threading.Thread(target=drain, args=(client, session_id, stop, shared), daemon=True)
    thread.start()
    while not stop.is_set():
        counted.value = shared[0]
        time.sleep(0.05)
    thread.join(timeout=30)
    counted.value = shared[0]


class Drain:
    """The draining learner, in a thread of this process or in a process of its own."""

    def __init__(self, client, address, session_id, in_process):
        if in_process:
            self.stop, self._counted = threading.Event(), [0]
            self._worker = threading.Thread(target=drain, args=(client, session_id, self.stop, self._counted))
        else:
            context = multiprocessing.get_context("spawn")
            self.stop, self._counted = context.Event(), context.Value("q", 0)
            self._worker = context.Process(target=drain_process, args=(address, session_id, self.stop, self._counted))
        self._worker.start()

    def batches(self):
        return self._counted[0] if isinstance(self._counted, list) else self._counted.value

    def finish(self):
        self.stop.set()
        self._worker.join()


def measure(binary, server_env, steps, in_process):
    rows = {}
    env = {"RADSERVE__SIM__VENV": sys.prefix, **server_env}
    with radserve.LocalServer(workers=2, binary=binary, env=env) as server:
        client = radserve.Client(server.address)
        pixels = client.make_vec("dmc/cartpole-balance", num_envs=1, seed=0, autoreset_mode="SameStep",
                                 replay_capacity=5000, render_profile="fast")
        pixel_actions = np.random.default_rng(0).uniform(-1, 1, (64, 1, 1)).astype(np.float32)
        latencies(pixels, 300, pixel_actions)  # fills the buffer
        state = client.make_vec("gym/CartPole-v1", num_envs=1, seed=0, autoreset_mode="SameStep")
        state_actions = np.random.default_rng(0).integers(0, 2, (64, 1))
        for case, envs, actions in [("own buffer (dmc pixels)", pixels, pixel_actions),
                                    ("other session (CartPole)", state, state_actions)]:
            count = steps // 4 if envs is pixels else steps
            quiet = latencies(envs, count, actions)
            draining = Drain(client, server.address, pixels.session_id, in_process)
            time.sleep(1.0 if in_process else 3.0)  # a spawned process imports numpy and grpc first
            started_batches, started = draining.batches(), time.perf_counter()
            busy = latencies(envs, count, actions)
            batches_per_s = (draining.batches() - started_batches) / (time.perf_counter() - started)
            draining.finish()
            rows[case] = (quiet, busy, batches_per_s)
        pixels.close()
        state.close()
    return rows


def percentile(values, q):
    return float(np.percentile(values, q))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--binary", action="append", default=None,
                        help="PATH or PATH@NAME=VALUE[,NAME=VALUE]: a server to measure, with these variables set")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--drain-in-process", action="store_true",
                        help="drain from a thread of the acting process (its GIL is then shared)")
    parser.add_argument("--no-results", action="store_true", help="print only; leave bench/results/ as it is")
    args = parser.parse_args()
    variants = []
    for text in args.binary or ["target/release/radserve"]:
        binary, _, settings = text.partition("@")
        variants.append((binary, dict(item.split("=", 1) for item in settings.split(",") if item)))
    results = {}
    for round_index in range(args.rounds):
        for binary, env in variants:
            settings = " ".join(f"{name}={value}" for name, value in env.items()) or "defaults"
            several_binaries = len({path for path, _ in variants}) > 1
            label = f"{binary} {settings}" if several_binaries else settings
            for case, row in measure(binary, env, args.steps, args.drain_in_process).items():
                results.setdefault((label, case), []).append(row)
            print(f"round {round_index + 1}/{args.rounds} {label} done", file=sys.stderr, flush=True)

    table_rows = []
    for (label, case), rows in results.items():
        quiet = [t for row in rows for t in row[0]]
        busy = [t for row in rows for t in row[1]]
        ratios = [percentile(row[1], 99) / percentile(row[0], 99) for row in rows]
        table_rows.append([label, case, f"{percentile(quiet, 50):.2f} / {percentile(quiet, 99):.2f}",
                           f"{percentile(busy, 50):.2f} / {percentile(busy, 99):.2f}",
                           record.ranged(ratios, digits=1, suffix="x"), record.ranged([row[2] for row in rows])])
        print(record.plain(table_rows[-1]))
    if not args.no_results:
        table = {"id": "acting_latency", "rows": table_rows, "align": ["l", "l", "r", "r", "r", "r"],
                 "columns": ["server", "acting", "quiet p50 / p99 ms", "while draining p50 / p99 ms", "p99 ratio",
                             "batches/s drained"],
                 "note": f"One Step over gRPC, {args.steps} steps per case (a quarter for pixels) quiet and while "
                         f"draining colour-jitter batches of 128 from {'a thread' if args.drain_in_process else 'a process'}"
                         f"; percentiles over all {args.rounds} rounds, ratio and rate: median (range) of the rounds."}
        record.write("acting_latency", [table], {"rounds": args.rounds, "steps": args.steps,
                                                 "drain_in_process": args.drain_in_process})


if __name__ == "__main__":
    main()
