"""The bytes on the socket: msgpack maps whose numpy arrays travel as tagged maps, as openpi's client expects.

openpi's ``openpi_client.msgpack_numpy`` (the wire format of its ``WebsocketClientPolicy``) sends an array as the map
``{b"__ndarray__": True, b"data": raw bytes, b"dtype": dtype.str, b"shape": shape}`` and a numpy scalar as
``{b"__npgeneric__": True, b"data": value, b"dtype": dtype.str}``; every request and reply is one binary frame of
that msgpack, and an error reply is a text frame. This module speaks the same format, so either side may be
openpi's package or ours. Object, void and complex arrays are refused: msgpack carries no Python objects.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bpp.errors import require_extra

_ARRAY, _SCALAR = b"__ndarray__", b"__npgeneric__"
_REFUSED_KINDS = "OVc"


class WireError(ValueError):
    """A frame that is not a well-formed message of this format."""


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray | np.generic) and obj.dtype.kind in _REFUSED_KINDS:
        raise WireError(f"cannot send a numpy array of dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        return {
            _ARRAY: True,
            b"data": np.ascontiguousarray(obj).tobytes(),
            b"dtype": obj.dtype.str,
            b"shape": obj.shape,
        }
    if isinstance(obj, np.generic):
        return {_SCALAR: True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send a {type(obj).__name__}")


def _decode(obj: dict) -> Any:
    if _ARRAY in obj:
        try:
            dtype = np.dtype(obj[b"dtype"])
            if dtype.kind in _REFUSED_KINDS:
                raise WireError(f"refusing an array of dtype {dtype}")
            shape = tuple(int(n) for n in obj[b"shape"])
            if any(n < 0 for n in shape):
                raise ValueError(f"shape {shape} has a negative length")
            # a read-only view of the frame's bytes: checks the byte count against the shape, copies nothing
            return np.frombuffer(obj[b"data"], dtype=dtype).reshape(shape)
        except (KeyError, TypeError, ValueError) as err:
            raise WireError(f"malformed array ({err})") from None
    if _SCALAR in obj:
        try:
            dtype = np.dtype(obj[b"dtype"])
            if dtype.kind in _REFUSED_KINDS:
                raise WireError(f"refusing a scalar of dtype {dtype}")
            value = dtype.type(obj[b"data"])
            if np.ndim(value):
                raise ValueError("its data is a sequence")
            return value
        except (KeyError, TypeError, ValueError, OverflowError) as err:
            raise WireError(f"malformed scalar ({err})") from None
    return obj


def pack(message: Any) -> bytes:
    """A message (nested dicts, lists, numbers, strings, numpy arrays) as one msgpack frame."""
    return require_extra("msgpack", "serve").packb(message, default=_encode)


def unpack(frame: bytes) -> Any:
    """One msgpack frame back to a message; arrays come back read-only. WireError if it is not one."""
    msgpack = require_extra("msgpack", "serve")
    try:
        return msgpack.unpackb(frame, object_hook=_decode, strict_map_key=False)
    except WireError:
        raise
    except Exception as err:  # noqa: BLE001 - msgpack raises several unrelated types for garbage
        raise WireError(f"not a msgpack message ({type(err).__name__}: {err})") from None
