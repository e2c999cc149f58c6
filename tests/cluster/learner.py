"""The learner side of the container tests (tests/cluster/test_cluster.py), run in the learner image.

It reads one command per line on stdin and answers each with one JSON line on stdout, so that the
test on the host can stop and start server containers between steps and check what a learner sees.
"""

import json
import sys
import threading
import time
import traceback
import warnings

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

import radserve

ENV, OPTIONS = "dmc/cartpole-balance", {"pixels": True, "height": 64, "width": 64, "frame_stack": 3,
                                        "render_profile": "fast"}


class Learner:
    def __init__(self, addresses: str):
        self.addresses = addresses.split(",")
        self.strict = self.lenient = self.stream = None
        self.warnings: "list[str]" = []
        self.drain: dict = {}

    def open(self) -> dict:
        """One sharded session per loss policy, envs on every server; sharded batches."""
        self.strict = radserve.Client(self.addresses)
        self.lenient = radserve.Client(self.addresses, on_server_loss="continue", reconnect_backoff=0.5,
                                       reconnect_backoff_max=2.0)
        self.strict_envs = self.strict.make_vec("gym/CartPole-v1", num_envs=6, seed=0, autoreset_mode="SameStep")
        self.strict_envs.reset(seed=0)
        self.envs = self.lenient.make_vec(ENV, num_envs=6, seed=0, autoreset_mode="SameStep",
                                          replay_capacity=3000, delivery="auto", name="cluster-sac", **OPTIONS)
        self.envs.reset(seed=0)
        for _ in range(20):
            self._step()
        self.stream = self.envs.sample_batches(32, augment="crop(56)", min_size=32,
                                                  delivery="auto")
        batches = [next(self.stream) for _ in range(3)]
        return {"servers": self.envs.servers, "sizes": [shard.size for shard in self.envs.shards],
                "delivery": self.envs.delivery, "shares": list(self.stream.shares.values()),
                "batch_sizes": [len(b) for b in batches], "obs_shape": list(batches[0].obs.shape),
                "batch_servers": [np.bincount(b.server, minlength=3).tolist() for b in batches]}

    def _step(self):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = self.envs.step(self.envs.action_space.sample())
        self.warnings += [str(w.message) for w in caught]
        return result

    def step_strict(self) -> dict:
        try:
            self.strict_envs.step(np.zeros(6, dtype=np.int64))
        except radserve.RadServeError as error:
            return {"error": type(error).__name__, "server": error.server, "message": str(error)}
        return {"error": None}

    def step_lenient(self, steps: str = "5") -> dict:
        truncated_lost, inactive = [], []
        for _ in range(int(steps)):
            _, _, _, truncated, infos = self._step()
            if "radserve_server_lost" in infos:
                truncated_lost = (truncated & infos["radserve_server_lost"]).tolist()
            inactive = infos.get("radserve_inactive", np.zeros(6, dtype=bool)).tolist()
        batch = next(self.stream)
        return {"active": self.envs.active.tolist(), "truncated_lost": truncated_lost, "inactive": inactive,
                "batch_size": len(batch), "batch_servers": sorted(set(batch.server.tolist())),
                "warnings": self.warnings[-3:]}

    def wait_snapshot(self, shard: str, timeout: str = "60") -> dict:
        """Waits (not stepping) until shard's server has a snapshot of everything recorded so far."""
        deadline = time.monotonic() + float(timeout)
        while time.monotonic() < deadline:
            replay = self.envs.shards[int(shard)].env.describe()[0].replay
            if replay.snapshot.age_seconds is not None and replay.snapshot.pending_frames == 0:
                return {"size": replay.size, "disk_bytes": replay.snapshot.disk_bytes}
            time.sleep(0.2)
        raise TimeoutError(f"no snapshot of shard {shard} within {timeout} s")

    def until_active(self, timeout: str = "180") -> dict:
        deadline = time.monotonic() + float(timeout)
        steps = 0
        while not self.envs.active.all() and time.monotonic() < deadline:
            self._step()
            steps += 1
            time.sleep(0.05)
        restored = [info.replay.snapshot.restored_transitions for info in self.envs.describe()]
        # The returned server's replay is restored: it takes its share again without refilling.
        seen: "set[int]" = set()
        while seen != {0, 1, 2} and time.monotonic() < deadline:
            self._step()
            seen = set(next(self.stream).server.tolist())
        return {"active": self.envs.active.tolist(), "steps": steps, "batch_servers": sorted(seen),
                "restored": restored, "warnings": self.warnings[-3:]}

    def watch_drain(self, server: str) -> dict:
        """While the host stops `server`: its health status over time (another thread), and the
        sharded session acting and sampling on (on_server_loss="continue") until it sees the
        server leave, with the message it saw."""
        self.drain = {"statuses": [], "loss": None, "batch_sizes": set()}
        channel = grpc.insecure_channel(server)
        health = health_pb2_grpc.HealthStub(channel)

        def poll():
            start = time.monotonic()
            while time.monotonic() - start < 60:
                try:
                    status = health.Check(health_pb2.HealthCheckRequest(), timeout=1).status
                    name = health_pb2.HealthCheckResponse.ServingStatus.Name(status)
                except grpc.RpcError as error:
                    name = f"error:{error.code().name}"
                entry = (round(time.monotonic() - start, 2), name)
                if not self.drain["statuses"] or self.drain["statuses"][-1][1] != name:
                    self.drain["statuses"].append(entry)
                if name.startswith("error"):
                    return
                time.sleep(0.1)

        def act():
            start, seen = time.monotonic(), len(self.warnings)
            try:
                while time.monotonic() - start < 60:
                    self._step()
                    with warnings.catch_warnings(record=True) as caught:  # the stream may see the loss first
                        warnings.simplefilter("always")
                        self.drain["batch_sizes"].add(len(next(self.stream)))
                    self.warnings += [str(w.message) for w in caught]
                    lost = [w for w in self.warnings[seen:] if f"server {server} lost" in w]
                    if lost:
                        self.drain["loss"] = lost[0]
                        return
            except Exception:  # reported to the host
                self.drain["error"] = traceback.format_exc()

        self.threads = [threading.Thread(target=poll, daemon=True), threading.Thread(target=act, daemon=True)]
        for thread in self.threads:
            thread.start()
        return {"watching": server}

    def drain_report(self) -> dict:
        for thread in self.threads:
            thread.join(60)
        return {**self.drain, "batch_sizes": sorted(self.drain["batch_sizes"])}

    def families(self) -> dict:
        """A session of each simulator family the server image serves, reset and stepped: the
        observation shape of each, or the error."""
        client = radserve.Client(self.addresses)
        shapes = {}
        for env_id, options in (("dmc/cartpole-balance", OPTIONS), ("gym/HalfCheetah-v5", {}), ("procgen/bigfish", {})):
            try:
                envs = client.make_vec(env_id, num_envs=2, seed=0, autoreset_mode="SameStep", **options)
                envs.reset(seed=0)
                for _ in range(3):
                    obs, *_ = envs.step(envs.action_space.sample())
                envs.close()
                shapes[env_id] = list(obs.shape)
            except radserve.RadServeError as error:
                shapes[env_id] = str(error)
        client.close()
        return shapes

    def same_host(self) -> dict:
        """In a server's network namespace: shared stepping and batches."""
        client = radserve.Client("127.0.0.1:50051")
        envs = client.make_vec(ENV, num_envs=2, seed=0, autoreset_mode="SameStep",
                               replay_capacity=500, delivery="shared_memory", **OPTIONS)
        envs.reset(seed=0)
        for _ in range(20):
            envs.step(envs.action_space.sample())
        with envs.sample_batches(16, augment="crop(56)", delivery="shared_memory") as stream:
            batch = next(stream)
            kind = type(stream).__name__
        envs.close()
        return {"acting": envs.delivery, "batches": kind, "obs_shape": list(batch.obs.shape)}


def main() -> None:
    learner = Learner(sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1:50051")
    for line in sys.stdin:
        command, *args = line.split()
        if command == "quit":
            break
        try:
            answer = getattr(learner, command)(*args)
        except Exception as error:  # the host test reports it
            answer = {"exception": f"{type(error).__name__}: {error}", "traceback": traceback.format_exc()}
        print(json.dumps(answer), flush=True)


if __name__ == "__main__":
    main()
