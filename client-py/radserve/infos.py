"""Info dicts as gymnasium's vector envs return them, built from what the server sent.

The envs' infos travel as typed columns (`InfoColumn`: per key and value type, the envs that
reported it and their values, a tensor for numbers and arrays, texts for strings and JSON for
anything else; `radserve_worker.common.info_columns` writes them). The client turns them into
gymnasium's vector infos straight away when each key has one column (`vector_infos`), and otherwise
rebuilds each env's dict (`env_infos`) and batches them in `VectorEnv._add_info`'s layout (a value
array and a `_key` mask per key; `add_flat` adds a run of flat infos key by key); it adds
radserve's own episode figures (`episode_infos`) and, for a sharded env, places each shard's infos at
its rows (`merge_infos`). The plain and the sharded vector envs both build their infos here.
"""

import json
from typing import Callable, Sequence

import numpy as np

from . import _convert
from ._proto import radserve_pb2 as pb


def _numpy_value(tagged: dict):
    """A JSON object as the worker wrote it (radserve_worker.common._tagged): numpy values rebuilt."""
    if "__numpy__" in tagged:
        dtype = np.dtype(tagged["__numpy__"])
        if "shape" in tagged:
            return np.array(tagged["value"], dtype=dtype).reshape(tagged["shape"])
        return dtype.type(tagged["value"])
    if set(tagged) == {"__repr__"}:
        return tagged["__repr__"]
    return tagged


# One decoder for every value: json.loads with an object_hook builds a new JSONDecoder per call.
_DECODER = json.JSONDecoder(object_hook=_numpy_value)


def column_values(column: "pb.InfoColumn") -> list:
    """A column's values, one per env of `column.envs`, as the envs' info dicts held them: Python
    numbers, numpy scalars, numpy arrays, strings, or what the JSON holds."""
    kind = column.kind
    if kind == pb.INFO_KIND_TEXT:
        return list(column.texts)
    if kind == pb.INFO_KIND_JSON:
        return [_DECODER.decode(text) for text in column.texts]
    values = _convert.to_numpy(column.values)
    if kind == pb.INFO_KIND_PYTHON:
        return values.tolist()
    if kind == pb.INFO_KIND_ARRAY:
        return [np.array(row) for row in values]  # copies, 0-d arrays included
    return list(values)  # numpy scalars


def env_infos(columns: "Sequence[pb.InfoColumn]") -> "dict[int, dict]":
    """Each env's info dict, rebuilt from the columns (nested dicts from the keys' paths), by env
    index; envs that reported nothing have no entry."""
    infos: "dict[int, dict]" = {}
    for column in columns:
        path = list(column.path)
        for env, value in zip(column.envs, column_values(column)):
            target = infos.setdefault(env, {})
            for part in path[:-1]:
                target = target.setdefault(part, {})
            target[path[-1]] = value
    return infos


def vector_infos(columns: "Sequence[pb.InfoColumn]", num_envs: int) -> "dict | None":
    """gymnasium's vector infos for `num_envs` envs straight from the columns, as `_add_info` of
    each env's dict in env order would make them: each key's array of its values' type (zeros where
    an env did not report it) and its `_key` mask, nested dicts with their own masks. None when the
    columns need each env's dict instead: a key with values of two types (gymnasium's array takes
    the first env's type and casts the others), a key both a value and a dict, JSON values, or
    gymnasium's special `final_obs`."""
    infos = _every_env_numbers(columns, num_envs)
    if infos is not None:
        return infos
    infos = {}
    leaves, parents = set(), set()
    every = None  # a mask of every env, copied for each key every env reported
    for column in columns:
        kind, path = column.kind, tuple(column.path)
        if kind == pb.INFO_KIND_JSON or path in leaves or path in parents or "final_obs" in path:
            return None
        leaves.add(path)
        # Envs are ascending and distinct: as many as the session has is every env.
        everyone = len(column.envs) == num_envs
        envs = slice(None) if everyone else np.asarray(column.envs, dtype=np.intp)
        target = infos
        if len(path) > 1:
            prefixes = [path[:end] for end in range(1, len(path))]
            if any(prefix in leaves for prefix in prefixes):
                return None
            parents.update(prefixes)
            for part in path[:-1]:
                if f"_{part}" not in target:
                    target[part], target[f"_{part}"] = {}, np.zeros(num_envs, dtype=np.bool_)
                target[f"_{part}"][envs] = True
                target = target[part]
        if kind == pb.INFO_KIND_TEXT:
            array = np.full(num_envs, None, dtype=object)
            array[envs] = np.array(list(column.texts), dtype=object)
        else:
            tensor = column.values
            values = np.frombuffer(tensor.data, dtype=_convert.NUMPY_DTYPES[tensor.dtype])
            if kind == pb.INFO_KIND_ARRAY:
                values = values.reshape(tuple(tensor.shape))
            if kind == pb.INFO_KIND_SCALAR and values.dtype == np.bool_:
                # np.bool_ is no np.number: gymnasium keeps numpy bools in an object array.
                array = np.full(num_envs, None, dtype=object)
                for env, value in zip(column.envs, values):
                    array[env] = value
            elif everyone:
                array = values.copy()  # writable, as gymnasium's
            else:
                array = np.zeros((num_envs,) + values.shape[1:], dtype=values.dtype)
                array[envs] = values
        if everyone:
            if every is None:
                every = np.ones(num_envs, dtype=np.bool_)
            mask = every.copy()
        else:
            mask = np.zeros(num_envs, dtype=np.bool_)
            mask[envs] = True
        target[path[-1]], target[f"_{path[-1]}"] = array, mask
    return infos


def _every_env_numbers(columns: "Sequence[pb.InfoColumn]", num_envs: int) -> "dict | None":
    """`vector_infos` of a step whose every key is a number every env reported (a gym step's infos),
    in the fewest calls: each key's values as the array, every mask all true. None for anything else."""
    infos: dict = {}
    every = None
    for column in columns:
        kind = column.kind
        if (kind != pb.INFO_KIND_PYTHON and kind != pb.INFO_KIND_SCALAR) or len(column.envs) != num_envs \
                or len(column.path) != 1:
            return None
        key, tensor = column.path[0], column.values
        dtype = _convert.NUMPY_DTYPES[tensor.dtype]
        masked = "_" + key
        if key in infos or masked in infos or key == "final_obs" or (kind == pb.INFO_KIND_SCALAR and dtype == np.bool_):
            return None
        if every is None:
            every = np.ones(num_envs, dtype=np.bool_)
        infos[key], infos[masked] = np.frombuffer(tensor.data, dtype).copy(), every.copy()
    return infos


_SCALARS = frozenset((int, float, bool))


def is_flat(info: dict) -> bool:
    """Whether gymnasium batches every value of `info` into a 1-D array of the value's own type
    (VectorEnv._add_info: int, float, bool and numpy numbers; dicts, arrays, other objects not)."""
    if "final_obs" in info:
        return False
    for value in info.values():
        if type(value) not in _SCALARS and not isinstance(value, np.number):
            return False
    return True


def add_flat(infos: dict, run: "list[tuple[int, dict]]", num_envs: int,
             add_info: "Callable[[dict, dict, int], dict]") -> dict:
    """gymnasium's `_add_info` (`add_info`) of each (env, info) of `run` in turn (envs in order, every
    info flat, see `is_flat`), done key by key: an array is made with the type of the first value it
    gets, as `_add_info` makes it, and filled at once. A gym step's infos are such dicts of floats,
    and one `_add_info` per env and key was most of the client's time per step. A key that `infos`
    already holds in another layout goes through `add_info` itself."""
    columns: "dict[str, tuple[list[int], list]]" = {}
    envs = [i for i, _ in run]
    first = run[0][1].keys()
    if all(info.keys() == first for _, info in run):  # the usual case: every env reports the same keys
        for key in first:
            columns[key] = (envs, [info[key] for _, info in run])
    else:
        for i, info in run:
            for key, value in info.items():
                column = columns.get(key)
                if column is None:
                    columns[key] = column = ([], [])
                column[0].append(i)
                column[1].append(value)
    for key, (envs, values) in columns.items():
        array = infos.get(key)
        if array is None:
            array = np.zeros(num_envs, dtype=type(values[0]))
        elif not isinstance(array, np.ndarray) or array.ndim != 1:
            for i, value in zip(envs, values):  # a key batched another way before: gymnasium's own path
                infos = add_info(infos, {key: value}, i)
            continue
        array[envs] = values
        mask = infos.get(f"_{key}")
        if mask is None:
            mask = np.zeros(num_envs, dtype=np.bool_)
        mask[envs] = True
        infos[key] = array
        infos[f"_{key}"] = mask
    return infos


def episode_infos(size: int, rows, returns, lengths, errors: "dict[int, str]") -> dict:
    """radserve's figures for the episodes that ended, as infos over `size` rows under names no
    gymnasium wrapper uses: `radserve_episode` (return `r`, length `l`) at `rows` (the k-th ended
    episode's row is `rows[k]`), and `radserve_error`, a simulator's message by row."""
    mask = np.zeros(size, dtype=bool)
    mask[rows] = True
    episode_returns, episode_lengths = np.zeros(size, dtype=np.float64), np.zeros(size, dtype=np.int64)
    episode_returns[rows], episode_lengths[rows] = returns, lengths
    infos = {"radserve_episode": {"r": episode_returns, "l": episode_lengths, "_r": mask.copy(), "_l": mask.copy()},
             "_radserve_episode": mask}
    if errors:
        messages = np.full(size, None, dtype=object)
        for row, message in errors.items():
            messages[row] = message
        infos["radserve_error"] = messages
        infos["_radserve_error"] = np.array([message is not None for message in messages])
    return infos


def merge_infos(parts: "list[tuple[int, int, dict]]", num_envs: int) -> dict:
    """One gymnasium info dict for `num_envs` envs from each shard's (first env, size, its info
    dict): every array placed at its shard's rows, as `VectorEnv._add_info` would have made it."""
    merged: dict = {}
    keys: "list[str]" = []
    for _, _, info in parts:
        keys += [key for key in info if key not in keys]
    for key in keys:
        present = [(start, size, info[key]) for start, size, info in parts if key in info]
        if all(isinstance(value, dict) for _, _, value in present):
            merged[key] = merge_infos(present, num_envs)
            continue
        arrays = [np.asarray(value) for _, _, value in present]
        first = arrays[0]
        alike = all(a.dtype == first.dtype and a.shape[1:] == first.shape[1:] and a.ndim >= 1 for a in arrays)
        if alike and first.dtype != object:
            full = np.zeros((num_envs, *first.shape[1:]), dtype=first.dtype)
        else:
            full = np.full(num_envs, None, dtype=object)
        for (start, size, _), array in zip(present, arrays):
            if full.dtype == object and not alike:
                for row in range(size):
                    full[start + row] = array[row]
            else:
                full[start:start + size] = array
        merged[key] = full
    return merged
