"""How long a saturated server takes to answer kubelet's gRPC probe: the latency of grpc.health.v1
Check, asked every 0.5 s, against a server pod run as the Kubernetes StatefulSet specifies it (the
dev overlay's pod through tests/k8s_harness.py: 2 CPUs, 8 GiB, two workers, read-only root...),
first quiet, then while a learner on this host keeps it busy (8 dm_control pixel envs stepping back
to back over gRPC, 100x100 frames, and a stream of crop(84) batches of 128). Prints the table and
writes bench/results/probe_latency.json (docs/performance.md renders it), beside the timeouts the
StatefulSet's probes had (1 s) and have (3 s).

    python bench/probe_latency.py [--rounds 2] [--seconds 60]     (needs the images: make images-local)
"""

import argparse
import statistics
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
import record

harness = record.tests_helper("k8s_harness")

PERIOD_S = 0.5
ENV, NUM_ENVS, BATCH = "dmc/cartpole-swingup", 8, 128


def probe_for(address: str, seconds: float, stop: threading.Event) -> "list[float]":
    """Latencies (s) of health checks every PERIOD_S for `seconds` (a failed one counts as 10 s)."""
    latencies = []
    end = time.monotonic() + seconds
    while time.monotonic() < end and not stop.is_set():
        begin = time.monotonic()
        ok = harness.grpc_health(address, "radserve.v1.RadServe", 10.0)
        latencies.append(time.monotonic() - begin if ok else 10.0)
        time.sleep(max(0.0, PERIOD_S - (time.monotonic() - begin)))
    return latencies


def load(address: str, stop: threading.Event, counts: dict) -> None:
    import radserve

    with radserve.Client(address) as client:
        envs = client.make_vec(ENV, num_envs=NUM_ENVS, seed=0, autoreset_mode="SameStep", replay_capacity=20_000)
        envs.reset(seed=0)
        for _ in range(40):
            envs.step(envs.action_space.sample())
        stream = envs.sample_batches(BATCH, augment="crop(84)", min_size=BATCH, prefetch=2)
        batches = iter(stream)
        counts["ready"].set()
        while not stop.is_set():
            envs.step(envs.action_space.sample())
            counts["steps"] += NUM_ENVS
            next(batches)
            counts["batches"] += 1
        stream.close()
        envs.close()


def summary(latencies: "list[float]") -> dict:
    ordered = sorted(latencies)
    return {"p50": statistics.median(ordered) * 1e3, "p99": ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] * 1e3,
            "max": ordered[-1] * 1e3, "over_1s": sum(x > 1.0 for x in ordered) / len(ordered) * 100,
            "over_3s": sum(x > 3.0 for x in ordered) / len(ordered) * 100, "n": len(ordered)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--tag", default="dev")
    args = parser.parse_args()
    rounds = {"quiet": [], "loaded": []}
    rates = []
    with tempfile.TemporaryDirectory() as scratch:
        workdir = Path(scratch)
        tree = harness.prepare(workdir, ["docker", "run", "--rm", f"radserve:{args.tag}", "token"])
        cluster = harness.Cluster(harness.overlay_documents(tree, "dev"), workdir / "cluster",
                                  f"radserve-probe-{uuid.uuid4().hex[:8]}", harness.namespace_labels())
        pod = cluster.pods[0]
        pod.image = f"radserve:{args.tag}"
        pod.probes = []  # measured here, every PERIOD_S, instead of at the pod's own timings
        with harness.Running(cluster) as running:
            name = running.start(pod)
            ip = harness.docker("inspect", "-f", "{{range .NetworkSettings.Networks}}{{.IPAddress}}{{end}}", name)
            address = f"{ip}:50051"
            deadline = time.monotonic() + 300
            while not harness.grpc_health(address, "", 5.0):
                assert time.monotonic() < deadline, running.logs(pod)
                time.sleep(1)
            for round_index in range(args.rounds):
                stop = threading.Event()
                rounds["quiet"].append(probe_for(address, args.seconds / 2, stop))
                counts = {"steps": 0, "batches": 0, "ready": threading.Event()}
                worker = threading.Thread(target=load, args=(address, stop, counts), daemon=True)
                worker.start()
                counts["ready"].wait(300)
                begin = time.monotonic()
                rounds["loaded"].append(probe_for(address, args.seconds, stop))
                elapsed = time.monotonic() - begin
                rates.append((counts["steps"] / elapsed, counts["batches"] / elapsed))
                stop.set()
                worker.join(60)
                print(f"round {round_index + 1}: quiet {summary(rounds['quiet'][-1])}, loaded {summary(rounds['loaded'][-1])}, "
                      f"{rates[-1][0]:.0f} env steps/s, {rates[-1][1]:.1f} batches/s")
    rows = []
    for phase in ("quiet", "loaded"):
        per_round = [summary(latencies) for latencies in rounds[phase]]
        pooled = summary([x for latencies in rounds[phase] for x in latencies])
        rows.append([phase, pooled["n"],
                     record.ranged([r["p50"] for r in per_round], 1), record.ranged([r["p99"] for r in per_round], 0),
                     record.ranged([r["max"] for r in per_round], 0),
                     record.cell(pooled["over_1s"], digits=1, suffix=" %"), record.cell(pooled["over_3s"], digits=1, suffix=" %")])
    steps = np.median([r[0] for r in rates])
    batches = np.median([r[1] for r in rates])
    table = {"id": "probe_latency",
             "columns": ["server", "checks", "p50 ms", "p99 ms", "max ms", "over 1 s (old timeout)", "over 3 s (timeout)"],
             "rows": rows,
             "note": (f"The dev overlay's server pod under Docker (2 CPUs, two workers), grpc.health.v1 Check of radserve.v1.RadServe "
                      f"every {PERIOD_S} s; loaded: {NUM_ENVS} {ENV} pixel envs stepping back to back over gRPC and crop(84) "
                      f"batches of {BATCH} from this host ({steps:.0f} env steps/s, {batches:.1f} batches/s, medians). "
                      "Medians of the rounds (their range); the shares pool every check.")}
    for row in rows:
        print(record.plain(row))
    record.write("probe_latency", [table], settings=vars(args))


if __name__ == "__main__":
    main()
