"""One learner, several servers: sharded sessions against three real servers on this host.

A sharded session must be indistinguishable from a single-server one of the same seed (env order,
seeds, observations bit for bit), its batches must have the requested size and say where each
transition came from, and the loss of a server must be either a clear error naming it or, when
asked for, something the session survives and recovers from.
"""

import signal
import time
import warnings

import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import radserve
from radserve.infos import merge_infos
from radserve.sharded import ShardedVectorEnv, apportion


@pytest.fixture(scope="module")
def servers():
    running = [radserve.LocalServer(workers=1) for _ in range(3)]
    try:
        for server in running:
            server.start()
        yield running
    finally:
        for server in running:
            server.stop()


@pytest.fixture(scope="module")
def sharded(servers):
    with radserve.Client([server.address for server in servers]) as client:
        yield client


def _run(envs, steps, seed):
    """Seeded random actions; everything the env returned."""
    rng = np.random.default_rng(seed)
    envs.action_space.seed(seed)
    obs, _ = envs.reset(seed=11)
    trace = [obs]
    for _ in range(steps):
        actions = envs.action_space.sample()
        obs, reward, terminated, truncated, infos = envs.step(actions)
        final = infos.get("final_obs")
        trace += [obs, reward, terminated, truncated]
        if final is not None:
            trace += [np.stack([row for row, present in zip(final, infos["_final_obs"]) if present])]
        if rng.random() < 0.1:  # a masked, unseeded reset now and then
            mask = rng.random(envs.num_envs) < 0.5
            if mask.any():
                obs, _ = envs.reset(options={"reset_mask": mask})
                trace.append(obs)
    return trace


def test_apportion_and_infos():
    assert apportion(7, [1, 1, 1]) == [3, 2, 2]
    assert apportion(32, [3, 2, 2]) == [14, 9, 9]
    assert apportion(2, [1, 1, 1]) == [1, 1, 0]
    assert sum(apportion(513, [5, 3, 9])) == 513
    merged = merge_infos([(0, 2, {"x": np.array([1, 2]), "_x": np.array([True, True])}),
                          (4, 1, {"x": np.array([5]), "_x": np.array([True]), "d": {"y": np.array([0.5])}})], 5)
    assert merged["x"].tolist() == [1, 2, 0, 0, 5]
    assert merged["_x"].tolist() == [True, True, False, False, True]
    assert merged["d"]["y"].tolist() == [0.0, 0.0, 0.0, 0.0, 0.5]


@pytest.mark.parametrize("env_id, options", [("gym/CartPole-v1", {}), ("dmc/cartpole-balance", {"pixels": False})])
def test_a_sharded_session_equals_a_single_server_one(servers, sharded, env_id, options):
    """Envs spread over three servers step the same episodes, bit for bit, as on one server."""
    with radserve.Client(servers[0].address) as single:
        reference = single.make_vec(env_id, num_envs=7, seed=3, **options)
        spread = sharded.make_vec(env_id, num_envs=7, seed=3, **options)
        try:
            assert isinstance(spread, ShardedVectorEnv)
            assert [shard.size for shard in spread.shards] == [3, 2, 2]
            assert spread.servers == [server.address for server in servers]
            assert spread.observation_space == reference.observation_space
            assert spread.action_space == reference.action_space
            expected, got = _run(reference, 120, seed=5), _run(spread, 120, seed=5)
            assert len(expected) == len(got)
            for a, b in zip(expected, got):
                np.testing.assert_array_equal(a, b)
            # Seeds per env (a list) land on the right servers too.
            seeds = [100 + 3 * i for i in range(7)]
            np.testing.assert_array_equal(reference.reset(seed=seeds)[0], spread.reset(seed=seeds)[0])
        finally:
            reference.close()
            spread.close()


def test_step_async_is_one_outstanding_step_per_server(sharded):
    envs = sharded.make_vec("gym/CartPole-v1", num_envs=6, seed=0)
    try:
        assert envs.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP  # gymnasium's default, as unsharded
        envs.reset(seed=0)
        envs.step_async(np.zeros(6, dtype=np.int64))
        with pytest.raises(RuntimeError):
            envs.step_async(np.zeros(6, dtype=np.int64))
        obs, reward, *_ = envs.step_wait()
        assert obs.shape == (6, 4) and reward.tolist() == [1.0] * 6
        with pytest.raises(radserve.InvalidArgumentError, match="one row per env"):
            envs.step(np.zeros(5, dtype=np.int64))
    finally:
        envs.close()
    # EnvPool's asynchronous mode is one server's: refused before any session is made.
    with pytest.raises(radserve.InvalidArgumentError, match="for a session on one server"):
        sharded.make_vec("gym/CartPole-v1", num_envs=6, engine="envpool", batch_size=2)


def test_sharded_batches_have_the_size_asked_for_and_say_where_they_came_from(sharded, servers):
    envs = sharded.make_vec("dmc/cartpole-balance", num_envs=7, seed=1, replay_capacity=700, frame_stack=3,
                            height=64, width=64, render_profile="fast")
    try:
        envs.reset(seed=1)
        for _ in range(12):
            envs.step(envs.action_space.sample())
        infos = envs.describe()
        assert [info.num_envs for info in infos] == [3, 2, 2]
        assert [info.replay.capacity for info in infos] == [300, 200, 200]
        with envs.sample_batches(32, augment="crop(56)", seed=4, max_batches=3) as stream:
            assert stream.shares == {servers[0].address: 14, servers[1].address: 9, servers[2].address: 9}
            batches = list(stream)
        assert len(batches) == 3
        for batch in batches:
            assert len(batch) == 32 and batch.obs.shape == (32, 9, 56, 56) and batch.next_obs.shape == (32, 9, 56, 56)
            assert np.bincount(batch.server, minlength=3).tolist() == [14, 9, 9]
            # env_index is the env's index in the whole session: each server's rows are its own envs.
            for server, rows in enumerate([range(0, 3), range(3, 5), range(5, 7)]):
                assert set(batch.env_index[batch.server == server].tolist()) <= set(rows)
        # Named views and n-step returns from every server, in the request's order.
        views = {"obs": "shift(4)", "obs_aug": "shift(4)", "next_obs": "none"}
        with envs.sample_batches(16, views=views, n_step=3, discount=0.99, seed=4, max_batches=2) as stream:
            for batch in stream:
                assert list(batch.views) == ["obs", "obs_aug", "next_obs"] and batch.obs is batch.views["obs"]
                assert batch.views["obs_aug"].shape == (16, 9, 64, 64) and batch.discount.shape == (16,)
                assert (batch.discount[~batch.terminated] > 0.97).all() and (batch.discount[batch.terminated] == 0).all()
                assert len(set(batch.server.tolist())) == 3
        # Prioritized: each server draws its share by its own priorities (all 1 before any update);
        # the batch's probability is per draw of the whole batch, each key goes back to its server.
        prioritized = dict(sampler="prioritized", priority_exponent=1.0, importance_sampling_exponent=1.0)
        with envs.sample_batches(16, seed=5, max_batches=1, **prioritized) as stream:
            batch = next(stream)
            sizes = np.array([info.replay.size for info in envs.describe()])
            assert (batch.table_size == sizes.sum()).all()
            shares = np.bincount(batch.server, minlength=3)
            np.testing.assert_allclose(batch.probability, shares[batch.server] / 16 / sizes[batch.server], rtol=1e-9)
            np.testing.assert_allclose(batch.weight, radserve.importance_weights(batch.probability, batch.table_size, 1.0),
                                       rtol=1e-6)
            assert stream.update_priorities(batch, np.full(16, 2.0)) == radserve.PriorityUpdate(updated=16, missing=0)
        # Sequences from every server: [batch, length] first, each sequence one env of one server.
        with envs.sample_batches(16, sequence=radserve.Sequence(8, burn_in=2), augment="crop(56)", seed=6,
                                 max_batches=1) as stream:
            batch = next(stream)
            assert batch.obs.shape == (16, 8, 9, 56, 56) and batch.mask.shape == (16, 8) and batch.mask.all()
            assert batch.server.shape == (16,) and len(set(batch.server.tolist())) == 3
            assert (batch.env_index == batch.env_index[:, :1]).all()
            for server, rows in enumerate([range(0, 3), range(3, 5), range(5, 7)]):
                assert set(batch.env_index[batch.server == server].ravel().tolist()) <= set(rows)
            # Consecutive steps of one env: each Step call's index follows the one before.
            assert (np.diff(batch.step_index, axis=1) == 1).all()
    finally:
        envs.close()
    # Closing the sharded session closes its session on every server.
    assert all(not any(s.env_id == "dmc/cartpole-balance" for s in sharded.list_sessions()) for _ in [0])


def test_a_lost_server_is_named_or_survived_and_comes_back(servers):
    """Kill one server: by default the step raises naming it; with on_server_loss="continue" the
    session goes on over the other two (its envs truncated, then inactive), sampling keeps its batch
    size, and when the server returns on its address a new session takes its envs again."""
    addresses = [server.address for server in servers]
    strict = radserve.Client(addresses)
    lenient = radserve.Client(addresses, on_server_loss="continue", reconnect_backoff=0.2, reconnect_backoff_max=0.5)
    first = strict.make_vec("gym/CartPole-v1", num_envs=6, seed=0)
    second = lenient.make_vec("gym/CartPole-v1", num_envs=6, seed=0, replay_capacity=600, autoreset_mode="SameStep")
    first.reset(seed=0)
    second.reset(seed=0)
    actions = np.zeros(6, dtype=np.int64)
    for _ in range(5):
        first.step(actions)
        second.step(actions)
    # A prioritized batch drawn before the loss: its keys name transitions of sessions as they are.
    prioritized = second.sample_batches(16, min_size=16, sampler="prioritized")
    before = next(prioritized)
    victims_rows = int((before.server == 1).sum())
    assert victims_rows > 0
    victim = servers[1]
    victim.process.send_signal(signal.SIGKILL)
    victim.process.wait()
    try:
        with pytest.raises(radserve.UnavailableError) as raised:
            first.step(actions)
        assert raised.value.server == victim.address and victim.address in str(raised.value)

        with pytest.warns(RuntimeWarning, match=f"server {victim.address} lost"):
            obs, reward, terminated, truncated, infos = second.step(actions)
        lost = np.array([False, False, True, True, False, False])
        assert truncated[lost].all() and (reward[lost] == 0).all()
        assert infos["radserve_server_lost"].tolist() == lost.tolist()
        assert infos["_final_obs"][lost].all()
        assert second.active.tolist() == (~lost).tolist()
        # Sampling keeps its batch size on the two servers left.
        stream = second.sample_batches(16, min_size=16)
        batch = next(stream)
        assert len(batch) == 16 and set(batch.server.tolist()) == {0, 2}
        for _ in range(3):
            obs, reward, terminated, truncated, infos = second.step(actions)
            assert infos["radserve_inactive"].tolist() == lost.tolist()
            assert not truncated[lost].any() and (reward[lost] == 0).all()

        # The server returns on its address: the next step after the backoff reconnects.
        victim.args[victim.args.index("--address") + 1] = victim.address
        victim.start()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            deadline = time.monotonic() + 60  # the restarted server builds its catalog first
            while time.monotonic() < deadline:
                obs, reward, terminated, truncated, infos = second.step(actions)
                if second.active.all():
                    break
                time.sleep(0.05)
        assert second.active.all(), "the returned server was not reconnected"
        assert any("is back" in str(w.message) for w in caught)
        # The reconnection's own row is a placeholder; the next step is a real one everywhere.
        assert infos["radserve_inactive"].tolist() == lost.tolist()
        obs, reward, *_ = second.step(actions)
        assert (reward == 1.0).all()
        # The new session's replay fills; then the returned server takes its share again (it is
        # asked at most once a second whether it holds its share).
        for _ in range(20):
            second.step(actions)
        deadline = time.monotonic() + 20
        servers_seen: set = set()
        while servers_seen != {0, 1, 2} and time.monotonic() < deadline:
            batch = next(stream)
            assert len(batch) == 16
            servers_seen = set(batch.server.tolist())
            time.sleep(0.1)
        assert servers_seen == {0, 1, 2}
        stream.close()
        # The prioritized stream draws from the returned server's new session too; the batch drawn
        # before the loss names the old session's transitions there: those keys count as missing,
        # never as the new session's transitions that happen to have the same env and frame.
        while 1 not in set(next(prioritized).server.tolist()):
            time.sleep(0.1)
        update = prioritized.update_priorities(before, np.ones(16))
        assert update == radserve.PriorityUpdate(updated=16 - victims_rows, missing=victims_rows)
        prioritized.close()
    finally:
        first.close()
        second.close()
        strict.close()
        lenient.close()


def test_a_lost_server_comes_back_to_the_servers_acting(servers):
    """With the servers acting, the learner makes no step, where lost servers are otherwise tried
    again: on_server_loss="continue" goes on with the others (acting() says None for the lost one)
    and set_policy reconnects it, sends it the policy and starts its actor with the settings the
    others act with; its transitions then reach the batches again."""
    import policies

    client = radserve.Client([server.address for server in servers], on_server_loss="continue", reconnect_backoff=0.2,
                             reconnect_backoff_max=0.5)
    envs = client.make_vec("gym/CartPole-v1", num_envs=6, seed=0, replay_capacity=3000, autoreset_mode="SameStep")
    model = policies.linear_categorical([[0.0, 0.0], [0.0, 0.0], [-1.0, 1.0], [0.0, 0.0]])
    victim = servers[2]
    try:
        envs.set_policy(model, head="categorical")
        envs.start_acting(seed=5, steps_per_second=600.0)
        stream = envs.sample_batches(12, min_size=12)
        assert set(next(stream).server.tolist()) <= {0, 1, 2}
        victim.process.send_signal(signal.SIGKILL)
        victim.process.wait()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # "server ... lost", from the stream
            for _ in range(5):
                assert len(next(stream)) == 12
            infos = envs.acting()
            assert infos[2] is None and infos[0].state == infos[1].state == "acting"
            envs.set_policy(model, head="categorical")  # the lost server is left out, not an error
            assert envs.policy_version == 2

            victim.args[victim.args.index("--address") + 1] = victim.address
            victim.start()
            deadline = time.monotonic() + 60  # the restarted server builds its catalog first
            while time.monotonic() < deadline:
                envs.set_policy(model, head="categorical")
                infos = envs.acting()
                if infos[2] is not None and infos[2].state == "acting":
                    break
                time.sleep(0.2)
            assert infos[2] is not None and infos[2].state == "acting", infos
            assert infos[2].policy_version == envs.policy_version
            # Its new session's replay fills from its own actor; then it takes its share of the batches.
            deadline = time.monotonic() + 30
            seen: set = set()
            while 2 not in seen and time.monotonic() < deadline:
                batch = next(stream)
                seen = set(batch.server.tolist())
                time.sleep(0.1)
            assert 2 in seen
        stream.close()
        stopped = envs.stop_acting()
        assert [info.state for info in stopped] == ["stopped"] * 3
    finally:
        envs.close()
        client.close()


def test_a_sharded_env_refuses_the_resets_a_plain_env_refuses(servers, sharded):
    """The same checks, sharded or not: a mask is a numpy bool array of num_envs marking at least one env
    (a list, an all-False mask and ints are refused), seeds are ints, one per env or None."""
    with radserve.Client(servers[0].address) as single:
        plain = single.make_vec("gym/CartPole-v1", num_envs=6, seed=0)
        spread = sharded.make_vec("gym/CartPole-v1", num_envs=6, seed=0)
        try:
            for envs in (plain, spread):
                envs.reset(seed=0)
                bad_masks = ([True] * 6, np.zeros(6, bool), np.ones(6, np.int64), np.ones(5, bool))
                for mask in bad_masks:
                    with pytest.raises(radserve.InvalidArgumentError, match="reset_mask"):
                        envs.reset(options={"reset_mask": mask})
                for seed in (-1, [1, None, 2, 3, 4, 5], [5, 6], 2.5, "5", True):
                    with pytest.raises(radserve.InvalidArgumentError, match="seed"):
                        envs.reset(seed=seed)
            # What both take, both do alike.
            mask = np.array([True, False, False, True, False, True])
            np.testing.assert_array_equal(plain.reset(seed=[3, 4, 5, 6, 7, 8])[0], spread.reset(seed=[3, 4, 5, 6, 7, 8])[0])
            np.testing.assert_array_equal(plain.reset(options={"reset_mask": mask})[0],
                                          spread.reset(options={"reset_mask": mask})[0])
        finally:
            plain.close()
            spread.close()


def test_addresses_name_one_or_several_servers():
    resolve = radserve.resolve_addresses
    assert resolve("a:1") == ["a:1"]
    assert resolve(["a:1", "b:2"]) == ["a:1", "b:2"]
    assert resolve("a:1, b:2") == ["a:1", "b:2"]
    assert "127.0.0.1:50051" in resolve("dns:///localhost:50051")
    with pytest.raises(ValueError, match="dns:///host:port"):
        resolve("dns:///localhost")
    with pytest.raises(radserve.UnavailableError, match="does not resolve"):
        resolve("dns:///no-such-host.invalid:50051")
    with pytest.raises(ValueError, match="once"):
        radserve.Client(["127.0.0.1:1", "127.0.0.1:1"], wait_ready=0)


def test_a_client_of_one_dns_name_with_one_address_is_a_plain_client(servers):
    port = servers[0].address.rsplit(":", 1)[1]
    with radserve.Client(f"dns:///127.0.0.1:{port}") as client:
        assert client.addresses == [servers[0].address]
        envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0)
        assert isinstance(envs, radserve.RemoteVectorEnv)
        envs.close()
