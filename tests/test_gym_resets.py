"""Seeding as gymnasium does it: a seeded reset sets the stream every later autoreset continues, the
same as gymnasium's own env given the same seed and actions."""

import gymnasium
import numpy as np


def test_a_seeded_reset_is_continued_by_the_autoresets_after_it(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=1, seed=0)
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
