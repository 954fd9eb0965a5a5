"""Pictures and tables of evaluation results for any benchmark: a prompt | rollout grid, rollout videos,
prompt-attention heatmaps, Markdown tables and bar charts."""

from __future__ import annotations

import errno
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from bpp.data.store import EpisodeStore
from bpp.media import contact_sheet, pyplot, save_animation, save_figure


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


def write_grid(results, benchmark, store: EpisodeStore, path: Path, per_row: int = 3, title: str = "") -> Path:
    """For each task: the prompt demonstration (the benchmark's picture), then its first rollout's outcome."""
    images, titles = [], []
    for r in results:
        first = r.rollouts[0]
        images += [benchmark.prompt_picture(store, first["prompt_episode"]), r.last_frame]
        titles += [
            f"{r.task_id}: prompt",
            f"{benchmark.describe_rollout(first)}: {benchmark.metric.format(first['score'])} (task {r.mean:.1f})",
        ]
    blank = np.full_like(images[0], 255)  # a rollout without frames keeps its place beside its prompt
    images = [blank if image is None else image for image in images]
    return contact_sheet(images, titles, path, columns=2 * per_row, title=title)


def write_attention(attention: np.ndarray, n_action_steps: int, path: Path, title: str = "") -> Path:
    """Heatmap of prompt attention during one rollout: rollout step on x, prompt chunk on y (sinks in the top row).

    attention: (calls, n_chunks + 1), column 0 the attention-sink mass, column i + 1 prompt chunk i.
    """
    plt = pyplot()
    used = np.flatnonzero(attention.sum(axis=0) > 0)
    attention = attention[:, : used.max() + 1] if len(used) else attention  # drop chunks padded in by batching
    calls, columns = attention.shape
    fig, ax = plt.subplots(figsize=(7, 4))
    image = ax.imshow(
        attention.T,
        aspect="auto",
        origin="upper",
        cmap="magma",
        extent=(0, calls * n_action_steps, columns - 1.5, -1.5),
        interpolation="nearest",
    )
    ax.set_xlabel("rollout step")
    ax.set_ylabel("prompt chunk (-1: attention sinks)")
    ax.set_title(title or "prompt attention during a rollout", fontsize=10)
    fig.colorbar(image, ax=ax, label="attention mass")
    return _save(fig, path)


def write_video(frames: Sequence[np.ndarray], stem: Path) -> Path:
    """``<stem>.mp4`` through imageio-ffmpeg; ``<stem>.gif``, with a warning, if the encoder fails (e.g. an ffmpeg
    without libx264). A full disk is an error, not a reason for a GIF. The suffix is added to `stem`, never put in
    place of a part of it ('rollout_star.v1' stays whole)."""
    try:
        return save_animation(frames, stem.with_name(f"{stem.name}.mp4"))
    except Exception as err:  # noqa: BLE001 - any encoder failure: fall back to the always-available GIF writer
        if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT):
            raise
        warnings.warn(f"{stem.name}.mp4 failed ({type(err).__name__}: {err}); writing a GIF", stacklevel=2)
        return save_animation(frames, stem.with_name(f"{stem.name}.gif"))


def markdown_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A GitHub Markdown table; floats with two decimals."""

    def cell(v):  # a task id may hold '|' or a line break, which would end the cell or the row
        return f"{v:.2f}" if isinstance(v, float) else " ".join(str(v).replace("|", "\\|").split())

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(" --- " for _ in header) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def bar_chart(values: Mapping[str, Mapping[str, tuple[float, float]]], path: Path, ylabel: str, title: str = ""):
    """Grouped bars: values[group][series] = (mean, std), e.g. values["unseen human"]["BPP"] = (3.4, 0.1)."""
    plt = pyplot()
    groups = list(values)
    series = list(dict.fromkeys(s for g in groups for s in values[g]))
    width = 0.8 / max(1, len(series))
    fig, ax = plt.subplots(figsize=(1.6 + 1.6 * len(groups) * max(1, len(series)) / 2, 3.6))
    for i, s in enumerate(series):
        xs = [g_i + (i - (len(series) - 1) / 2) * width for g_i in range(len(groups))]
        means = [values[g].get(s, (np.nan, 0))[0] for g in groups]
        stds = [values[g].get(s, (np.nan, 0))[1] for g in groups]
        bars = ax.bar(xs, means, width, yerr=stds, capsize=3, label=s)
        ax.bar_label(bars, fmt="%.1f", fontsize=7, padding=2)
    ax.set_xticks(range(len(groups)), groups)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    return _save(fig, path)
