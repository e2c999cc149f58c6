"""Infos as typed columns, from the worker's encoder (radserve_worker.common.info_columns) through the
proto's InfoColumn to the client (radserve.infos): on random info dicts of every kind (Python and
numpy numbers, arrays, strings, nested dicts, values only JSON holds), each env's dict comes back as
the env returned it, and the vector infos built straight from the columns are gymnasium's own
(`VectorEnv._add_info` env by env): same keys, values, dtypes and masks."""

import sys
from pathlib import Path

import numpy as np
from gymnasium.vector import VectorEnv
from hypothesis import given, settings
from hypothesis import strategies as st

from radserve import _convert
from radserve._proto import radserve_pb2 as pb
from radserve.infos import env_infos, vector_infos



def _worker_common():
    """The worker's `common` module (server/sim/python/radserve_worker, the package the worker
    embeds), loaded from its files: it is not installed, and nothing here edits sys.path."""
    import importlib
    import importlib.util

    package = Path(__file__).resolve().parents[2] / "server" / "sim" / "python" / "radserve_worker"
    if "radserve_worker" not in sys.modules:
        spec = importlib.util.spec_from_file_location("radserve_worker", package / "__init__.py",
                                                      submodule_search_locations=[str(package)])
        sys.modules["radserve_worker"] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules["radserve_worker"])
    return importlib.import_module("radserve_worker.common")


info_columns = _worker_common().info_columns

KINDS = {"python": pb.INFO_KIND_PYTHON, "scalar": pb.INFO_KIND_SCALAR, "array": pb.INFO_KIND_ARRAY,
         "text": pb.INFO_KIND_TEXT, "json": pb.INFO_KIND_JSON}


def to_proto(columns, offset=0):
    """The worker's columns as the server sends them (server/service/src/convert.rs, infos_to_proto)."""
    messages = []
    for path, kind, dtype, shape, envs, data, texts in columns:
        message = pb.InfoColumn(path=path, envs=[offset + env for env in envs], kind=KINDS[kind], texts=texts)
        if kind not in ("text", "json"):
            values = np.frombuffer(data, dtype=dtype).reshape([len(envs)] + shape)
            message.values.CopyFrom(_convert.to_tensor(values))
        messages.append(message)
    return messages


class Batcher(VectorEnv):
    def __init__(self, num_envs):
        self.num_envs = num_envs


def gymnasium_infos(infos: "dict[int, dict]", num_envs: int) -> dict:
    batcher, vector = Batcher(num_envs), {}
    for env in sorted(infos):
        vector = batcher._add_info(vector, infos[env], env)
    return vector


def assert_same(want, have, where="infos"):
    """Equal values of equal types: dicts key by key, arrays with their dtype and shape."""
    assert type(want) is type(have), (where, type(want), type(have))
    if isinstance(want, dict):
        assert list(want) == list(have) or want.keys() == have.keys(), (where, want.keys(), have.keys())
        for key in want:
            assert_same(want[key], have[key], f"{where}[{key!r}]")
    elif isinstance(want, np.ndarray):
        assert want.dtype == have.dtype and want.shape == have.shape, (where, want.dtype, have.dtype, want.shape, have.shape)
        if want.dtype == object:
            for i, (a, b) in enumerate(zip(want, have)):
                assert_same(a, b, f"{where}[{i}]")
        else:
            np.testing.assert_array_equal(want, have, err_msg=where)
    elif isinstance(want, float) and want != want:
        assert have != have, where  # NaN
    elif isinstance(want, list):
        assert len(want) == len(have), where
        for i, (a, b) in enumerate(zip(want, have)):
            assert_same(a, b, f"{where}[{i}]")
    else:
        assert want == have, (where, want, have)


finite = st.floats(allow_nan=False, allow_infinity=True, width=64)
finite32 = st.floats(allow_nan=False, allow_infinity=True, width=32)
leaf = st.one_of(
    finite,
    st.integers(-(1 << 70), 1 << 70),  # beyond int64 they travel as JSON
    st.booleans(),
    finite32.map(np.float32),
    st.integers(-(1 << 63), (1 << 63) - 1).map(np.int64),
    st.booleans().map(np.bool_),
    st.integers(0, 255).map(np.uint8),
    st.floats(-100, 100).map(np.float16),  # no name in the proto's DType: JSON with its dtype
    st.lists(finite32, min_size=2, max_size=2).map(lambda v: np.array(v, dtype=np.float32)),
    st.integers(-9, 9).map(lambda v: np.array(v, dtype=np.int64)),  # a 0-d array
    st.text(max_size=4),
    st.lists(st.integers(-3, 3), max_size=3),
    st.none(),
    st.just({}),
)
KEYS = st.sampled_from(["a", "b", "c", "x_position"])
info = st.dictionaries(KEYS, st.one_of(leaf, st.dictionaries(KEYS, leaf, min_size=1, max_size=2)), max_size=3)
# The usual case: every env reports the same keys with values of one type.
flat_kind = st.sampled_from([lambda r: r, np.float32, np.float64, lambda r: int(r * 100), lambda r: r > 0.5])


@settings(max_examples=300, deadline=None)
@given(st.lists(info, min_size=1, max_size=6), st.data())
def test_every_kind_of_info_comes_back_as_the_env_returned_it(dicts, data):
    reported = {env: value for env, value in enumerate(dicts) if value}
    # Two groups, as two worker processes report them: the second's envs after the first's.
    split = data.draw(st.integers(0, len(dicts)))
    first = [(env, value) for env, value in reported.items() if env < split]
    second = [(env - split, value) for env, value in reported.items() if env >= split]
    columns = to_proto(info_columns(first)) + to_proto(info_columns(second), offset=split)
    rebuilt = env_infos(columns)
    assert rebuilt.keys() == reported.keys()
    for env, value in reported.items():
        assert_same(value, rebuilt[env], f"env {env}")
    vector = vector_infos(columns, len(dicts))
    if vector is not None:
        assert_same(gymnasium_infos(reported, len(dicts)), vector)


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 16), st.lists(st.tuples(KEYS, flat_kind), min_size=1, max_size=4, unique_by=lambda kv: kv[0]),
       st.randoms(use_true_random=False))
def test_a_steps_flat_infos_become_gymnasiums_vector_infos_without_each_envs_dict(num_envs, keys, rng):
    reports = [(env, {key: kind(rng.random()) for key, kind in keys}) for env in range(num_envs)
               if env == 0 or rng.random() < 0.8]
    columns = to_proto(info_columns(reports))
    # One column per key, however many envs reported it.
    assert [list(column.path) for column in columns] == [[key] for key, _ in keys]
    vector = vector_infos(columns, num_envs)
    assert vector is not None
    assert_same(gymnasium_infos(dict(reports), num_envs), vector)


def test_values_of_two_types_under_one_key_take_the_first_envs_type_as_gymnasium_does():
    reports = [(0, {"a": 1}), (1, {"a": 2.5}), (2, {"a": np.float32(3)})]
    columns = to_proto(info_columns(reports))
    assert len(columns) == 3 and vector_infos(columns, 3) is None
    rebuilt = env_infos(columns)
    assert type(rebuilt[0]["a"]) is int and type(rebuilt[1]["a"]) is float and type(rebuilt[2]["a"]) is np.float32
    vector = gymnasium_infos(rebuilt, 3)
    assert vector["a"].dtype == np.int64 and vector["a"].tolist() == [1, 2, 3]
