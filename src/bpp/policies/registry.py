"""Methods by name: adding a method is one entry here and one folder under ``bpp/policies``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Method:
    name: str
    config_cls: type
    model_cls: type
    presets: dict[str, Any]


def get_method(name: str) -> Method:
    if name == "bpp":
        from bpp.policies.bpp.config import PRESETS, BPPConfig
        from bpp.policies.bpp.model import BPPModel

        return Method("bpp", BPPConfig, BPPModel, PRESETS)
    raise ValueError(f"unknown method {name!r}; available: bpp")


METHODS = ("bpp",)
