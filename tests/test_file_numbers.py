"""Numbers and shapes read from user files: drawing files (JSON, SVG), LIBERO views (``--where``) and LIBERO dataset
files (HDF5).

A number that overflows or is not one the format allows, a transform that scales coordinates out of range, a
malformed view and a file of the wrong kind are refused with a message naming the file (or the flag), the element
and the problem; nothing is skipped, converted or reported as something else."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bpp.drawing.drawing import Drawing, DrawingError
from bpp.drawing.files import load_drawings
from bpp.errors import UserError

DIGITS_500 = "9" * 500
DIGITS_5000 = "9" * 5000  # more than Python's int() converts (sys.get_int_max_str_digits)


def _json_file(tmp_path: Path, coordinate: str, name: str = "d.json") -> Path:
    path = tmp_path / name
    path.write_text(f'{{"drawings": [{{"id": "a", "strokes": [[[0.1, 0.1], [{coordinate}, 0.2]]]}}]}}')
    return path


def _svg_file(tmp_path: Path, body: str, name: str = "d.svg") -> Path:
    path = tmp_path / name
    path.write_text(f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 200 200">{body}</svg>')
    return path


def _refusal(path: Path) -> str:
    with pytest.raises(DrawingError) as err:
        load_drawings(path)
    message = str(err.value)
    assert message.startswith(str(path)) and "\n" not in message and len(message) < 400, message
    return message


# ------------------------------------------------------------------------------------------------ JSON drawings


@pytest.mark.parametrize(
    ("coordinate", "shown"),
    [
        ("1e309", "1e309"),
        ("-1e400", "-1e400"),
        (DIGITS_500, "9999999999999999...9999 (500 characters)"),
        (DIGITS_5000, "9999999999999999...9999 (5000 characters)"),
        ("NaN", "NaN"),
        ("-Infinity", "-Infinity"),
    ],
)
def test_a_json_coordinate_that_is_no_finite_number_is_refused_naming_its_point(tmp_path, coordinate, shown):
    path = _json_file(tmp_path, coordinate)
    assert _refusal(path) == f"{path}: drawing 'a', stroke 0, point 1: coordinate {shown} is not a finite number"


def test_huge_json_integers_elsewhere_name_the_file_or_are_ignored_where_unused(tmp_path):
    bad_id = tmp_path / "id.json"
    bad_id.write_text(f'{{"drawings": [{{"id": {DIGITS_5000}, "strokes": [[[0.1, 0.1], [0.2, 0.2]]]}}]}}')
    assert "every drawing needs a non-empty string 'id', got 9999999999999999...9999" in _refusal(bad_id)
    extra = tmp_path / "extra.json"  # a key the format does not read: its number is never converted
    extra.write_text(f'{{"drawings": [{{"id": "a", "strokes": [[[0.1, 0.1], [0.2, 0.2]]], "n": {DIGITS_5000}}}]}}')
    (drawing,) = load_drawings(extra)
    np.testing.assert_allclose(drawing.strokes[0], [[0.1, 0.1], [0.2, 0.2]])


def test_strokes_given_in_memory_name_the_point_that_is_no_finite_number():
    """The studio's strokes reach Drawing.from_strokes without a file: an int beyond float64 and an inf are refused
    there too, naming the stroke (and the point)."""
    with pytest.raises(DrawingError, match=r"drawing 'a', stroke 1: a coordinate is too large to be a finite number"):
        Drawing.from_strokes("a", [[[0.1, 0.1]], [[0.2, 0.2], [10**400, 0.3]]], source="strokes")
    with pytest.raises(DrawingError, match=r"drawing 'a', stroke 0, point 2: coordinate inf is not a finite number"):
        Drawing.from_strokes("a", [[[0.1, 0.1], [0.2, 0.2], [0.3, float("inf")]]], source="strokes")


def test_a_stroke_of_one_point_is_a_dot_as_documented(tmp_path):
    """Documented rather than refused: the studio's task file keeps a click as a one-point stroke, and `bpp eval
    --files` must read it back; the demonstrator inks a dot there."""
    from bpp.benchmarks.draw.demonstrator import demonstrate, replay_paths
    from bpp.drawing.geometry import unit_to_canvas

    path = tmp_path / "dot.json"
    path.write_text(json.dumps({"drawings": [{"id": "i", "strokes": [[[0.5, 0.2], [0.5, 0.7]], [[0.5, 0.9]]]}]}))
    (drawing,) = load_drawings(path)
    assert drawing.strokes[1].shape == (1, 2)
    demo = demonstrate(drawing, 0.0, np.array([100.0, 100.0]), np.random.default_rng(0))
    dot = unit_to_canvas(np.array([[0.5, 0.9]]), 0.0)[0]
    inked = np.concatenate([p.reshape(-1, 2) for p in replay_paths(demo.states, demo.actions)])
    assert np.linalg.norm(inked - dot, axis=1).min() < 3.0
    docs = (Path(__file__).parents[1] / "docs" / "drawanything.md").read_text()
    assert "A stroke of one point (or of points that coincide)" in docs and "is a dot" in docs


# ------------------------------------------------------------------------------------------------ SVG drawings


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        ('<path d="M 0 0 L 1e309 10"/>', "<path> #1, attribute 'd': 1e309 is not a finite number"),
        ('<path d="M -1.7e308 0 L 1.7e308 10"/>', "<path> #1, attribute 'd': -1.7e308 is beyond ±1e15"),
        (
            f'<path d="M 0 0 L {DIGITS_5000} 10"/>',
            "<path> #1, attribute 'd': 9999999999999999...9999 (5000 characters) is not",
        ),
        ('<polyline points="0,0 1e308,0 -1e308,0"/>', "<polyline> #1, attribute 'points': 1e308 is beyond ±1e15"),
        ('<line x1="0" y1="0" x2="1e999" y2="0"/>', "<line> #1, attribute 'x2': 1e999 is not a finite number"),
        ('<circle cx="10" cy="10" r="1e309"/>', "<circle> #1, attribute 'r': 1e309 is not a finite number"),
        ('<rect width="1e308" height="1e308"/>', "<rect> #1, attribute 'width': 1e308 is beyond ±1e15"),
        (
            '<path d="M 0 0 L 9 9"/><path id="wing" d="M 0 0 Q 1e308 1e308 1e308 0"/>',
            "<path id='wing'>, attribute 'd': 1e308 is beyond ±1e15",
        ),
    ],
)
def test_svg_coordinates_near_or_beyond_float64s_range_are_refused_naming_element_and_attribute(
    tmp_path, body, expected
):
    path = _svg_file(tmp_path, body)
    assert f"{path}: {expected}" in _refusal(path)


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        ('<g transform="scale(1e300)"><path d="M 0 0 L 1 1"/></g>', "<g> #1, attribute 'transform': 1e300 is beyond"),
        (
            '<g transform="scale(1e10)"><g><path transform="scale(1e10)" d="M 0 0 L 1 1"/></g></g>',
            "<path> #1, attribute 'transform': with the transforms of its groups it scales or moves coordinates by "
            "1e+20, beyond 1e15",
        ),
        (
            '<g transform="rotate(30) skewX(90)"><path d="M 0 0 L 1 1"/></g>',
            "<g> #1, attribute 'transform': with the transforms of its groups it scales or moves coordinates by",
        ),
        (
            f'<g transform="translate({DIGITS_5000})"><path d="M 0 0 L 1 1"/></g>',
            "<g> #1, attribute 'transform': 9999999999999999...9999 (5000 characters) is not a finite number",
        ),
        ('<g transform="foo(1)"><path d="M 0 0 L 1 1"/></g>', "<g> #1, attribute 'transform': cannot read 'foo(1)'"),
    ],
)
def test_svg_transforms_that_overflow_or_cannot_be_read_are_refused_not_skipped(tmp_path, body, expected):
    path = _svg_file(tmp_path, body + '<path d="M 0 0 L 100 100"/>')
    assert f"{path}: {expected}" in _refusal(path)


def test_an_svg_element_that_computes_to_nan_is_refused_not_dropped(tmp_path):
    """Before, a path with non-finite points was dropped without a word (the drawing lost a stroke), or the file was
    called empty, or sampling raised a ValueError."""
    half = _svg_file(tmp_path, '<path d="M 0 0 L 10 10"/><path d="M 0 0 L 1e309 10"/>', "half.svg")
    assert "<path> #2, attribute 'd': 1e309 is not a finite number" in _refusal(half)
    arc = _svg_file(tmp_path, '<path d="M 0 0 L 10 10"/><path d="M 5 5 A 1e-320 1e-320 0 0 1 20 20"/>', "arc.svg")
    assert "<path> #2: the length of its segment 0 (Arc) is not a finite number" in _refusal(arc)


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        ('<polyline points="0,0 nan,1 2,2"/>', "<polyline> #1, attribute 'points': 'nan' is not a number"),
        ('<polyline points="0,0 inf,1 2,2"/>', "<polyline> #1, attribute 'points': 'inf' is not a number"),
        ('<polyline points="10,10 20,20 30"/>', "<polyline> #1, attribute 'points': 5 numbers; expected x,y pairs"),
        ('<rect x="nan" width="5" height="5"/>', "<rect> #1, attribute 'x': expected a number (without units), got"),
        ('<rect width="10px" height="5"/>', "<rect> #1, attribute 'width': expected a number (without units), got"),
        ('<circle r="-5"/>', "<circle> #1, attribute 'r': -5 is negative; expected a size >= 0"),
        ('<ellipse rx="4" ry="-1"/>', "<ellipse> #1, attribute 'ry': -1 is negative; expected a size >= 0"),
    ],
)
def test_svg_numbers_that_svg_does_not_allow_are_refused_not_skipped(tmp_path, body, expected):
    """svgpathtools skips what its number pattern does not match in a list of points (so 'inf' shifted every pair
    after it), reads an odd last coordinate as nothing, and draws negative radii."""
    path = _svg_file(tmp_path, body + '<path d="M 0 0 L 100 100"/>')
    assert f"{path}: {expected}" in _refusal(path)


def test_svg_shapes_of_zero_size_leave_no_ink_as_in_svg(tmp_path):
    """A zero width, height or radius disables an element's rendering in SVG; svgpathtools drew such a rect as a line
    and such a circle as a dot."""
    path = _svg_file(tmp_path, '<rect width="0" height="50"/><circle cx="9" cy="9"/><path d="M 0 0 L 100 100"/>')
    (drawing,) = load_drawings(path)
    assert len(drawing.strokes) == 1


# ------------------------------------------------------------------------------------------------ LIBERO views


@pytest.mark.parametrize(
    ("where", "expected"),
    [
        ("", "where '' is empty"),
        ("  ", "where '  ' is empty"),
        (";", "where ';': clause 1 is empty"),
        ("pick=TD;", "where 'pick=TD;': clause 2 is empty"),
        ("pick=TD;;bowl=1", "where 'pick=TD;;bowl=1': clause 2 is empty"),
        ("pick", "where 'pick': 'pick' is not field=value[,value...]"),
        ("pick==TD", "where 'pick==TD': 'pick==TD' is not field=value[,value...]"),
        ("pick=!TD", "where 'pick=!TD': 'pick=!TD' is not field=value[,value...]"),
        ("=TD", "where '=TD': '=TD' is not field=value[,value...]"),
        (" pik =TD", "where ' pik =TD': ' pik =TD' is not field=value[,value...] over instruction, scene"),
    ],
)
def test_an_empty_or_malformed_view_is_refused_quoting_it(where, expected):
    from bpp.benchmarks.libero.commands import LiberoTasks
    from bpp.benchmarks.libero.dataset import LiberoDataConfig
    from bpp.benchmarks.libero.suites import combination, view

    for build in (lambda: view(combination(), where), lambda: LiberoDataConfig(where=where).tasks()):
        with pytest.raises(UserError) as err:
            build()
        assert expected in str(err.value)
    if "over" not in expected:  # the syntax is checked when the command's flags are read
        with pytest.raises(UserError, match="clauses field=value"):
            LiberoTasks(where=where)


def test_no_view_is_every_task_and_a_view_of_an_empty_value_is_a_field_not_set():
    from bpp.benchmarks.libero.chain import chain
    from bpp.benchmarks.libero.dataset import LiberoDataConfig
    from bpp.benchmarks.libero.suites import combination, view

    assert view(combination(), None) == combination()
    assert len(LiberoDataConfig().tasks()) == len(combination().train)
    unset = view(chain(), "start=")
    assert unset.train and all(t.describe()["start"] is None for t in (*unset.train, *unset.test))


def test_task_indices_outside_the_view_say_where_they_may_come_from():
    from dataclasses import replace

    from bpp.benchmarks.libero.dataset import PRESETS

    with pytest.raises(UserError, match=r"task_indices \[0\] are not in the view 'pick=TD' \(task_indices come from"):
        replace(PRESETS["debug"], where="pick=TD").tasks()


# ------------------------------------------------------------------------------------------------ LIBERO files


@pytest.mark.libero
def test_a_file_that_is_not_hdf5_is_named_by_libero_import(tmp_path, capsys):
    from bpp.cli import main

    notes = tmp_path / "notes_demo.hdf5"
    notes.write_text("hello")
    with pytest.raises(SystemExit) as stop:
        main(["libero", "import", str(notes), "--out", str(tmp_path / "out.zarr")])
    assert (
        stop.value.code
        == f"bpp libero import: error: {notes}: not an HDF5 file (LIBERO dataset files are HDF5, e.g. *_demo.hdf5)"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes_demo.hdf5"]


@pytest.mark.libero
def test_libero_demonstrations_with_bad_numbers_or_layout_are_refused_naming_file_and_demo(tmp_path):
    import h5py

    from bpp.benchmarks.libero.importer import open_dataset_file, read_demos

    def file(name: str, **demos) -> Path:
        path = tmp_path / f"{name}.hdf5"
        with h5py.File(path, "w") as f:
            for demo, datasets in demos.items():
                for key, value in datasets.items():
                    f.create_dataset(f"data/{demo}/{key}", data=value)
        return path

    good = {"actions": np.zeros((3, 7)), "states": np.zeros((3, 5))}
    cases = {
        file(
            "nan", demo_0=good, demo_1={**good, "states": np.array([[0.0] * 5, [0.0, np.nan, 0, 0, 0], [0.0] * 5])}
        ): ":demo_1: states[1, 1] = nan is not a finite number",
        file(
            "big", demo_0={**good, "actions": np.full((3, 7), 1e300)}
        ): ":demo_0: actions[0, 0] = 1e+300 is not a finite float32",
        file("missing", demo_0={"actions": np.zeros((3, 7))}): ":demo_0: no states",
        file("empty", demo_0={"actions": np.zeros((0, 7)), "states": np.zeros((0, 5))}): "T > 0, got (0, 7) and (0, 5)",
        file("odd", demo_0=good, demo_final=good): ": data/demo_final is not a demonstration name",
    }
    for path, expected in cases.items():
        with open_dataset_file(h5py, path) as f, pytest.raises(UserError) as err:
            list(read_demos(f, path))
        assert str(err.value).startswith(str(path)) and expected in str(err.value), str(err.value)
    with open_dataset_file(h5py, file("fine", demo_1=good, demo_0=good)) as f:
        assert [name for name, *_ in read_demos(f, tmp_path / "fine.hdf5")] == ["demo_0", "demo_1"]
    truncated = tmp_path / "truncated.hdf5"
    truncated.write_bytes((tmp_path / "fine.hdf5").read_bytes()[:600])
    with pytest.raises(UserError, match="truncated.hdf5: cannot read this HDF5 file"):
        open_dataset_file(h5py, truncated)
