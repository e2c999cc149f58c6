"""The Prometheus endpoint of a real server (metrics.address), scraped over HTTP while a session acts
and parsed by Prometheus' own parser (prometheus_client's OpenMetrics parser). Each metric's
meaning over the fake simulators (counters, gauges, the histogram, the endpoint's other paths):
server/radserve/tests/metrics.rs."""

import socket
import urllib.error
import urllib.request

import numpy as np
import pytest
from prometheus_client.openmetrics.parser import text_string_to_metric_families

import radserve


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def scrape(port: int) -> dict:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as answer:
        assert answer.headers["Content-Type"].startswith("application/openmetrics-text")
        text = answer.read().decode()
    return {family.name: family for family in text_string_to_metric_families(text)}


def value(families: dict, name: str, suffix: str = "", **labels) -> float:
    (sample,) = [s for s in families[name].samples if s.name == name + suffix and s.labels == labels]
    return sample.value


def test_a_real_server_exposes_what_its_sessions_do():
    port = free_port()
    with radserve.LocalServer(workers=2, env={"RADSERVE__METRICS__ADDRESS": f"127.0.0.1:{port}"}) as server, \
            radserve.Client(server.address) as client:
        families = scrape(port)
        assert families["radserve_env_steps"].type == "counter"
        assert families["radserve_step_seconds"].type == "histogram"
        assert value(families, "radserve_workers") == 2
        assert families["radserve_build"].type == "info"
        assert value(families, "radserve_build", "_info", version=radserve.__version__, api="radserve.v1") == 1
        baseline = value(families, "radserve_env_steps", "_total", family="gym")

        envs = client.make_vec("gym/CartPole-v1", num_envs=4, seed=0, replay_capacity=1000, autoreset_mode="SameStep")
        envs.reset(seed=0)
        for _ in range(25):
            envs.step(np.zeros(4, np.int64))
        stream = envs.sample_batches(8, max_batches=3)
        assert len(list(stream)) == 3

        families = scrape(port)
        assert value(families, "radserve_env_steps", "_total", family="gym") - baseline == 100
        assert value(families, "radserve_envs", family="gym") == 4
        assert value(families, "radserve_sessions") == 1
        assert value(families, "radserve_batches", "_total") == 3
        assert value(families, "radserve_replay_transitions") == 100
        assert value(families, "radserve_step_seconds", "_count") == 25
        assert value(families, "radserve_step_seconds", "_bucket", le="+Inf") == 25
        assert value(families, "radserve_worker_restarts", "_total") == 0
        assert value(families, "radserve_episodes", "_total") > 0  # CartPole falls within 25 steps of action 0
        envs.close()
        assert value(scrape(port), "radserve_sessions") == 0

        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10)
        assert refused.value.code == 404
