"""Turn user drawings into tasks: the JSON stroke format and SVG path files.

JSON stroke format (coordinates in the unit square, y up, strokes in drawing order)::

    {"drawings": [{"id": "house", "strokes": [[[0.2, 0.2], [0.8, 0.2], [0.8, 0.6]], [[0.2, 0.6], [0.5, 0.9]]]}]}

SVG: every ``<path>`` (and line, polyline, polygon, rect, circle, ellipse) of the file becomes strokes of one
drawing, one stroke per continuous sub-path, in document order; the drawing is scaled uniformly to fit the
board (SVG's y-down is flipped) and named after the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bpp.envs.draw.drawing import Drawing, DrawingError

SVG_SAMPLE_SPACING = 0.004
"""Arc length between samples of SVG curves, as a fraction of the drawing's longest side."""


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
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise DrawingError(f"{path}: cannot read file ({err})") from None
    except json.JSONDecodeError as err:
        raise DrawingError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("drawings"), list):
        raise DrawingError(f'{path}: expected an object {{"drawings": [...]}} at the top level')
    if not doc["drawings"]:
        raise DrawingError(f"{path}: 'drawings' is empty")
    out = []
    for i, item in enumerate(doc["drawings"]):
        if not isinstance(item, dict) or "id" not in item or "strokes" not in item:
            raise DrawingError(f"{path}: drawing #{i} must be an object with 'id' and 'strokes'")
        if not isinstance(item["strokes"], list):
            raise DrawingError(f"{path}: drawing {item['id']!r}: 'strokes' must be a list of strokes")
        out.append(Drawing.from_strokes(item["id"], item["strokes"], source=str(path)))
    return out


def save_json(drawings, path: str | Path) -> Path:
    """Write drawings in the JSON stroke format."""
    path = Path(path)
    path.write_text(json.dumps({"drawings": [d.to_json() for d in drawings]}, indent=1), encoding="utf-8")
    return path


def load_svg(path: str | Path, margin: float = 0.1) -> Drawing:
    """Parse an SVG file into one drawing named after the file."""
    from svgpathtools import svg2paths

    path = Path(path)
    try:
        svg_paths, _ = svg2paths(str(path))
    except Exception as err:  # svgpathtools raises many types (ParseError, ValueError, ...) on bad input
        raise DrawingError(f"{path}: not a readable SVG file ({type(err).__name__}: {err})") from None
    step = max(_svg_extent(svg_paths), 1e-9) * SVG_SAMPLE_SPACING
    raw = []
    for svg_path in svg_paths:
        for sub in svg_path.continuous_subpaths():
            if len(sub) == 0:
                continue
            pts = [sub[0].start]
            for seg in sub:
                n = max(2, int(np.ceil(seg.length(error=1e-4) / step)))
                pts += [seg.point(t) for t in np.linspace(0.0, 1.0, n)[1:]]
            arr = np.array([[p.real, -p.imag] for p in pts], dtype=np.float64)
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
    return Drawing.from_strokes(path.stem, unit, source=str(path)).normalized(margin)


def _svg_extent(svg_paths) -> float:
    boxes = np.array([p.bbox() for p in svg_paths if len(p)])  # (xmin, xmax, ymin, ymax)
    if len(boxes) == 0:
        return 1.0
    return float(max(boxes[:, 1].max() - boxes[:, 0].min(), boxes[:, 3].max() - boxes[:, 2].min()))
