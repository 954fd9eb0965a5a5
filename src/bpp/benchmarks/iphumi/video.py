"""The recordings' videos, read and written through FFmpeg (imageio-ffmpeg's bundled binary: no system FFmpeg).

Reading streams the video once and keeps only the frames asked for, scaled by FFmpeg while decoding, so a minute of
60 Hz 1920x1440 video costs one decode and little memory. The app logs a time for every frame it meant to record,
including frames the encoder dropped, so a time list may be a few entries longer than its video: indices past the
last decoded frame read that frame (and are counted), and a video far shorter than its times is refused as truncated.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bpp.benchmarks.iphumi.recording import RecordingError
from bpp.media import ffmpeg

FULL_DISK = 16 << 20
"""Free bytes under which a video FFmpeg stopped writing is reported as written to a full disk."""
MAX_DROPPED = 0.05
"""A video may lack at most this share of its logged frame times (dropped frames); more is a truncated file."""


def read_frames(path: Path, indices: Sequence[int], logged: int, fit: int | None = None) -> tuple[np.ndarray, int]:
    """Frames `indices` (any order, repeats allowed) of the video `path` whose time list has `logged` entries ->
    ((len(indices), H, W, 3) uint8 RGB, how many indices were past the decoded frames). With `fit`, frames are
    scaled while decoding to fit inside a fit x fit square, keeping their aspect ratio."""
    imageio_ffmpeg = ffmpeg()

    indices = np.asarray(indices, dtype=np.int64)
    if len(indices) and (indices.min() < 0 or indices.max() >= logged):
        raise ValueError(f"frame indices must be in [0, {logged}), got [{indices.min()}, {indices.max()}]")
    wanted = set(indices.tolist())
    last_needed = int(indices.max()) if len(indices) else -1
    kept: dict[int, np.ndarray] = {}
    decoded, shape, previous = 0, None, None
    try:
        scale = f"scale={fit}:{fit}:force_original_aspect_ratio=decrease:flags=area"
        reader = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24", output_params=["-vf", scale] if fit else None)
        log = logging.getLogger("imageio_ffmpeg")
        level = log.level
        log.setLevel(logging.ERROR)  # it warns that the scaled size differs from the video's, as asked
        try:
            width, height = next(reader)["size"]  # the size FFmpeg sends
        finally:
            log.setLevel(level)
        shape = (height, width, 3)
        for raw in reader:
            if decoded in wanted:
                kept[decoded] = np.frombuffer(raw, dtype=np.uint8).reshape(shape)
            previous = raw
            decoded += 1
            if decoded > last_needed:
                reader.close()
                break
    except (OSError, RuntimeError, StopIteration) as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise RecordingError(f"{path}: cannot decode the video ({reason})") from None
    if decoded == 0 or previous is None:
        raise RecordingError(f"{path}: the video holds no frames")
    if decoded <= last_needed and decoded < logged * (1 - MAX_DROPPED):
        raise RecordingError(
            f"{path}: {decoded} frames decoded for {logged} logged frame times; the video is truncated (at most "
            f"{MAX_DROPPED:.0%} of the frames may be dropped)"
        )
    last = np.frombuffer(previous, dtype=np.uint8).reshape(shape)
    beyond = int(np.sum(indices >= decoded))
    frames = np.stack([kept.get(int(i), last) for i in indices]) if len(indices) else np.zeros((0, *shape), np.uint8)
    return frames, beyond


def write_video(path: Path, frames, fps: float, size: tuple[int, int]) -> None:
    """Write (H, W, 3) uint8 frames as H.264 in a QuickTime container, as the phone app does. `size` = (W, H)."""
    imageio_ffmpeg = ffmpeg()

    writer = imageio_ffmpeg.write_frames(
        str(path),
        size,
        fps=fps,
        codec="libx264",
        pix_fmt_in="rgb24",
        quality=8,
        macro_block_size=1,
        output_params=["-f", "mov", "-preset", "veryfast"],
        ffmpeg_log_level="error",
    )
    try:
        writer.send(None)
        for frame in frames:
            writer.send(np.ascontiguousarray(frame, dtype=np.uint8))
        writer.close()
    except OSError as err:  # FFmpeg stopped: the pipe to it breaks, and neither names the file nor says why
        if shutil.disk_usage(path.parent).free < FULL_DISK:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path)) from None
        raise OSError(err.errno, f"FFmpeg stopped writing it ({err})", str(path)) from None
