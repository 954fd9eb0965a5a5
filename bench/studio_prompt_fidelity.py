"""How faithfully a drawn prompt records what was drawn: Chamfer (px) of the prompt's recorded ink to the strokes.

    python bench/studio_prompt_fidelity.py

A person draws a house (walls, roof, door) on the studio's board, the pointer sampled at 120 Hz, slowly and
quickly. Two ways to prompt with it: "as drawn" (the page's 10 Hz samples of the pointer are the demonstration's
cursor targets, executed by the cursor's dynamics) and "traced" (the strokes themselves, demonstrated by the
scripted demonstrator). Prints the Chamfer distance of each recorded prompt's ink to the drawn strokes.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from bpp.benchmarks.draw.studio.engine import Studio
from bpp.drawing.geometry import unit_to_canvas
from bpp.drawing.metric import chamfer_distance, ink_mask

HOUSE = [
    [[0.25, 0.2], [0.25, 0.55], [0.75, 0.55], [0.75, 0.2], [0.25, 0.2]],
    [[0.22, 0.55], [0.5, 0.82], [0.78, 0.55]],
    [[0.45, 0.2], [0.45, 0.38], [0.55, 0.38], [0.55, 0.2]],
]


def person_samples(strokes, px_per_s: float, hz: float = 120.0) -> list[list[float]]:
    """The page's 10 Hz samples [x, y, pen] of a pointer tracing `strokes` at `px_per_s` (board angle 0), pen up
    for 0.3 s between strokes."""
    timeline, t = [], 0.0
    for stroke in strokes:
        canvas = unit_to_canvas(np.asarray(stroke, dtype=np.float64), 0.0)
        lengths = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(canvas, axis=0), axis=1))]
        times = np.arange(0.0, lengths[-1] / px_per_s, 1.0 / hz)
        pointer = np.c_[[np.interp(times * px_per_s, lengths, canvas[:, k]) for k in range(2)]].T
        pointer = np.r_[pointer, canvas[-1:]]
        timeline += [(t + k / hz, *p, 1.0) for k, p in enumerate(pointer)]
        t += len(pointer) / hz
        timeline.append((t, *canvas[-1], 0.0))
        t += 0.3
    timeline = np.array(timeline)
    at = [max(np.searchsorted(timeline[:, 0], k / 10, side="right") - 1, 0) for k in range(int(t * 10) + 1)]
    return timeline[at, 1:].tolist()


def main() -> None:
    drawn = ink_mask([unit_to_canvas(np.asarray(s), 0.0) for s in HOUSE])
    with tempfile.TemporaryDirectory() as tmp:
        studio = Studio([], Path(tmp))
        sid = studio.new_session()
        print("| drawing speed | prompt | steps | Chamfer of its ink to the drawn strokes (px) |")
        print("|---|---|---:|---:|")
        for name, speed in (("slow, 150 px/s", 150.0), ("normal, 350 px/s", 350.0), ("fast, 700 px/s", 700.0)):
            samples = person_samples(HOUSE, speed)
            for how, prompt in (
                ("as drawn (10 Hz samples)", lambda s=samples: studio.add_drawn_prompt(sid, s, 0.0)),
                ("traced by the demonstrator", lambda: studio.add_strokes_prompt(sid, HOUSE, 0.0)),
            ):
                p = prompt()
                score = chamfer_distance(drawn, ink_mask([np.asarray(line) for line in p.ink]))
                print(f"| {name} | {how} | {p.steps} | {score:.2f} |")
                studio.delete_prompt(sid, p.id)
        studio.close()


if __name__ == "__main__":
    main()
