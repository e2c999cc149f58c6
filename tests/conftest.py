"""End-to-end fixtures: the real radserve binary on a free localhost port, real simulators."""

import os

import pytest

import radserve

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="session")
def server():
    with radserve.LocalServer(workers=2) as running:
        yield running


@pytest.fixture(scope="session")
def client(server):
    with radserve.Client(server.address) as connected:
        yield connected


@pytest.fixture(scope="session")
def catalog(client):
    return {env.id: env for env in client.list_envs()}
