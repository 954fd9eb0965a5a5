"""Turn user drawings into tasks: the JSON stroke format and SVG path files.

JSON stroke format (coordinates in the unit square, y up, strokes in drawing order)::

    {"drawings": [{"id": "house", "strokes": [[[0.2, 0.2], [0.8, 0.2], [0.8, 0.6]], [[0.2, 0.6], [0.5, 0.9]]]}]}

Coordinates must be finite JSON numbers (a string such as ``"0.5"`` or a boolean is refused, not converted; so are
``NaN``, ``Infinity`` and numbers beyond float64's range, such as ``1e309`` or an integer of 400 digits). A stroke
of one point (or of points that coincide) is a dot: the pen goes down and up there, as a click in the studio draws
one.

SVG: every ``<path>`` (and line, polyline, polygon, rect, circle, ellipse) of the file becomes strokes of one
drawing, one stroke per continuous sub-path, in document order, with every ``transform`` of the element and its
groups applied; elements inside ``<defs>``, ``<clipPath>``, ``<mask>``, ``<symbol>``, ``<marker>`` and
``<pattern>`` are not drawn and ``<use>`` is not followed; a rect, circle or ellipse of zero size is not drawn either,
as in SVG. The drawing is scaled uniformly to fit the board (SVG's y-down is flipped) and named after the file.
Straight segments keep their end points; curves are sampled every :data:`SVG_SAMPLE_SPACING` of the drawing's size.
Every number of an element's geometry and transform is checked first: a number SVG does not allow there (``nan``,
``10px``, a negative size, an odd count of polyline coordinates), one that overflows (``1e309``) or one beyond
:data:`MAX_SVG_NUMBER` is refused, and so is a transform that, with those of its groups, scales or moves
coordinates beyond :data:`MAX_SVG_NUMBER`; the message names the element (``<path> #3``: the third ``<path>`` drawn,
in document order, or its id) and the attribute.

Limits (so any file is read in bounded time, with a message saying which limit it hit): a file is at most
:data:`MAX_FILE_BYTES`; points closer than :data:`MIN_POINT_SPACING` to the previous point of their stroke are
merged; after that a drawing has at most :data:`MAX_STROKES` strokes and :data:`MAX_POINTS` points.
"""

from __future__ import annotations

import json
import math
import re
import warnings
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path

import numpy as np

from bpp.drawing.drawing import Drawing, DrawingError

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
MAX_SVG_NUMBER = 1e15
"""Largest magnitude of a number in an SVG element's geometry or transform, and of an entry of the transform an
element's own and its groups' transforms make together: float64 resolves a tenth of a unit up to there, and no
computation on such numbers (an arc squares its radii twice) can overflow."""
_MAX_SVG_TEXT = "1e15"
"""How messages write :data:`MAX_SVG_NUMBER`."""


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
    doc = _read_json(path)
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


def _number_text(text: str) -> str:
    """A number as a file spells it, shortened if it is long (an integer of 5000 digits)."""
    return text if len(text) <= 32 else f"{text[:16]}...{text[-4:]} ({len(text)} characters)"


class _NotFinite:
    """A JSON number that is no finite float64 (``1e309``, an integer of 400 digits, ``NaN``, ``Infinity``), kept as
    the file spells it so that a refusal can quote it."""

    def __init__(self, text: str):
        self.text = text

    def __repr__(self) -> str:
        return _number_text(self.text)


def _json_number(text: str) -> int | float | _NotFinite:
    """A JSON number (or NaN / Infinity) as the parser reads it. Every one goes through float first: that never
    raises, however many digits (Python's int() refuses more than 4300), and says whether it is finite; only a finite
    one becomes an int or a float."""
    value = float(text)
    if not math.isfinite(value):
        return _NotFinite(text)
    return int(text) if re.fullmatch("-?[0-9]+", text) else value


def _read_json(path: Path):
    """The JSON document in `path` with numbers read by :func:`_json_number`, or a DrawingError naming the file: not
    readable, not UTF-8, not JSON, or nested too deeply for the parser (Python's RecursionError)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise DrawingError(f"{path}: cannot read the drawing file ({err})") from None
    try:
        return json.loads(text, parse_int=_json_number, parse_float=_json_number, parse_constant=_json_number)
    except json.JSONDecodeError as err:
        raise DrawingError(f"{path}: the drawing file is not valid JSON ({err})") from None
    except RecursionError:
        raise DrawingError(f"{path}: the drawing file is nested too deeply to parse") from None


def _json_stroke(stroke, where: str) -> np.ndarray:
    """A stroke as an (N, 2) array, refusing anything but a list of [number, number] pairs of finite numbers (JSON
    true, false and strings are not numbers here, even though Python would convert them)."""
    if not isinstance(stroke, list) or not stroke:
        raise DrawingError(f"{where}: expected a non-empty list of [x, y] pairs, got {_short(stroke)}")
    for j, point in enumerate(stroke):
        if isinstance(point, list) and len(point) == 2:
            for v in point:
                if isinstance(v, _NotFinite):
                    raise DrawingError(f"{where}, point {j}: coordinate {v!r} is not a finite number")
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
_SVG_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
"""A number as SVG writes one: no ``nan``, ``inf``, ``1_000`` or units, which Python's float() would take (or which
svgpathtools would skip in a list of points)."""
_SCALARS = {
    "line": ("x1", "y1", "x2", "y2"),
    "rect": ("x", "y", "width", "height", "rx", "ry"),
    "circle": ("cx", "cy", "r"),
    "ellipse": ("cx", "cy", "rx", "ry", "r"),
}
"""The attributes of one number each that svgpathtools reads for a shape (it also takes ``r`` for an ellipse)."""
_SIZES = {"rect": ("width", "height", "rx", "ry"), "circle": ("r",), "ellipse": ("rx", "ry", "r")}
"""The attributes of a shape that are sizes: a negative one is an error in SVG."""


def _clip(text: str, limit: int = 200) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _reason(err: Exception) -> str:
    """An exception of a parser as a short reason: its type and (clipped) message, if it has one."""
    return f"{type(err).__name__}: {_clip(str(err))}" if str(err) else type(err).__name__


def _check_range(tokens: list[str], where: str) -> np.ndarray:
    """`tokens` (SVG numbers) as float64, or a DrawingError naming `where` for the first that is not finite or is
    beyond :data:`MAX_SVG_NUMBER`."""
    values = np.array(tokens, dtype=np.float64) if tokens else np.zeros(0)
    bad = np.flatnonzero(~(np.abs(values) <= MAX_SVG_NUMBER))
    if len(bad):
        text = _number_text(tokens[bad[0]])
        if not np.isfinite(values[bad[0]]):
            raise DrawingError(f"{where}: {text} is not a finite number")
        raise DrawingError(f"{where}: {text} is beyond ±{_MAX_SVG_TEXT}, the largest number an SVG file may give")
    return values


def _number_list(text: str, where: str) -> np.ndarray:
    """The numbers of a list such as a polyline's points (separated by spaces and commas), each checked."""
    rest = re.search(r"[^\s,]+", _SVG_NUMBER.sub(" ", text))
    if rest is not None:
        raise DrawingError(f"{where}: {_clip(rest.group(), 40)!r} is not a number")
    return _check_range(_SVG_NUMBER.findall(text), where)


def _drawn_shape(elem, tag: str, where: str) -> bool:
    """Whether drawable element `elem` (a `tag`) is drawn, after checking every number svgpathtools reads from it:
    False for a rect, circle or ellipse of zero size, which SVG does not render. A number that SVG does not allow
    there, that is not finite or is beyond :data:`MAX_SVG_NUMBER`, a negative size and an odd count of polyline
    coordinates are a DrawingError naming `where` (the element) and the attribute."""
    if tag == "path":  # the grammar of d is svgpathtools' to check; its numbers are checked here
        _check_range(_SVG_NUMBER.findall(elem.get("d", "")), f"{where}, attribute 'd'")
        return True
    if tag in ("polyline", "polygon"):
        values = _number_list(elem.get("points", ""), f"{where}, attribute 'points'")
        if len(values) % 2:
            raise DrawingError(f"{where}, attribute 'points': {len(values)} numbers; expected x,y pairs")
        return True
    values = {}
    for attr in _SCALARS[tag]:
        text = elem.get(attr)
        if text is None:
            continue
        if _SVG_NUMBER.fullmatch(text.strip()) is None:
            raise DrawingError(
                f"{where}, attribute {attr!r}: expected a number (without units), got {_clip(text, 40)!r}"
            )
        (values[attr],) = _check_range([text.strip()], f"{where}, attribute {attr!r}")
    for attr in _SIZES.get(tag, ()):
        if values.get(attr, 0.0) < 0:
            raise DrawingError(
                f"{where}, attribute {attr!r}: {elem.get(attr).strip()} is negative; expected a size >= 0"
            )
    if tag == "rect":
        return values.get("width", 0.0) > 0 and values.get("height", 0.0) > 0
    if tag == "circle" or "r" in values:
        return values.get("r", 0.0) > 0
    if tag == "ellipse":
        return values.get("rx", 0.0) > 0 and values.get("ry", 0.0) > 0
    return True


def _svg_elements(path: Path):
    """(name, path d-string, 3x3 transform to document coordinates) for every drawn element, in document order;
    the name is how messages refer to the element (``<path> #3``, or ``<path id='wing'>``)."""

    # svgpathtools: half a second to import, for SVG files only
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
    seen: Counter[str] = Counter()
    stack = [(root, np.eye(3))]
    while stack:  # depth-first, children pushed in reverse so they pop in document order; no recursion limit
        elem, matrix = stack.pop()
        tag = elem.tag.rsplit("}", 1)[-1] if isinstance(elem.tag, str) else ""
        if tag in _HIDDEN_ELEMENTS:
            continue
        seen[tag] += 1
        ident = elem.get("id")
        name = f"<{tag} id={_clip(ident, 40)!r}>" if ident else f"<{tag}> #{seen[tag]}"
        transform = elem.get("transform")
        if transform:
            where = f"{path}: {name}, attribute 'transform'"
            _check_range(_SVG_NUMBER.findall(transform), where)
            try:
                with warnings.catch_warnings():  # svgpathtools skips a transform it cannot read, with a UserWarning
                    warnings.simplefilter("error", UserWarning)
                    matrix = matrix @ parse_transform(transform)
            except Exception as err:  # noqa: BLE001 - svgpathtools raises ValueError, warnings, ... on bad transforms
                raise DrawingError(f"{where}: cannot read {_clip(transform, 60)!r} ({_clip(str(err))})") from None
            peak = float(np.abs(matrix).max())
            if not peak <= MAX_SVG_NUMBER:
                raise DrawingError(
                    f"{where}: with the transforms of its groups it scales or moves coordinates by {peak:.3g}, "
                    f"beyond {_MAX_SVG_TEXT}"
                )
        if tag in to_d and _drawn_shape(elem, tag, f"{path}: {name}"):
            try:
                d = to_d[tag](elem)
            except Exception as err:  # noqa: BLE001 - svgpathtools raises ValueError, IndexError, ... on bad attributes
                raise DrawingError(f"{path}: cannot read {name} ({_reason(err)})") from None
            if d:
                out.append((name, d, matrix))
        stack.extend((child, matrix) for child in reversed(list(elem)))
    return out


def load_svg(path: str | Path, margin: float = 0.1) -> Drawing:
    """Parse an SVG file into one drawing named after the file (see the module docstring for what is read)."""
    # svgpathtools: half a second to import, for SVG files only
    from svgpathtools import Line, parse_path

    path = Path(path)
    parsed = []
    for name, d, matrix in _svg_elements(path):
        try:  # quietly: an arc of zero radius is a line (as SVG says), one of a radius too small is checked below
            with warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore")
                svg_path = parse_path(d)
        except Exception as err:  # noqa: BLE001
            raise DrawingError(f"{path}: {name} has an unreadable path ({_reason(err)})") from None
        for sub in svg_path.continuous_subpaths():
            if len(sub):
                parsed.append((name, sub, matrix))
    if not parsed:
        raise DrawingError(f"{path}: contains no drawable paths (expected <path>, <line>, <polyline>, ...)")
    if len(parsed) > MAX_STROKES:
        raise DrawingError(f"{path} has {len(parsed)} strokes; a drawing may have at most {MAX_STROKES}")

    def document_points(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
        return points @ matrix[:2, :2].T + matrix[:2, 2]

    def vertices(sub) -> np.ndarray:
        return np.array([[p.real, p.imag] for p in [sub[0].start, *(seg.end for seg in sub)]])

    # The numbers of every element and transform are bounded (MAX_SVG_NUMBER), so what follows cannot overflow.
    # Sampling density from the extent of the segment end points (curves can bulge past them; that only makes the
    # samples slightly finer). Each curve's length bounds the samples it needs, checked before sampling.
    corners = np.concatenate([document_points(vertices(sub), m) for _, sub, m in parsed])
    corners = corners[np.all(np.isfinite(corners), axis=1)]
    extent = float((corners.max(axis=0) - corners.min(axis=0)).max()) if len(corners) else 0.0
    step = max(extent, 1e-9) * SVG_SAMPLE_SPACING
    # An arc whose radii are too small for float64 computes to NaN (with warnings from numpy, scipy and svgpathtools,
    # which would only repeat that): its non-finite length or points are refused below, naming the element.
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        plans, total = [], 0
        for name, sub, matrix in parsed:
            stretch = float(np.linalg.norm(matrix[:2, :2], 2))  # the most a transform lengthens a curve
            counts = []
            for k, seg in enumerate(sub):
                if isinstance(seg, Line):
                    counts.append(1)
                    continue
                length = seg.length(error=1e-4) * stretch
                if not math.isfinite(length):
                    raise DrawingError(
                        f"{path}: {name}: the length of its segment {k} ({type(seg).__name__}) is not a finite number "
                        "(its numbers are too large or too small to compute with)"
                    )
                counts.append(max(2, int(np.ceil(length / step))))
            total += sum(counts)
            if total > 20 * MAX_POINTS:  # merging close points could not bring it under MAX_POINTS
                raise DrawingError(f"{path}: its paths need more than {20 * MAX_POINTS} points; simplify it")
            plans.append((name, sub, matrix, counts))
        raw = []
        for name, sub, matrix, counts in plans:
            pts = [sub[0].start]
            for seg, n in zip(sub, counts, strict=True):
                pts += [seg.end] if n == 1 else [seg.point(t) for t in np.linspace(0.0, 1.0, n)[1:]]
            arr = document_points(np.array([[p.real, p.imag] for p in pts], dtype=np.float64), matrix)
            if not np.all(np.isfinite(arr)):
                raise DrawingError(
                    f"{path}: {name}: its points are not all finite numbers (its numbers are too large or too small "
                    "to compute with)"
                )
            arr[:, 1] *= -1.0
            raw.append(arr)
    allpts = np.concatenate(raw)
    lo = allpts.min(axis=0)
    extent = float((allpts.max(axis=0) - lo).max())
    if extent <= 0:
        raise DrawingError(f"{path}: all path points coincide; nothing to draw")
    unit = [(s - lo) / extent for s in raw]
    drawing = Drawing.from_strokes(path.stem, unit, source=str(path)).normalized(margin)
    return bounded(drawing, str(path))
