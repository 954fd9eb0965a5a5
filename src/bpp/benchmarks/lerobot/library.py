"""LeRobot's dataset library, imported when used, and what running it offline and quietly takes.

The ``lerobot`` extra installs LeRobot itself (Hugging Face's ``lerobot`` package, 0.4.3 or a later 0.4 release; 0.5
and newer need Python 3.12), whose ``lerobot.datasets`` reads and writes the v3 format with ``LeRobotDataset``. LeRobot
pins an older torch than bpp's lock, so its tests run in an environment of their own (``.venv-lerobot``, built LeRobot
first and bpp on top; docs/installation.md).

Camera frames are decoded here with PyAV (FFmpeg inside its wheel, a dependency of the library), not through
``LeRobotDataset.__getitem__``, whose decoders need torchcodec with a system FFmpeg or a torchvision video reader that
current torchvision no longer has; the frames are picked by the timestamps the library's metadata gives.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import io
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from bpp.errors import UserError, require_extra

MODULE = "lerobot.datasets.lerobot_dataset"
"""Where LeRobot keeps ``LeRobotDataset`` and ``LeRobotDatasetMetadata``."""
READ_MAJOR = 3
"""The LeRobot dataset format this reads and writes: codebase_version v3.x."""


def dataset_library():
    """LeRobot's module with ``LeRobotDataset`` and ``LeRobotDatasetMetadata``; a UserError naming the extra if
    LeRobot is not installed."""
    return require_extra(MODULE, "lerobot")


@contextlib.contextmanager
def offline_and_quiet(beside: Path) -> Iterator[None]:
    """While the library runs: no network (a file it cannot find locally is an error rather than a download from the
    Hugging Face Hub), no progress bars or encoder banners in the output, and nothing written outside the command's
    output: the `datasets` package, through which the library reads parquet files, keeps an Arrow copy of each in its
    cache (under the user's home by default), here a hidden temporary folder beside `beside`, removed afterwards."""
    # PyAV, the `datasets` package: the lerobot extra
    import av
    import datasets
    import huggingface_hub.constants as hub
    from datasets.utils import logging as datasets_logging

    beside = Path(beside)
    beside.parent.mkdir(parents=True, exist_ok=True)
    cache_before = datasets.config.HF_DATASETS_CACHE
    offline, bars = hub.HF_HUB_OFFLINE, datasets_logging.is_progress_bar_enabled()
    svt = os.environ.get("SVT_LOG")
    hub.HF_HUB_OFFLINE = True
    level = _ffmpeg_log_level(av.logging.ERROR)
    datasets_logging.disable_progress_bar()
    os.environ["SVT_LOG"] = "1"  # SVT-AV1 (LeRobot's default encoder) prints its settings for every video otherwise
    cache = Path(tempfile.mkdtemp(prefix=f".{beside.name}.datasets-cache-", dir=beside.parent))
    try:
        datasets.config.HF_DATASETS_CACHE = cache
        yield
    finally:
        datasets.config.HF_DATASETS_CACHE = cache_before
        shutil.rmtree(cache, ignore_errors=True)
        hub.HF_HUB_OFFLINE = offline
        _ffmpeg_log_level(level)
        if bars:
            datasets_logging.enable_progress_bar()
        if svt is None:
            os.environ.pop("SVT_LOG", None)
        else:
            os.environ["SVT_LOG"] = svt


def _ffmpeg_log_level(level: int | None) -> int | None:
    """Set the log level of the FFmpeg inside PyAV's wheel; returns the previous one (None where it cannot be set).

    LeRobot's video writer hands FFmpeg's logging back to FFmpeg's own printer, which prints at FFmpeg's level (info:
    a line per video written); PyAV has no call for that level, so it is set in FFmpeg's library directly."""
    if level is None:
        return None

    # PyAV: the lerobot extra
    import av

    found = glob.glob(os.path.join(os.path.dirname(av.__file__), os.pardir, "av.libs", "libavutil*"))
    if not found:
        return None
    avutil = ctypes.CDLL(found[0])
    previous = int(avutil.av_log_get_level())
    avutil.av_log_set_level(int(level))
    return previous


FITS = ("stretch", "pad")
"""How a camera frame becomes square: stretched to the square, or scaled to fit it and padded with black."""


def fit_image(image, size: int, fit: str = "stretch") -> np.ndarray:
    """A PIL image -> (size, size, 3) uint8 RGB, resized (antialiased) as `fit` says (:data:`FITS`)."""
    image = image.convert("RGB")
    if fit == "stretch" or image.width == image.height:
        return np.asarray(image.resize((size, size), Image.BILINEAR))
    scale = size / max(image.width, image.height)
    inner = image.resize((max(1, round(image.width * scale)), max(1, round(image.height * scale))), Image.BILINEAR)
    canvas = Image.new("RGB", (size, size))
    canvas.paste(inner, ((size - inner.width) // 2, (size - inner.height) // 2))
    return np.asarray(canvas)


def decode_png(data: bytes | None, path: str | None, root: Path):
    """An image stored in a parquet column (``{"bytes", "path"}``) as a PIL image."""
    if data is not None:
        return Image.open(io.BytesIO(data))
    if path:
        file = Path(path) if Path(path).is_absolute() else root / path
        if file.is_file():
            return Image.open(file)
    raise UserError(f"{root}: an image frame has neither bytes nor a readable file ({path!r})")


class VideoFile:
    """One video file of a LeRobot dataset (several episodes one after another), decoded in order with PyAV."""

    def __init__(self, path: Path):
        # PyAV: the lerobot extra
        import av

        self.path = path
        try:
            self.container = av.open(str(path))
            self.stream = self.container.streams.video[0]
        except (av.error.FFmpegError, IndexError) as err:
            raise UserError(f"{path}: not a readable video ({err})") from None

    def frames_at(self, times: Sequence[float], tolerance: float) -> list:
        """PIL images of the frames shown at `times` (seconds into the file, ascending): for each, the first frame
        at or after ``time - tolerance``, which must lie within `tolerance` of it."""
        # PyAV: the lerobot extra
        import av

        times = np.asarray(times, dtype=np.float64)
        base = self.stream.time_base
        try:  # to the key frame at or before the first time, then forward
            self.container.seek(int(max(times[0] - tolerance, 0.0) / base), stream=self.stream, backward=True)
            frames = self.container.decode(self.stream)
            images, frame = [], next(frames, None)
            for time in times:
                while frame is not None and _seconds(frame, base) < time - tolerance:
                    frame = next(frames, None)
                if frame is None or abs(_seconds(frame, base) - time) > tolerance:
                    found = "the end of the video" if frame is None else f"{_seconds(frame, base):.3f} s"
                    raise UserError(
                        f"{self.path}: no frame at {time:.3f} s (next: {found}); the dataset's timestamps and its "
                        "video disagree"
                    )
                images.append(frame.to_image())
            return images
        except av.error.FFmpegError as err:
            raise UserError(f"{self.path}: cannot decode the video ({err})") from None

    def close(self) -> None:
        self.container.close()


def _seconds(frame, base) -> float:
    return float(frame.pts * base) if frame.pts is not None else float(frame.time)
