"""Seeding as gymnasium does it: a seeded reset sets the stream every later autoreset continues, the
same as gymnasium's own env given the same seed and actions."""

import gymnasium
import numpy as np
import pytest

import radserve


def test_a_seeded_reset_is_continued_by_the_autoresets_after_it(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=1, seed=0, autoreset_mode="SameStep")
    reference = gymnasium.make("CartPole-v1")
    try:
        obs, _ = envs.reset(seed=100)
        expected, _ = reference.reset(seed=100)
        np.testing.assert_allclose(obs[0], expected, rtol=1e-6)
        episodes = 0
        for _ in range(200):  # pushing one way ends CartPole's episodes in ~10 steps
            obs, _, terminated, truncated, _ = envs.step(np.zeros(1, dtype=np.int64))
            expected, _, ended, cut, _ = reference.step(0)
            if ended or cut:
                episodes += 1
                expected, _ = reference.reset()  # continues seed 100's stream
            assert bool(terminated[0] or truncated[0]) == bool(ended or cut)
            np.testing.assert_allclose(obs[0], expected, rtol=1e-6)
        assert episodes >= 3, "the comparison should cross several autoresets"
    finally:
        envs.close()
        reference.close()


def test_seeds_as_gymnasium_passes_them(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=3, seed=0)
    try:
        by_int, _ = envs.reset(seed=5)
        by_list, _ = envs.reset(seed=[5, 6, 7])
        by_numpy, _ = envs.reset(seed=np.int64(5))
        np.testing.assert_array_equal(by_int, by_list)
        np.testing.assert_array_equal(by_int, by_numpy)
        envs.reset(seed=[None, None, None])
        # Any seed per env, as gymnasium takes them: env 1 seeded 6 starts as env 1 of the first reset.
        by_env, _ = envs.reset(seed=[1, 6, 2])
        np.testing.assert_array_equal(by_env[1], by_int[1])
        for bad in (-1, [1, None, 2], [5, 6], 2.5, "5", True):
            with pytest.raises(radserve.InvalidArgumentError):
                envs.reset(seed=bad)
    finally:
        envs.close()
