"""One contract every simulator family must honour, run against the real server (the model is
dm_env's EnvironmentTestMixin: each family only instantiates the class with its env id)."""

import numpy as np
import pytest
from gymnasium import spaces

import radserve


class EnvContract:
    env_id: str
    options: dict = {}
    # Options that make episodes end within a few steps, to see autoreset.
    short_episode_options: dict = {}
    num_envs = 2
    max_steps_to_episode_end = 50
    # How the client acts: gRPC, or shared memory with the server (same host).
    delivery = "grpc"
    # The contract is the server's: an episode's end resets its env in the same step (SameStep; the
    # client's other modes are gymnasium's, checked against SyncVectorEnv in test_gymnasium_contract).
    autoreset_mode = "SameStep"

    def make(self, client, seed=0, **extra):
        envs = client.make_vec(
            self.env_id, num_envs=self.num_envs, seed=seed, delivery=self.delivery,
            autoreset_mode=self.autoreset_mode, **{**self.options, **extra}
        )
        assert envs.delivery == self.delivery
        return envs

    def random_actions(self, envs, rng):
        space = envs.single_action_space
        if isinstance(space, spaces.Discrete):
            return rng.integers(0, space.n, size=self.num_envs)
        return rng.uniform(space.low, space.high, size=(self.num_envs,) + space.shape).astype(np.float32)

    def test_spaces_match_the_catalog(self, client, catalog):
        entry = catalog[self.env_id]
        envs = self.make(client)
        try:
            if not self.options:
                assert envs.single_observation_space == entry.observation_space
            assert envs.single_action_space == entry.action_space
            assert envs.observation_space.shape == (self.num_envs,) + envs.single_observation_space.shape
        finally:
            envs.close()

    def test_reset_and_step_match_the_spaces(self, client):
        envs = self.make(client)
        rng = np.random.default_rng(0)
        try:
            obs, _ = envs.reset()
            assert obs.dtype == envs.single_observation_space.dtype
            assert obs.shape == envs.observation_space.shape
            assert envs.observation_space.contains(obs)
            for _ in range(3):
                obs, rewards, terminated, truncated, _ = envs.step(self.random_actions(envs, rng))
                assert obs.shape == envs.observation_space.shape and obs.dtype == envs.single_observation_space.dtype
                assert rewards.shape == (self.num_envs,) and rewards.dtype == np.float64
                assert terminated.shape == truncated.shape == (self.num_envs,) and terminated.dtype == bool
            assert envs.describe()[0].total_env_steps == 3 * self.num_envs
        finally:
            envs.close()

    def test_frames_are_stacked_oldest_first(self, client):
        envs = self.make(client, frame_stack=3)
        rng = np.random.default_rng(1)
        try:
            obs, _ = envs.reset()
            frame = obs.shape[1] // 3
            assert envs.single_observation_space.shape[0] == 3 * frame
            # At reset the first frame fills the stack.
            np.testing.assert_array_equal(obs[:, :frame], obs[:, 2 * frame:])
            next_obs, _, terminated, truncated, _ = envs.step(self.random_actions(envs, rng))
            for i in np.flatnonzero(~(terminated | truncated)):
                np.testing.assert_array_equal(next_obs[i, :2 * frame], obs[i, frame:])
        finally:
            envs.close()

    def test_episodes_end_reset_themselves_and_are_reported(self, client):
        envs = self.make(client, **self.short_episode_options)
        rng = np.random.default_rng(2)
        try:
            envs.reset()
            returns = np.zeros(self.num_envs)
            lengths = np.zeros(self.num_envs, dtype=int)
            for _ in range(self.max_steps_to_episode_end):
                obs, rewards, terminated, truncated, infos = envs.step(self.random_actions(envs, rng))
                returns += rewards
                lengths += 1
                done = terminated | truncated
                if done.any():
                    break
            else:
                pytest.fail(f"no episode of {self.env_id} ended within {self.max_steps_to_episode_end} steps")
            np.testing.assert_array_equal(infos["_final_obs"], done)
            np.testing.assert_array_equal(infos["_radserve_episode"], done)
            for i in np.flatnonzero(done):
                assert infos["final_obs"][i].shape == envs.single_observation_space.shape
                assert infos["radserve_episode"]["l"][i] == lengths[i]
                assert infos["radserve_episode"]["r"][i] == pytest.approx(returns[i])
            # The session keeps going: the next step continues the new episodes.
            envs.step(self.random_actions(envs, rng))
        finally:
            envs.close()

    def test_same_seed_and_actions_give_the_same_observations(self, client):
        first, second = self.make(client, seed=11), self.make(client, seed=11)
        rng = np.random.default_rng(3)
        try:
            obs_a, _ = first.reset()
            obs_b, _ = second.reset()
            np.testing.assert_array_equal(obs_a, obs_b)
            for _ in range(4):
                actions = self.random_actions(first, rng)
                step_a, step_b = first.step(actions), second.step(actions)
                np.testing.assert_array_equal(step_a[0], step_b[0])
                np.testing.assert_array_equal(step_a[1], step_b[1])
        finally:
            first.close()
            second.close()

    def test_reseeding_at_reset_replays_the_same_episode(self, client):
        envs = self.make(client, seed=5)
        rng = np.random.default_rng(4)
        try:
            actions = [self.random_actions(envs, rng) for _ in range(3)]
            runs = []
            for _ in range(2):
                obs, _ = envs.reset(seed=21)
                trajectory = [obs.copy()]
                for action in actions:
                    trajectory.append(envs.step(action)[0].copy())
                runs.append(trajectory)
            for a, b in zip(*runs):
                np.testing.assert_array_equal(a, b)
        finally:
            envs.close()

    def test_bad_actions_are_rejected_and_change_nothing(self, client):
        envs = self.make(client)
        rng = np.random.default_rng(5)
        try:
            envs.reset()
            with pytest.raises(radserve.InvalidArgumentError, match="of shape"):
                envs.step(self.random_actions(envs, rng)[:1])
            if isinstance(envs.single_action_space, spaces.Discrete):
                bad = np.full(self.num_envs, envs.single_action_space.n)
                match = "outside"
            else:
                bad = self.random_actions(envs, rng)
                bad.reshape(self.num_envs, -1)[0, 0] = np.nan
                match = "NaN"
            with pytest.raises(radserve.InvalidArgumentError, match=match):
                envs.step(bad)
            assert envs.describe()[0].total_env_steps == 0
            envs.step(self.random_actions(envs, rng))
            assert envs.describe()[0].total_env_steps == self.num_envs
        finally:
            envs.close()


class TestDmcPixels(EnvContract):
    env_id = "dmc/cartpole-balance"
    options = {"height": 48, "width": 48, "render_profile": "fast"}
    short_episode_options = {"action_repeat": 250}


class TestDmcState(EnvContract):
    env_id = "dmc/cheetah-run"
    options = {"pixels": False}
    short_episode_options = {"action_repeat": 250}


class TestGymMujoco(EnvContract):
    env_id = "gym/HalfCheetah-v5"
    short_episode_options = {"max_episode_steps": 5}


class TestGymDiscrete(EnvContract):
    env_id = "gym/CartPole-v1"
    short_episode_options = {"max_episode_steps": 5}


class TestProcgen(EnvContract):
    env_id = "procgen/bigfish"
    num_envs = 4
    max_steps_to_episode_end = 3000

    def test_procgen_threads_do_not_change_the_frames(self, client):
        """num_threads only decides where procgen steps (the worker's thread by default, or procgen's own
        pool): the same seed and actions give the same frames and rewards either way."""
        rng = np.random.default_rng(5)
        actions = [rng.integers(0, 15, size=self.num_envs) for _ in range(40)]
        runs = []
        for threads in (0, 2):
            envs = self.make(client, seed=11, num_threads=threads)
            try:
                frames, rewards = [envs.reset()[0]], []
                for action in actions:
                    obs, reward, _, _, _ = envs.step(action)
                    frames.append(obs)
                    rewards.append(reward)
                runs.append((np.stack(frames), np.stack(rewards)))
            finally:
                envs.close()
        np.testing.assert_array_equal(runs[0][0], runs[1][0])
        np.testing.assert_array_equal(runs[0][1], runs[1][1])
        assert runs[0][0][1:].std() > 0  # the frames move, so equality says something


# The same contract through shared stepping, for a pixel, a state, a discrete and a ProcGen env.
class TestDmcPixelsSharedMemory(TestDmcPixels):
    delivery = "shared_memory"


class TestGymMujocoSharedMemory(TestGymMujoco):
    delivery = "shared_memory"


class TestGymDiscreteSharedMemory(TestGymDiscrete):
    delivery = "shared_memory"


class TestProcgenSharedMemory(TestProcgen):
    delivery = "shared_memory"
