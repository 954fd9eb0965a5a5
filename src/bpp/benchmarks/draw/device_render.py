"""DrawAnything's camera frames rendered on the training device, from what draws them, with no loader work.

:func:`bpp.benchmarks.draw.render.render_frames` renders a batch's frames in numpy, in the loader processes; at a GPU's
rate the loader processes take most of the machine's cores to draw pixels, and the training process takes time to
receive them (a paper batch moves 19.5 MB: BENCHMARKS.md, "Feeding the GPU"). Here the loader sends a frame
*reference* instead, (episode + 1, step), 16 bytes (see :mod:`bpp.data.frame_refs`), and :class:`DrawFrameTable`
holds what every frame of the store is drawn from: each episode's ink segments and the step that inks them (on the
device), its board angle and its cursor positions. :meth:`DrawFrameTable.render` then draws a batch's frames with
the same float64 operations, in the same order, as the numpy renderer, for all frames at once:

1. the board of each episode the batch shows, every pixel measured;
2. each needed ink segment's coverage over its pixel window, maxed into the first wanted frame of its episode
   that shows it (a scatter), then carried to the episode's later frames (a segmented running max, log-steps);
3. the composite, then the cursor in a window around it, rounded to uint8 as the numpy renderer rounds.

On a CPU the frames are the numpy renderer's bit for bit (tests pin it). On a GPU they are the same arithmetic in
IEEE float64 (CUDA's float64 add, multiply, divide and square root round as a CPU's do); only ``hypot``, the
cursor's distance, may differ in its last bit, which can move a pixel of the cursor's rim by one level.
"""

from __future__ import annotations

import numpy as np
import torch

from bpp.benchmarks.draw import physics, render
from bpp.data.store import EpisodeStore
from bpp.drawing import raster
from bpp.drawing.geometry import CANVAS_SIZE, board_corners, unit_to_canvas

SEGMENT_ENTRIES = 1 << 24
"""Segment-pixel coverages measured at once (float64 temporaries of about 8 bytes x a few each)."""
COMPOSITE_PIXELS = 1 << 24
"""Frame pixels composited at once (three float64 channels each)."""

_HELPER_UNIT = np.array([[0, 0, 1, 1], [0, 1, 1, 0], [0.5, 0, 0.5, 1], [0, 0.5, 1, 0.5]], dtype=np.float64)


def board_lines(angle: float) -> np.ndarray:
    """(8, 4) canvas segments of the static scene, as :func:`render.render_board` draws them: 4 helper lines, the
    three black edges, the red top edge."""
    helpers = unit_to_canvas(_HELPER_UNIT.reshape(-1, 2), angle).reshape(-1, 4)
    tl, tr, br, bl = board_corners(angle)
    edges = np.array([np.r_[tr, br], np.r_[br, bl], np.r_[bl, tl]])
    return np.concatenate([helpers, edges, np.r_[tl, tr][None]])


# (first line, last line + 1, half width, colour) of each layer of the board, in render_board's order.
_BOARD_LAYERS = (
    (0, 4, render.HELPER_LINE_WIDTH / 2, render.HELPER_LINE_RGB),
    (4, 7, render.BOARD_EDGE_WIDTH / 2, render.BOARD_EDGE_RGB),
    (7, 8, render.BOARD_EDGE_WIDTH / 2, render.BOARD_TOP_EDGE_RGB),
)


def _distance(px: torch.Tensor, py: torch.Tensor, dx, dy, length2) -> torch.Tensor:
    """raster.segment_distance's arithmetic for one segment (length2 > 0), from the point's offset (px, py)."""
    t = torch.clamp((px * dx + py * dy) / length2, 0.0, 1.0)
    px = px - t * dx
    py = py - t * dy
    return torch.sqrt(px * px + py * py)


def _coverage(distance: torch.Tensor, half_width: float, pixel: float) -> torch.Tensor:
    return torch.clamp((half_width - distance) / pixel + 0.5, 0.0, 1.0)


class DrawFrameTable:
    """What every camera frame of a DrawAnything store is drawn from: each episode's ink segments on `device` (32
    bytes a segment, about 7 segments a step: 21 MB for 1,000 demonstrations, so about 215 MB for the paper's
    10,000), the rest on the host.

    ``table.render(refs, size)`` turns (N, 2) references (episode + 1, step; 0: a blank, all-zero frame) into the
    (N, size, size, 3) uint8 frames :func:`bpp.benchmarks.draw.dataset.render_episode_steps` makes, on the device. The
    references come on the host (as a loader gives them): which pixels each segment may ink is worked out there, so
    that the device is never waited for and the host goes on issuing the training step.
    """

    def __init__(self, store: EpisodeStore, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        states = np.asarray(store.array("state"), dtype=np.float64)
        actions = np.asarray(store.array("action"), dtype=np.float64)
        starts, ends = store.episode_starts.astype(np.int64), store.episode_ends.astype(np.int64)
        down = np.flatnonzero(actions[:, 2] > physics.PEN_THRESHOLD)
        # render.ink_segments of every episode in one batched physics call (rows are independent: the same bits).
        paths = physics.control_steps(states[down], actions[down])[1]
        self.segments = np.concatenate([paths[:, :-1], paths[:, 1:]], axis=2).reshape(-1, 4)
        seg_row = np.repeat(down, physics.SUBSTEPS)
        self.segment_step = seg_row - starts[np.searchsorted(starts, seg_row, side="right") - 1]
        self.segment_start, self.segment_end = np.searchsorted(seg_row, starts), np.searchsorted(seg_row, ends)
        self.cursor = states[:, :2]
        self.after_last = physics.control_steps(states[ends - 1], actions[ends - 1])[0][:, :2]  # the cursor at T
        self.starts, self.lengths = starts, ends - starts
        self.angles = np.asarray(store.column("board_angle"), dtype=np.float64)
        self.device_segments = torch.as_tensor(self.segments).to(self.device)
        self._colours: dict[tuple, torch.Tensor] = {}

    cameras = ("image",)
    """The cameras it draws: the canvas as seen (the board's own view, ``board_image``, is drawn by the loader)."""

    # ------------------------------------------------------------------ public
    def render(self, refs, size: int) -> torch.Tensor:
        """(N, 2) int64 references, on the host -> (N, size, size, 3) uint8 frames on the table's device."""
        if size < 8:
            raise ValueError(f"image resolution must be at least 8 px, got {size}")
        refs = torch.as_tensor(refs).cpu().numpy().reshape(-1, 2).astype(np.int64)
        out = torch.zeros((len(refs), size, size, 3), dtype=torch.uint8, device=self.device)
        real = np.flatnonzero(refs[:, 0] > 0)
        if not len(real):
            return out
        episode, step = refs[real, 0] - 1, refs[real, 1]
        if episode.max() >= len(self.starts) or step.min() < 0 or np.any(step > self.lengths[episode]):
            raise IndexError(
                f"frame references out of range: episodes 1..{len(self.starts)}, steps 0..the episode's length"
            )
        span = int(self.lengths.max()) + 2
        key, inverse = np.unique(episode * span + step, return_inverse=True)  # the distinct frames, sorted
        out[self._put(real)] = self._frames(key, span, size)[self._put(inverse.reshape(-1))]
        return out

    # ------------------------------------------------------------------ internals
    def _blend(self, image: torch.Tensor, cover: torch.Tensor, rgb) -> torch.Tensor:
        """render._blend's arithmetic: image * (1 - cover) + cover * rgb, (..., 3) float64."""
        if rgb not in self._colours:  # made once: a new tensor would be a copy to the device every call
            self._colours[rgb] = torch.tensor(rgb, dtype=torch.float64, device=self.device)
        return image * (1.0 - cover[..., None]) + cover[..., None] * self._colours[rgb]

    def _put(self, array: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(array)).to(self.device, non_blocking=True)

    def _frames(self, key: np.ndarray, span: int, size: int) -> torch.Tensor:
        """(U, R, R, 3) uint8 frames for sorted keys episode * span + step."""
        device, n_px, n = self.device, size * size, len(key)
        layer_episode, layer_step = key // span, key % span
        episodes, slot, per_episode = np.unique(layer_episode, return_inverse=True, return_counts=True)
        position = np.arange(n) - (np.cumsum(per_episode) - per_episode)[slot]  # the frame's rank in its episode
        coordinate = (torch.arange(size, dtype=torch.float64, device=device) + 0.5) * (CANVAS_SIZE / size)
        pixel = CANVAS_SIZE / size

        board = self._boards(episodes, coordinate, pixel)  # (E, R*R, 3) float64
        ink = torch.zeros(n * n_px, dtype=torch.float64, device=device)
        self._scatter_ink(ink, key, episodes, span, coordinate, pixel, size)
        ink = ink.view(n, n_px)
        shift, position = 1, self._put(position)
        while shift < per_episode.max():  # a running max along each episode's frames (Hillis-Steele)
            # Frame i takes frame i - shift's ink where both are its episode's (ink >= 0: elsewhere max with 0).
            earlier = ink[:-shift] * (position[shift:, None] >= shift)
            ink[shift:] = torch.maximum(ink[shift:], earlier)  # computed whole before any row is written
            shift *= 2

        slot = self._put(slot)
        frames = torch.empty((n, n_px, 3), dtype=torch.uint8, device=device)
        chunk = max(1, COMPOSITE_PIXELS // n_px)
        for lo in range(0, n, chunk):
            rows = slice(lo, lo + chunk)
            image = torch.round(self._blend(board[slot[rows]], ink[rows], render.INK_RGB))  # half to even, as np.rint
            frames[rows] = image.to(torch.uint8)
        frames = frames.view(n, size, size, 3)
        self._draw_cursors(frames, layer_episode, layer_step, coordinate, pixel)
        return frames

    def _draw_cursors(self, frames, layer_episode, layer_step, coordinate, pixel) -> None:
        """The cursor on each frame, in the pixel window around it only, as render_frames draws it."""
        ended = layer_step == self.lengths[layer_episode]
        row = np.minimum(self.starts[layer_episode] + layer_step, len(self.cursor) - 1)
        cursor = np.where(ended[:, None], self.after_last[layer_episode], self.cursor[row])
        size, outer = frames.shape[1], render.CURSOR_RADIUS + render.CURSOR_OUTLINE_WIDTH
        scale = size / CANVAS_SIZE
        margin = outer + pixel
        lo = np.floor((cursor - margin) * scale - 0.5).astype(np.int64)  # as render._window_starts
        width = int((np.ceil((cursor + margin) * scale + 0.5).astype(np.int64) - lo).max())
        window = torch.arange(width, device=self.device)
        lo, cursor = self._put(lo), self._put(cursor)
        cols = (lo[:, 0, None] + window).clamp(0, size - 1)[:, None, :]  # (N, 1, W), clipped pixels repeat
        rows = (lo[:, 1, None] + window).clamp(0, size - 1)[:, :, None]  # (N, W, 1)
        distance = torch.hypot(coordinate[cols] - cursor[:, 0, None, None], coordinate[rows] - cursor[:, 1, None, None])
        index = (torch.arange(len(frames), device=self.device)[:, None, None], rows, cols)
        patch = self._blend(frames[index].double(), _coverage(distance, outer, pixel), render.CURSOR_OUTLINE_RGB)
        patch = self._blend(patch, _coverage(distance, render.CURSOR_RADIUS, pixel), render.CURSOR_RGB)
        frames[index] = torch.round(patch).to(torch.uint8)

    def _boards(self, episodes: np.ndarray, coordinate: torch.Tensor, pixel: float) -> torch.Tensor:
        """render.render_board of each episode's angle, every pixel measured: (E, R*R, 3) float64."""
        size = len(coordinate)
        x, y = coordinate.repeat(size), coordinate.repeat_interleave(size)  # (R*R,) pixel centres, row-major
        lines = self._put(np.stack([board_lines(a) for a in self.angles[episodes]]))  # (E, 8, 4)
        x0, y0, x1, y1 = (lines[..., j, None] for j in range(4))  # (E, 8, 1) each: all lines at once
        dx, dy = x1 - x0, y1 - y0
        distance = _distance(x - x0, y - y0, dx, dy, dx * dx + dy * dy)  # (E, 8, R*R)
        image = torch.full((len(episodes), size * size, 3), 255.0, dtype=torch.float64, device=self.device)
        for begin, stop, half_width, rgb in _BOARD_LAYERS:
            nearest = distance[:, begin:stop].amin(dim=1)  # segment_distance's minimum over the layer's lines
            image = self._blend(image, _coverage(nearest, half_width, pixel), rgb)
        return image

    def _scatter_ink(self, ink, key, episodes, span, coordinate, pixel, size) -> None:
        """Max each needed segment's coverage (render._ink_entries' arithmetic) into the first frame of its episode
        that shows it: frame t shows the ink of steps < t."""
        begin, counts = self.segment_start[episodes], self.segment_end[episodes] - self.segment_start[episodes]
        if not counts.sum():
            return
        owner = np.repeat(np.arange(len(episodes)), counts)
        index = begin[owner] + np.arange(counts.sum()) - (np.cumsum(counts) - counts)[owner]
        layer = np.searchsorted(key, episodes[owner] * span + self.segment_step[index], side="right")
        needed = layer < len(key)
        needed[needed] = key[layer[needed]] // span == episodes[owner[needed]]
        index, layer = index[needed], layer[needed]
        if not len(index):
            return
        # Each segment's pixel window, as render._window_starts works it out.
        seg = self.segments[index]
        margin, scale = raster.INK_WIDTH / 2 + pixel, size / CANVAS_SIZE
        lo = np.floor((np.minimum(seg[:, :2], seg[:, 2:]) - margin) * scale - 0.5).astype(np.int64)
        hi = np.ceil((np.maximum(seg[:, :2], seg[:, 2:]) + margin) * scale + 0.5).astype(np.int64)
        width = int((hi - lo).max())
        window = torch.arange(width, device=self.device)
        per_chunk = max(1, SEGMENT_ENTRIES // (width * width))
        for a in range(0, len(index), per_chunk):
            s = self.device_segments[self._put(index[a : a + per_chunk])]
            lo_s, layer_s = self._put(lo[a : a + per_chunk]), self._put(layer[a : a + per_chunk])
            cols = (lo_s[:, 0, None] + window).clamp(0, size - 1)[:, None, :]  # (S, 1, W)
            rows = (lo_s[:, 1, None] + window).clamp(0, size - 1)[:, :, None]  # (S, W, 1)
            x0, y0, x1, y1 = (s[:, i, None, None] for i in range(4))
            dx, dy = x1 - x0, y1 - y0
            length2 = dx * dx + dy * dy
            long = length2 > 0.0
            px, py = coordinate[cols] - x0, coordinate[rows] - y0
            t = (px * dx + py * dy) / torch.where(long, length2, 1.0)
            t = torch.clamp(t, 0.0, 1.0) * long  # a dot is not projected onto
            px = px - t * dx
            py = py - t * dy
            cover = _coverage(torch.sqrt(px * px + py * py), raster.INK_WIDTH / 2, pixel)
            target = layer_s[:, None, None] * (size * size) + rows * size + cols
            ink.scatter_reduce_(0, target.reshape(-1), cover.reshape(-1), reduce="amax")
