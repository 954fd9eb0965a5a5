"""Checkpoints as data: safetensors for tensors, JSON for everything else, written atomically.

A run directory::

    <run>/config.json                 resolved training + model configuration
    <run>/checkpoints/step_00001000/  model.safetensors, ema.safetensors, optimizer.safetensors, state.json
    <run>/checkpoints/last            the name of the newest complete checkpoint folder

A checkpoint folder is written under a temporary name and renamed when complete, then ``last`` is replaced
atomically, so a crash at any moment leaves the previous checkpoint loadable. Only then are checkpoints beyond
the newest few deleted (each holds the model twice and the optimizer state, so a long CPU run would otherwise
fill a disk with gigabytes of them). A save that fails (a full disk) or is interrupted (Ctrl-C, SIGTERM) removes
its temporary folder; the next save removes those of processes that were killed outright.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import sys
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load, save_file

from bpp.errors import UserError
from bpp.policies.agent import PolicyAgent
from bpp.policies.registry import get_method
from bpp.utils import (
    atomic_path,
    from_dict,
    process_alive,
    read_json,
    remove_stale_partials,
    write_json_atomic,
    write_text_atomic,
)

FORMAT = "bpp-checkpoint"
VERSION = 1
STATE_KEYS = ("step", "optimizer", "method", "model_config", "train_config", "stats", "dataset")
"""What every checkpoint's ``state.json`` holds besides its format and version."""


def _tensors(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().to("cpu").contiguous().clone() for k, v in state.items()}


def _flatten_optimizer(state: dict) -> tuple[dict[str, torch.Tensor], dict]:
    tensors, skeleton = {}, {"param_groups": state["param_groups"], "state": {}}
    for index, entry in state["state"].items():
        skeleton["state"][str(index)] = {}
        for name, value in entry.items():
            if isinstance(value, torch.Tensor):
                tensors[f"{index}/{name}"] = value
                skeleton["state"][str(index)][name] = "__tensor__"
            else:
                skeleton["state"][str(index)][name] = value
    return _tensors(tensors), skeleton


def _unflatten_optimizer(tensors: dict[str, torch.Tensor], skeleton: dict) -> dict:
    state = {}
    for index, entry in skeleton["state"].items():
        state[int(index)] = {
            name: tensors[f"{index}/{name}"] if value == "__tensor__" else value for name, value in entry.items()
        }
    return {"state": state, "param_groups": skeleton["param_groups"]}


def save_checkpoint(
    run_dir: str | Path,
    step: int,
    model: torch.nn.Module,
    ema: torch.nn.Module,
    optimizer,
    meta: dict[str, Any],
    keep: int = 0,
) -> Path:
    """Write checkpoint `step` (complete or not at all, also when a full disk, Ctrl-C or SIGTERM stops it: the
    temporary folder is removed, and an OSError names the checkpoint), point ``last`` at it, then keep only the
    newest `keep` checkpoints (0: keep all)."""
    ckpt_dir = Path(run_dir) / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    _remove_stale_temporaries(ckpt_dir)
    name = f"step_{step:08d}"
    final = ckpt_dir / name
    with atomic_path(final) as tmp:
        tmp.mkdir()
        _save_tensors(_tensors(model.state_dict()), tmp / "model.safetensors")
        _save_tensors(_tensors(ema.state_dict()), tmp / "ema.safetensors")
        opt_tensors, opt_skeleton = _flatten_optimizer(optimizer.state_dict())
        _save_tensors(opt_tensors, tmp / "optimizer.safetensors")
        rng = {"torch_cpu": torch.get_rng_state()}
        if torch.cuda.is_available():
            for i, s in enumerate(torch.cuda.get_rng_state_all()):
                rng[f"torch_cuda_{i}"] = s
        _save_tensors(_tensors(rng), tmp / "rng.safetensors")
        state = {"format": FORMAT, "version": VERSION, "step": step, "optimizer": opt_skeleton, **meta}
        write_json_atomic(tmp / "state.json", state)
        if final.exists():  # the same step saved again (a resumed run repeats the steps after its checkpoint)
            shutil.rmtree(final)
    write_text_atomic(ckpt_dir / "last", name)
    if keep:
        prune_checkpoints(ckpt_dir, keep)
    return final


def _save_tensors(tensors: dict[str, torch.Tensor], path: Path) -> None:
    """safetensors' save_file, with its I/O errors (a full disk) as OSErrors naming `path`: safetensors reports them
    as its own error type."""
    try:
        save_file(tensors, path)
    except Exception as err:  # noqa: BLE001 - SafetensorError; its message carries the system's error number
        code = re.search(r"os error (\d+)", str(err))
        if code is None:
            raise
        raise OSError(int(code[1]), os.strerror(int(code[1])), str(path)) from None


_LEGACY_TEMPORARY = re.compile(r"\.(?:step_[0-9]{8}|last)\.tmp-(?P<pid>[0-9]+)")
"""The temporary names of checkpoints and ``last`` before bpp removed them on failure; older runs may hold some."""


def _remove_stale_temporaries(ckpt_dir: Path) -> None:
    """Delete the half-written checkpoints of training processes that were killed outright (SIGKILL, a power loss)
    or, before this was handled, stopped by an error: each holds up to a checkpoint's size."""
    remove_stale_partials(ckpt_dir)
    for entry in ckpt_dir.iterdir():
        match = _LEGACY_TEMPORARY.fullmatch(entry.name)
        if match and not process_alive(int(match["pid"])):
            if entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


def prune_checkpoints(ckpt_dir: str | Path, keep: int) -> list[Path]:
    """Delete all but the newest `keep` step folders of `ckpt_dir` (never the one ``last`` names); returns them."""
    if keep < 1:
        raise ValueError(f"keep must be at least 1, got {keep}")
    ckpt_dir = Path(ckpt_dir)
    last = (ckpt_dir / "last").read_text().strip()
    steps = sorted(p for p in ckpt_dir.glob("step_*") if p.is_dir() and p.name != last)
    removed = steps[: max(len(steps) - (keep - 1), 0)]
    for path in removed:
        shutil.rmtree(path)
    return removed


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint folder from a run directory (its ``last``), a checkpoints folder, or the folder itself.

    If ``last`` names a folder that is missing or incomplete, the newest step folder with a ``state.json`` is used
    instead, and a line on stderr says so."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such checkpoint or run directory")
    if (path / "state.json").is_file():
        return path
    for base in (path / "checkpoints", path):
        last = base / "last"
        if last.is_file():
            name = last.read_text(errors="replace").strip()
            target = base / name
            if _STEP_NAME.fullmatch(name) and (target / "state.json").is_file():
                return target
            intact = step_folders(base)
            if intact:
                print(
                    f"[checkpoint] {last} names {target.name}, which is missing or incomplete; using {intact[0].name}",
                    file=sys.stderr,
                )
                return intact[0]
    raise FileNotFoundError(f"{path}: no checkpoint found (expected state.json, or checkpoints/last in a run dir)")


_STEP_NAME = re.compile(r"step_[0-9]{8}")


def step_folders(ckpt_dir: Path) -> list[Path]:
    """Step folders of `ckpt_dir` that have a state.json, newest first."""
    return sorted((p for p in ckpt_dir.glob("step_*") if (p / "state.json").is_file()), reverse=True)


def _load_tensors(path: Path) -> tuple[dict[str, torch.Tensor], str]:
    """The tensors of a safetensors file and the file's SHA-256 (its bytes are read once for both)."""
    try:
        data = path.read_bytes()
        return load(data), hashlib.sha256(data).hexdigest()
    except Exception as err:  # noqa: BLE001 - safetensors raises its own error types for truncated or foreign files
        raise UserError(f"{path}: unreadable weights ({type(err).__name__}: {err})") from None


def read_state(path: str | Path) -> dict:
    ckpt = resolve_checkpoint(path)
    state = read_json(ckpt / "state.json", "checkpoint state")
    if not isinstance(state, dict) or state.get("format") != FORMAT or state.get("version") != VERSION:
        raise UserError(f"{ckpt}: not a bpp checkpoint of version {VERSION}")
    missing = [key for key in STATE_KEYS if key not in state]
    if missing:
        raise UserError(f"{ckpt / 'state.json'}: damaged checkpoint state (no {', '.join(missing)})")
    return state


def load_training_state(path: str | Path, model, ema, optimizer) -> int:
    """Restore model, EMA, optimizer and RNG in place from the newest intact checkpoint of run `path`; returns the
    step to continue from. A damaged newest checkpoint is skipped with a line on stderr naming the bad file."""
    newest = resolve_checkpoint(path)
    candidates = [newest, *(p for p in step_folders(newest.parent) if p.name < newest.name)]
    for ckpt in candidates:
        try:
            state = read_state(ckpt)
            tensors = {
                name: _load_tensors(ckpt / f"{name}.safetensors")[0] for name in ("model", "ema", "optimizer", "rng")
            }
        except (UserError, OSError) as err:
            print(f"[checkpoint] skipping {ckpt.name}: {err}", file=sys.stderr)
            continue
        model.load_state_dict(tensors["model"])
        ema.load_state_dict(tensors["ema"])
        optimizer.load_state_dict(_unflatten_optimizer(tensors["optimizer"], state["optimizer"]))
        torch.set_rng_state(tensors["rng"]["torch_cpu"])
        if ckpt != newest:
            print(f"[checkpoint] resuming from {ckpt.name}, the newest intact checkpoint", file=sys.stderr)
        return int(state["step"])
    raise UserError(f"{path}: no intact checkpoint to resume from (see the lines above for each one's problem)")


class Checkpoint:
    """One checkpoint read from disk once: its folder, its ``state.json`` and one set of weights (the EMA or the
    trained ones), passed down from there (to build the model in this process or, pickled, in worker processes).

    ``state`` holds ``method``, ``model_config``, ``train_config``, ``stats``, ``dataset`` and ``step``."""

    def __init__(self, path: Path, state: dict, weights: dict[str, torch.Tensor], weights_sha256: str):
        self.path, self.state, self.weights = path, state, weights
        self.weights_sha256 = weights_sha256
        """SHA-256 of the weights file read: what evaluation results are keyed on, with the tasks' content."""

    @classmethod
    def load(cls, path: str | Path, use_ema: bool = True) -> Checkpoint:
        """Resolve `path` (run directory or checkpoint folder) and read it, with the EMA weights or the trained ones."""
        ckpt = resolve_checkpoint(path)
        state = read_state(ckpt)
        weights, sha256 = _load_tensors(ckpt / ("ema.safetensors" if use_ema else "model.safetensors"))
        return cls(ckpt, state, weights, sha256)

    @property
    def method(self) -> str:
        return self.state["method"]

    @property
    def step(self) -> int:
        return int(self.state["step"])

    @property
    def benchmark(self) -> str:
        """The benchmark of the store it was trained on."""
        return self.state["dataset"]["benchmark"]

    def model_config(self):
        return from_dict(get_method(self.method).config_cls, self.state["model_config"])

    def build_model(self, device: str | torch.device = "cpu"):
        """The trained model (config, normalisation statistics and the loaded weights), in eval mode."""
        model = get_method(self.method).model_cls(self.model_config(), self.state["stats"])
        model.load_state_dict(self.weights)
        return model.to(device).eval()


def load_policy(path: str | Path, device: str | torch.device = "cpu", use_ema: bool = True):
    """Rebuild a trained model from a checkpoint (config, normalisation statistics and weights)."""
    return Checkpoint.load(path, use_ema).build_model(device)


def load_agent(path: str | Path, device: str = "cpu", use_ema: bool = True, **options) -> PolicyAgent:
    """A :class:`~bpp.policies.agent.PolicyAgent` acting with the model of checkpoint (or run) `path`; `options`
    are the agent's (``n_action_steps``, ``record_attention``, ...)."""
    return PolicyAgent(load_policy(path, device, use_ema), device, **options)
