"""The unseen evaluation drawings: glyphs designed by hand (A. V. Hershey's stroke fonts, 1967).

The paper evaluates on 50 drawings a person made, deliberately unlike the procedural training drawings. We
cannot ask a person here, so we take strokes a person designed: the Hershey vector fonts (shipped by the
``Hershey-Fonts`` package on PyPI), which are stroke sequences in the order a pen draws them. The selection
below mixes symbols, Latin capitals, digits, cursive script and Greek letters; the list is fixed so the
benchmark never changes under you.
"""

from __future__ import annotations

import functools

import numpy as np
from HersheyFonts import HersheyFonts

from bpp.drawing.drawing import Drawing

# (font, character, name). Names are the task ids.
HUMAN_GLYPHS: tuple[tuple[str, str, str], ...] = (
    ("symbolic", "L", "star"),
    ("symbolic", "`", "hexagram"),
    ("symbolic", "n", "heart"),
    ("symbolic", "m", "spade"),
    ("symbolic", "p", "club"),
    ("symbolic", "a", "bell"),
    ("symbolic", "X", "anchor"),
    ("symbolic", "V", "flag"),
    ("symbolic", "R", "nested-triangles"),
    ("symbolic", "^", "cross"),
    ("symbolic", "_", "moon"),
    ("symbolic", "h", "shamrock"),
    ("symbolic", "i", "section"),
    ("symbolic", "~", "pentagram"),
    ("symbolic", "K", "diamond"),
    ("symbolic", "J", "triangle"),
    ("symbolic", "I", "square"),
    ("symbolic", "7", "zigzag"),
    ("symbolic", ":", "fish"),
    ("symbolic", "?", "loop"),
    ("symbolic", "w", "pretzel"),
    ("symbolic", "d", "trefoil"),
    ("futural", "A", "A"),
    ("futural", "B", "B"),
    ("futural", "E", "E"),
    ("futural", "G", "G"),
    ("futural", "K", "K"),
    ("futural", "M", "M"),
    ("futural", "R", "R"),
    ("futural", "S", "S"),
    ("futural", "W", "W"),
    ("futural", "Z", "Z"),
    ("futural", "2", "two"),
    ("futural", "3", "three"),
    ("futural", "5", "five"),
    ("futural", "8", "eight"),
    ("futural", "&", "ampersand"),
    ("futural", "@", "at"),
    ("scripts", "a", "script-a"),
    ("scripts", "f", "script-f"),
    ("scripts", "g", "script-g"),
    ("scripts", "k", "script-k"),
    ("scripts", "G", "script-G"),
    ("scripts", "S", "script-S"),
    ("greek", "a", "alpha"),
    ("greek", "b", "beta"),
    ("greek", "d", "delta"),
    ("greek", "l", "lambda"),
    ("greek", "w", "omega"),
    ("greek", "z", "zeta"),
)


@functools.cache
def _font(name: str):
    font = HersheyFonts()
    font.load_default_font(name)
    return font


def glyph_drawing(font: str, char: str, name: str, margin: float = 0.12) -> Drawing:
    """One Hershey glyph as a drawing centred on the board, long side spanning [margin, 1 - margin]."""
    strokes = [np.asarray(s, dtype=np.float64) for s in _font(font).strokes_for_text(char) if len(s) > 1]
    if not strokes:
        raise ValueError(f"Hershey font {font!r} has no strokes for {char!r}")
    # Hershey coordinates are y-down; drawings are y-up.
    strokes = [s * np.array([1.0, -1.0]) for s in strokes]
    pts = np.concatenate(strokes)
    lo = pts.min(axis=0)
    extent = max(float((pts.max(axis=0) - lo).max()), 1e-9)
    unit = [(s - lo) / extent for s in strokes]
    return Drawing.from_strokes(f"hershey-{name}", unit, source=f"Hershey font {font!r}").normalized(margin)


def human_drawings() -> list[Drawing]:
    """The 50 built-in unseen evaluation drawings, in a fixed order."""
    return [glyph_drawing(font, char, name) for font, char, name in HUMAN_GLYPHS]
