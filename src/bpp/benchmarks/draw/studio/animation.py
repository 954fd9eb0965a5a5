"""A finished rollout replayed into a GIF or an MP4, frame by frame into the encoder, the prompt's target blended in."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from bpp.benchmarks.draw.env import DrawEnv
from bpp.benchmarks.draw.studio.state import Rollout
from bpp.benchmarks.draw.viz import TARGET_RGB, target_coverage
from bpp.media import ffmpeg


class Cancelled(Exception):
    """An animation's client left."""


def render_animation(
    rollout: Rollout, action_frame: str, path: Path, fmt: str, size: int, max_frames: int, cancel
) -> None:
    """Replay `rollout` into `path`, frame by frame into the encoder (never all frames in memory at once)."""
    actions = np.asarray(rollout.actions, dtype=np.float64).reshape(-1, 3)
    every = max(1, int(np.ceil(len(actions) / max(1, max_frames - 1))))
    # Without a target the env skips the per-step Chamfer update; the target is blended in here instead.
    env = DrawEnv(
        image_size=None,
        max_episode_steps=max(1, len(actions)),
        render_mode="rgb_array",
        render_size=size,
        action_frame=action_frame,
        early_stop=False,
    )
    env.reset(seed=rollout.seed, options={"board_angle": rollout.board_angle})
    cover = (0.35 * target_coverage(rollout.prompt.target, rollout.board_angle, size))[..., None]
    tint = cover * np.asarray(TARGET_RGB, dtype=np.float64)

    def frames():
        for step in range(len(actions) + 1):
            if step:
                env.step(actions[step - 1])
            if step % every == 0 or step == len(actions):
                if cancel is not None and cancel.is_set():
                    raise Cancelled
                yield np.rint(env.render() * (1.0 - cover) + tint).astype(np.uint8)

    if fmt == "mp4":
        ffmpeg()  # before imageio's writer starts it
        # imageio: for video and GIF files only
        import imageio.v2 as iio2

        with iio2.get_writer(path, format="FFMPEG", fps=10 / every, codec="libx264", macro_block_size=16) as out:
            for frame in frames():
                out.append_data(frame)
    else:
        # A GIF is written at the end; frames are kept as 1-byte palette images (a third of RGB) meanwhile.
        palette = _palette()
        images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in frames()]
        images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=100 * every, loop=0)


def _palette():
    """A fixed GIF palette: a 6x6x6 colour cube plus 40 greys, so every frame shares it."""
    levels = [0, 51, 102, 153, 204, 255]
    colours = [(r, g, b) for r in levels for g in levels for b in levels]
    colours += [(v, v, v) for v in np.linspace(0, 255, 40).astype(int)]
    image = Image.new("P", (1, 1))
    image.putpalette([c for rgb in colours for c in rgb])
    return image
