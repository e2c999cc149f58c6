"""What every adapter uses: spaces as the worker protocol writes them, info dicts as JSON, the
frame copy."""

import json

import numpy as np


# Options the server consumes itself, and the engine choice (make_group's); adapters never see them.
SERVER_OPTIONS = {"frame_stack", "engine", "batch_size"}


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


def info_json(info):
    """An env's info dict as JSON text for the client (None when empty). numpy values are tagged with
    their dtype, `{"__numpy__": dtype, "value": ...}` (and `"shape"` for arrays), so the client
    rebuilds them as the env returned them (gymnasium batches infos by their values' types);
    anything JSON cannot hold travels as its repr."""
    if not info:
        return None
    return _ENCODER.encode(info)


def _tagged(value):
    if isinstance(value, np.ndarray):
        return {"__numpy__": value.dtype.str, "shape": list(value.shape), "value": value.ravel().tolist()}
    if isinstance(value, np.generic):
        return {"__numpy__": value.dtype.str, "value": value.item()}
    return {"__repr__": repr(value)}


# One encoder for every info: json.dumps with `default` builds a new JSONEncoder per call.
_ENCODER = json.JSONEncoder(default=_tagged)


def hwc_to_chw(src, dst):
    """Copies frames [n, h, w, c] into [n, c, h, w]. The worker replaces this with its native copy
    (server/sim/src/pixels.rs, ~13x faster than numpy's strided loop); this is for the module
    imported on its own."""
    np.einsum("nhwc->nchw", src, out=dst)
