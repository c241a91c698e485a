"""openpi's wire format: msgpack, with numpy arrays as tagged maps.

Written against openpi-client's ``openpi_client/msgpack_numpy.py`` (0.1.2), so the server needs
no openpi package; tests/test_serve.py checks it against that module and its client. An array is
the map ``{b"__ndarray__": True, b"data": raw bytes, b"dtype": dtype.str, b"shape": shape}``, a
numpy scalar ``{b"__npgeneric__": True, b"data": item, b"dtype": dtype.str}``; object, void and
complex dtypes are refused both ways (openpi refuses them on packing: no pickle).
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

_REFUSED_KINDS = ("V", "O", "c")


class WireError(ValueError):
    """A message that is not openpi's msgpack-numpy."""


def _pack_numpy(obj: Any) -> Any:
    if isinstance(obj, np.ndarray | np.generic) and obj.dtype.kind in _REFUSED_KINDS:
        raise WireError(f"cannot send a numpy array of dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        return {
            b"__ndarray__": True,
            b"data": obj.tobytes(),
            b"dtype": obj.dtype.str,
            b"shape": obj.shape,
        }
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send a {type(obj).__name__}")


def _unpack_numpy(obj: dict[Any, Any]) -> Any:
    if b"__ndarray__" in obj or b"__npgeneric__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind in _REFUSED_KINDS:
            raise WireError(f"numpy dtype {dtype} is not accepted")
        if b"__npgeneric__" in obj:
            return dtype.type(obj[b"data"])
        # A view of the message's bytes (read-only), as openpi's unpack_array.
        return np.ndarray(buffer=obj[b"data"], dtype=dtype, shape=obj[b"shape"])
    return obj


def packb(value: Any) -> bytes:
    """``value`` (dicts, lists, str, numbers, numpy arrays and scalars) as one message."""
    return msgpack.packb(value, default=_pack_numpy)


def unpackb(message: bytes) -> Any:
    """One message back into Python values and numpy arrays; ``WireError`` for anything else."""
    try:
        return msgpack.unpackb(message, object_hook=_unpack_numpy)
    except WireError:
        raise
    except (ValueError, TypeError, KeyError, msgpack.UnpackException) as err:
        raise WireError(
            f"not an openpi msgpack-numpy message ({type(err).__name__}: {err})"
        ) from err
