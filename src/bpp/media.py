"""Pictures and animations for any benchmark: titled image grids and GIF/MP4 files."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np


def save_animation(frames: Sequence[np.ndarray], path: str | Path, fps: int = 10) -> Path:
    """Write frames as a GIF (or MP4 if the suffix is .mp4)."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".mp4":
        import imageio.v2 as iio2  # the ffmpeg writer (imageio-ffmpeg ships its own ffmpeg binary)

        with iio2.get_writer(path, fps=fps, codec="libx264", macro_block_size=16) as writer:
            for frame in frames:
                writer.append_data(frame)
    else:
        iio.imwrite(path, np.stack(frames), duration=1000 / fps, loop=0)
    return path


def contact_sheet(
    images: Sequence[np.ndarray], titles: Sequence[str], path: str | Path, columns: int = 8, title: str = ""
) -> Path:
    """Lay out images in a titled grid and save as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = max(1, int(np.ceil(len(images) / columns)))
    fig, axes = plt.subplots(rows, columns, figsize=(columns * 1.9, rows * 2.05), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, image, name in zip(axes.flat, images, titles, strict=False):
        ax.imshow(image)
        ax.set_title(name, fontsize=7)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / fig.get_figheight()) if title else None)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
