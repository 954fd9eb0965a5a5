"""A drawing task: ordered pen-down strokes in the board's unit square (y up), and how a store keeps it (one ragged
per-task row, ``strokes``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bpp.data.store import EpisodeStore
from bpp.errors import UserError


class DrawingError(UserError):
    """A drawing (or a drawing file) is not usable; the message names the source and the problem."""


@dataclass(frozen=True)
class Drawing:
    """An ordered list of strokes; each stroke is a (N, 2) float64 polyline in the unit square, y up.

    Pen-up travel between strokes is not part of the drawing: the demonstrator (or the person) chooses it.
    Build with :meth:`from_strokes`, which validates.
    """

    id: str
    strokes: tuple[np.ndarray, ...]
    source: str = field(default="", compare=False)
    """Where it came from (a file path, or a generator), for messages about it."""

    @property
    def name(self) -> str:
        """How messages refer to it: ``<source>: drawing '<id>'``."""
        return f"{self.source}: drawing {self.id!r}" if self.source else f"drawing {self.id!r}"

    @classmethod
    def from_strokes(cls, drawing_id: str, strokes, source: str = "<memory>") -> Drawing:
        """Validate and build. `source` names the file (or origin) in error messages."""
        where = f"{source}: drawing {drawing_id!r}"
        if not isinstance(drawing_id, str) or not drawing_id:
            raise DrawingError(f"{source}: every drawing needs a non-empty string 'id', got {drawing_id!r}")
        if strokes is None or len(strokes) == 0:
            raise DrawingError(f"{where} is empty: expected at least one stroke")
        out = []
        for i, stroke in enumerate(strokes):
            try:
                arr = np.asarray(stroke, dtype=np.float64)
            except OverflowError:  # a Python int beyond float64's range
                raise DrawingError(f"{where}, stroke {i}: a coordinate is too large to be a finite number") from None
            except (TypeError, ValueError) as err:
                raise DrawingError(f"{where}, stroke {i}: expected a list of [x, y] pairs ({err})") from None
            if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) == 0:
                raise DrawingError(
                    f"{where}, stroke {i}: expected a non-empty list of [x, y] pairs, got shape {arr.shape}"
                )
            if not np.all(np.isfinite(arr)):
                j, axis = np.argwhere(~np.isfinite(arr))[0]
                raise DrawingError(f"{where}, stroke {i}, point {j}: coordinate {arr[j, axis]} is not a finite number")
            if arr.min() < 0.0 or arr.max() > 1.0:
                raise DrawingError(
                    f"{where}, stroke {i}: coordinates must lie in the unit square [0, 1]^2, "
                    f"found range [{arr.min():.4g}, {arr.max():.4g}]"
                )
            out.append(arr)
        return cls(drawing_id, tuple(out), source)

    @property
    def ink_length(self) -> float:
        """Total pen-down length in unit-square units."""
        return float(sum(np.linalg.norm(np.diff(s, axis=0), axis=1).sum() for s in self.strokes))

    def to_json(self) -> dict:
        """The documented JSON form: ``{"id": str, "strokes": [[[x, y], ...], ...]}``."""
        return {"id": self.id, "strokes": [np.round(s, 6).tolist() for s in self.strokes]}

    def normalized(self, margin: float = 0.1) -> Drawing:
        """Scale and centre uniformly (aspect kept) so the drawing spans [margin, 1 - margin] on its long side."""
        pts = np.concatenate(self.strokes)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        extent = max(float((hi - lo).max()), 1e-9)
        scale = (1.0 - 2.0 * margin) / extent
        offset = 0.5 - (lo + hi) / 2.0 * scale
        return Drawing(self.id, tuple(s * scale + offset for s in self.strokes), self.source)


def strokes_array(drawing: Drawing) -> np.ndarray:
    """(P, 3) float64 [u, v, stroke_index]: a drawing as one ragged-store row."""
    return np.concatenate([np.c_[s, np.full(len(s), i, dtype=np.float64)] for i, s in enumerate(drawing.strokes)])


def drawing_from_array(drawing_id: str, arr: np.ndarray) -> Drawing:
    """Inverse of :func:`strokes_array`."""
    idx = arr[:, 2].astype(int)
    return Drawing.from_strokes(drawing_id, [arr[idx == i, :2] for i in np.unique(idx)], source="store")


def task_drawing(store: EpisodeStore, task_index: int) -> Drawing:
    """The drawing of task `task_index` of `store`, as its ``strokes`` row keeps it."""
    return drawing_from_array(store.tasks[task_index]["id"], store.task_array("strokes", task_index))
