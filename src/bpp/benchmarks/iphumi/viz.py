"""Pictures of processed iPhUMI demonstrations (``bpp iphumi plot``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.media import pyplot

FRAMES = 5
"""Main-camera frames shown per episode."""


def plot_episodes(store: EpisodeStore, episodes: Sequence[int], out: Path) -> None:
    """One row per episode: the gripper's path in 3-D (colour: time; thick where the gripper is nearly closed), its
    width over time, and main-camera frames along the way (if the store has them)."""
    for episode in episodes:
        if not 0 <= episode < store.num_episodes:
            raise UserError(f"{store.path} has episodes 0 to {store.num_episodes - 1}, got {episode}")
    plt = pyplot()
    cameras = "rgb" in store.keys
    columns = 2 + (FRAMES if cameras else 0)
    fig = plt.figure(figsize=(7.6 + (1.3 * FRAMES if cameras else 0), 3.0 * len(episodes)))
    grid = fig.add_gridspec(
        len(episodes),
        columns,
        width_ratios=[3.2, 2.6] + [1.2] * (columns - 2),
        wspace=0.45,
        hspace=0.4,
        left=0.02,
        right=0.99,
    )
    fps = float(store.config.get("fps") or 10)
    for row, episode in enumerate(episodes):
        data = store.episode(episode, ["pose", "width"] + (["rgb"] if cameras else []))
        position, width = data["pose"][:, :3].astype(np.float64) * 100, data["width"][:, 0] * 1000
        seconds = np.arange(len(width)) / fps
        task = store.tasks[int(store.column("task_index")[episode])]
        ax = fig.add_subplot(grid[row, 0], projection="3d")
        closed = width < 0.2 * max(width.max(), 1e-9)
        ax.scatter(*position.T, c=seconds, cmap="viridis", s=np.where(closed, 14, 4))
        ax.plot(*position.T, color="0.6", linewidth=0.6)
        ax.set(xlabel="x", ylabel="y")  # z, the gripper's forward axis, keeps its ticks only: its label would collide
        ax.set_title(f"episode {episode}: {task['instruction'] or task['id']} (path in cm)", fontsize=9)
        ax = fig.add_subplot(grid[row, 1])
        ax.plot(seconds, width)
        ax.set(xlabel="time (s)", ylabel="gripper width (mm)", ylim=(-2, max(width.max() * 1.1, 10)))
        ax.grid(alpha=0.3)
        if cameras:
            for k, step in enumerate(np.linspace(0, len(width) - 1, FRAMES).round().astype(int)):
                ax = fig.add_subplot(grid[row, 2 + k])
                ax.imshow(data["rgb"][step])
                ax.set_title(f"{seconds[step]:.1f} s", fontsize=8)
                ax.axis("off")
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
