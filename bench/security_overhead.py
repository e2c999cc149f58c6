"""What authentication and TLS cost each path, in one run: two servers of the same build, one open
(loopback, no token, no TLS) and one with a tokens file and TLS, measured in alternating rounds.

    .venv/bin/python bench/security_overhead.py [--rounds 3]     (make bench-security)

Paths: gym CartPole acting (8 envs) through the shared-memory channel and through gRPC Step calls,
and augmented minibatches (batch 256 of 3x64x64 ProcGen frames stacked 3, crop 64->56) through shared
memory and through the gRPC byte stream. The shared-memory paths authenticate once, when the channel
or stream opens; per step and per batch nothing else changes, so they should not move. Prints a
table of medians (with the rounds' range) and the secured/open ratio, and writes it to
bench/results/security_overhead.json (docs/performance.md and the README render it).
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import radserve
import record  # bench/record.py: the results file
from radserve.server import find_binary


def secured_server(folder: Path) -> "tuple[radserve.LocalServer, dict]":
    import trustme

    made = subprocess.run([find_binary(), "token", "--name", "bench"], capture_output=True, text=True, check=True)
    entry = "\n".join(line for line in made.stderr.splitlines() if not line.startswith("#"))
    (folder / "tokens.toml").write_text(entry + "\n")
    ca = trustme.CA()
    certificate = ca.issue_cert("localhost")
    certificate.cert_chain_pems[0].write_to_path(str(folder / "cert.pem"))
    certificate.private_key_pem.write_to_path(str(folder / "key.pem"))
    ca.cert_pem.write_to_path(str(folder / "ca.pem"))
    env = {"RADSERVE__AUTH__TOKENS_FILE": str(folder / "tokens.toml"),
           "RADSERVE__TLS__CERT_FILE": str(folder / "cert.pem"), "RADSERVE__TLS__KEY_FILE": str(folder / "key.pem")}
    return radserve.LocalServer(workers=1, env=env), {"token": made.stdout.strip(),
                                                      "tls": radserve.TlsConfig(ca=folder / "ca.pem")}


def acting_rate(client, delivery: str, steps: int) -> float:
    envs = client.make_vec("gym/CartPole-v1", num_envs=8, seed=0, autoreset_mode="SameStep", delivery=delivery)
    envs.reset(seed=0)
    actions = np.zeros(8, np.int64)
    for _ in range(50):
        envs.step(actions)
    started = time.perf_counter()
    for _ in range(steps):
        envs.step(actions)
    elapsed = time.perf_counter() - started
    envs.close()
    return steps * 8 / elapsed


def batch_rate(client, session_id: str, delivery: str, batches: int) -> float:
    stream = client.sample_batches(session_id, 256, augment="crop(size=56)", delivery=delivery, prefetch=4)
    iterator = iter(stream)
    for _ in range(6):
        next(iterator)
    started = time.perf_counter()
    for _ in range(batches):
        batch = next(iterator)
        float(batch.obs[0, 0, 0, 0])  # touch the batch, as a learner would
    elapsed = time.perf_counter() - started
    stream.close()
    return batches / elapsed


def replay_session(client):
    envs = client.make_vec("procgen/coinrun", num_envs=8, seed=0, autoreset_mode="SameStep",
                           replay_capacity=20_000, frame_stack=3)
    envs.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(300):
        envs.step(rng.integers(0, 15, 8))
    return envs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--batches", type=int, default=60)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        secured, credentials = secured_server(Path(folder))
        with radserve.LocalServer(workers=1) as open_server, secured:
            port = secured.address.rsplit(":", 1)[1]
            clients = {
                "open": radserve.Client(open_server.address),
                "tokens+TLS": radserve.Client(f"grpcs://localhost:{port}", **credentials),
            }
            sessions = {name: replay_session(client) for name, client in clients.items()}
            paths = {
                "acting, shared memory (gym CartPole x8, steps/s)": lambda c, s: acting_rate(c, "shared_memory", args.steps),
                "acting, gRPC Step (steps/s)": lambda c, s: acting_rate(c, "grpc", args.steps // 3),
                "batches, shared memory (256 x 9x56x56 crop, obs + next_obs, batches/s)": lambda c, s: batch_rate(c, s.session_id, "shared_memory", args.batches),
                "batches, gRPC stream (same batches, batches/s)": lambda c, s: batch_rate(c, s.session_id, "grpc", args.batches),
            }
            results = {path: {name: [] for name in clients} for path in paths}
            for round_index in range(args.rounds):
                for path, measure in paths.items():
                    order = list(clients) if round_index % 2 == 0 else list(clients)[::-1]
                    for name in order:
                        results[path][name].append(measure(clients[name], sessions[name]))
            for envs in sessions.values():
                envs.close()
    rows = []
    for path, by_server in results.items():
        ratios = [secure / plain for plain, secure in zip(by_server["open"], by_server["tokens+TLS"])]
        rows.append([path, record.ranged(by_server["open"]), record.ranged(by_server["tokens+TLS"]),
                     record.ranged(ratios, digits=2)])
    table = {"id": "security_overhead", "columns": ["path", "open", "tokens + TLS", "tokens + TLS / open"], "rows": rows,
             "note": f"Medians of {args.rounds} alternating rounds (their range), one worker per server."}
    for row in rows:
        print(record.plain(row))
    record.write("security_overhead", [table], {"rounds": args.rounds, "steps": args.steps, "batches": args.batches})


if __name__ == "__main__":
    main()
