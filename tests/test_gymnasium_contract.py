"""radserve's vector env against gymnasium's own SyncVectorEnv of the same envs, in each autoreset
mode: the same observations, rewards, flags and infos (radserve's extras, `radserve_*`, aside) through
seeded, unseeded, per-env and masked resets and episode ends; and gymnasium's vector wrappers on
radserve envs."""

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv

import radserve

N = 3
STEPS = 240
# Short episodes, so that every id ends several inside the run (random actions rarely end
# Acrobot or MountainCarContinuous before their own limits).
MAX_STEPS = 40
# Hopper returns infos of its own at reset and at every step (positions, reward terms): they travel
# from the worker as typed columns and are batched as SyncVectorEnv batches them.
IDS = ("CartPole-v1", "Pendulum-v1", "Acrobot-v1", "MountainCarContinuous-v0", "Hopper-v5")
MODES = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED)


def ours_only(infos: dict) -> dict:
    return {key: value for key, value in infos.items() if not key.lstrip("_").startswith("radserve")}


def assert_same_infos(want: dict, have: dict, observation_dtype) -> None:
    assert want.keys() == have.keys(), (want.keys(), have.keys())
    for key, value in want.items():
        if key == "final_obs":
            for i, row in enumerate(value):
                if row is None:
                    assert have[key][i] is None
                else:
                    np.testing.assert_array_equal(np.asarray(row, observation_dtype), have[key][i])
        elif isinstance(value, dict):
            assert_same_infos(value, have[key], observation_dtype)
        else:
            np.testing.assert_array_equal(value, have[key], err_msg=key)
            assert value.dtype == have[key].dtype, (key, value.dtype, have[key].dtype)


def compare(want, have, what: str) -> None:
    """One step's (or reset's) results, gymnasium's against radserve's."""
    want_obs, have_obs = want[0], have[0]
    dtype = have_obs.dtype
    np.testing.assert_array_equal(np.asarray(want_obs, dtype), have_obs, err_msg=f"obs at {what}")
    for index, name in ((1, "rewards"), (2, "terminated"), (3, "truncated")):
        if len(want) > 3:
            np.testing.assert_array_equal(want[index], have[index], err_msg=f"{name} at {what}")
    assert_same_infos(want[-1], ours_only(have[-1]), dtype)


@pytest.mark.parametrize("mode", MODES, ids=lambda mode: mode.value)
@pytest.mark.parametrize("env_id,delivery", [(env_id, "grpc") for env_id in IDS] + [("Hopper-v5", "shared_memory")])
def test_the_same_as_gymnasium_sync_vector_env(client, env_id, delivery, mode):
    reference = SyncVectorEnv([lambda: gymnasium.make(env_id, max_episode_steps=MAX_STEPS) for _ in range(N)],
                              autoreset_mode=mode)
    envs = client.make_vec(f"gym/{env_id}", num_envs=N, seed=0, autoreset_mode=mode, max_episode_steps=MAX_STEPS,
                           delivery=delivery)
    try:
        assert envs.metadata["autoreset_mode"] == mode
        reference.single_action_space.seed(0)
        compare(reference.reset(seed=5), envs.reset(seed=5), "reset(seed=5)")
        episodes = 0
        for t in range(STEPS):
            actions = np.stack([reference.single_action_space.sample() for _ in range(N)])
            want, have = reference.step(actions), envs.step(actions)
            compare(want, have, f"step {t}")
            ended = want[2] | want[3]
            episodes += int(ended.sum())
            if mode == AutoresetMode.DISABLED and ended.any():
                options = {"reset_mask": ended.copy()}
                compare(reference.reset(options=dict(options)), envs.reset(options=dict(options)),
                        f"masked reset after step {t}")
            if t == 80:
                compare(reference.reset(), envs.reset(), "reset()")
            if t == 140:
                seeds = [7, 100, 3]
                compare(reference.reset(seed=seeds), envs.reset(seed=seeds), "reset(seed=[7, 100, 3])")
            if t == 190 and mode != AutoresetMode.DISABLED:
                options = {"reset_mask": np.array([True, False, True])}
                compare(reference.reset(options=dict(options)), envs.reset(options=dict(options)),
                        "reset(options={'reset_mask': [True, False, True]})")
        assert episodes >= N, f"only {episodes} episodes ended: the run did not cover episode ends"
    finally:
        envs.close()
        reference.close()


def test_disabled_mode_refuses_to_step_an_ended_env(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0, autoreset_mode="Disabled")
    try:
        envs.reset(seed=0)
        for _ in range(500):
            _, _, terminated, truncated, _ = envs.step(np.zeros(2, np.int64))
            if (terminated | truncated).any():
                break
        with pytest.raises(radserve.FailedPreconditionError, match="reset them"):
            envs.step(np.zeros(2, np.int64))
        envs.reset(options={"reset_mask": terminated | truncated})
        envs.step(np.zeros(2, np.int64))
        for bad in (np.array([1, 0]), np.array([False, False]), [True, False]):
            with pytest.raises(radserve.InvalidArgumentError, match="reset_mask"):
                envs.reset(options={"reset_mask": bad})
        with pytest.raises(radserve.InvalidArgumentError, match="autoreset_mode"):
            client.make_vec("gym/CartPole-v1", autoreset_mode="sometimes")
    finally:
        envs.close()


def test_the_default_autoreset_mode_is_gymnasiums(client):
    """make_vec without autoreset_mode gives gymnasium's default, NEXT_STEP, which gymnasium's vector
    observation wrappers require (they refuse SAME_STEP); EnvPool's asynchronous mode, which resets in
    the ending step only, defaults to SAME_STEP."""
    from gymnasium.wrappers import vector as wrappers

    envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0)
    same = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0, autoreset_mode="SameStep")
    asynchronous = client.make_vec("gym/CartPole-v1", num_envs=4, seed=0, batch_size=2)
    try:
        assert envs.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP
        assert gymnasium.make_vec("CartPole-v1", num_envs=2).metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP
        wrapped = wrappers.FlattenObservation(envs)
        wrapped.reset(seed=0)
        ended = False
        for _ in range(100):  # pushing one way ends CartPole's episodes within ~10 steps
            obs, _, terminated, truncated, infos = wrapped.step(np.zeros(2, np.int64))
            if ended:  # the step after an end: the new episode's first observation, reward 0
                break
            ended = bool((terminated | truncated).any())
            assert "final_obs" not in infos
        assert ended
        with pytest.raises(ValueError, match="NEXT_STEP"):
            wrappers.FlattenObservation(same)
        assert asynchronous.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    finally:
        envs.close()
        same.close()
        asynchronous.close()


@pytest.mark.parametrize("delivery", ["grpc", "shared_memory"])
def test_gymnasium_vector_wrappers_run_on_radserve(client, delivery):
    """The wrappers the issue names, on a NEXT_STEP env (which they require), and RecordEpisodeStatistics
    counting the same episodes as radserve's own figures."""
    from gymnasium.wrappers import vector as wrappers

    def make():
        return client.make_vec("gym/CartPole-v1", num_envs=2, seed=0, autoreset_mode=AutoresetMode.NEXT_STEP,
                               delivery=delivery)

    stacks = [
        lambda env: wrappers.NormalizeObservation(env),
        lambda env: wrappers.TransformObservation(env, lambda obs: obs * 2.0),
        lambda env: wrappers.FlattenObservation(env),
        lambda env: wrappers.DtypeObservation(env, np.float64),
        lambda env: wrappers.VectorizeTransformObservation(
            env, gymnasium.wrappers.TransformObservation, func=lambda obs: obs + 1.0,
            observation_space=env.single_observation_space),
        lambda env: wrappers.RecordEpisodeStatistics(env),
    ]
    for wrap in stacks:
        env = wrap(make())
        try:
            obs, _ = env.reset(seed=1)
            assert obs.shape == env.observation_space.shape
            counted = 0
            for _ in range(120):
                obs, _, terminated, truncated, infos = env.step(env.action_space.sample())
                if "episode" in infos:
                    counted += int(infos["_episode"].sum())
                    np.testing.assert_array_equal(infos["_episode"], infos["_radserve_episode"])
                    ended = infos["_episode"]
                    np.testing.assert_array_equal(infos["episode"]["r"][ended], infos["radserve_episode"]["r"][ended])
            if isinstance(env, wrappers.RecordEpisodeStatistics):
                assert counted > 0
        finally:
            env.close()


@pytest.mark.parametrize("env_id,options", [("procgen/coinrun", {}),
                                             ("dmc/cartpole-balance", {"height": 48, "width": 48, "action_repeat": 8})])
def test_gymnasium_vector_wrappers_run_on_radserve_pixels(client, env_id, options):
    """The observation wrappers on pixel envs, channels last (gymnasium's image layout, which
    GrayscaleObservation needs): each wrapped env's observations equal the wrapper applied to the
    bare env's (the same seed and actions), step for step."""
    from gymnasium.wrappers import vector as wrappers

    def make():
        return client.make_vec(env_id, num_envs=2, seed=4, autoreset_mode=AutoresetMode.NEXT_STEP, channels_last=True,
                               frame_stack=1, **options)

    stacks = [
        (lambda env: wrappers.GrayscaleObservation(env),
         lambda obs: (obs.astype(np.float64) @ np.array([0.2125, 0.7154, 0.0721])).astype(np.uint8)),
        (lambda env: wrappers.GrayscaleObservation(env, keep_dim=True), None),
        (lambda env: wrappers.TransformObservation(env, lambda obs: obs // 2), lambda obs: obs // 2),
        (lambda env: wrappers.DtypeObservation(env, np.float32), lambda obs: obs.astype(np.float32)),
        (lambda env: wrappers.FlattenObservation(env), lambda obs: obs.reshape(len(obs), -1)),
        (lambda env: wrappers.NormalizeObservation(env), None),
        (lambda env: wrappers.RecordEpisodeStatistics(env), lambda obs: obs),
    ]
    bare = make()
    try:
        assert bare.single_observation_space.shape[-1] == 3
        for wrap, expected in stacks:
            env = wrap(make())
            try:
                obs, _ = env.reset(seed=4)
                bare_obs, _ = bare.reset(seed=4)
                for _ in range(40):
                    assert obs.shape == env.observation_space.shape
                    if expected is not None:
                        np.testing.assert_allclose(obs, expected(bare_obs), atol=1)
                    actions = bare.action_space.sample()
                    obs, *_ = env.step(actions)
                    bare_obs, *_ = bare.step(actions)
            finally:
                env.close()
    finally:
        bare.close()


@pytest.mark.parametrize("env_id", ["procgen/bigfish", "gym/Hopper-v5", "dmc/cartpole-balance"])
def test_next_step_is_same_step_one_step_later(client, env_id):
    """Where gymnasium has no reference (ProcGen, whose games are stepped as one procgen vector; dm_control):
    under NEXT_STEP an ending step returns what SAME_STEP gives as final_obs, and the next step
    returns, with reward 0 and no flags, what SAME_STEP returned as the new episode's start; the
    other envs are unaffected by the skipped one."""
    same = client.make_vec(env_id, num_envs=4, seed=3, autoreset_mode="SameStep")
    nxt = client.make_vec(env_id, num_envs=4, seed=3, autoreset_mode="NextStep")
    try:
        np.testing.assert_array_equal(same.reset(seed=3)[0], nxt.reset(seed=3)[0])
        for _ in range(3000):
            actions = np.stack([same.single_action_space.sample() for _ in range(4)])
            a, b = same.step(actions), nxt.step(actions)
            np.testing.assert_array_equal(a[1], b[1])
            ended = a[2] | a[3]
            if not ended.any():
                np.testing.assert_array_equal(a[0], b[0])
                continue
            i = int(np.flatnonzero(ended)[0])
            np.testing.assert_array_equal(a[4]["final_obs"][i], b[0][i])
            started = a[0][i].copy()
            after = nxt.step(np.stack([same.single_action_space.sample() for _ in range(4)]))
            np.testing.assert_array_equal(after[0][i], started)
            assert after[1][i] == 0.0 and not after[2][i] and not after[3][i]
            break
        else:
            pytest.fail("no episode ended")
    finally:
        same.close()
        nxt.close()


def test_infos_travel_as_one_typed_column_per_key(server):
    """Over the raw API, a Hopper x4 step's infos are one column per key over the four envs (the two
    worker processes' columns joined), numpy float64 scalars as the env returns them."""
    import grpc

    from radserve._proto import radserve_pb2 as pb
    from radserve._proto import radserve_pb2_grpc as pb_grpc
    from radserve.proto import to_numpy, to_tensor

    reference = gymnasium.make("Hopper-v5")
    _, want = reference.reset(seed=0)
    reference.close()
    with grpc.insecure_channel(server.address) as channel:
        stub = pb_grpc.RadServeStub(channel)
        session = stub.CreateSession(pb.CreateSessionRequest(env_id="gym/Hopper-v5", num_envs=4, seed=0))
        try:
            reset = stub.Reset(pb.ResetRequest(session_id=session.session_id, seed=0))
            assert [list(column.path) for column in reset.reset_infos] == [[key] for key in want]
            step = stub.Step(pb.StepRequest(session_id=session.session_id,
                                            actions=to_tensor(np.zeros((4, 3), np.float32))))
            assert len(step.step_infos) >= 4 and not step.reset_infos
            for column in step.step_infos:
                assert list(column.envs) == [0, 1, 2, 3] and len(column.path) == 1
                assert column.kind in (pb.INFO_KIND_SCALAR, pb.INFO_KIND_PYTHON)
                assert to_numpy(column.values).shape == (4,)
        finally:
            stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id))


@pytest.mark.parametrize("delivery", ["grpc", "shared_memory"])
def test_send_infos_false_leaves_the_envs_infos_out(client, delivery):
    quiet = client.make_vec("gym/Hopper-v5", num_envs=2, seed=0, delivery=delivery, send_infos=False,
                            autoreset_mode="SameStep", max_episode_steps=5)
    talking = client.make_vec("gym/Hopper-v5", num_envs=2, seed=0, delivery=delivery,
                              autoreset_mode="SameStep", max_episode_steps=5)
    try:
        assert quiet.reset(seed=0)[1] == {} and "x_position" in talking.reset(seed=0)[1]
        for t in range(6):  # across an episode end: radserve's own figures still come
            actions = np.zeros((2, 3), np.float32)
            _, _, _, truncated, infos = quiet.step(actions)
            _, _, _, _, said = talking.step(actions)
            assert ours_only(infos) == ({"final_obs": infos["final_obs"], "_final_obs": infos["_final_obs"],
                                         "final_info": {}, "_final_info": infos["_final_info"]}
                                        if truncated.any() else {}), t
            assert said["_x_position"].all()
            if t == 4:
                assert truncated.all() and infos["_radserve_episode"].all()
    finally:
        quiet.close()
        talking.close()
