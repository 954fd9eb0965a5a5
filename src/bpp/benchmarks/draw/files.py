"""Turn user drawings into tasks: the JSON stroke format and SVG path files.

JSON stroke format (coordinates in the unit square, y up, strokes in drawing order)::

    {"drawings": [{"id": "house", "strokes": [[[0.2, 0.2], [0.8, 0.2], [0.8, 0.6]], [[0.2, 0.6], [0.5, 0.9]]]}]}

Coordinates must be JSON numbers (a string such as ``"0.5"`` or a boolean is refused, not converted).

SVG: every ``<path>`` (and line, polyline, polygon, rect, circle, ellipse) of the file becomes strokes of one
drawing, one stroke per continuous sub-path, in document order, with every ``transform`` of the element and its
groups applied; elements inside ``<defs>``, ``<clipPath>``, ``<mask>``, ``<symbol>``, ``<marker>`` and
``<pattern>`` are not drawn and ``<use>`` is not followed. The drawing is scaled uniformly to fit the board
(SVG's y-down is flipped) and named after the file. Straight segments keep their end points; curves are sampled
every :data:`SVG_SAMPLE_SPACING` of the drawing's size.

Limits (so any file is read in bounded time, with a message saying which limit it hit): a file is at most
:data:`MAX_FILE_BYTES`; points closer than :data:`MIN_POINT_SPACING` to the previous point of their stroke are
merged; after that a drawing has at most :data:`MAX_STROKES` strokes and :data:`MAX_POINTS` points.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bpp.benchmarks.draw.drawing import Drawing, DrawingError
from bpp.utils import read_json

SVG_SAMPLE_SPACING = 0.004
"""Arc length between samples of SVG curves, as a fraction of the drawing's longest side."""
MAX_FILE_BYTES = 16 << 20
"""Largest drawing file read (JSON or SVG)."""
MIN_POINT_SPACING = 1e-3
"""Points of a stroke closer than this (unit square; 0.35 px on the board) to the point kept before them are
dropped (a stroke's last point is always kept)."""
MAX_STROKES = 100
"""Most strokes in one drawing: each stroke costs the demonstrator a pen-up move and two waits, so more would
not fit the 400-step episode anyway."""
MAX_POINTS = 5000
"""Most points in one drawing after merging close points (a circle drawn with the finest useful detail needs
about 3000)."""


def load_drawings(paths) -> list[Drawing]:
    """Load drawings from one or more ``.json`` / ``.svg`` files; ids must be unique across all of them."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    drawings: list[Drawing] = []
    for path in map(Path, paths):
        if not path.exists():
            raise DrawingError(f"{path}: no such file")
        if path.is_dir():
            raise DrawingError(f"{path}: is a directory; expected a .json or .svg drawing file")
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise DrawingError(
                f"{path}: {size / 2**20:.1f} MiB; a drawing file may have at most {MAX_FILE_BYTES >> 20} MiB"
            )
        suffix = path.suffix.lower()
        if suffix == ".json":
            drawings += load_json(path)
        elif suffix == ".svg":
            drawings.append(load_svg(path))
        else:
            raise DrawingError(f"{path}: unsupported drawing file type {suffix!r}; expected .json or .svg")
    seen: dict[str, int] = {}
    for d in drawings:
        seen[d.id] = seen.get(d.id, 0) + 1
    dupes = sorted(k for k, n in seen.items() if n > 1)
    if dupes:
        raise DrawingError(f"{', '.join(map(str, paths))}: duplicate drawing ids {dupes}")
    return drawings


def load_json(path: str | Path) -> list[Drawing]:
    """Parse a JSON stroke file (format in the module docstring)."""
    path = Path(path)
    try:
        doc = read_json(path, "drawing file", max_bytes=MAX_FILE_BYTES)
    except ValueError as err:
        raise DrawingError(str(err)) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("drawings"), list):
        raise DrawingError(f'{path}: expected an object {{"drawings": [...]}} at the top level')
    if not doc["drawings"]:
        raise DrawingError(f"{path}: 'drawings' is empty")
    out = []
    for i, item in enumerate(doc["drawings"]):
        if not isinstance(item, dict) or "id" not in item or "strokes" not in item:
            raise DrawingError(f"{path}: drawing #{i} must be an object with 'id' and 'strokes'")
        where = f"{path}: drawing {item['id']!r}"
        if not isinstance(item["strokes"], list):
            raise DrawingError(f"{where}: 'strokes' must be a list of strokes")
        if len(item["strokes"]) > MAX_STROKES:
            raise DrawingError(f"{where} has {len(item['strokes'])} strokes; a drawing may have at most {MAX_STROKES}")
        strokes = [_json_stroke(stroke, f"{where}, stroke {k}") for k, stroke in enumerate(item["strokes"])]
        out.append(bounded(Drawing.from_strokes(item["id"], strokes, source=str(path)), where))
    return out


def _json_stroke(stroke, where: str) -> np.ndarray:
    """A stroke as an (N, 2) array, refusing anything but a list of [number, number] pairs (JSON true, false and
    strings are not numbers here, even though Python would convert them)."""
    if not isinstance(stroke, list) or not stroke:
        raise DrawingError(f"{where}: expected a non-empty list of [x, y] pairs, got {_short(stroke)}")
    for j, point in enumerate(stroke):
        if (
            not isinstance(point, list)
            or len(point) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in point)
        ):
            raise DrawingError(f"{where}, point {j}: expected [x, y] with two numbers, got {_short(point)}")
    return np.asarray(stroke, dtype=np.float64)


def _short(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def bounded(drawing: Drawing, where: str) -> Drawing:
    """`drawing` with close points merged (:data:`MIN_POINT_SPACING`), or a DrawingError naming `where` if it
    still exceeds :data:`MAX_STROKES` or :data:`MAX_POINTS`."""
    if len(drawing.strokes) > MAX_STROKES:
        raise DrawingError(f"{where} has {len(drawing.strokes)} strokes; a drawing may have at most {MAX_STROKES}")
    strokes = tuple(merge_close_points(s, MIN_POINT_SPACING) for s in drawing.strokes)
    points = sum(len(s) for s in strokes)
    if points > MAX_POINTS:
        raise DrawingError(
            f"{where} has {points} points at least {MIN_POINT_SPACING} apart; a drawing may have at most "
            f"{MAX_POINTS} (simplify it, e.g. fewer vertices in zigzags)"
        )
    return Drawing(drawing.id, strokes, drawing.source)


def merge_close_points(stroke: np.ndarray, spacing: float) -> np.ndarray:
    """Drop each point closer than `spacing` to the point kept before it; the last point always stays (it
    replaces the point kept before it if those two are too close). Linear time."""
    if len(stroke) <= 2:
        return stroke
    keep = [0]
    last = stroke[0]
    for i in range(1, len(stroke) - 1):
        if np.hypot(*(stroke[i] - last)) >= spacing:
            keep.append(i)
            last = stroke[i]
    if len(keep) > 1 and np.hypot(*(stroke[-1] - last)) < spacing:
        keep.pop()
    keep.append(len(stroke) - 1)
    return stroke[keep]


def save_json(drawings, path: str | Path) -> Path:
    """Write drawings in the JSON stroke format."""
    path = Path(path)
    path.write_text(json.dumps({"drawings": [d.to_json() for d in drawings]}, indent=1), encoding="utf-8")
    return path


# ------------------------------------------------------------------------------------------------ SVG
_HIDDEN_ELEMENTS = {"defs", "clipPath", "mask", "symbol", "marker", "pattern", "metadata", "title", "desc", "style"}


def _svg_elements(path: Path):
    """(element, 3x3 transform to document coordinates) for every drawable element, in document order."""
    import xml.etree.ElementTree as ET

    from svgpathtools.parser import parse_transform
    from svgpathtools.svg_to_paths import (
        ellipse2pathd,
        line2pathd,
        path2pathd,
        polygon2pathd,
        polyline2pathd,
        rect2pathd,
    )

    to_d = {
        "path": path2pathd,
        "line": line2pathd,
        "polyline": polyline2pathd,
        "polygon": polygon2pathd,
        "rect": rect2pathd,
        "circle": ellipse2pathd,
        "ellipse": ellipse2pathd,
    }
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as err:
        raise DrawingError(f"{path}: not a readable SVG file ({err})") from None
    out = []
    stack = [(root, np.eye(3))]
    while stack:  # depth-first, children pushed in reverse so they pop in document order; no recursion limit
        elem, matrix = stack.pop()
        tag = elem.tag.rsplit("}", 1)[-1] if isinstance(elem.tag, str) else ""
        if tag in _HIDDEN_ELEMENTS:
            continue
        try:
            matrix = matrix @ parse_transform(elem.get("transform"))
            d = to_d[tag](elem) if tag in to_d else None
        except Exception as err:  # noqa: BLE001 - svgpathtools raises ValueError, IndexError, ... on bad attributes
            raise DrawingError(f"{path}: cannot read a <{tag}> element ({type(err).__name__}: {err})") from None
        if d:
            out.append((tag, d, matrix))
        stack.extend((child, matrix) for child in reversed(list(elem)))
    return out


def load_svg(path: str | Path, margin: float = 0.1) -> Drawing:
    """Parse an SVG file into one drawing named after the file (see the module docstring for what is read)."""
    from svgpathtools import Line, parse_path

    path = Path(path)
    parsed = []
    for tag, d, matrix in _svg_elements(path):
        try:
            svg_path = parse_path(d)
        except Exception as err:  # noqa: BLE001
            raise DrawingError(
                f"{path}: a <{tag}> element has an unreadable path ({type(err).__name__}: {err})"
            ) from None
        for sub in svg_path.continuous_subpaths():
            if len(sub):
                parsed.append((sub, matrix))
    if not parsed:
        raise DrawingError(f"{path}: contains no drawable paths (expected <path>, <line>, <polyline>, ...)")
    if len(parsed) > MAX_STROKES:
        raise DrawingError(f"{path} has {len(parsed)} strokes; a drawing may have at most {MAX_STROKES}")

    def document_points(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
        return points @ matrix[:2, :2].T + matrix[:2, 2]

    def vertices(sub) -> np.ndarray:
        return np.array([[p.real, p.imag] for p in [sub[0].start, *(seg.end for seg in sub)]])

    # Sampling density from the extent of the segment end points (curves can bulge past them; that only makes the
    # samples slightly finer). Each curve's length bounds the samples it needs, checked before sampling.
    corners = np.concatenate([document_points(vertices(sub), m) for sub, m in parsed])
    corners = corners[np.all(np.isfinite(corners), axis=1)]
    extent = float((corners.max(axis=0) - corners.min(axis=0)).max()) if len(corners) else 0.0
    step = max(extent, 1e-9) * SVG_SAMPLE_SPACING
    plans, total = [], 0
    for sub, matrix in parsed:
        stretch = float(np.linalg.norm(matrix[:2, :2], 2))  # the most a transform lengthens a curve
        counts = [
            1 if isinstance(seg, Line) else max(2, int(np.ceil(seg.length(error=1e-4) * stretch / step))) for seg in sub
        ]
        total += sum(counts)
        if total > 20 * MAX_POINTS:  # merging close points could not bring it under MAX_POINTS
            raise DrawingError(f"{path}: its paths need more than {20 * MAX_POINTS} points; simplify it")
        plans.append((sub, matrix, counts))
    raw = []
    for sub, matrix, counts in plans:
        pts = [sub[0].start]
        for seg, n in zip(sub, counts, strict=True):
            pts += [seg.end] if n == 1 else [seg.point(t) for t in np.linspace(0.0, 1.0, n)[1:]]
        arr = document_points(np.array([[p.real, p.imag] for p in pts], dtype=np.float64), matrix)
        arr[:, 1] *= -1.0
        if np.all(np.isfinite(arr)):
            raw.append(arr)
    if not raw:
        raise DrawingError(f"{path}: contains no drawable paths (expected <path>, <line>, <polyline>, ...)")
    allpts = np.concatenate(raw)
    lo = allpts.min(axis=0)
    extent = float((allpts.max(axis=0) - lo).max())
    if extent <= 0:
        raise DrawingError(f"{path}: all path points coincide; nothing to draw")
    unit = [(s - lo) / extent for s in raw]
    drawing = Drawing.from_strokes(path.stem, unit, source=str(path)).normalized(margin)
    return bounded(drawing, str(path))
