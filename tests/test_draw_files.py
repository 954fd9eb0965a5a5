import json

import numpy as np
import pytest

from bpp.benchmarks.draw.dataset import DrawDataConfig, generate
from bpp.drawing.drawing import Drawing, DrawingError, task_drawing
from bpp.drawing.files import load_drawings, save_json

GOOD = {
    "drawings": [
        {"id": "v", "strokes": [[[0.2, 0.8], [0.5, 0.2], [0.8, 0.8]]]},
        {"id": "dot-line", "strokes": [[[0.1, 0.1]], [[0.3, 0.3], [0.6, 0.3]]]},
    ]
}


def _json(tmp_path, doc, name="d.json"):
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def test_json_round_trip(tmp_path):
    drawings = load_drawings(_json(tmp_path, GOOD))
    assert [d.id for d in drawings] == ["v", "dot-line"]
    np.testing.assert_allclose(drawings[0].strokes[0], [[0.2, 0.8], [0.5, 0.2], [0.8, 0.8]])
    again = load_drawings(save_json(drawings, tmp_path / "out.json"))
    for a, b in zip(drawings, again, strict=True):
        assert a.id == b.id and all(np.allclose(p, q) for p, q in zip(a.strokes, b.strokes, strict=True))


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ("{not json", "not valid JSON"),
        ({"shapes": []}, "expected an object"),
        ({"drawings": []}, "'drawings' is empty"),
        ({"drawings": [{"id": "a"}]}, "with 'id' and 'strokes'"),
        ({"drawings": [{"id": "a", "strokes": []}]}, "drawing 'a' is empty"),
        ({"drawings": [{"id": "a", "strokes": [[]]}]}, "stroke 0: expected a non-empty list"),
        ({"drawings": [{"id": "a", "strokes": [[[0.1, 0.2, 0.3]]]}]}, "two numbers"),
        ({"drawings": [{"id": "a", "strokes": [[[0.1, 0.2], [0.3, 1.5]]]}]}, "unit square"),
        ('{"drawings": [{"id": "a", "strokes": [[[0.1, NaN]]]}]}', "NaN"),
        ({"drawings": [{"id": "", "strokes": [[[0.1, 0.2]]]}]}, "non-empty string 'id'"),
        (
            {"drawings": [{"id": "a", "strokes": [[[0.1, 0.2]]]}, {"id": "a", "strokes": [[[0.3, 0.2]]]}]},
            "duplicate drawing ids",
        ),
    ],
)
def test_bad_json_files_name_the_file_and_the_problem(tmp_path, doc, message):
    path = _json(tmp_path, doc)
    with pytest.raises(DrawingError, match=message) as err:
        load_drawings(path)
    assert str(path) in str(err.value)


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(DrawingError, match="no such file"):
        load_drawings(tmp_path / "nope.json")
    (tmp_path / "x.png").write_bytes(b"\x89PNG")
    with pytest.raises(DrawingError, match="unsupported drawing file type"):
        load_drawings(tmp_path / "x.png")


SVG = """<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 200 100">
<path d="M10 90 L100 10 L190 90"/><path d="M40 60 C 60 40, 140 40, 160 60 M100 95 L100 80"/></svg>"""


def test_svg_paths_become_strokes(tmp_path):
    (tmp_path / "roof.svg").write_text(SVG)
    (drawing,) = load_drawings(tmp_path / "roof.svg")
    assert drawing.id == "roof" and len(drawing.strokes) == 3
    first = drawing.strokes[0]
    # Aspect ratio kept (200 x 80 -> 0.8 wide x 0.32 tall) and SVG's y-down flipped: the apex is on top.
    pts = np.concatenate(drawing.strokes)
    assert (pts.max(0) - pts.min(0))[0] == pytest.approx(0.8, abs=1e-6)
    apex = first[np.argmax(first[:, 1])]
    assert apex[0] == pytest.approx(0.5, abs=0.01)
    assert first[0, 1] < apex[1]


def test_bad_svg_files(tmp_path):
    (tmp_path / "empty.svg").write_text('<svg xmlns="http://www.w3.org/2000/svg"></svg>')
    with pytest.raises(DrawingError, match="no drawable paths"):
        load_drawings(tmp_path / "empty.svg")
    (tmp_path / "broken.svg").write_text("<svg <path")
    with pytest.raises(DrawingError, match="not a readable SVG"):
        load_drawings(tmp_path / "broken.svg")


def test_files_become_a_task_store_and_bad_files_write_nothing(tmp_path):
    good = _json(tmp_path, GOOD)
    (tmp_path / "roof.svg").write_text(SVG)
    cfg = DrawDataConfig(source="files", drawings=(good, tmp_path / "roof.svg"), demos_per_task=2)
    store = generate(cfg, tmp_path / "mine.zarr", workers=1, progress=False)
    assert [t["id"] for t in store.tasks] == ["v", "dot-line", "roof"]
    assert store.num_episodes == 6
    d = task_drawing(store, 0)
    assert isinstance(d, Drawing) and np.allclose(d.strokes[0], GOOD["drawings"][0]["strokes"][0])
    bad = _json(tmp_path, {"drawings": [{"id": "a", "strokes": [[[0.1, 2.0]]]}]}, "bad.json")
    cfg = DrawDataConfig(source="files", drawings=(good, bad))
    with pytest.raises(DrawingError, match="bad.json"):
        generate(cfg, tmp_path / "never.zarr", workers=1, progress=False)
    assert not any(p.name.startswith((".never", "never")) for p in tmp_path.iterdir())
