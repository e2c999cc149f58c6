"""Info dicts as gymnasium's vector envs return them, built from what the server sent.

An env's info travels as JSON text (numpy values tagged as `radserve_worker.common.info_json`
writes them); the client decodes it (`decode`, `decode_all`), batches envs' infos in
`VectorEnv._add_info`'s layout (a value array and a `_key` mask per key; `add_flat` adds a run of
flat infos key by key), adds radserve's own episode figures (`episode_infos`) and, for a sharded
env, places each shard's infos at its rows (`merge_infos`). The plain and the sharded vector envs
both build their infos here.
"""

import json
from typing import Callable

import numpy as np


def _numpy_value(tagged: dict):
    """A JSON object as the worker wrote it (radserve_worker.common.info_json): numpy values rebuilt."""
    if "__numpy__" in tagged:
        dtype = np.dtype(tagged["__numpy__"])
        if "shape" in tagged:
            return np.array(tagged["value"], dtype=dtype).reshape(tagged["shape"])
        return dtype.type(tagged["value"])
    if set(tagged) == {"__repr__"}:
        return tagged["__repr__"]
    return tagged


# One decoder for every info: json.loads with an object_hook builds a new JSONDecoder per call.
_DECODER = json.JSONDecoder(object_hook=_numpy_value)


def decode(text: "str | None") -> dict:
    """An env's info dict from its JSON text (empty when none travelled)."""
    return _DECODER.decode(text) if text else {}


def decode_all(texts: "list[str]") -> "dict[str, dict]":
    """Each non-empty text's info, decoded in one call (one JSON array) rather than one per env."""
    texts = [text for text in texts if text]
    return dict(zip(texts, _DECODER.decode("[" + ",".join(texts) + "]"))) if texts else {}


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
