"""Named sessions whose replay survives the server: real servers killed with SIGKILL and started
again over the same snapshot directory, real simulators.

A named session's replay is written to `[replay] snapshot_dir` in the background; after a kill, the
same name (same owner, env, num_envs, options, capacity) restores it before the first step, and a
sharded learner that survives the loss (`on_server_loss="continue"`) gets the server's share of its
batches back from the restored replay, without ever stopping.
"""

import os
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
        if replay.snapshot.age_seconds is not None and replay.snapshot.pending_frames == 0:
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
            assert envs.info.replay.snapshot == radserve.SnapshotInfo(restored_transitions=0, disk_bytes=0,
                                                                       age_seconds=None, pending_frames=0)
            with pytest.raises(radserve.AlreadyExistsError, match="cartpole-sac"):
                client.make_vec(ENV, num_envs=4, seed=3, replay_capacity=2000, name="cartpole-sac")
            envs.reset(seed=3)
            _steps(envs, 150)
            saved = _snapshot_of_everything(client, envs.session_id)
            assert saved.size == 600 and saved.snapshot.disk_bytes > 0
            with envs.sample_batches(32) as stream:
                before = next(stream)
        _kill(server)

        server = _server(tmp_path)
        with radserve.Client(server.address) as client:
            envs = client.make_vec(ENV, num_envs=4, seed=3, replay_capacity=2000, name="cartpole-sac",
                                   autoreset_mode="SameStep")
            replay = envs.info.replay
            assert replay.size == saved.size, "the replay is back before the first step"
            assert replay.snapshot.restored_transitions == saved.size
            assert envs.info.total_env_steps == 600
            # Batches come at once, from the transitions recorded before the kill.
            with envs.sample_batches(32, seed=1) as stream:
                batch = next(stream)
            assert batch.obs.shape == before.obs.shape and batch.step_index.max() < 150
            envs.reset(seed=3)
            _steps(envs, 20)
            assert client.describe_session(envs.session_id).replay.size == saved.size + 80
            envs.close()
            # Another session under the same name (other num_envs): the snapshot is set aside, the
            # session starts empty, and the old files stay beside it.
            other = client.make_vec(ENV, num_envs=2, seed=3, replay_capacity=2000, name="cartpole-sac")
            assert other.info.replay.size == 0
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
        stream = envs.sample_batches(24, min_size=24)
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
        assert replay.snapshot.restored_transitions >= saved.size > 0
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
            assert value(families, "radserve_snapshot_bytes", "_total") >= saved.snapshot.disk_bytes > 0
            assert value(families, "radserve_snapshot_disk_bytes") == saved.snapshot.disk_bytes
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
            assert client.describe_session(envs.session_id).replay.snapshot.disk_bytes == saved.snapshot.disk_bytes
            directory.unlink()
            kept.rename(directory)
            latest = _snapshot_of_everything(client, envs.session_id)
            assert latest.size == saved.size + 50
        _kill(server)
        server = _server(tmp_path)
        with radserve.Client(server.address) as client:
            envs = client.make_vec(ENV, num_envs=2, seed=0, replay_capacity=1000, name="metered",
                                   autoreset_mode="SameStep")
            assert envs.info.replay.snapshot.restored_transitions == latest.size
    finally:
        server.stop()


def _vm_hwm_bytes(pid):
    """The peak resident memory of process `pid` (VmHWM)."""
    with open(f"/proc/{pid}/status") as status:
        line = next(line for line in status if line.startswith("VmHWM:"))
    return int(line.split()[1]) * 1024


def _named(client, name="hostile"):
    return client.make_vec(ENV, num_envs=2, seed=1, replay_capacity=500, name=name, autoreset_mode="SameStep")


def test_a_hostile_snapshot_directory_is_never_followed_and_shutdown_finishes(tmp_path):
    """What a tenant with write access under snapshot_dir could plant (docs/security.md): a MANIFEST
    linked to /proc/self/pagemap (claims 0 bytes, reads without end), a FIFO in place of a segment
    (opening it waits for a writer for ever), a session directory that is a link to another
    directory, and links at the names the next writes use. Each is refused or replaced at once, the
    server's memory stays put, nothing outside the directory is read, written or removed, and a
    SIGTERM with a FIFO planted ends the server within its drain time."""
    snapshots = tmp_path / "snapshots"
    outside = tmp_path / "outside"
    outside.mkdir()
    victim = outside / "victim"
    victim.write_bytes(b"precious")
    server = _server(snapshots, RADSERVE__SERVER__DRAIN_TIMEOUT_S="5")
    try:
        with radserve.Client(server.address) as client:
            envs = _named(client)
            envs.reset(seed=1)
            _steps(envs, 60)
            saved = _snapshot_of_everything(client, envs.session_id)
        _kill(server)
        directory = next(snapshots.iterdir()) / "hostile"
        assert (directory / "seg-00000001.rsnap").is_file()

        # The session directory a link to a copy elsewhere (with a stray the restore would delete).
        elsewhere = outside / "elsewhere"
        directory.rename(elsewhere)
        directory.symlink_to(elsewhere)
        (elsewhere / "MANIFEST.tmp").write_bytes(b"not the server's")
        (elsewhere / "seg-00000099.rsnap").write_bytes(b"not the server's either")
        before = sorted((path.name, path.read_bytes()) for path in elsewhere.iterdir())
        server = _server(snapshots, RADSERVE__SERVER__DRAIN_TIMEOUT_S="5")
        with radserve.Client(server.address) as client:
            envs = _named(client)
            assert envs.info.replay.size == 0, "a linked directory is set aside, never restored from"
            assert sorted((path.name, path.read_bytes()) for path in elsewhere.iterdir()) == before
            assert any(path.is_symlink() and path.name.startswith("hostile.rejected-") for path in directory.parent.iterdir())
            envs.reset(seed=1)
            _steps(envs, 10)
            _snapshot_of_everything(client, envs.session_id)
            assert directory.is_dir() and not directory.is_symlink(), "a directory of its own in the link's place"
            # Links at the names of the next segment and of the manifest's temporary file.
            sequences = sorted(int(path.name[4:12]) for path in directory.glob("seg-*.rsnap"))
            (directory / f"seg-{sequences[-1] + 1:08d}.rsnap").symlink_to(victim)
            (directory / "MANIFEST.tmp").symlink_to(victim)
            _steps(envs, 10)
            _snapshot_of_everything(client, envs.session_id)
            assert victim.read_bytes() == b"precious"
            assert not [path for path in directory.iterdir() if path.is_symlink()]
        _kill(server)

        # The manifest a link to /proc/self/pagemap, then a FIFO in place of a segment.
        manifest = directory / "MANIFEST"
        good = manifest.read_bytes()
        manifest.unlink()
        manifest.symlink_to("/proc/self/pagemap")
        server = _server(snapshots, RADSERVE__SERVER__DRAIN_TIMEOUT_S="5")
        with radserve.Client(server.address) as client:
            started = time.monotonic()
            envs = _named(client)
            assert envs.info.replay.size == 0 and time.monotonic() - started < 10
            assert _vm_hwm_bytes(server.process.pid) < 1 << 30, "the server read the link"
            envs.close()
        _kill(server)
        aside = next(path for path in directory.parent.iterdir() if path.name.startswith("hostile.rejected-") and path.is_dir())
        aside.rename(directory.with_name("restored"))
        restored = directory.with_name("restored")
        for leftover in directory.iterdir():
            leftover.unlink()
        directory.rmdir()
        restored.rename(directory)
        (directory / "MANIFEST").unlink()
        (directory / "MANIFEST").write_bytes(good)
        segment = sorted(directory.glob("seg-*.rsnap"))[0]
        segment.unlink()
        os.mkfifo(segment)
        server = _server(snapshots, RADSERVE__SERVER__DRAIN_TIMEOUT_S="5")
        with radserve.Client(server.address) as client:
            started = time.monotonic()
            envs = _named(client)
            assert envs.info.replay.size == 0 and time.monotonic() - started < 10, "a FIFO is refused at once"
            envs.reset(seed=1)
            _steps(envs, 5)
            _snapshot_of_everything(client, envs.session_id)
            # A FIFO planted where the next snapshot writes (the final one, at SIGTERM, or the
            # periodic one before it): SIGTERM still ends the server in time.
            sequences = sorted(int(path.name[4:12]) for path in directory.glob("seg-*.rsnap"))
            fifo = directory / f"seg-{sequences[-1] + 1:08d}.rsnap"
            os.mkfifo(fifo)
            _steps(envs, 5)
        started = time.monotonic()
        server.process.send_signal(signal.SIGTERM)
        assert server.process.wait(timeout=15) == 0
        assert time.monotonic() - started < 8, "shutdown outlived its drain time"
        assert fifo.is_file() and not fifo.is_fifo(), "the FIFO was replaced by the segment"
        assert saved.size > 0
    finally:
        server.stop()
