"""The check of an array from outside (a policy server's client, an uploaded or stored demonstration): one function,
:func:`check_array`, so that every door refuses the same things with the same words."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from bpp.errors import UserError


@dataclass(frozen=True)
class Bounds:
    """The values a feature may take: `low` and `high` broadcast over an array's last axis (one per feature), and
    what they are, for the message."""

    low: np.ndarray | float
    high: np.ndarray | float
    what: str


FLOAT32_RANGE = Bounds(-float(np.finfo(np.float32).max), float(np.finfo(np.float32).max), "float32's range")


def check_array(
    name: str,
    value: Any,
    shape: tuple[int | None, ...],
    dtype: type[np.generic],
    *,
    kinds: str = "f",
    bounds: Bounds = FLOAT32_RANGE,
    expected: str = "",
    error: type[UserError] = UserError,
) -> np.ndarray:
    """`value` (an array, or nested lists of numbers) as an array of `dtype` and `shape`, or `error` naming `name` and
    what is wrong with it.

    `shape` holds None for an axis of any length (e.g. ``(None, 2)``: any number of steps of width 2); `expected`
    describes it in the message (default: the shape, None written as "steps"). uint8 (images) takes uint8 only.
    float32 takes arrays of the dtype kinds in `kinds` (default floating point only: a boolean or an integer where a
    measurement belongs is a mistake; stored demonstrations may pass "fiub"), whose values must be finite and within
    `bounds`; they come back as float32.
    """
    array = as_array(name, value, error)
    if array.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, array.shape, strict=True)):
        raise error(f"{name} must have shape {expected or _shape_text(shape)}, got {array.shape}")
    if np.dtype(dtype) == np.uint8:
        if array.dtype != np.uint8:
            raise error(f"{name} must be uint8 RGB (0-255), got {array.dtype}")
        return array
    assert np.dtype(dtype) == np.float32, f"check_array checks uint8 or float32 arrays, not {dtype}"
    if array.dtype.kind not in kinds:
        allowed = "floating point" if kinds == "f" else "numeric"
        raise error(f"{name} must be {allowed} (float32), got {array.dtype}")
    wide = array.astype(np.float64)  # checked before the cast, which would turn what float32 cannot hold into inf
    bad = ~np.isfinite(wide)
    if bad.any():
        raise error(f"{name} contains NaN or infinite values (at index {_first(bad)})")
    outside = (wide < bounds.low) | (wide > bounds.high)
    if outside.any():
        at = _first(outside)
        low, high = (np.broadcast_to(b, wide.shape)[at] for b in (bounds.low, bounds.high))
        raise error(f"{name} holds {wide[at]:.4g} at index {at}, outside [{low:.4g}, {high:.4g}] ({bounds.what})")
    return array.astype(np.float32, copy=False)


def as_array(name: str, value: Any, error: type[UserError] = UserError) -> np.ndarray:
    """`value` (an array, or nested lists of numbers) as a numpy array, or `error` naming `name`: the first step of
    :func:`check_array`."""
    if value is None or isinstance(value, str | bytes | Mapping):
        raise error(f"{name} must be an array, got {type(value).__name__}")
    try:
        return np.asarray(value)
    except (ValueError, TypeError, OverflowError) as err:  # ragged lists, or numbers numpy cannot hold
        raise error(f"{name} must be an array or equally long lists of numbers ({err})") from None


def _shape_text(shape: tuple[int | None, ...]) -> str:
    """``(None, 2)`` -> ``"(steps, 2)"``."""
    return str(tuple("steps" if n is None else n for n in shape)).replace("'", "")


def first_non_finite(values: np.ndarray) -> tuple[int, int] | None:
    """(row, item) of the first NaN or infinity of `values` (rows along the first axis, the rest flattened), or None
    where every value is finite or the dtype holds no such values."""
    if values.dtype.kind not in "fc" or np.isfinite(values).all():
        return None
    step, item = _first(~np.isfinite(values.reshape(len(values), -1)))
    return step, item


def _first(mask: np.ndarray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(mask)[0])
