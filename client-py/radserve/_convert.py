"""Tensors and spaces between radserve's messages and numpy / gymnasium."""

import numpy as np
from gymnasium import spaces

from ._proto import radserve_pb2 as pb

NUMPY_DTYPES = {
    pb.DTYPE_UINT8: np.dtype(np.uint8),
    pb.DTYPE_INT32: np.dtype("<i4"),
    pb.DTYPE_INT64: np.dtype("<i8"),
    pb.DTYPE_FLOAT32: np.dtype("<f4"),
    pb.DTYPE_FLOAT64: np.dtype("<f8"),
    pb.DTYPE_BOOL: np.dtype(np.bool_),
}
_PROTO_DTYPES = {dtype.name: code for code, dtype in NUMPY_DTYPES.items()}


def to_numpy(tensor: "pb.Tensor") -> np.ndarray:
    """A read-only array over the message's bytes (no copy beyond the one protobuf made)."""
    return np.frombuffer(tensor.data, dtype=NUMPY_DTYPES[tensor.dtype]).reshape(tuple(tensor.shape))


def to_tensor(array: np.ndarray) -> "pb.Tensor":
    """A message holding `array`'s bytes, little-endian, C order (TypeError for a dtype radserve
    tensors cannot hold)."""
    array = np.ascontiguousarray(array)
    dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
    if dtype.name not in _PROTO_DTYPES:
        raise TypeError(f"radserve tensors cannot hold dtype {array.dtype}")
    return pb.Tensor(dtype=_PROTO_DTYPES[dtype.name], shape=array.shape, data=array.astype(dtype, copy=False).tobytes())


def to_space(space: "pb.Space") -> spaces.Space:
    """The gymnasium space a `Space` message describes (Discrete, or a Box of its dtype and bounds)."""
    kind = space.WhichOneof("kind")
    if kind == "discrete":
        return spaces.Discrete(space.discrete.n)
    box = space.box
    shape = tuple(box.shape)
    dtype = NUMPY_DTYPES[box.dtype]

    def bound(values):
        values = np.asarray(values, dtype=np.float64)
        return values.reshape(shape) if values.size > 1 else np.full(shape, values[0] if values.size else np.inf)

    low, high = bound(box.low), bound(box.high)
    if np.issubdtype(dtype, np.integer):
        low = np.clip(low, np.iinfo(dtype).min, np.iinfo(dtype).max)
        high = np.clip(high, np.iinfo(dtype).min, np.iinfo(dtype).max)
    return spaces.Box(low=low.astype(dtype), high=high.astype(dtype), shape=shape, dtype=dtype)


def option_value(value) -> "pb.OptionValue":
    """An env option's value as the message carries it (bool, int, float or str)."""
    # bool before int: True is an int in Python.
    if isinstance(value, (bool, np.bool_)):
        return pb.OptionValue(bool_value=bool(value))
    if isinstance(value, (int, np.integer)):
        return pb.OptionValue(int_value=int(value))
    if isinstance(value, (float, np.floating)):
        return pb.OptionValue(float_value=float(value))
    if isinstance(value, str):
        return pb.OptionValue(string_value=value)
    raise TypeError(f"option values must be bool, int, float or str, got {type(value).__name__}")


def from_option_value(value: "pb.OptionValue"):
    """The Python value an `OptionValue` message holds."""
    return getattr(value, value.WhichOneof("value"))
