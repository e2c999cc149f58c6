"""DeepMind Control Suite tasks (dmc/...): pixels rendered channel-first, or the flattened state."""

import numpy as np

from radserve_worker.common import box


class DmcEnv:
    """A DeepMind Control Suite task; pixels rendered channel-first, or the flattened state."""

    def __init__(self, name, options, seed):
        self.domain, self.task = name.split("-", 1)
        self.pixels = options["pixels"]
        self.height, self.width = options["height"], options["width"]
        self.camera_id = options["camera_id"]
        self.action_repeat = options["action_repeat"]
        self.fast_render = options["render_profile"] == "fast"
        self.env = None
        self.camera = None
        self._load(seed)

    def _load(self, seed):
        from dm_control import suite

        self.close()
        self.env = suite.load(self.domain, self.task, task_kwargs={"random": seed})
        if self.fast_render:
            # The fast profile for CPU-only hosts: no shadows, no reflections, no multisampling.
            model = self.env.physics.model
            model.vis.quality.shadowsize = 0
            model.vis.quality.offsamples = 0
            model.mat_reflectance[:] = 0
            model.light_castshadow[:] = 0
        self.action_spec = self.env.action_spec()
        if self.pixels:
            from dm_control.mujoco.engine import Camera

            # One camera for the env's life. physics.render() builds a Camera, and with it an MjvScene,
            # for every frame and frees it after; keeping one renders the same pixels (the test
            # against physics.render checks it) in 34-38 ms instead of 42 ms per default-look frame.
            self.camera = Camera(self.env.physics, height=self.height, width=self.width, camera_id=self.camera_id)

    def spec(self):
        if self.pixels:
            observation = box(np.uint8, (3, self.height, self.width), 0, 255)
        else:
            size = sum(int(np.prod(v.shape)) for v in self.env.observation_spec().values())
            observation = box(np.float32, (size,), -np.inf, np.inf)
        action = box(np.float32, self.action_spec.shape, self.action_spec.minimum, self.action_spec.maximum)
        return {"observation": observation, "action": action}

    def _observe(self, time_step):
        if self.pixels:
            return self.camera.render().transpose(2, 0, 1)
        return np.concatenate([np.asarray(v, dtype=np.float32).reshape(-1) for v in time_step.observation.values()])

    def reset(self, seed):
        if seed is not None:
            self._load(seed)
        # dm_control's time steps carry no info dict.
        return self._observe(self.env.reset()), {}

    def step(self, action):
        reward = 0.0
        for _ in range(self.action_repeat):
            time_step = self.env.step(action)
            reward += time_step.reward or 0.0
            if time_step.last():
                break
        # dm_env: a last step with discount 0 is a termination, otherwise the time limit truncated it.
        ended = time_step.last()
        terminated = ended and time_step.discount == 0.0
        return self._observe(time_step), reward, terminated, ended and not terminated, {}

    def close(self):
        if self.camera is not None:
            # What physics.render() does after each frame: the scene's memory is not garbage-collected.
            self.camera._scene.free()
            self.camera = None
        if self.env is not None:
            self.env.close()
            self.env = None
