"""EnvPool's C++ ports as the engine of a session (option engine="envpool"): dm_control state tasks,
gymnasium's MuJoCo and classic-control tasks, ProcGen games."""

import numpy as np

from radserve_worker.common import box, discrete
from radserve_worker.group import Group


def _import_envpool():
    try:
        import envpool
        from envpool.python import data
    except ImportError as exc:
        raise ValueError(f"engine 'envpool' needs EnvPool in the server's Python environment ({exc})") from None
    if not getattr(data, "_radserve_patched", False):
        # EnvPool 1.2.5 asks of every one-element bound whether it is a small integer with
        # np.isclose(bound, int(bound)); for an unbounded float spec (dm_control walker's `height`,
        # +-1.8e308) int() is a 309-digit Python int that numpy 1.x (procgen pins numpy<2) cannot
        # convert, and building the space raises TypeError. Such a bound is no small integer: answer
        # None, which is what the function returns for every other non-integer bound.
        original = data._maybe_scalar_int

        def maybe_scalar_int(value):
            try:
                return original(value)
            except (TypeError, OverflowError):
                return None

        data._maybe_scalar_int = maybe_scalar_int
        data._radserve_patched = True
    return envpool


def envpool_task(family, name, options):
    """EnvPool's task id and make() keywords for a radserve env id and its options (engine="envpool")."""
    envpool = _import_envpool()

    if family == "dmc":  # state only: the server refuses engine "envpool" with pixels (catalog.rs)
        # cheetah-run -> CheetahRun-v1, ball_in_cup-catch -> BallInCupCatch-v1
        task = "".join(part[:1].upper() + part[1:] for part in name.replace("_", "-").split("-")) + "-v1"
        kwargs = {}
    elif family == "gym":
        task = name
        kwargs = {"max_episode_steps": options["max_episode_steps"]} if options["max_episode_steps"] > 0 else {}
    else:
        task = f"{name.capitalize()}{options['distribution_mode'].capitalize()}-v0"
        kwargs = {key: options[key] for key in (
            "num_levels", "start_level", "restrict_themes", "use_backgrounds", "use_monochrome_assets",
            "center_agent", "use_sequential_levels", "paint_vel_info", "use_generated_assets")}
    known = envpool.list_all_envs()
    if task not in known:
        raise ValueError(f"engine 'envpool' has no port of {family}/{name} (EnvPool task {task}); "
                         f"use engine 'native' for it")
    return task, kwargs


class EnvpoolGroup(Group):
    """A session's envs in this worker stepped by EnvPool's C++ ports (option engine="envpool"):
    dm_control state tasks, gymnasium's MuJoCo and classic-control tasks, ProcGen games.

    One EnvPool in synchronous mode (batch = the group) with its own stepping threads (the server puts
    the whole session in one worker and passes `envpool_threads`): the worker thread hands it the
    group's actions and waits, as it waits for its own Python stepping otherwise.
    EnvPool's sync mode also takes a subset of envs (env_id), which gives radserve's contract:
    - same-step autoreset: envs whose episode ended are reset right after the step (one more EnvPool
      call, only on steps where an episode ends), their last observation kept as the final one;
    - action repeat as radserve does it for the native engine: the action is sent `action_repeat`
      times, rewards summed, an env leaving the repeat when its episode ends. (EnvPool's own
      `frame_skip` is not this: for dm_control it multiplies the physics substeps of one control
      step and scores only the last, for MuJoCo-gym it is the model's frame skip.);
    - seeds: env i gets its own seed through EnvPool's `env_seed`; a seeded reset rebuilds the pool.
    Results follow EnvPool's ports, not dm_control's or gymnasium's Python (docs/performance.md,
    "EnvPool engine"); envs' info dicts are not sent (EnvPool's are its bookkeeping: env_id,
    elapsed_step, players).
    """

    def __init__(self, family, name, options, seeds):
        self.family, self.name = family, name
        self.task, self.kwargs = envpool_task(family, name, options)
        self.repeat = int(options.get("action_repeat", 1))
        # EnvPool's stepping threads: ProcGen's num_threads when given, else one per worker process of the
        # server (groups.rs puts an envpool session's envs in one worker and says how many).
        threads = int(options.get("num_threads", 0)) if family == "procgen" else 0
        self.threads = threads if threads > 0 else max(1, int(options.get("envpool_threads", 1)))
        self.seeds = [int(seed) for seed in seeds]
        self.n = len(self.seeds)
        self.ids = np.arange(self.n, dtype=np.int32)
        # EnvPool's asynchronous mode (send/recv, below) when below num_envs: results come back `batch`
        # envs at a time.
        batch = int(options.get("batch_size", 0))
        self.batch = batch if 0 < batch < self.n else self.n
        self.pool = self._build()
        self.fresh = True  # built and not stepped since: a reset with its own seeds need not rebuild
        obs_space, act_space = self.pool.observation_space, self.pool.action_space
        if hasattr(obs_space, "spaces"):  # dm_control: a dict of arrays, flattened as the native engine does
            self.keys = self._dmc_keys(obs_space)
            size = sum(int(np.prod(obs_space.spaces[key].shape)) for key in self.keys)
            observation = box(np.float32, (size,), -np.inf, np.inf)
        else:
            self.keys = None
            if obs_space.dtype == np.uint8:
                observation = box(np.uint8, obs_space.shape, 0, 255)
            else:
                observation = box(np.float32, obs_space.shape, obs_space.low, obs_space.high)
        if hasattr(act_space, "n"):
            action = discrete(act_space.n)
            self.action_dtype, self.action_shape, self.send_dtype = np.dtype(np.int64), (), np.int32
        else:
            action = box(np.float32, act_space.shape, act_space.low, act_space.high)
            self.action_dtype, self.action_shape = np.dtype(np.float32), tuple(act_space.shape)
            self.send_dtype = act_space.dtype
        self._spec = {"observation": observation, "action": action}
        self.state_index = self._index_state()
        self.current = self.final = None
        if self.batch < self.n and self.state_index is None:
            self.pool.close()
            raise ValueError("engine 'envpool' with batch_size below num_envs needs EnvPool's raw interface "
                             "(_send/_recv), which this EnvPool lacks")
        self.phase = np.full(self.n, _IDLE, dtype=np.int8)
        self.left = np.zeros(self.n, dtype=np.int64)  # repeats still to send, per stepping env
        self.sent = None  # each env's action of its current agent step (EnvPool's dtype)
        self.acc = np.zeros(self.n)  # reward summed over the repeats so far
        self.ended = np.zeros((self.n, 2), dtype=bool)  # terminated, truncated of the current agent step
        self.ready = []  # env ids whose agent step is complete and not yet returned by recv, in order

    def _index_state(self):
        """Positions, in EnvPool's raw state list (`_recv()`), of what a step needs, or None when this
        EnvPool lacks the raw interface. The raw calls skip its Python wrapper (action conversion, the
        state tree, the info dict), 60-70 us of the worker's time per call on this 2-core VM
        (bench/envpool_calls.py); tests/test_envpool_engine.py checks they give what `step` gives."""
        pool = self.pool
        names = list(getattr(pool, "_state_keys", ()))
        actions = list(getattr(getattr(pool, "_spec", None), "_action_keys", ()))
        obs = [f"obs:{key}" for key in self.keys] if self.keys is not None else ["obs"]
        needed = ["info:env_id", "reward", "done", "trunc"] + obs
        if not (hasattr(pool, "_send") and hasattr(pool, "_recv") and hasattr(pool, "_reset")
                and actions == ["env_id", "players.env_id", "action"] and all(key in names for key in needed)):
            return None
        return [names.index(key) for key in needed]

    def _dmc_keys(self, obs_space):
        """dm_control's observation names for the task, in its order. EnvPool's dict holds every
        observation of the domain (finger-spin has finger-turn's target too), so the names come from
        dm_control's own spec: the same vector as the native engine's."""
        from dm_control import suite

        domain, task = self.name.split("-", 1)
        env = suite.load(domain, task)
        try:
            keys = list(env.observation_spec())
        finally:
            env.close()
        missing = [key for key in keys if key not in obs_space.spaces]
        if missing:
            raise ValueError(f"EnvPool's {self.task} lacks dm_control's observations {missing}")
        return keys

    def _build(self):
        return _import_envpool().make(self.task, env_type="gymnasium", num_envs=self.n, batch_size=self.batch,
                                      num_threads=self.threads, env_seed=self.seeds, **self.kwargs)

    def _rebuild(self):
        self.pool.close()
        self.pool = self._build()  # the same task: state_index still holds

    def spec(self):
        return self._spec

    def _call(self, actions, env_ids):
        """One EnvPool step of envs `env_ids` (actions in that order; None: a reset of them). Returns
        (observation parts, reward, terminated, truncated, env ids), rows in EnvPool's order."""
        index = self.state_index
        if index is None:  # EnvPool's public interface
            if actions is None:
                obs, info = self.pool.reset(env_ids)
                reward = terminated = truncated = None
            else:
                obs, reward, terminated, truncated, info = self.pool.step(actions, env_ids)
            parts = [obs] if self.keys is None else [obs[key] for key in self.keys]
            return parts, reward, terminated, truncated, info["env_id"]
        if actions is None:
            self.pool._reset(env_ids)
        else:
            self.pool._send([env_ids, env_ids, actions])
        state = self.pool._recv()
        done, truncated = state[index[2]], state[index[3]]
        return [state[i] for i in index[4:]], state[index[1]], done & ~truncated, truncated, state[index[0]]

    def _write(self, target, parts, rows, env_ids):
        """Observations `parts` (rows `rows` of them, all when None) into `target` at `env_ids`."""
        if len(parts) == 1:
            target[env_ids] = parts[0] if rows is None else parts[0][rows]
            return
        start = 0
        for part in parts:
            part = part.reshape(len(part), -1)
            if rows is not None:
                part = part[rows]
            target[env_ids, start:start + part.shape[1]] = part
            start += part.shape[1]

    def _synchronous(self, what):
        if self.batch < self.n:
            raise ValueError(f"a group of batch_size {self.batch} below its {self.n} envs is stepped with "
                             f"async_reset/send/recv, not {what}")

    def reset(self, seeds, mask=None):
        self._synchronous("reset")
        partial = mask is not None and not all(mask)
        if seeds is not None and not (self.fresh and [int(seed) for seed in seeds] == self.seeds):
            if partial:
                raise ValueError("engine 'envpool' re-seeds a session's envs together: a seeded reset "
                                 "must reset every env (EnvPool seeds envs when it builds them)")
            self.seeds = [int(seed) for seed in seeds]
            self._rebuild()
        self.fresh = False
        ids = self.ids if not partial else self.ids[np.asarray(mask, dtype=bool)]
        if len(ids):
            parts, _, _, _, env_ids = self._call(None, ids)
            self._write(self.current, parts, None, env_ids)
        return []

    def step(self, actions, skip=None):
        self._synchronous("step")
        self.fresh = False
        actions = np.frombuffer(actions, dtype=self.action_dtype).reshape((self.n,) + self.action_shape)
        actions = actions.astype(self.send_dtype)
        rewards = np.zeros(self.n)
        terminated = np.zeros(self.n, dtype=bool)
        truncated = np.zeros(self.n, dtype=bool)
        active = self.ids if skip is None else self.ids[~np.asarray(skip, dtype=bool)]
        if not len(active):
            return rewards.tolist(), terminated.tolist(), truncated.tolist(), [], [], []
        sent = actions if len(active) == self.n else actions[active]
        try:
            for repeat in range(self.repeat, 0, -1):
                parts, reward, term, trunc, env_ids = self._call(sent, active)
                rewards[env_ids] += reward
                terminated[env_ids] = term
                truncated[env_ids] = trunc
                ended = term | trunc
                if repeat == 1:  # observations are written once per agent step, not once per repeat
                    self._write(self.current, parts, None, env_ids)
                elif ended.any():  # an env leaving the repeat early keeps the observation it ended on
                    self._write(self.current, parts, ended, env_ids[ended])
                    active = env_ids[~ended]
                    if not len(active):
                        break
                    sent = actions[active]
            ended = np.flatnonzero(terminated | truncated)
            if len(ended):
                # Same-step autoreset: keep the last observation, start the next episode now.
                self.final[ended] = self.current[ended]
                parts, _, _, _, env_ids = self._call(None, ended.astype(np.int32))
                self._write(self.current, parts, None, env_ids)
        except Exception as exc:  # EnvPool raised: which env is unknown, so every episode ends
            message = f"{type(exc).__name__}: {exc}"
            self.final[:] = self.current
            self._rebuild()
            parts, _, _, _, env_ids = self._call(None, self.ids)
            self._write(self.current, parts, None, env_ids)
            return [0.0] * self.n, [False] * self.n, [True] * self.n, [(j, message) for j in range(self.n)], [], []
        return rewards.tolist(), terminated.tolist(), truncated.tolist(), [], [], []

    # EnvPool's asynchronous mode (batch_size < num_envs), the interface EnvPool's users step with:
    # send(actions, env_ids) hands envs their next action and returns at once, recv() waits for the first
    # `batch` envs whose agent step is complete, so the learner picks actions for those while EnvPool
    # steps the others. (EnvPool's documentation, "Asynchronous API"; its C++ ports are stepped through
    # the same raw _send/_recv/_reset as the synchronous mode here.) radserve's contract is kept per env:
    # action repeat (the worker re-sends an env's action as its results come back, summing the rewards)
    # and same-step autoreset (an env whose episode ended is reset at once; its result is complete
    # with the next episode's first observation, the last one in `final`). Each env is in one phase:
    # idle (its result was returned; it waits for an action), stepping, resetting, or ready.

    def async_reset(self, seeds=None):
        """Resets every env; their first observations come back through recv(), `batch` at a time."""
        if self.batch == self.n:
            raise ValueError("async_reset needs a session whose batch_size is below its num_envs")
        seeded = seeds is not None and not (self.fresh and [int(seed) for seed in seeds] == self.seeds)
        if seeded:  # EnvPool seeds envs when it builds them, as in reset()
            self.seeds = [int(seed) for seed in seeds]
        # Results still in flight would come back mixed with the new episodes' first observations.
        if seeded or (self.phase != _IDLE).any():
            self._rebuild()
        self.fresh = False
        self.ready = []
        self.acc[:] = 0
        self.ended[:] = False
        self.phase[:] = _RESETTING
        self.pool._reset(self.ids)

    def send(self, actions, env_ids):
        """Starts the next agent step of envs `env_ids` (each idle: its last result was returned by recv)
        with `actions` (raw bytes, one action per env id, in that order)."""
        env_ids = np.asarray(env_ids, dtype=np.int32)
        if len(env_ids) == 0:
            return
        listed = env_ids.tolist()
        if min(listed) < 0 or max(listed) >= self.n or len(set(listed)) != len(listed):
            raise ValueError(f"send takes distinct env ids in [0, {self.n}), got {listed}")
        waiting = env_ids[self.phase[env_ids] != _IDLE]
        if len(waiting):
            raise ValueError(f"envs {waiting.tolist()} were sent an action before recv returned their last result")
        actions = np.frombuffer(actions, dtype=self.action_dtype).reshape((len(env_ids),) + self.action_shape)
        if self.sent is None:
            self.sent = np.zeros((self.n,) + self.action_shape, dtype=self.send_dtype)
        self.fresh = False
        self.sent[env_ids] = actions
        self.acc[env_ids] = 0
        self.ended[env_ids] = False
        self.left[env_ids] = self.repeat - 1
        self.phase[env_ids] = _STEPPING
        self.pool._send([env_ids, env_ids, self.sent[env_ids]])

    def recv(self):
        """Waits until `batch` envs have completed their agent step and returns them (fewer when fewer are
        left in EnvPool than a batch, and some are complete): (env ids, rewards, terminated, truncated),
        the envs' observations in `current`, ended ones' last in `final`."""
        index = self.state_index
        while len(self.ready) < self.batch:
            # EnvPool's recv waits for `batch` results: with fewer envs in it, it would wait forever. Those
            # already complete are returned instead (the session asks only with a batch's worth sent).
            in_flight = int(np.count_nonzero((self.phase == _STEPPING) | (self.phase == _RESETTING)))
            if in_flight < self.batch:
                if self.ready:
                    break
                raise ValueError(f"recv returns {self.batch} envs at a time and {in_flight} are stepping: "
                                 f"send actions to more envs first")
            state = self.pool._recv()
            env_ids = state[index[0]]
            parts = [state[i] for i in index[4:]]
            resetting = self.phase[env_ids] == _RESETTING
            if self.repeat == 1 and not resetting.any() and not (state[index[2]] | state[index[3]]).any():
                # The common case, kept short (its numpy calls are the worker's cost per recv): every env
                # stepped once, none ended, each agent step complete.
                self.acc[env_ids] = state[index[1]]
                self._write(self.current, parts, None, env_ids)
                self.phase[env_ids] = _READY
                self.ready.extend(env_ids.tolist())
                continue
            if resetting.any():  # the next episode's first observation: the agent step is complete
                self._write(self.current, parts, resetting, env_ids[resetting])
                self.phase[env_ids[resetting]] = _READY
                self.ready.extend(env_ids[resetting].tolist())
            stepping = ~resetting
            if not stepping.any():
                continue
            rows, ids = np.flatnonzero(stepping), env_ids[stepping]
            done, trunc = state[index[2]][rows], state[index[3]][rows]
            self.acc[ids] += state[index[1]][rows]
            ended = done | trunc
            self.ended[ids, 0] = done & ~trunc
            self.ended[ids, 1] = trunc
            last = ended | (self.left[ids] == 0)
            if ended.any():  # same-step autoreset: the last observation is the final one, reset now
                self._write(self.final, parts, rows[ended], ids[ended])
                self.phase[ids[ended]] = _RESETTING
                self.pool._reset(ids[ended])
            complete = last & ~ended
            if complete.any():
                self._write(self.current, parts, rows[complete], ids[complete])
                self.phase[ids[complete]] = _READY
                self.ready.extend(ids[complete].tolist())
            again = ~last
            if again.any():  # the next repeat of the same action
                self.left[ids[again]] -= 1
                self.pool._send([ids[again], ids[again], self.sent[ids[again]]])
        done_ids = np.array(self.ready[:self.batch], dtype=np.int64)
        del self.ready[:self.batch]
        self.phase[done_ids] = _IDLE
        rewards = self.acc[done_ids].copy()
        self.acc[done_ids] = 0
        return done_ids, rewards, self.ended[done_ids, 0].copy(), self.ended[done_ids, 1].copy()

    def close(self):
        if self.pool is not None:
            self.pool.close()
        self.pool = None
        self.current = self.final = None


# An env's phase in EnvpoolGroup's asynchronous mode.
_IDLE, _STEPPING, _RESETTING, _READY = 0, 1, 2, 3
