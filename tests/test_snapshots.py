"""Named sessions whose replay survives the server: real servers killed with SIGKILL and started
again over the same snapshot directory, real simulators.

A named session's replay is written to `[replay] snapshot_dir` in the background; after a kill, the
same name (same owner, env, num_envs, options, capacity) restores it before the first step, and a
sharded learner that survives the loss (`on_server_loss="continue"`) gets the server's share of its
batches back from the restored replay, without ever stopping.
"""

import signal
import time
import warnings

import numpy as np
import pytest

import radserve
from test_metrics import free_port, scrape, value

ENV = "gym/CartPole-v1"


def _server(directory, interval="0.3", address="127.0.0.1:0", **settings):
    env = {"RADSERVE__REPLAY__SNAPSHOT_DIR": str(directory), "RADSERVE__REPLAY__SNAPSHOT_INTERVAL_S": interval,
           **settings}
    server = radserve.LocalServer(workers=1, env=env, address=address)
    server.start()
    return server


def _kill(server):
    server.process.send_signal(signal.SIGKILL)
    server.process.wait()


def _snapshot_of_everything(client, session_id, timeout=20.0):
    """The session's replay once a snapshot on disk holds everything it recorded."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        replay = client.describe_session(session_id).replay
        if replay["snapshot"]["age_seconds"] is not None and replay["snapshot"]["pending_frames"] == 0:
            return replay
        time.sleep(0.1)
    raise AssertionError(f"no snapshot of everything {session_id} recorded within {timeout} s: {replay}")


def _steps(envs, count, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(count):
        envs.step(rng.integers(0, 2, size=envs.num_envs))


def test_a_named_replay_survives_sigkill_and_restart(tmp_path):
    server = _server(tmp_path)
    try:
        with radserve.Client(server.address) as client:
            envs = client.make_vec(ENV, num_envs=4, seed=3, replay_capacity=2000, name="cartpole-sac",
                                   autoreset_mode="SameStep")
            assert envs.info.name == "cartpole-sac"
            assert envs.info.replay["snapshot"] == {"restored_transitions": 0, "disk_bytes": 0, "age_seconds": None,
                                                    "pending_frames": 0}
            with pytest.raises(radserve.AlreadyExistsError, match="cartpole-sac"):
                client.make_vec(ENV, num_envs=4, seed=3, replay_capacity=2000, name="cartpole-sac")
            envs.reset(seed=3)
            _steps(envs, 150)
            saved = _snapshot_of_everything(client, envs.session_id)
            assert saved["size"] == 600 and saved["snapshot"]["disk_bytes"] > 0
            with client.sample_batches(envs.session_id, 32) as stream:
                before = next(stream)
        _kill(server)

        server = _server(tmp_path)
        with radserve.Client(server.address) as client:
            envs = client.make_vec(ENV, num_envs=4, seed=3, replay_capacity=2000, name="cartpole-sac",
                                   autoreset_mode="SameStep")
            replay = envs.info.replay
            assert replay["size"] == saved["size"], "the replay is back before the first step"
            assert replay["snapshot"]["restored_transitions"] == saved["size"]
            assert envs.info.total_env_steps == 600
            # Batches come at once, from the transitions recorded before the kill.
            with client.sample_batches(envs.session_id, 32, seed=1) as stream:
                batch = next(stream)
            assert batch.obs.shape == before.obs.shape and batch.step_index.max() < 150
            envs.reset(seed=3)
            _steps(envs, 20)
            assert client.describe_session(envs.session_id).replay["size"] == saved["size"] + 80
            envs.close()
            # Another session under the same name (other num_envs): the snapshot is set aside, the
            # session starts empty, and the old files stay beside it.
            other = client.make_vec(ENV, num_envs=2, seed=3, replay_capacity=2000, name="cartpole-sac")
            assert other.info.replay["size"] == 0
            _snapshot_of_everything(client, other.session_id)
            owner = next(path for path in tmp_path.iterdir())
            names = sorted(path.name for path in owner.iterdir())
            assert names[0] == "cartpole-sac" and names[1].startswith("cartpole-sac.rejected-"), names
            # Discarded at close: the session's snapshot is gone, the rejected one stays.
            other.close(discard_snapshot=True)
            assert sorted(path.name for path in owner.iterdir()) == names[1:]
    finally:
        server.stop()


def test_a_sharded_learner_gets_a_killed_servers_replay_back(tmp_path):
    """Three servers, one killed mid-run and started again on its address over its directory: the
    learner steps and samples throughout, and once the server is back its session's replay holds
    at least what its last snapshot held, and batches include its share again."""
    servers = [_server(tmp_path / str(index)) for index in range(3)]
    addresses = [server.address for server in servers]
    try:
        client = radserve.Client(addresses, on_server_loss="continue", reconnect_backoff=0.2, reconnect_backoff_max=0.5)
        envs = client.make_vec(ENV, num_envs=6, seed=0, replay_capacity=1200, name="sharded-sac",
                               autoreset_mode="SameStep")
        envs.reset(seed=0)
        _steps(envs, 60)
        victim = servers[1]
        with radserve.Client(victim.address) as direct:
            saved = _snapshot_of_everything(direct, envs.shards[1].env.session_id)
        stream = client.sample_batches(envs.session_id, 24, min_size=24)
        assert set(next(stream).server.tolist()) == {0, 1, 2}
        _kill(victim)

        steps = 0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            _steps(envs, 5)
            assert not envs.active.all()
            assert len(next(stream)) == 24, "sampling goes on over the two servers left"
            victim.args[victim.args.index("--address") + 1] = victim.address
            victim.start()
            deadline = time.monotonic() + 60
            while not envs.active.all() and time.monotonic() < deadline:
                _steps(envs, 1)
                steps += 1
        assert envs.active.all(), "the restarted server was not reconnected"
        with radserve.Client(victim.address) as direct:
            replay = direct.describe_session(envs.shards[1].env.session_id).replay
        assert replay["snapshot"]["restored_transitions"] >= saved["size"] > 0
        # Its share comes from the restored replay: no need to refill it first.
        seen: set = set()
        deadline = time.monotonic() + 20
        while seen != {0, 1, 2} and time.monotonic() < deadline:
            _steps(envs, 1)
            batch = next(stream)
            assert len(batch) == 24
            seen = set(batch.server.tolist())
            time.sleep(0.1)
        assert seen == {0, 1, 2}
        stream.close()
        envs.close()
        client.close()
    finally:
        for server in servers:
            server.stop()


def test_a_failed_snapshot_is_a_warning_and_a_metric_and_the_previous_one_stays(tmp_path):
    """The session's directory replaced by a file (the writes fail, as on a full or broken disk):
    the failures are counted, acting goes on, the last good snapshot is untouched, and the next
    snapshot once the directory is back holds everything."""
    port = free_port()
    server = _server(tmp_path, RADSERVE__METRICS__ADDRESS=f"127.0.0.1:{port}")
    try:
        with radserve.Client(server.address) as client:
            envs = client.make_vec(ENV, num_envs=2, seed=0, replay_capacity=1000, name="metered",
                                   autoreset_mode="SameStep")
            envs.reset(seed=0)
            _steps(envs, 50)
            saved = _snapshot_of_everything(client, envs.session_id)
            families = scrape(port)
            assert value(families, "radserve_snapshots", "_total") >= 1
            assert value(families, "radserve_snapshot_bytes", "_total") >= saved["snapshot"]["disk_bytes"] > 0
            assert value(families, "radserve_snapshot_disk_bytes") == saved["snapshot"]["disk_bytes"]
            assert value(families, "radserve_snapshot_failures", "_total") == 0
            assert value(families, "radserve_snapshot_age_seconds") < 5

            directory = next(tmp_path.iterdir()) / "metered"
            kept = directory.with_name("kept")
            directory.rename(kept)
            directory.write_text("not a directory")
            _steps(envs, 20)
            deadline = time.monotonic() + 20
            while value(scrape(port), "radserve_snapshot_failures", "_total") == 0 and time.monotonic() < deadline:
                time.sleep(0.1)
            assert value(scrape(port), "radserve_snapshot_failures", "_total") >= 1
            _steps(envs, 5)  # the server keeps serving
            assert client.describe_session(envs.session_id).replay["snapshot"]["disk_bytes"] == saved["snapshot"]["disk_bytes"]
            directory.unlink()
            kept.rename(directory)
            latest = _snapshot_of_everything(client, envs.session_id)
            assert latest["size"] == saved["size"] + 50
        _kill(server)
        server = _server(tmp_path)
        with radserve.Client(server.address) as client:
            envs = client.make_vec(ENV, num_envs=2, seed=0, replay_capacity=1000, name="metered",
                                   autoreset_mode="SameStep")
            assert envs.info.replay["snapshot"]["restored_transitions"] == latest["size"]
    finally:
        server.stop()
