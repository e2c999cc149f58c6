"""gymnasium's tasks (gym/...): MuJoCo (v5) and classic control, state observations."""

import numpy as np

from radserve_worker.common import box, discrete


# The gymnasium ids radserve hosts: MuJoCo tasks (v5) and classic control.
GYM_IDS = [
    "Ant-v5", "HalfCheetah-v5", "Hopper-v5", "Humanoid-v5", "HumanoidStandup-v5",
    "InvertedDoublePendulum-v5", "InvertedPendulum-v5", "Pusher-v5", "Reacher-v5", "Swimmer-v5",
    "Walker2d-v5", "CartPole-v1", "Pendulum-v1", "Acrobot-v1", "MountainCar-v0",
    "MountainCarContinuous-v0",
]


class GymEnv:
    """A gymnasium task with state observations (cast to float32)."""

    def __init__(self, name, options, seed):
        import gymnasium

        kwargs = {}
        if options["max_episode_steps"] > 0:
            kwargs["max_episode_steps"] = options["max_episode_steps"]
        self.env = gymnasium.make(name, **kwargs)
        self.action_repeat = options["action_repeat"]
        self.seed = seed
        self.discrete = isinstance(self.env.action_space, gymnasium.spaces.Discrete)

    def spec(self):
        obs_space = self.env.observation_space
        observation = box(np.float32, obs_space.shape, obs_space.low, obs_space.high)
        act_space = self.env.action_space
        if self.discrete:
            action = discrete(act_space.n)
        else:
            action = box(np.float32, act_space.shape, act_space.low, act_space.high)
        return {"observation": observation, "action": action}

    def reset(self, seed):
        # The first reset seeds the environment with its own seed unless it is given one; every later
        # unseeded reset (autoresets included) continues the stream of the last seed.
        if seed is None:
            seed = self.seed
        self.seed = None
        obs, info = self.env.reset(seed=seed)
        return obs, info

    def step(self, action):
        action = int(action) if self.discrete else action
        reward, terminated, truncated = 0.0, False, False
        for _ in range(self.action_repeat):
            obs, r, terminated, truncated, info = self.env.step(action)
            reward += float(r)
            if terminated or truncated:
                break
        # The info of the last step of the action repeat.
        return obs, reward, bool(terminated), bool(truncated), info

    def close(self):
        self.env.close()
