"""Contact sheets of a DrawAnything store: each row a task (upright) followed by its demonstrations."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bpp.benchmarks.draw.viz import contact_sheet, group_strokes, render_drawing, render_strokes
from bpp.data.store import EpisodeStore
from bpp.drawing.drawing import task_drawing
from bpp.errors import UserError


def write_contact_sheet(store_path: str | Path, out: str | Path, tasks: int = 8, demos: int = 5, size: int = 160):
    """Rows: `tasks` tasks spread evenly over the store; columns: the task, then up to `demos` demonstrations."""
    store = EpisodeStore(store_path)
    if tasks < 1 or demos < 0:
        raise UserError(f"need tasks >= 1 and demos >= 0, got tasks={tasks}, demos={demos}")
    chosen = np.unique(np.linspace(0, store.num_tasks - 1, min(tasks, store.num_tasks)).round().astype(int))
    by_task = store.task_episodes()
    angles = store.column("board_angle")
    ends = store.episode_ends
    images, titles = [], []
    columns = 1 + demos
    for t in chosen:
        drawing = task_drawing(store, int(t))
        images.append(render_drawing(drawing, 0.0, size))
        titles.append(drawing.id)
        episodes = list(by_task[t][:demos])
        for e in episodes:
            ep = store.episode(int(e), ("state", "action"))
            strokes = group_strokes(ep["state"], ep["action"].astype(np.float64))
            images.append(render_strokes(strokes, float(angles[e]), size))
            length = int(ends[e] - (ends[e - 1] if e else 0))
            titles.append(f"demo {e}: {np.degrees(angles[e]):+.0f}°, {length} steps")
        for _ in range(demos - len(episodes)):
            images.append(np.full((size, size, 3), 255, np.uint8))
            titles.append("")
    title = f"{Path(store_path).name}: {store.num_tasks} tasks, {store.num_episodes} demos (strokes: purple→yellow)"
    return contact_sheet(images, titles, out, columns=columns, title=title)
