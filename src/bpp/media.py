"""Pictures and animations for any benchmark: titled image grids and GIF/MP4 files, each written complete or not at
all (:func:`bpp.utils.atomic_path`)."""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from bpp.utils import atomic_path


def headless_opengl() -> None:
    """Call before a process's first OpenGL context: MuJoCo renders headless through EGL unless ``MUJOCO_GL`` says
    otherwise, and triton is loaded first. Mesa's software renderer links the system's LLVM, and so does triton (which
    comes with torch's wheels and which torch loads lazily, e.g. when diffusers imports ``torch._dynamo``): loading
    triton after a GL context exists crashes the process, loading it first is safe."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    with contextlib.suppress(ImportError):
        # triton: before any OpenGL context, see above
        import triton._C.libtriton  # noqa: F401


def ffmpeg():
    """imageio-ffmpeg, set to start ffmpeg by vfork rather than fork. It forks to give ffmpeg a process group of its
    own (out of reach of Ctrl-C), and a fork duplicates the caller's address space (gigabytes for an evaluation that
    holds torch and a simulator), which fails with ENOMEM where memory is tight. Started by vfork, ffmpeg gets Ctrl-C
    with the rest of the job, and the file it was writing is dropped (:func:`bpp.utils.atomic_path`).
    ``IMAGEIO_FFMPEG_NO_PREVENT_SIGINT=0`` in the environment restores the fork."""
    os.environ.setdefault("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", "1")
    # imageio-ffmpeg: for video files only
    import imageio_ffmpeg

    return imageio_ffmpeg


def resize_frames(frames: np.ndarray, size: int) -> np.ndarray:
    """(T, H, W, 3) uint8 frames as (T, size, size, 3), bilinearly resized (returned as they are if already so)."""
    frames = np.asarray(frames, dtype=np.uint8)
    if frames.shape[1:3] == (size, size):
        return frames

    return np.stack([np.asarray(Image.fromarray(f).resize((size, size), Image.BILINEAR)) for f in frames])


def save_animation(frames: Sequence[np.ndarray], path: str | Path, fps: int = 10) -> Path:
    """Write frames as a GIF (or MP4 if the suffix is .mp4), complete or not at all."""
    # imageio: for video and GIF files only
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        if path.suffix.lower() == ".mp4":
            ffmpeg()  # before imageio's writer starts it
            import imageio.v2 as iio2  # the ffmpeg writer (imageio-ffmpeg ships its own ffmpeg binary)

            with iio2.get_writer(
                tmp, fps=fps, codec="libx264", macro_block_size=16, ffmpeg_log_level="quiet"
            ) as writer:
                for frame in frames:
                    writer.append_data(frame)
            _check_video(tmp, len(frames))
        else:
            # Encoded in memory, then written: a failed write is then one OSError, not also an encoder's error
            # printed again when it is garbage-collected.
            tmp.write_bytes(iio.imwrite("<bytes>", np.stack(frames), extension=".gif", duration=1000 / fps, loop=0))
    return path


def _check_video(path: Path, frames: int) -> None:
    """Refuse the video ffmpeg wrote to `path` unless it holds all `frames`: imageio-ffmpeg ignores how ffmpeg ended,
    so a video cut short (a full disk) would otherwise pass as written."""
    try:
        count, _ = ffmpeg().count_frames_and_secs(str(path))
    except (RuntimeError, OSError):  # ffmpeg cannot read it (cut short before its index)
        count = None
    if count != frames:
        raise OSError(errno.EIO, f"ffmpeg wrote {count or 0} of {frames} frames (is the disk full?)", str(path))


def pyplot():
    """matplotlib's pyplot, drawing off screen (the Agg backend): every picture of bpp is made with it."""
    # matplotlib: half a second to import, for pictures only
    import matplotlib

    matplotlib.use("Agg")
    # pyplot after the backend is chosen
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int) -> Path:
    """Save a matplotlib figure (its format from `path`'s suffix), complete or not at all, and close it."""
    # matplotlib: half a second to import, for pictures only (whichever backend made the figure)
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi)
    finally:
        plt.close(fig)
    return path


def contact_sheet(
    images: Sequence[np.ndarray], titles: Sequence[str], path: str | Path, columns: int = 8, title: str = ""
) -> Path:
    """Lay out images in a titled grid and save as PNG."""
    plt = pyplot()
    rows = max(1, int(np.ceil(len(images) / columns)))
    fig, axes = plt.subplots(rows, columns, figsize=(columns * 1.9, rows * 2.05), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, image, name in zip(axes.flat, images, titles, strict=False):
        ax.imshow(image)
        ax.set_title(name, fontsize=7)
    height = fig.get_figheight()
    if title:  # placed and given room in inches: a figure fraction would grow with the rows and cover the first
        fig.suptitle(title, fontsize=11, y=1 - 0.08 / height, va="top")
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.42 / height) if title else None)
    return save_figure(fig, path, dpi=110)
