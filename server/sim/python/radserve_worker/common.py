"""What every adapter uses: spaces as the worker protocol writes them, info dicts as typed columns,
the frame copy."""

import json
import struct

import numpy as np


# Options the server consumes itself, and the engine choice (make_group's); adapters never see them.
SERVER_OPTIONS = {"frame_stack", "engine", "batch_size", "send_infos"}


def _quiet_absl():
    try:
        from absl import logging as absl_logging

        absl_logging.set_verbosity(absl_logging.ERROR)
    except ImportError:
        pass


def _bounds(values):
    """Bounds as a flat list of floats; a constant bound collapses to one value."""
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    if flat.size > 0 and np.all(flat == flat[0]):
        return [float(flat[0])]
    return [float(v) for v in flat]


def box(dtype, shape, low, high):
    return {"kind": "box", "dtype": np.dtype(dtype).name, "shape": [int(d) for d in shape],
            "low": _bounds(low), "high": _bounds(high)}


def discrete(n):
    return {"kind": "discrete", "n": int(n)}


# The dtypes an info column's numbers travel in (radserve.v1.DType); numbers of other dtypes travel
# as JSON (tagged with their dtype) instead.
_DTYPES = frozenset(("uint8", "int32", "int64", "float32", "float64", "bool"))
_PYTHON = {float: "float64", int: "int64", bool: "bool"}
_INT64 = (-(1 << 63), 1 << 63)


def info_columns(reports):
    """The info dicts `reports` (env, info) of a group's envs, in ascending env order, as columns for
    the server (server/core/src/infos.rs): per key path (a nested dict's keys under their parent's)
    and value type, the envs that reported it and their values. A column is a tuple (path, kind,
    dtype, shape, envs, data, texts): kind "python" for Python bool/int/float (dtype bool, int64,
    float64), "scalar" for numpy scalars and "array" for numpy arrays of one shape (their dtype,
    `data` the little-endian values), "text" for strings and "json" for anything else (`texts`: each
    value as JSON, numpy values tagged with their dtype). This is what a client needs to rebuild the
    values as the env returned them, and gymnasium's vector infos (`VectorEnv._add_info`, which
    batches a key by its first value's type) without decoding each env's dict."""
    if len(reports) > 1:
        columns = _flat_columns(reports)
        if columns is not None:
            return columns
    columns = {}
    for env, info in reports:
        _collect(columns, (), env, info)
    return [_column(signature, envs, values) for signature, (envs, values) in columns.items()]


# A value type's column kind and dtype when its values are numbers of a column dtype (else None).
_NUMBER_KINDS = {kind: ("python", dtype) for kind, dtype in _PYTHON.items()}
# struct's codes of the column dtypes, for a column of scalars.
_STRUCT = {"float64": "d", "float32": "f", "int64": "q", "int32": "i", "uint8": "B", "bool": "?"}


def _number_kind(kind):
    found = _NUMBER_KINDS.get(kind, False)
    if found is False:
        found = None
        if issubclass(kind, np.generic):
            try:
                name = np.dtype(kind).name
            except TypeError:
                name = ""
            found = ("scalar", name) if name in _DTYPES else None
        _NUMBER_KINDS[kind] = found
    return found


def _flat_columns(reports):
    """The usual case, in a few calls per key: every info of `reports` has the first's keys (str),
    each key's values numbers of one type (Python, or numpy scalars of a column dtype). None
    otherwise."""
    first = reports[0][1]
    keys = first.keys()
    for _, info in reports:
        if info.keys() != keys:
            return None
    envs = [env for env, _ in reports]
    columns = []
    for key, value in first.items():
        number = _number_kind(type(value))
        if number is None or type(key) is not str:
            return None
        values = [info[key] for _, info in reports]
        if len(set(map(type, values))) != 1:
            return None
        if type(value) is int and not all(_INT64[0] <= v < _INT64[1] for v in values):
            return None
        data = struct.pack(f"<{len(values)}{_STRUCT[number[1]]}", *values)
        columns.append(([key], number[0], number[1], [], envs, data, []))
    return columns


def _collect(columns, prefix, env, info):
    for key, value in info.items():
        path = prefix + (key if type(key) is str else str(key),)
        kind = type(value)
        number = _number_kind(kind)
        if number is not None and (kind is not int or _INT64[0] <= value < _INT64[1]):
            signature = (path,) + number + ((),)
        elif kind is str:
            signature = (path, "text", "", ())
        elif kind is dict and value:
            _collect(columns, path, env, value)
            continue
        elif isinstance(value, np.ndarray) and value.dtype.name in _DTYPES:
            signature = (path, "array", value.dtype.name, value.shape)
        else:
            signature, value = (path, "json", "", ()), _ENCODER.encode(value)
        column = columns.get(signature)
        if column is None:
            columns[signature] = ([env], [value])
        else:
            column[0].append(env)
            column[1].append(value)


def _column(signature, envs, values):
    path, kind, dtype, shape = signature
    if kind in ("text", "json"):
        return list(path), kind, "", [], envs, b"", values
    data = np.array(values, dtype=dtype).tobytes()
    return list(path), kind, dtype, list(shape), envs, data, []


def _tagged(value):
    """What JSON cannot hold, as the client's `radserve.infos` rebuilds it: numpy values with their
    dtype (`{"__numpy__": dtype, "value": ...}`, and `"shape"` for arrays), anything else as its repr."""
    if isinstance(value, np.ndarray):
        return {"__numpy__": value.dtype.str, "shape": list(value.shape), "value": value.ravel().tolist()}
    if isinstance(value, np.generic):
        return {"__numpy__": value.dtype.str, "value": value.item()}
    return {"__repr__": repr(value)}


# One encoder for every value: json.dumps with `default` builds a new JSONEncoder per call.
_ENCODER = json.JSONEncoder(default=_tagged)


def hwc_to_chw(src, dst):
    """Copies frames [n, h, w, c] into [n, c, h, w]. The worker replaces this with its native copy
    (server/sim/src/pixels.rs, ~13x faster than numpy's strided loop); this is for the module
    imported on its own."""
    np.einsum("nhwc->nchw", src, out=dst)
