"""Models from a hostile tenant (issue 53, docs/security.md "Policies"): a real server, real
simulators, models built with onnx.helper (tests/policies.py).

The server never loads a model itself: each policy runs in a `radserve policy-runtime` process that
can open no file and whose data memory is limited to `acting.policy_memory_bytes`, which the
session's owner is charged for. What the tests below measure is the server's own process tree
(the server, its simulator workers and its policy runtimes), sampled while each probe runs.
"""

import os
import threading
import time

import numpy as np
import pytest

import radserve
from radserve import FailedPreconditionError, InvalidArgumentError, ResourceExhaustedError

import policies

MIB = 1 << 20
POLICY_MEMORY = 256 * MIB


def _children(pid):
    """Every descendant of `pid`."""
    parents = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as stat:
                    parents[int(entry)] = int(stat.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    found, frontier = [], [pid]
    while frontier:
        current = frontier.pop()
        for child, parent in parents.items():
            if parent == current:
                found.append(child)
                frontier.append(child)
    return found


def _rss(pid):
    try:
        with open(f"/proc/{pid}/status") as status:
            return next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmRSS:"))
    except (OSError, StopIteration):
        return 0


def _runtimes(pid):
    """The server's policy runtime processes."""
    found = []
    for child in _children(pid):
        try:
            with open(f"/proc/{child}/cmdline", "rb") as cmdline:
                if b"policy-runtime" in cmdline.read():
                    found.append(child)
        except OSError:
            continue
    return found


class TreePeak:
    """The peak RSS of the server with its workers and policy runtimes, sampled every 10 ms."""

    def __init__(self, pid):
        self.pid, self.peak, self.runtime_peak = pid, 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self):
        while not self._stop.is_set():
            runtimes = _runtimes(self.pid)
            self.runtime_peak = max(self.runtime_peak, sum(_rss(pid) for pid in runtimes))
            self.peak = max(self.peak, _rss(self.pid) + sum(_rss(pid) for pid in _children(self.pid)))
            time.sleep(0.01)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


@pytest.fixture
def hostile_server(tmp_path, monkeypatch):
    """A server started in a directory holding creds.txt (LocalServer runs in the learner's
    working directory), with 256 MiB per policy and a 1 GiB budget."""
    secret = np.array([1e6, 2e6, 3e6, 4e6], dtype=np.float32).tobytes()
    (tmp_path / "creds.txt").write_bytes(secret)
    monkeypatch.chdir(tmp_path)
    server = radserve.LocalServer(workers=1, env={
        "RADSERVE__ACTING__POLICY_MEMORY_BYTES": str(POLICY_MEMORY),
        "RADSERVE__LIMITS__MEMORY_BYTES": str(1 << 30),
    })
    server.start()
    try:
        yield server
    finally:
        server.stop()


def _cartpole(client, **kwargs):
    return client.make_vec("gym/CartPole-v1", num_envs=2, seed=0, **kwargs)


def test_a_model_cannot_read_the_servers_files(hostile_server):
    """A Constant whose sparse_value keeps its values in external data named relative to the
    server's working directory (where creds.txt is): refused at SetPolicy, naming the node and
    attribute; a name that exists and one that does not give the same answer (nothing is opened,
    so nothing can be probed). The runtime's own containment, for a check that would miss it, is
    server/policy/tests/load.rs::a_model_cannot_read_a_file_even_past_the_checks."""
    with radserve.Client(hostile_server.address) as client:
        envs = _cartpole(client, rollout_steps=16)
        answers = []
        for location in ("creds.txt", "no-such-file.txt"):
            with pytest.raises(InvalidArgumentError, match="attribute 'sparse_value'") as refused:
                envs.set_policy(policies.sparse_exfiltration((4,), 2, location=location), head="categorical")
            answers.append(str(refused.value))
        assert answers[0] == answers[1]
        assert envs.acting()[0] is None, "nothing was set"


def test_memory_bombs_are_refused_or_fail_their_actor_within_the_charged_memory(hostile_server):
    """Issue 53's allocation probes, a few hundred bytes each: refused at SetPolicy (constant
    folding past the limit) or failing the actor at its first real frame (a Pad sized from the
    observations), while the server's process tree stays within its baseline plus the policy's
    charged memory and ONNX Runtime's shared library; the server serves on."""
    pid = hostile_server.process.pid
    with radserve.Client(hostile_server.address) as client:
        envs = _cartpole(client, rollout_steps=64)
        envs.reset(seed=0)
        time.sleep(0.5)
        baseline = _rss(pid) + sum(_rss(child) for child in _children(pid))
        with TreePeak(pid) as peak:
            for kind in ("concat", "broadcast"):
                with pytest.raises(ResourceExhaustedError, match=f"{POLICY_MEMORY} bytes a policy may use"):
                    envs.set_policy(policies.memory_bomb((4,), 2, kind), head="categorical")
            # CartPole's observations are ~0.05: 2^34 columns per unit is gigabytes per env.
            envs.set_policy(policies.memory_bomb((4,), 2, "pad", pad_scale=float(1 << 34)), head="categorical")
            envs.start_acting()
            deadline = time.monotonic() + 60
            while (info := envs.acting()[0]).state == "acting":
                assert time.monotonic() < deadline, info
                time.sleep(0.05)
        assert info.state == "failed" and str(POLICY_MEMORY) in info.error, info
        # Its runtime was stopped: the policy is gone (its charge returned), not set again.
        with pytest.raises(FailedPreconditionError, match="SetPolicy before StartActing"):
            envs.start_acting()
        # The runtime's own memory: its data limit plus ONNX Runtime's library text (~25 MiB).
        assert peak.runtime_peak < POLICY_MEMORY + 64 * MIB, (peak.runtime_peak, POLICY_MEMORY)
        assert peak.peak < baseline + POLICY_MEMORY + 128 * MIB, (peak.peak, baseline)
        # The session is the learner's again, and the server serves on.
        envs.reset(seed=1)
        envs.step(np.zeros(2, dtype=np.int64))
        with pytest.raises(InvalidArgumentError, match="at most 10000"):
            envs.set_policy(policies.many_nodes((4,), 2, 10_001), head="categorical")


def test_policies_are_charged_to_the_owners_budget(hostile_server):
    """Each policy held is charged its runtime's memory and the model's bytes: under a 1 GiB budget
    and 256 MiB a policy, the fourth is refused with the numbers, a replay that would have fit
    before is refused while they are held, and closing their sessions gives the memory back."""
    with radserve.Client(hostile_server.address) as client:
        held = []
        for _ in range(3):
            envs = _cartpole(client)
            envs.set_policy(policies.linear_categorical(np.eye(4, 2)), head="categorical")
            held.append(envs)
        fourth = _cartpole(client)
        with pytest.raises(ResourceExhaustedError, match="a policy") as refused:
            fourth.set_policy(policies.linear_categorical(np.eye(4, 2)), head="categorical")
        assert "limits.memory_bytes" in str(refused.value) or "budget" in str(refused.value), refused.value
        # A replay of 9.4M CartPole transitions (540 MB with its metadata and envs): within the budget alone,
        # past it beside three policies.
        with pytest.raises(ResourceExhaustedError):
            _cartpole(client, replay_capacity=9_400_000)
        for envs in held:
            envs.close()
        big = _cartpole(client, replay_capacity=9_400_000)
        fourth.set_policy(policies.linear_categorical(np.eye(4, 2)), head="categorical")
        big.close()
        fourth.close()


def test_random_models_are_refused_or_act_within_the_charged_memory(hostile_server):
    """The property test over a grammar of the allowed operators (policies.random_policy): each
    model, small or needing gigabytes, is refused at SetPolicy, acts, or fails its actor, and
    whatever it does, no policy runtime passes its charged memory (plus ONNX Runtime's library
    text) and the server's process tree stays within its baseline plus one policy's charge."""
    pid = hostile_server.process.pid
    outcomes = {}
    with radserve.Client(hostile_server.address) as client:
        envs = _cartpole(client)
        envs.reset(seed=0)
        time.sleep(0.5)
        baseline = _rss(pid) + sum(_rss(child) for child in _children(pid))
        with TreePeak(pid) as peak:
            for seed in range(24):
                model = policies.random_policy(seed, 4, 2)
                try:
                    envs.set_policy(model, head="categorical")
                except (InvalidArgumentError, ResourceExhaustedError) as refused:
                    outcomes[seed] = type(refused).__name__
                    continue
                envs.start_acting(max_env_steps=20)
                deadline = time.monotonic() + 60
                while (info := envs.acting()[0]).state == "acting":
                    assert time.monotonic() < deadline, (seed, info)
                    time.sleep(0.02)
                outcomes[seed] = info.state
                assert info.state in ("stopped", "failed"), (seed, info)
                if info.state == "stopped":
                    assert info.env_steps == 20, (seed, info)
        assert peak.runtime_peak < 2 * POLICY_MEMORY + 64 * MIB, (peak.runtime_peak, outcomes)
        assert peak.peak < baseline + 2 * POLICY_MEMORY + 128 * MIB, (peak.peak, baseline, outcomes)
        # The grammar reaches both sides of the limit.
        assert "stopped" in outcomes.values() and "ResourceExhaustedError" in outcomes.values(), outcomes
        envs.reset(seed=0)
