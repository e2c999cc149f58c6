"""ProcGen games (procgen/...): one game for the catalog's spec, a group of games as one procgen vector."""

import contextlib
import io

import numpy as np

from radserve_worker import common
from radserve_worker.common import SERVER_OPTIONS, box, discrete
from radserve_worker.group import Group


PROCGEN_GAMES = [
    "bigfish", "bossfight", "caveflyer", "chaser", "climber", "coinrun", "dodgeball", "fruitbot",
    "heist", "jumper", "leaper", "maze", "miner", "ninja", "plunder", "starpilot",
]


def _procgen(num, name, options, seed):
    """A ProcgenGym3Env of `num` games seeded `seed`, with the session's options."""
    # procgen imports the legacy gym package, which prints a deprecation banner on import.
    with contextlib.redirect_stderr(io.StringIO()):
        from procgen import ProcgenGym3Env

    # num_threads=0 steps the games on the worker's own thread. procgen's default hands every act()
    # to a pool of 4 threads per object: measured here, 32 one-env objects stepped in 5.9 ms with
    # it and 2.2 ms without (the same frames; the worker's thread waits for the step either way).
    kwargs = {"num_threads": 0, **{k: v for k, v in options.items() if k not in SERVER_OPTIONS}}
    return ProcgenGym3Env(num=num, env_name=name, rand_seed=int(seed), **kwargs)


class ProcgenSpec:
    """The spec of a ProcGen game, for the catalog. Groups of games are ProcgenGroup's."""

    def __init__(self, name, options, seed):
        self.env = _procgen(1, name, options, seed)

    def spec(self):
        return {"observation": box(np.uint8, (3, 64, 64), 0, 255), "action": discrete(self.env.ac_space.eltype.n)}

    def close(self):
        self.env.close()


class ProcgenGroup(Group):
    """A group of ProcGen games stepped as one procgen vector env, each game seeded exactly like a
    one-game env with its own seed.

    gym3 resets an episode inside the step that ends it and never shows its last frame, so the "final
    observation" of a ProcGen episode is the frame before its last action.

    procgen derives the games of a vector from one seed, so env i could not get seed s+i from the
    vector's constructor. Instead each game's state is taken from a one-game env seeded s+i and set
    into slot i (procgen's get_state/set_state carry the level-seed generator too, so the episodes
    that follow match as well: tests/test_procgen_determinism.py compares them). One act()/observe() for the
    whole group costs about 60% of 32 separate one-game calls (measured in one script on this machine:
    1.2 ms against 1.9-2.0 ms per 32-game step of bigfish).
    """

    def __init__(self, name, options, seeds):
        self.family, self.name, self.options = "procgen", name, options
        self.seeds = list(seeds)
        self.n = len(self.seeds)
        # Per game: unseeded resets since its last seed, and whether it has not moved since a reset.
        self.unseeded_resets = [0] * self.n
        self.fresh = [True] * self.n
        self.vec = self._fresh_vector()
        self._spec = {"observation": box(np.uint8, (3, 64, 64), 0, 255),
                      "action": discrete(self.vec.ac_space.eltype.n)}
        self.action_dtype, self.action_shape = np.dtype(np.int64), ()
        self.current = self.final = None

    def _fresh_vector(self):
        vec = _procgen(self.n, self.name, self.options, 0)
        vec.set_state([_procgen(1, self.name, self.options, seed).get_state()[0] for seed in self.seeds])
        return vec

    def _frames(self):
        _, obs, _ = self.vec.observe()
        return obs["rgb"].transpose(0, 3, 1, 2)

    def reset(self, seeds, mask=None):
        games = {}
        for j in range(self.n):
            if mask is not None and not mask[j]:
                continue
            if seeds is not None:
                self.seeds[j] = seeds[j]
                self.unseeded_resets[j] = 0
                games[j] = self.seeds[j]
            elif not self.fresh[j]:
                # gym3 games have no reset of their own: an unseeded reset starts the game from a seed
                # drawn from its own, so that later resets go on to new levels (the same ones for the
                # same seed and the same number of resets).
                self.unseeded_resets[j] += 1
                draw = np.random.SeedSequence([self.seeds[j], self.unseeded_resets[j]]).generate_state(1)[0]
                games[j] = int(draw & 0x7FFFFFFF)
            self.fresh[j] = True
        if games:
            states = self.vec.get_state()
            for j, seed in games.items():
                states[j] = _procgen(1, self.name, self.options, seed).get_state()[0]
            self.vec.set_state(states)
        self.current[:] = self._frames()
        # gym3's info (level seeds) is not an env's gymnasium info: none travels.
        return []

    def step(self, actions, skip=None):
        actions = np.frombuffer(actions, dtype=self.action_dtype).astype(np.int32)
        # A procgen vector steps every game: a skipped game is stepped too, then put back as it was.
        skipped = [] if skip is None else [j for j in range(self.n) if skip[j]]
        kept = self.vec.get_state() if skipped else None
        for j in range(self.n):
            if j not in skipped:
                self.fresh[j] = False
        try:
            self.vec.act(actions)
            rewards, obs, first = self.vec.observe()
        except Exception as exc:  # procgen raised: which game is unknown, so every episode ends
            message = f"{type(exc).__name__}: {exc}"
            self.final[:] = self.current
            self.vec = self._fresh_vector()
            self.current[:] = self._frames()
            return [0.0] * self.n, [False] * self.n, [True] * self.n, [(j, message) for j in range(self.n)], [], []
        ended = first.astype(bool)
        rewards = rewards.astype(np.float64)
        if skipped:
            states = self.vec.get_state()
            for j in skipped:
                states[j] = kept[j]
            self.vec.set_state(states)
            ended[skipped] = False
            rewards[skipped] = 0.0
            held = self.current[skipped].copy()
        # gym3 has already started the next episode of a game whose episode ended: its final frame is
        # the one before the last action.
        self.final[ended] = self.current[ended]
        # The worker replaces common.hwc_to_chw with its native copy (looked up at each call).
        common.hwc_to_chw(obs["rgb"], self.current)
        if skipped:
            self.current[skipped] = held
        return rewards.tolist(), ended.tolist(), [False] * self.n, [], [], []

    def close(self):
        if self.vec is not None:
            self.vec.close()
        self.vec = None
        self.current = self.final = None
