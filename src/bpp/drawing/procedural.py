"""Procedural drawing tasks: 1-6 parts among lines, Bézier curves, (partial) ovals and pen-up moves.

Follows the authors' published recipe (parameter ranges converted from their pixels to the board's unit
square, 1 unit = 350 px): each part starts where the previous one ended; with probability ``connect_prob`` it
ends at an earlier endpoint, otherwise at a fresh point at least 50 px away; ovals have a semi-axis of
30-200 px, an aspect ratio of 0.2-3, a random orientation and direction, and are partial (π/8 to 2π of arc)
half of the time. A pen-up move starts a new stroke and is never followed by another move.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bpp.drawing.drawing import Drawing
from bpp.drawing.geometry import BOARD_SIZE
from bpp.utils import check_fields

PART_TYPES = ("line", "curve", "oval", "move")
MAX_PARTS = 30
"""Most parts a drawing may have (six is the paper's; more would not fit an episode)."""
_PART_WORDS = {"line": "draw a line", "curve": "draw a curve", "oval": "draw an oval", "move": "lift the pen and move"}
_PX = 1.0 / BOARD_SIZE  # one canvas pixel in unit-square units
_SAMPLE_SPACING = 2.0 * _PX  # dense polyline resolution of generated parts


@dataclass(frozen=True)
class ProceduralConfig:
    """Parameters of the procedural generator (defaults: the paper's training distribution)."""

    min_parts: int = 1
    """Fewest parts per drawing (lines, curves, ovals, pen-up moves)."""
    max_parts: int = 6
    """Most parts per drawing (the paper's ablations use 1-3 and 4-6)."""
    connect_prob: float = 0.5
    """Probability that a part ends at an earlier endpoint instead of a fresh point."""
    min_new_point_px: float = 50.0
    """A fresh endpoint lies at least this far from the part's start."""
    oval_axis_px: tuple[float, float] = (30.0, 200.0)
    """Range of an oval's first semi-axis."""
    oval_aspect: tuple[float, float] = (0.2, 3.0)
    """Range of the ratio of an oval's second semi-axis to its first."""
    partial_oval_prob: float = 0.5
    """Probability that an oval is partial."""
    partial_arc_deg: tuple[float, float] = (22.5, 360.0)
    """Range of a partial oval's arc."""

    def __post_init__(self):
        lo_axis, hi_axis = self.oval_axis_px
        lo_aspect, hi_aspect = self.oval_aspect
        lo_arc, hi_arc = self.partial_arc_deg
        check_fields(
            self,
            ("min_parts", self.min_parts >= 1, ">= 1"),
            ("max_parts", self.min_parts <= self.max_parts <= MAX_PARTS, f"in [min_parts, {MAX_PARTS}]"),
            ("connect_prob", 0.0 <= self.connect_prob <= 1.0, "in [0, 1]"),
            ("min_new_point_px", 0.0 <= self.min_new_point_px <= 200.0, "in [0, 200] (a board side is 350)"),
            ("oval_axis_px", 0.0 < lo_axis <= hi_axis <= BOARD_SIZE, f"lo, hi with 0 < lo <= hi <= {BOARD_SIZE:g}"),
            ("oval_aspect", 0.0 < lo_aspect <= hi_aspect <= 10.0, "lo, hi with 0 < lo <= hi <= 10"),
            ("partial_oval_prob", 0.0 <= self.partial_oval_prob <= 1.0, "in [0, 1]"),
            ("partial_arc_deg", 0.0 < lo_arc <= hi_arc <= 360.0, "lo, hi with 0 < lo <= hi <= 360"),
        )


def _dense(points: np.ndarray) -> np.ndarray:
    """Resample a polyline so consecutive points are about _SAMPLE_SPACING apart (keeps the ends)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] == 0.0:
        return points[:1]
    n = max(int(np.ceil(s[-1] / _SAMPLE_SPACING)), 1) + 1
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])], axis=1)


def _bezier(p0, p1, p2, p3, n: int = 200) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t**2 * p2 + t**3 * p3


def _oval(rng: np.random.Generator, start: np.ndarray, cfg: ProceduralConfig) -> np.ndarray | None:
    """An (partial) ellipse through `start` at parameter 0, inside the unit square; None after 100 misses."""
    for _ in range(100):
        a = rng.uniform(*cfg.oval_axis_px) * _PX
        b = a * rng.uniform(*cfg.oval_aspect)
        phi = rng.uniform(0.0, 2 * np.pi)
        sweep = np.radians(rng.uniform(*cfg.partial_arc_deg)) if rng.random() < cfg.partial_oval_prob else 2 * np.pi
        direction = rng.choice([-1.0, 1.0])
        n = max(int(np.ceil(sweep * max(a, b) / _SAMPLE_SPACING)), 8)
        t = direction * np.linspace(0.0, sweep, n)
        rot = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
        local = np.stack([a * (np.cos(t) - 1.0), b * np.sin(t)], axis=1) @ rot.T
        pts = start + local
        if pts.min() >= 0.0 and pts.max() <= 1.0:
            return pts
    return None


def procedural_id(seed: int, index: int) -> str:
    """The task id of the `index`-th procedural drawing generated with `seed`: ``procedural-00012``, or
    ``procedural-s7-00012`` for a seed other than 0. Drawings of different seeds are different tasks, so pieces of
    one dataset generated with different seeds (on several machines) have different ids and merge into one store."""
    return f"procedural-{index:05d}" if seed == 0 else f"procedural-s{seed}-{index:05d}"


def generate_drawing(rng: np.random.Generator, cfg: ProceduralConfig, drawing_id: str) -> tuple[Drawing, list]:
    """One random drawing and its list of part types (in drawing order)."""
    current = rng.uniform(0.0, 1.0, size=2)
    endpoints = [current]
    strokes: list[list[np.ndarray]] = [[current[None]]]
    kinds: list[str] = []
    n_parts = int(rng.integers(cfg.min_parts, cfg.max_parts + 1))
    while len(kinds) < n_parts:
        options = ("line", "curve", "oval") if not kinds or kinds[-1] == "move" else PART_TYPES
        kind = str(rng.choice(options))
        if kind == "oval":
            pts = _oval(rng, current, cfg)
            if pts is None:
                kind, pts = "line", None
        if kind != "oval":
            earlier = [p for p in endpoints if np.linalg.norm(p - current) > 1e-9]
            if earlier and rng.random() < cfg.connect_prob:
                end = earlier[int(rng.integers(len(earlier)))]
            else:
                end = current
                for _ in range(100):
                    cand = rng.uniform(0.0, 1.0, size=2)
                    if np.linalg.norm(cand - current) >= cfg.min_new_point_px * _PX:
                        end = cand
                        break
            if kind == "curve":
                pts = _bezier(current, rng.uniform(0, 1, 2), rng.uniform(0, 1, 2), end)
            else:
                pts = np.stack([current, end])
        if kind == "move":
            strokes.append([pts[-1:]])
        else:
            strokes[-1].append(_dense(pts)[1:])
        current = pts[-1]
        endpoints.append(current)
        kinds.append(kind)
    polylines = [np.concatenate(s) for s in strokes]
    polylines = [np.clip(p, 0.0, 1.0) for p in polylines if len(p) > 1]
    if not polylines:  # only degenerate parts: retry deterministically with the same generator
        return generate_drawing(rng, cfg, drawing_id)
    return Drawing.from_strokes(drawing_id, polylines, source="procedural generator"), kinds


def describe_parts(kinds: Sequence[str]) -> str:
    """A drawing's parts in words, as an instruction: ["line", "move", "oval"] ->
    "draw a line, then lift the pen and move, then draw an oval"."""
    unknown = [k for k in kinds if k not in _PART_WORDS]
    if unknown or not kinds:
        raise ValueError(f"need a non-empty list of parts among {PART_TYPES}, got {list(kinds)}")
    return ", then ".join(_PART_WORDS[k] for k in kinds)
