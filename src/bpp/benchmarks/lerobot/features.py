"""How LeRobot features map to store keys and back.

A LeRobot v3 dataset describes each per-frame column in ``meta/info.json``'s ``features``: a name such as
``observation.state``, a dtype and a shape. On import:

* cameras (dtype ``video`` or ``image``, RGB) become ``camera0``, ``camera1``, ... in the order chosen, stored at one
  square size, so that observation presets can name them whatever the dataset calls its cameras;
* ``action`` stays ``action``; ``observation.state`` becomes ``state``; any other ``observation.X`` becomes ``X`` and
  any other name has its dots replaced by underscores (``next.reward`` -> ``next_reward``); numeric features of any
  shape are stored as flat vectors, float32 (float64 stays float64);
* LeRobot's bookkeeping columns (``timestamp``, ``frame_index``, ``episode_index``, ``index``, ``task_index``) are not
  stored as keys: they place the frames, episodes and tasks.

The store's config keeps every key's LeRobot name, dtype, shape and names, so that an export restores them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from bpp.errors import UserError

BOOKKEEPING = ("timestamp", "frame_index", "episode_index", "index", "task_index")
"""LeRobot's own per-frame columns, present in every dataset."""
CAMERA_DTYPES = ("video", "image")


@dataclass(frozen=True)
class Mapped:
    """One LeRobot feature and the store key it becomes."""

    key: str
    feature: str
    dtype: str
    """The LeRobot dtype ("float32", "bool", "video", "image", ...)."""
    shape: tuple[int, ...]
    names: object = None

    @property
    def is_camera(self) -> bool:
        return self.dtype in CAMERA_DTYPES

    @property
    def width(self) -> int:
        """Features per step of a numeric feature, flattened."""
        return int(np.prod(self.shape)) if self.shape else 1

    @property
    def store_dtype(self) -> np.dtype:
        """What a numeric feature is stored as: float64 if it is float64, else float32."""
        return np.dtype(np.float64) if np.dtype(self.dtype) == np.float64 else np.dtype(np.float32)

    def to_json(self) -> dict:
        return {**asdict(self), "shape": list(self.shape)}

    @classmethod
    def from_json(cls, data: Mapping) -> Mapped:
        return cls(**{**data, "shape": tuple(data["shape"])})


@dataclass(frozen=True)
class FeatureMap:
    """A dataset's features, mapped: numeric per-step keys, cameras (in order) and the action."""

    lowdim: tuple[Mapped, ...]
    cameras: tuple[Mapped, ...]
    action: Mapped

    @property
    def all(self) -> tuple[Mapped, ...]:
        return (*self.lowdim, self.action, *self.cameras)


def store_key(feature: str) -> str:
    """The store key of a numeric LeRobot feature (see the module docstring)."""
    if feature == "observation.state":
        return "state"
    if feature.startswith("observation."):
        feature = feature[len("observation.") :]
    return feature.replace(".", "_")


def _resolve(names: Sequence[str], features: Mapping, flag: str) -> list[str]:
    """Feature names given on the command line (full, or their last dotted part when that is unambiguous) -> full."""
    resolved = []
    for name in names:
        if name in features:
            resolved.append(name)
            continue
        matches = [f for f in features if f.rsplit(".", 1)[-1] == name]
        if len(matches) != 1:
            found = "matches several features" if matches else "is not a feature of the dataset"
            raise UserError(f"{flag} {name!r} {found}; its features: {', '.join(features)}")
        resolved.append(matches[0])
    return resolved


def _is_numeric(dtype: str) -> bool:
    try:
        return np.dtype(dtype).kind in "biuf"
    except TypeError:
        return False


def map_features(
    features: Mapping[str, Mapping], cameras: Sequence[str] = (), skip: Sequence[str] = (), action: str = "action"
) -> FeatureMap:
    """Map a dataset's ``info.json`` features; `cameras` picks cameras and their order (default: every camera in the
    order listed), `skip` leaves features out. A feature that cannot be stored is refused with what to do about it."""
    skipped = set(_resolve(skip, features, "--skip"))
    chosen = _resolve(cameras, features, "--cameras")
    if action in skipped or action not in features:
        raise UserError(
            f"the dataset has no action feature {action!r} (name it with --action); its features: {', '.join(features)}"
        )
    all_cameras = [name for name, spec in features.items() if spec.get("dtype") in CAMERA_DTYPES]
    for name in chosen:
        if name not in all_cameras:
            raise UserError(f"--cameras {name!r} is not a camera (a video or image feature) of the dataset")
    order = chosen or [name for name in all_cameras if name not in skipped]
    lowdim, mapped_cameras, keys, action_item = [], [], {}, None
    for name, spec in features.items():
        if name in BOOKKEEPING or name in skipped or (spec.get("dtype") in CAMERA_DTYPES and name not in order):
            continue
        dtype, shape = str(spec.get("dtype")), tuple(int(n) for n in spec.get("shape") or ())
        if dtype in CAMERA_DTYPES:
            info = spec.get("info") or {}
            channels = int(info.get("video.channels") or (3 if shape and 3 in (shape[0], shape[-1]) else 0))
            if info.get("video.is_depth_map") or channels != 3 or len(shape) != 3:
                raise UserError(
                    f"feature {name!r} (shape {shape}) is not an RGB camera; leave it out with --skip {name}"
                )
            item = Mapped(f"camera{order.index(name)}", name, dtype, shape, spec.get("names"))
            mapped_cameras.append(item)
        elif _is_numeric(dtype):
            item = Mapped("action" if name == action else store_key(name), name, dtype, shape, spec.get("names"))
            if name == action:
                action_item = item
            else:
                lowdim.append(item)
        else:
            raise UserError(
                f"feature {name!r} has dtype {dtype!r}, which bpp cannot store (it stores numeric vectors and RGB "
                f"cameras); leave it out with --skip {name}"
            )
        if item.key in keys:
            raise UserError(f"features {keys[item.key]!r} and {name!r} would both be stored as {item.key!r}")
        keys[item.key] = name
    if action_item is None:
        raise UserError(f"the action feature {action!r} is a camera; name a numeric feature with --action")
    mapped_cameras.sort(key=lambda m: order.index(m.feature))
    return FeatureMap(tuple(lowdim), tuple(mapped_cameras), action_item)
