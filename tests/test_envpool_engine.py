"""Sessions stepped by EnvPool's C++ ports (option engine="envpool"), through the real server: the same
contract as the native engine (spaces, per-env seeds, same-step autoreset with final observations,
action repeat, partial resets and skipped envs), and errors for what EnvPool cannot host."""

import contextlib
import os

import numpy as np
import pytest

import radserve


def run(envs, actions, steps):
    """(observations, rewards, terminated, truncated, infos) of `steps` steps with the given actions."""
    record = []
    for t in range(steps):
        record.append(envs.step(actions[t % len(actions)]))
    return record


def random_actions(space, num_envs, count=32, seed=0):
    rng = np.random.default_rng(seed)
    if hasattr(space, "n"):
        return [rng.integers(0, space.n, num_envs) for _ in range(count)]
    return [rng.uniform(space.low, space.high, (num_envs,) + space.shape).astype(np.float32) for _ in range(count)]


def test_spaces_match_the_native_engine(client):
    for env_id, options in [("dmc/cheetah-run", {"pixels": False}), ("gym/HalfCheetah-v5", {}),
                            ("gym/CartPole-v1", {}), ("procgen/bigfish", {})]:
        native = client.make_vec(env_id, num_envs=1, **options)
        envpool = client.make_vec(env_id, num_envs=1, engine="envpool", **options)
        try:
            assert envpool.single_observation_space == native.single_observation_space, env_id
            assert envpool.single_action_space == native.single_action_space, env_id
            assert envpool.describe()[0].options["engine"] == "envpool"
        finally:
            native.close()
            envpool.close()


def test_a_dm_control_episode_lasts_as_long_as_dm_controls(client):
    # cheetah-run: 1000 control steps; action repeat 4 (the paper's) makes 250 agent steps.
    envs = client.make_vec("dmc/cheetah-run", num_envs=2, seed=1, engine="envpool", pixels=False,
                           autoreset_mode="SameStep")
    try:
        envs.reset()
        actions = random_actions(envs.single_action_space, 2)
        for t in range(250):
            obs, reward, terminated, truncated, infos = envs.step(actions[t % 32])
            assert np.all(reward >= 0) and np.all(reward <= 4), "4 control steps of a reward in [0, 1]"
            if t < 249:
                assert not truncated.any() and not terminated.any(), t
        assert truncated.all() and not terminated.any()
        # Same-step autoreset: the episode's last observation in the infos, the next episode's first in obs.
        assert infos["_final_obs"].all()
        assert not np.array_equal(np.stack(infos["final_obs"]), obs)
        np.testing.assert_array_equal(infos["radserve_episode"]["l"], [250, 250])
    finally:
        envs.close()


def test_action_repeat_sums_the_rewards_of_repeated_steps(client):
    one = client.make_vec("dmc/cartpole-balance", num_envs=2, seed=3, engine="envpool", pixels=False, action_repeat=1)
    three = client.make_vec("dmc/cartpole-balance", num_envs=2, seed=3, engine="envpool", pixels=False,
                            action_repeat=3)
    try:
        np.testing.assert_array_equal(one.reset()[0], three.reset()[0])
        for action in random_actions(one.single_action_space, 2, count=10, seed=4):
            total = np.zeros(2)
            for _ in range(3):
                obs_one, reward, *_ = one.step(action)
                total += reward
            obs_three, reward_three, *_ = three.step(action)
            np.testing.assert_array_equal(obs_one, obs_three)
            np.testing.assert_allclose(reward_three, total, rtol=1e-6)
    finally:
        one.close()
        three.close()


def test_env_i_of_seed_s_is_env_0_of_seed_s_plus_i(client):
    # The native engine's contract: a session seeded s seeds env i with s + i.
    for env_id, options in [("dmc/walker-walk", {"pixels": False}), ("gym/Hopper-v5", {}), ("procgen/coinrun", {})]:
        four = client.make_vec(env_id, num_envs=4, seed=10, engine="envpool", **options)
        single = client.make_vec(env_id, num_envs=1, seed=13, engine="envpool", **options)
        try:
            actions = random_actions(four.single_action_space, 4, count=20)
            first4, first1 = four.reset()[0], single.reset()[0]
            np.testing.assert_array_equal(first4[3], first1[0])
            for action in actions:
                obs4 = four.step(action)[0]
                obs1 = single.step(action[3:])[0]
                np.testing.assert_array_equal(obs4[3], obs1[0])
        finally:
            four.close()
            single.close()


def test_procgen_options_reach_envpools_procgen(client):
    # One level (num_levels=1 from start_level 5): every env starts the same level whatever its seed,
    # and for these games EnvPool's level is the native engine's (procgen's own C++ generates both;
    # the levels of a seed differ, EnvPool deriving level seeds its own way).
    for game, as_native in (("coinrun", False), ("bigfish", True), ("starpilot", True)):
        options = {"num_levels": 1, "start_level": 5}
        envpool = client.make_vec(f"procgen/{game}", num_envs=2, seed=21, engine="envpool", **options)
        native = client.make_vec(f"procgen/{game}", num_envs=1, seed=3, **options)
        try:
            first = envpool.reset()[0]
            np.testing.assert_array_equal(first[0], first[1])
            if as_native:
                np.testing.assert_array_equal(first[0], native.reset()[0][0])
        finally:
            envpool.close()
            native.close()


def test_sessions_and_seeded_resets_are_reproducible(client):
    runs = []
    for _ in range(2):
        envs = client.make_vec("gym/CartPole-v1", num_envs=3, seed=5, engine="envpool", autoreset_mode="SameStep")
        try:
            actions = random_actions(envs.single_action_space, 3, seed=9)
            first = envs.reset(seed=40)[0]
            record = run(envs, actions, 120)
            again = envs.reset(seed=40)[0]  # the same seed after steps: the same start
            np.testing.assert_array_equal(first, again)
            runs.append((first, record))
        finally:
            envs.close()
    (first_a, record_a), (first_b, record_b) = runs
    np.testing.assert_array_equal(first_a, first_b)
    ended = 0
    for (obs_a, rew_a, term_a, trunc_a, info_a), (obs_b, rew_b, term_b, trunc_b, _) in zip(record_a, record_b):
        np.testing.assert_array_equal(obs_a, obs_b)
        np.testing.assert_array_equal(rew_a, rew_b)
        np.testing.assert_array_equal(term_a, term_b)
        np.testing.assert_array_equal(trunc_a, trunc_b)
        ended += int((term_a | trunc_a).sum())
        for i in np.flatnonzero(term_a | trunc_a):
            assert info_a["_final_obs"][i]
    assert ended >= 3, "CartPole's random episodes end within 120 steps: the comparison crossed autoresets"


def test_next_step_autoreset_and_partial_resets(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0, engine="envpool", autoreset_mode="NextStep")
    try:
        envs.reset()
        left = np.zeros(2, dtype=np.int64)
        for _ in range(100):
            obs, reward, terminated, truncated, _ = envs.step(left)
            if (terminated | truncated).any():
                break
        ended = terminated | truncated
        assert ended.any()
        # gymnasium's NEXT_STEP: the ended env's next step is its reset: reward 0, no flag, a fresh start.
        obs, reward, terminated, truncated, _ = envs.step(left)
        assert np.all(reward[ended] == 0) and not terminated[ended].any()
        assert np.all(np.abs(obs[ended]) <= 0.05), "CartPole starts within +-0.05"
        # A partial reset resets only the envs it marks.
        before = envs.step(left)[0]
        after, _ = envs.reset(options={"reset_mask": np.array([True, False])})
        np.testing.assert_array_equal(after[1], before[1])
        assert np.all(np.abs(after[0]) <= 0.05)
    finally:
        envs.close()


def worker_cpu(server) -> "dict[int, int]":
    """CPU ticks (user + system) so far of each worker process of the server that hosts sessions."""
    pid, ticks = server.process.pid, {}
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as listing:
            for child in listing.read().split():
                with contextlib.suppress(FileNotFoundError), open(f"/proc/{child}/stat") as stat:
                    fields = stat.read().rsplit(")", 1)[1].split()  # from the state, field 3
                    if int(fields[16]) == 0:  # not the catalog's background worker (niceness 19)
                        ticks[int(child)] = int(fields[11]) + int(fields[12])
    return ticks


def test_an_envpool_session_is_stepped_in_one_worker(client, server):
    # groups.rs puts an envpool session's envs in one worker (EnvPool's threads step them in parallel
    # there); the native engine splits them over the fixture's 2 workers.
    for engine, busy in (("envpool", 1), ("native", 2)):
        envs = client.make_vec("gym/Hopper-v5", num_envs=8, seed=0, engine=engine)
        try:
            envs.reset()
            actions = random_actions(envs.single_action_space, 8)
            before = worker_cpu(server)
            run(envs, actions, 1500)
            after = worker_cpu(server)
            used = sorted(after[pid] - before[pid] for pid in before.keys() & after.keys())
            assert sum(ticks >= 5 for ticks in used) == busy, (engine, used)
            assert all(ticks <= 2 for ticks in used[:-busy]), (engine, used)
        finally:
            envs.close()


def test_what_envpool_cannot_host_is_refused_with_the_reason(client):
    with pytest.raises(radserve.InvalidArgumentError, match="pixels=false"):
        client.make_vec("dmc/cheetah-run", num_envs=1, engine="envpool")
    with pytest.raises(radserve.InvalidArgumentError, match="one of native, envpool"):
        client.make_vec("gym/CartPole-v1", num_envs=1, engine="brax")
    with pytest.raises(radserve.RadServeError, match="no port of procgen/bigfish"):
        client.make_vec("procgen/bigfish", num_envs=1, engine="envpool", distribution_mode="memory")
    envs = client.make_vec("gym/CartPole-v1", num_envs=4, seed=0, engine="envpool")
    try:
        envs.reset()
        with pytest.raises(radserve.RadServeError, match="seeded reset must reset every env"):
            envs.reset(seed=3, options={"reset_mask": np.array([True, False, True, True])})
        # Unseeded partial resets and seeded full ones are fine, and the session still steps.
        envs.reset(options={"reset_mask": np.array([False, False, True, True])})
        envs.reset(seed=3)
        envs.step(np.zeros(4, dtype=np.int64))
    finally:
        envs.close()


def _worker_module():
    """The worker's entry points (server/sim/python/radserve_worker/adapters.py), from the package the
    worker embeds."""
    from _procs import worker_module

    return worker_module("adapters")


PROCGEN_DEFAULTS = {"num_levels": 0, "start_level": 0, "distribution_mode": "easy", "restrict_themes": False,
                    "use_backgrounds": True, "use_monochrome_assets": False, "center_agent": True,
                    "use_sequential_levels": False, "paint_vel_info": False, "use_generated_assets": False}


@pytest.mark.parametrize("family, name, options, steps", [
    ("dmc", "cheetah-run", {"action_repeat": 4}, 255),
    ("dmc", "cartpole-balance", {"action_repeat": 3}, 340),  # episodes end inside a repeat (1000 % 3)
    ("gym", "CartPole-v1", {"max_episode_steps": 0}, 200),  # terminations, same-step resets
    ("gym", "HalfCheetah-v5", {"max_episode_steps": 25}, 60),  # truncations
    ("procgen", "bigfish", PROCGEN_DEFAULTS, 150),
])
def test_raw_envpool_calls_give_what_its_public_interface_gives(family, name, options, steps):
    # The worker steps EnvPool through its raw _send/_recv (EnvpoolGroup._call), not its Python
    # wrapper: the same seeds and actions must give the same frames, final frames, rewards and flags
    # as the wrapper's step() and reset(), partial steps (skipped envs) included.
    worker = _worker_module()
    groups = []
    for raw in (True, False):
        group = worker.make_group(family, name, {"engine": "envpool", "envpool_threads": 1, **options}, [7, 8, 9])
        assert (group.state_index is not None) is True, "EnvPool 1.2.5 has the raw interface"
        if not raw:
            group.state_index = None
        observation = group.spec()["observation"]
        size = 2 * 3 * int(np.prod(observation["shape"])) * np.dtype(observation["dtype"]).itemsize
        group.attach(memoryview(bytearray(size)))
        group.reset(None)
        groups.append(group)
    try:
        raw, public = groups
        np.testing.assert_array_equal(raw.current, public.current)
        rng = np.random.default_rng(0)
        space = raw.spec()["action"]
        ended = 0
        for t in range(steps):
            if space["kind"] == "discrete":
                actions = rng.integers(0, space["n"], 3)
            else:
                actions = rng.uniform(space["low"], space["high"], (3,) + tuple(space["shape"]))
            actions = actions.astype(raw.action_dtype).tobytes()
            skip = [t % 5 == 4, False, False]
            a, b = raw.step(actions, skip), public.step(actions, skip)
            assert a == b, t
            ended += sum(a[1]) + sum(a[2])
            np.testing.assert_array_equal(raw.current, public.current)
            np.testing.assert_array_equal(raw.final, public.final)
        assert ended > 0, "the run covers episode ends"
    finally:
        for group in groups:
            group.close()


def _group(worker, family, name, options, seeds, batch_size=0):
    group = worker.make_group(family, name, {"engine": "envpool", "envpool_threads": 2, "batch_size": batch_size,
                                             **options}, seeds)
    observation = group.spec()["observation"]
    size = 2 * len(seeds) * int(np.prod(observation["shape"])) * np.dtype(observation["dtype"]).itemsize
    group.attach(memoryview(bytearray(size)))
    return group


@pytest.mark.parametrize("family, name, options, steps", [
    ("dmc", "cartpole-balance", {"action_repeat": 3}, 340),  # episodes end inside a repeat (1000 % 3)
    ("gym", "CartPole-v1", {"max_episode_steps": 0, "action_repeat": 2}, 150),  # terminations
    ("gym", "HalfCheetah-v5", {"max_episode_steps": 25}, 60),  # truncations
    ("procgen", "bigfish", PROCGEN_DEFAULTS, 120),
])
def test_envpool_async_gives_each_env_the_trajectory_the_synchronous_mode_gives(family, name, options, steps):
    # EnvPool's asynchronous mode (send/recv of `batch_size` envs): envs come back in whatever order
    # EnvPool's threads finish them, but each env's own sequence (observations, final observations,
    # rewards over the repeats, flags) is the one the synchronous mode gives for the same seeds and
    # per-env actions.
    worker = _worker_module()
    seeds, n = [11, 12, 13, 14, 15, 16], 6
    sync = _group(worker, family, name, options, seeds)
    asyn = _group(worker, family, name, options, seeds, batch_size=2)
    try:
        assert asyn.batch == 2 and sync.batch == n
        space = sync.spec()["action"]
        rng = np.random.default_rng(1)
        if space["kind"] == "discrete":
            table = rng.integers(0, space["n"], (n, steps))
        else:
            table = rng.uniform(space["low"], space["high"], (n, steps) + tuple(space["shape"]))
        table = table.astype(sync.action_dtype)

        def record(group, env):
            return group.current[env].copy()

        expected = [[] for _ in range(n)]  # per env: (obs, reward, terminated, truncated, final or None)
        sync.reset(None)
        for env in range(n):
            expected[env].append((record(sync, env), 0.0, False, False, None))
        for t in range(steps):
            rewards, terminated, truncated, errors, *_ = sync.step(table[:, t].tobytes())
            assert not errors
            for env in range(n):
                ended = terminated[env] or truncated[env]
                expected[env].append((record(sync, env), rewards[env], terminated[env], truncated[env],
                                      sync.final[env].copy() if ended else None))

        got = [[] for _ in range(n)]
        asyn.async_reset()
        with pytest.raises(ValueError, match="before recv returned"):
            asyn.send(table[:1, 0].tobytes(), [0])
        order = []
        while min(len(g) for g in got) < steps + 1:
            env_ids, rewards, terminated, truncated = asyn.recv()
            assert len(env_ids) == 2
            order.extend(env_ids.tolist())
            for j, env in enumerate(env_ids):
                ended = terminated[j] or truncated[j]
                got[env].append((record(asyn, env), rewards[j], terminated[j], truncated[j],
                                 asyn.final[env].copy() if ended else None))
            sending = [env for env in env_ids if len(got[env]) <= steps]
            if len(sending) < len(env_ids):  # an env at the end of the table: keep the others going
                break
            asyn.send(table[sending, [len(got[env]) - 1 for env in sending]].tobytes(), sending)
        ends = 0
        for env in range(n):
            for t, (a, b) in enumerate(zip(got[env], expected[env])):
                np.testing.assert_array_equal(a[0], b[0], err_msg=f"env {env} step {t}")
                assert a[1] == pytest.approx(b[1], rel=1e-6) and a[2:4] == b[2:4], (env, t, a[1:4], b[1:4])
                assert (a[4] is None) == (b[4] is None), (env, t)
                if a[4] is not None:
                    np.testing.assert_array_equal(a[4], b[4], err_msg=f"env {env} step {t} final")
                    ends += 1
            assert len(got[env]) > steps // 2, env
        assert ends > 0, "the run covers episode ends"
        # Fewer envs in EnvPool than a batch: recv refuses instead of waiting forever.
        while True:
            try:
                asyn.recv()
            except ValueError as error:
                assert "send actions to more envs first" in str(error)
                break
        with pytest.raises(ValueError, match="async_reset/send/recv, not step"):
            asyn.step(table[:, 0].tobytes())
        # A seeded async reset, with results still in flight, starts the seeds' episodes again.
        asyn.async_reset(seeds)
        first = {}
        for _ in range(n // 2):
            env_ids, rewards, terminated, truncated = asyn.recv()
            assert not rewards.any() and not terminated.any() and not truncated.any()
            first.update({int(env): record(asyn, env) for env in env_ids})
        assert sorted(first) == list(range(n))
        for env in range(n):
            np.testing.assert_array_equal(first[env], expected[env][0][0], err_msg=f"env {env}")
    finally:
        sync.close()
        asyn.close()


# --- EnvPool's asynchronous mode through the server (option batch_size) ----------------------------

def _action(env, t):
    """A fixed action per env and step, so that each env's trajectory does not depend on the order
    in which envs come back."""
    return (env * 7 + t * 3 + t // 5) % 2


def _sync_trajectories(client, num_envs, steps, engine):
    """Per env: its `steps` results (obs, reward, terminated, truncated, final obs or None) of a
    synchronous session, the first being its reset."""
    envs = client.make_vec("gym/CartPole-v1", num_envs=num_envs, seed=4, engine=engine, autoreset_mode="SameStep")
    try:
        obs, _ = envs.reset()
        record = [[(obs[i], 0.0, False, False, None)] for i in range(num_envs)]
        for t in range(steps - 1):
            obs, rewards, terminated, truncated, infos = envs.step(np.array([_action(i, t) for i in range(num_envs)]))
            for i in range(num_envs):
                final = infos["final_obs"][i] if infos.get("_final_obs", np.zeros(num_envs, bool))[i] else None
                record[i].append((obs[i], rewards[i], terminated[i], truncated[i], final))
        return record
    finally:
        envs.close()


@pytest.mark.parametrize("engine,delivery", [("envpool", "shared_memory"), ("envpool", "grpc"),
                                             ("native", "shared_memory"), ("native", "grpc")])
def test_async_sessions_give_each_env_the_trajectory_a_synchronous_session_gives(client, engine, delivery):
    # EnvPool's own loop (recv the first ready batch, send it its actions), through the server: whatever
    # order the envs come back in, each env's observations, rewards, ends and final observations are
    # those of the same env of a synchronous session of the same engine given the same actions. (The
    # native engine's batches are its groups of batch_size envs, each stepped whole.)
    num_envs, batch, steps = 6, 2, 40
    expected = _sync_trajectories(client, num_envs, steps, engine)
    envs = client.make_vec("gym/CartPole-v1", num_envs=num_envs, seed=4, engine=engine, batch_size=batch,
                           delivery=delivery)
    try:
        assert envs.delivery == delivery and envs.is_async and envs.batch_size == batch
        envs.async_reset()
        got = [[] for _ in range(num_envs)]
        result = envs.recv()
        for round_ in range(10 * steps):
            obs, rewards, terminated, truncated, infos = result
            ids = infos["env_id"]
            assert len(ids) == batch and obs.shape == (batch, 4)
            if engine == "native":
                assert ids[0] % batch == 0 and ids[1] == ids[0] + 1, f"one group: {ids}"
            for row, env in enumerate(ids):
                final = infos["final_obs"][row] if infos.get("_final_obs", np.zeros(batch, bool))[row] else None
                got[env].append((obs[row], rewards[row], terminated[row], truncated[row], final))
            if min(len(record) for record in got) >= steps:
                break
            actions = np.array([_action(env, len(got[env]) - 1) for env in ids])
            if round_ % 2:  # EnvPool's step(action, env_id): send and recv in one call
                result = envs.step(actions, ids)
            else:
                envs.send(actions, ids)
                result = envs.recv()
        ended = 0
        for env in range(num_envs):
            for t, ((obs, reward, term, trunc, final), want) in enumerate(zip(got[env], expected[env])):
                where = f"env {env} step {t}"
                np.testing.assert_array_equal(obs, want[0], err_msg=where)
                assert (reward, term, trunc) == tuple(want[1:4]), where
                assert (final is None) == (want[4] is None), where
                if final is not None:
                    np.testing.assert_array_equal(final, want[4], err_msg=where)
                    ended += 1
        assert ended >= num_envs, "CartPole's episodes end within 40 steps of these actions"
        assert envs.describe()[0].total_env_steps > 0
    finally:
        envs.close()


def test_async_sessions_refuse_what_their_mode_does_not_do(client):
    with pytest.raises(radserve.InvalidArgumentError, match="above num_envs 4"):
        client.make_vec("gym/CartPole-v1", num_envs=4, engine="envpool", batch_size=5)
    with pytest.raises(radserve.InvalidArgumentError, match="num_envs must be a multiple of batch_size"):
        client.make_vec("gym/CartPole-v1", num_envs=4, batch_size=3)
    before = len(client.list_sessions())
    with pytest.raises(radserve.InvalidArgumentError, match="autoreset_mode must be SameStep"):
        client.make_vec("gym/CartPole-v1", num_envs=4, engine="envpool", batch_size=2, autoreset_mode="NextStep")
    assert len(client.list_sessions()) == before, "the refused env's session was closed"
    for delivery in ("shared_memory", "grpc"):
        envs = client.make_vec("gym/CartPole-v1", num_envs=4, seed=0, engine="envpool", batch_size=2,
                               delivery=delivery)
        try:
            with pytest.raises(radserve.RadServeError, match="async_reset and stepped with send/recv"):
                envs.reset()
            with pytest.raises(radserve.FailedPreconditionError, match="AsyncReset before Send/Recv"):
                envs.recv()  # nothing was reset yet
            envs.async_reset(seed=1)
            first = envs.recv()[4]["env_id"]
            with pytest.raises(radserve.RadServeError, match="still stepping"):
                envs.send(np.zeros(1, dtype=np.int64), [int(({0, 1, 2, 3} - set(first.tolist())).pop())])
            with pytest.raises(radserve.InvalidArgumentError, match="env_id must be in"):
                envs.send(np.zeros(1, dtype=np.int64), [4])
            with pytest.raises(radserve.RadServeError, match="outside"):
                envs.send(np.full(2, 7, dtype=np.int64), first)
            envs.send(np.zeros(2, dtype=np.int64), first)  # refused sends changed nothing
            assert len(envs.recv()[4]["env_id"]) == 2
        finally:
            envs.close()
    # The native engine's batches are whole groups: part of one is refused, and changes nothing.
    envs = client.make_vec("gym/CartPole-v1", num_envs=4, seed=0, batch_size=2)
    try:
        envs.async_reset()
        first = envs.recv()[4]["env_id"]
        with pytest.raises(radserve.InvalidArgumentError, match="send names whole groups"):
            envs.send(np.zeros(1, dtype=np.int64), first[:1])
        assert sorted(envs.step(np.zeros(2, dtype=np.int64), first)[4]["env_id"].tolist()) in ([0, 1], [2, 3])
    finally:
        envs.close()
    sync = client.make_vec("gym/CartPole-v1", num_envs=2, engine="envpool")
    try:
        with pytest.raises(radserve.FailedPreconditionError, match="steps with reset"):
            sync.recv()
    finally:
        sync.close()
