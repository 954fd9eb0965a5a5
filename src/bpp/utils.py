"""Small helpers: dataclass <-> JSON, tensors <-> devices, atomic file writes."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import typing
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

import numpy as np

from bpp.errors import UserError


def to_dict(obj: Any) -> Any:
    """A (nested) dataclass as plain JSON-able data."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def from_dict(cls: type, data: dict) -> Any:
    """Rebuild a (nested, frozen) dataclass from :func:`to_dict` output (a saved config); unknown keys are a
    :class:`~bpp.errors.UserError`."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise UserError(f"{cls.__name__}: unknown fields {sorted(unknown)}")
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _convert(hints[name], value)
    return cls(**kwargs)


def _convert(tp: Any, value: Any) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp) and isinstance(value, dict):
        return from_dict(tp, value)
    if origin is tuple and isinstance(value, list):
        args = typing.get_args(tp)
        inner = args[0] if args else Any
        return tuple(_convert(inner, v) for v in value)
    if tp is Path or (origin is typing.Union and Path in typing.get_args(tp) and isinstance(value, str)):
        return Path(value)
    return value


def check_fields(obj: Any, *rules: tuple[str, bool, str]) -> None:
    """Range checks for a config's ``__post_init__``: each rule is (field, whether it holds, what the field must
    be; a dotted name reaches into a nested config). Raises a UserError naming the first field that fails, what it must
    be and the value given. Write rules as positive conditions (``x > 0``), so a NaN fails them."""
    for name, ok, expected in rules:
        if not ok:
            value = functools.reduce(getattr, name.split("."), obj)
            raise UserError(f"{name} must be {expected}, got {value!r}")


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


MAX_JSON_BYTES = 64 << 20
"""JSON files bpp reads (configs, checkpoint state, results, drawing files) are refused above this size."""


def read_json(path: str | Path, what: str = "JSON file", max_bytes: int = MAX_JSON_BYTES) -> Any:
    """Parse the JSON file `path`, or raise a UserError naming it and `what` it should be: unreadable, over
    `max_bytes`, not UTF-8, not JSON, or nested too deeply for the parser (Python's RecursionError)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            limit = max_bytes / 2**20
            raise UserError(f"{path}: {size / 2**20:.0f} MiB, more than the {limit:.0f} MiB a {what} may have")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: cannot read the {what} ({err})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise UserError(f"{path}: the {what} is not valid JSON ({err})") from None
    except RecursionError:
        raise UserError(f"{path}: the {what} is nested too deeply to parse") from None


def write_json_atomic(path: str | Path, data: Any) -> None:
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def to_torch(batch: Any, device: torch.device | str) -> Any:
    """Nested dicts of numpy arrays / tensors -> tensors on `device` (floats as float32, images kept uint8)."""
    import torch

    if isinstance(batch, dict):
        return {k: to_torch(v, device) for k, v in batch.items()}
    if isinstance(batch, np.ndarray):
        batch = torch.from_numpy(batch)
    if isinstance(batch, torch.Tensor):
        if batch.dtype == torch.float64:
            batch = batch.float()
        return batch.to(device, non_blocking=True)
    return batch
