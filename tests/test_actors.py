"""Server-side actors with the real simulators: the server steps dm_control pixels with RAD's SAC
actor (gaussian_tanh), a gymnasium MuJoCo task with a state MLP, and ProcGen with a categorical
policy into a rollout; batches carry the acting version (and, for rollouts, log-probabilities and
values); a client's step is refused while the server acts; bad models are refused with the reason.
Models are built with onnx.helper (tests/policies.py), so no torch is needed here. Over gRPC on the
fake simulators: server/radserve/tests/actors.rs; the actor's loop alone: core/src/actor/tests.rs."""

import time

import numpy as np
import pytest

from radserve import FailedPreconditionError, InvalidArgumentError
from radserve.training import evaluate, evaluate_on_servers

import policies


def wait_for(envs, done, timeout=120.0):
    deadline = time.monotonic() + timeout
    while True:
        info = envs.acting()[0]
        if done(info):
            return info
        assert time.monotonic() < deadline, f"the actor never got there: {info}"
        time.sleep(0.05)


def test_rad_actor_acts_on_dm_control_pixels_and_batches_carry_its_version(client):
    envs = client.make_vec("dmc/cartpole-swingup", num_envs=4, seed=3, replay_capacity=4000,
                           observation_view="center_crop(84)", autoreset_mode="SameStep")
    try:
        channels, size, _ = envs.single_observation_space.shape
        action_dim = envs.single_action_space.shape[0]
        model = policies.rad_actor(frames=channels, size=size, action_dim=action_dim)
        (loaded,) = envs.set_policy(model, head="gaussian_tanh")
        assert loaded.version == 1 and "Conv" in loaded.ops and "LayerNormalization" in loaded.ops
        (started,) = envs.start_acting(random_steps=8)
        assert started.state == "acting"
        with pytest.raises(FailedPreconditionError, match="StopActing"):
            envs.step(np.zeros((4, action_dim), dtype=np.float32))
        info = wait_for(envs, lambda info: info.env_steps >= 64)
        assert info.acting_version == 1 and info.head == "gaussian_tanh" and info.inference_seconds > 0
        low, high = envs.single_action_space.low, envs.single_action_space.high
        versions = set()
        with envs.sample_batches(batch_size=32, augment="crop(84)", max_batches=3) as stream:
            for batch in stream:
                assert batch.obs.shape == (32, channels, 84, 84)
                assert batch.policy_version.dtype == np.int32
                versions.update(batch.policy_version.tolist())
                assert np.all(batch.action >= low) and np.all(batch.action <= high)
                # The two random steps (8 env steps over 4 envs) carry no version.
                assert np.all((batch.policy_version == -1) == (batch.step_index < 2))
        assert 1 in versions
        (stopped,) = envs.stop_acting()
        assert stopped.state == "stopped" and stopped.env_steps >= 64
        assert envs.describe()[0].total_env_steps == stopped.env_steps
        obs, *_ = envs.step(np.zeros((4, action_dim), dtype=np.float32))
        assert obs.shape == (4, channels, size, size)
    finally:
        envs.close()


def test_a_state_policy_acts_on_gymnasium_mujoco(client):
    envs = client.make_vec("gym/HalfCheetah-v5", num_envs=2, seed=0, replay_capacity=500)
    try:
        obs_dim, action_dim = envs.single_observation_space.shape[0], envs.single_action_space.shape[0]
        envs.set_policy(policies.mlp_gaussian(obs_dim, action_dim), head="gaussian_tanh", version=7)
        envs.start_acting(max_env_steps=200)
        info = wait_for(envs, lambda info: info.state != "acting")
        assert (info.state, info.env_steps, info.acting_version) == ("stopped", 200, 7)
        assert envs.describe()[0].replay.size == 200
    finally:
        envs.close()


def test_a_categorical_policy_fills_a_procgen_rollout_with_log_probs_and_values(client):
    envs = client.make_vec("procgen/bigfish", num_envs=4, seed=1, rollout_steps=16, num_levels=10)
    try:
        shape, n = envs.single_observation_space.shape, int(envs.single_action_space.n)
        model = policies.conv_categorical(shape, n, value=True, uint8=True)
        envs.set_policy(model, head="categorical")
        envs.start_acting(max_env_steps=64, seed=9)
        wait_for(envs, lambda info: info.state != "acting")
        batches = list(envs.sample_batches(batch_size=64, source="rollout"))
        assert len(batches) == 1
        batch = batches[0]
        assert np.all(batch.policy_version == 1)
        assert np.all((batch.action >= 0) & (batch.action < n))
        # The recorded log-probabilities and values are the model's on the observations acted on
        # (a rollout's obs is what the action was taken on), computed here with ONNX Runtime.
        import onnxruntime

        logits, value = onnxruntime.InferenceSession(model).run(None, {"obs": batch.obs})
        log_softmax = logits - logits.max(1, keepdims=True)
        log_softmax -= np.log(np.exp(log_softmax).sum(1, keepdims=True))
        np.testing.assert_allclose(batch.log_prob, log_softmax[np.arange(64), batch.action], atol=1e-4)
        np.testing.assert_allclose(batch.value, value[:, 0], atol=1e-4)
    finally:
        envs.close()


def test_bad_models_are_refused_with_the_reason_and_change_nothing(client):
    envs = client.make_vec("procgen/bigfish", num_envs=2, replay_capacity=100)
    try:
        shape, n = envs.single_observation_space.shape, int(envs.single_action_space.n)
        with pytest.raises(InvalidArgumentError, match="not an ONNX model"):
            envs.set_policy(b"\x00\x01 not onnx", head="categorical")
        with pytest.raises(InvalidArgumentError, match="RandomNormalLike"):
            envs.set_policy(policies.with_op(shape, n), head="categorical")
        with pytest.raises(InvalidArgumentError, match="external data"):
            envs.set_policy(policies.external_data(shape, n), head="categorical")
        with pytest.raises(InvalidArgumentError, match="does not take this session's observations"):
            envs.set_policy(policies.conv_categorical((3, 32, 32), n), head="categorical")
        with pytest.raises(InvalidArgumentError, match="use gaussian_tanh or deterministic_noise|use categorical"):
            envs.set_policy(policies.conv_categorical(shape, n), head="gaussian_tanh")
        with pytest.raises(FailedPreconditionError, match="SetPolicy before StartActing"):
            envs.start_acting()
        assert envs.acting()[0] is None
        obs, _ = envs.reset(seed=0)
        assert obs.shape == (2, *shape)
    finally:
        envs.close()


def test_a_nan_policy_stops_its_actor_with_the_error_in_describe(client):
    envs = client.make_vec("procgen/bigfish", num_envs=2, replay_capacity=100)
    try:
        shape, n = envs.single_observation_space.shape, int(envs.single_action_space.n)
        # Finite on the zero observations of the load check, NaN on a real frame.
        envs.set_policy(policies.nan_policy(shape, n), head="categorical")
        envs.start_acting()
        info = wait_for(envs, lambda info: info.state != "acting")
        assert info.state == "failed" and "not finite" in info.error
        assert envs.describe()[0].acting.state == "failed"
        envs.reset(seed=0)
    finally:
        envs.close()


def test_steps_per_env_acts_one_rollout_and_returns_name_their_env(client):
    envs = client.make_vec("procgen/bigfish", num_envs=3, seed=4, rollout_steps=8, num_levels=10)
    try:
        shape, n = envs.single_observation_space.shape, int(envs.single_action_space.n)
        envs.set_policy(policies.conv_categorical(shape, n, value=True, uint8=True), head="categorical")
        for bad in (0, -1, 1.5, True, "8"):
            with pytest.raises(InvalidArgumentError, match="steps_per_env must be a positive integer"):
                envs.start_acting(steps_per_env=bad)
        with pytest.raises(InvalidArgumentError, match="not both"):
            envs.start_acting(steps_per_env=8, max_env_steps=24)
        assert envs.acting()[0].state == "idle"
        for rollout in range(2):
            envs.start_acting(steps_per_env=8, seed=rollout)
            info = wait_for(envs, lambda info: info.state != "acting")
            assert (info.state, info.env_steps) == ("stopped", 24)
            assert len(info.recent_envs) == len(info.recent_returns) and set(info.recent_envs) <= {0, 1, 2}
            (batch,) = envs.sample_batches(batch_size=24, source="rollout")
            # One whole rollout, every (t, env) once, all acted by the policy.
            assert sorted(zip(batch.t.tolist(), batch.env_index.tolist())) == [(t, e) for t in range(8) for e in range(3)]
            assert np.all(batch.policy_version == 1)
        assert envs.describe()[0].total_env_steps == 48
    finally:
        envs.close()


def test_evaluating_on_the_servers_gives_the_learner_side_evaluation(client):
    """evaluate_on_servers (the servers act, eval: argmax) returns what `evaluate` returns for the
    same policy run here, same seeds: each env's first episodes in the same order, although CartPole's
    episodes end at different steps (the first to end would favour the short ones)."""
    import onnxruntime

    # Push towards where the pole leans (its angle only): it balances for a while, episodes of
    # different lengths.
    model = policies.linear_categorical([[0.0, 0.0], [0.0, 0.0], [-1.0, 1.0], [0.0, 0.0]])
    session = onnxruntime.InferenceSession(model)
    here = client.make_vec("gym/CartPole-v1", num_envs=3, seed=21, autoreset_mode="SameStep")
    there = client.make_vec("gym/CartPole-v1", num_envs=3, seed=21, autoreset_mode="SameStep")
    try:
        expected = evaluate(here, lambda obs: session.run(None, {"obs": obs.astype(np.float32)})[0].argmax(1), 7)
        returns = evaluate_on_servers(there, model, "categorical", 7, seed=21)
        assert len(returns) == 7 and len(set(returns)) > 1, returns
        assert returns == expected
        assert there.acting()[0].state == "stopped"
    finally:
        here.close()
        there.close()
