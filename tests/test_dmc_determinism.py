"""The server's pixels for seed s are dm_control's own: `suite.load(domain, task,
task_kwargs={'random': s})` rendered from the same camera after the same actions, bit for bit."""

import numpy as np
from dm_control import suite


def test_pixels_equal_dm_control_rendered_in_process(client):
    seed, action_repeat = 3, 8
    envs = client.make_vec("dmc/cartpole-swingup", num_envs=2, seed=seed)
    try:
        obs, _ = envs.reset()
        assert envs.info.options["action_repeat"] == action_repeat
        direct = [suite.load("cartpole", "swingup", task_kwargs={"random": seed + i}) for i in range(2)]
        for env in direct:
            env.reset()

        def rendered(env):
            return env.physics.render(height=100, width=100, camera_id=0).transpose(2, 0, 1)

        for i, env in enumerate(direct):
            np.testing.assert_array_equal(obs[i, -3:], rendered(env))
        rng = np.random.default_rng(0)
        for _ in range(3):
            actions = rng.uniform(-1, 1, size=(2, 1)).astype(np.float32)
            obs, rewards, _, _, _ = envs.step(actions)
            for i, env in enumerate(direct):
                reward = sum(env.step(actions[i]).reward for _ in range(action_repeat))
                np.testing.assert_array_equal(obs[i, -3:], rendered(env))
                assert rewards[i] == reward

        # Reseeding loads the tasks anew (and the worker its cameras): still dm_control's own pixels.
        obs, _ = envs.reset(seed=11)
        direct = [suite.load("cartpole", "swingup", task_kwargs={"random": 11 + i}) for i in range(2)]
        for i, env in enumerate(direct):
            env.reset()
            np.testing.assert_array_equal(obs[i, -3:], rendered(env))
        obs, _, _, _, _ = envs.step(actions)
        for i, env in enumerate(direct):
            for _ in range(action_repeat):
                env.step(actions[i])
            np.testing.assert_array_equal(obs[i, -3:], rendered(env))
    finally:
        envs.close()
