"""The client's batched info path (radserve.infos.add_flat) against gymnasium's own
VectorEnv._add_info called env by env, on random flat infos: same keys, values, dtypes and masks."""

import random

import numpy as np
from gymnasium.vector import VectorEnv

from radserve.infos import add_flat, is_flat

VALUES = [lambda r: r.random(), lambda r: r.randint(-5, 5), lambda r: r.random() < 0.5,
          lambda r: np.float32(r.random()), lambda r: np.int64(r.randint(0, 9)), lambda r: np.float64(r.random())]


class Batcher(VectorEnv):
    def __init__(self, num_envs):
        self.num_envs = num_envs


def random_info(rng, keys):
    return {key: rng.choice(VALUES)(rng) for key in rng.sample(keys, rng.randint(1, len(keys)))}


def test_flat_infos_batch_as_gymnasium_batches_them():
    rng = random.Random(0)
    for case in range(300):
        num_envs = rng.randint(1, 12)
        keys = ["a", "b", "c", "d"]
        same_keys = case % 2 == 0
        shared = random_info(rng, keys)
        run = []
        for i in sorted(rng.sample(range(num_envs), rng.randint(1, num_envs))):
            info = {key: rng.choice(VALUES)(rng) for key in shared} if same_keys else random_info(rng, keys)
            assert is_flat(info)
            run.append((i, info))
        batcher = Batcher(num_envs)
        start = {}
        if rng.random() < 0.5:  # some keys already batched by an earlier env of the step
            start = batcher._add_info({}, random_info(rng, keys), 0)
        expected = {key: value.copy() for key, value in start.items()}
        for i, info in run:
            expected = batcher._add_info(expected, info, i)
        got = add_flat({key: value.copy() for key, value in start.items()}, run, num_envs, batcher._add_info)
        assert got.keys() == expected.keys()
        for key in expected:
            assert got[key].dtype == expected[key].dtype, (case, key)
            np.testing.assert_array_equal(got[key], expected[key])


def test_what_is_not_flat():
    assert not is_flat({"final_obs": 1.0})
    assert not is_flat({"a": np.zeros(3)})
    assert not is_flat({"a": {"b": 1.0}})
    assert not is_flat({"a": "text"})
    assert not is_flat({"a": np.bool_(True)})  # gymnasium puts numpy bools in an object array
    assert is_flat({"a": 1, "b": 2.0, "c": True, "d": np.float32(1)})
