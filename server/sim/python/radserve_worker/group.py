"""A group: the envs of one session that live in this worker, each its family's adapter, stepped
together under one GIL hold."""

import numpy as np

from radserve_worker.common import info_columns


class Group:
    """Environments of one session that live in this worker, stepped together under one GIL hold."""

    def __init__(self, adapter, name, options, seeds):
        self.adapter, self.name, self.options = adapter, name, options
        # The session's option send_infos=False: the envs' info dicts are not collected or sent.
        self.send_infos = bool(options.get("send_infos", True))
        self.seeds = list(seeds)
        self.envs = [adapter(name, options, seed) for seed in self.seeds]
        self._spec = self.envs[0].spec()
        action = self._spec["action"]
        if action["kind"] == "discrete":
            self.action_dtype, self.action_shape = np.dtype(np.int64), ()
        else:
            self.action_dtype, self.action_shape = np.dtype(action["dtype"]), tuple(action["shape"])
        self.current = self.final = None

    def attach(self, frames):
        """Views shared memory as, per env, its current frame then the final frame of its last episode."""
        observation = self._spec["observation"]
        dtype = np.dtype(observation["dtype"])
        shape = tuple(observation["shape"])
        n = len(self.seeds)
        slots = np.frombuffer(frames, dtype=dtype, count=2 * n * int(np.prod(shape))).reshape((n, 2) + shape)
        self.current = slots[:, 0]
        self.final = slots[:, 1]

    def spec(self):
        return self._spec

    def reset(self, seeds, mask=None):
        """Resets every env, or those whose `mask` entry is true; `seeds` (one per env of the group)
        re-seed the envs reset. Returns the reset infos as columns (common.info_columns)."""
        infos = []
        for j, env in enumerate(self.envs):
            if mask is not None and not mask[j]:
                continue
            if seeds is not None:
                self.seeds[j] = seeds[j]
            self.current[j], info = env.reset(None if seeds is None else seeds[j])
            if info and self.send_infos:
                infos.append((j, info))
        return info_columns(infos)

    def _restart(self, j):
        """Resets env j after its simulator raised (its frame and reset info); rebuilds it when even
        the reset fails."""
        try:
            return self.envs[j].reset(None)
        except Exception:
            self.envs[j] = self.adapter(self.name, self.options, self.seeds[j])
            return self.envs[j].reset(None)

    def step(self, actions, skip=None):
        """Steps every env, except those whose `skip` entry is true (gymnasium NEXT_STEP's reset step:
        they keep their frame, reward 0, no flag). Returns rewards, terminated, truncated, errors
        (env, message) and the step's and the resets' infos as columns (common.info_columns)."""
        n = len(self.envs)
        actions = np.frombuffer(actions, dtype=self.action_dtype).reshape((n,) + self.action_shape)
        rewards = [0.0] * n
        terminated = [False] * n
        truncated = [False] * n
        errors, step_infos, reset_infos = [], [], []
        for j, env in enumerate(self.envs):
            if skip is not None and skip[j]:
                continue
            reset_info = None
            try:
                frame, rewards[j], terminated[j], truncated[j], info = env.step(actions[j])
            except Exception as exc:  # the simulator raised: end this episode, keep the worker
                errors.append((j, f"{type(exc).__name__}: {exc}"))
                self.final[j] = self.current[j]
                truncated[j] = True
                self.current[j], reset_info = self._restart(j)
                if reset_info and self.send_infos:
                    reset_infos.append((j, reset_info))
                continue
            if terminated[j] or truncated[j]:
                self.final[j] = frame
                self.current[j], reset_info = env.reset(None)
            else:
                self.current[j] = frame
            if self.send_infos:
                if info:
                    step_infos.append((j, info))
                if reset_info:
                    reset_infos.append((j, reset_info))
        return rewards, terminated, truncated, errors, info_columns(step_infos), info_columns(reset_infos)

    def close(self):
        for env in self.envs:
            env.close()
        self.envs = []
        self.current = self.final = None
