"""Measured numbers have one source: BENCHMARKS.md.

README.md and the guides in docs/ state measured results (a score in px, a time, a rate, a memory size, a speed-up,
a count out of a total); each must be a number BENCHMARKS.md holds, so that no document disagrees with the current
measurements. The numbers the paper reports count as a source too, as docs/results.md quotes them under "The paper's
numbers". BENCHMARKS.md itself holds current results only and stays short enough to read.

What is a claim (in prose outside fenced code blocks, inline code blanked, as tests/test_docs.py reads it):

- a number, a range (``26.5-39.4``), a list (``32.77 and 32.52``) or a value with its error (``18.84 ± 0.79``),
  followed by a unit of :data:`UNITS`: ``18.84 px``, ``39.9 min``, ``10 min 25 s``, ``1,390 samples/s``,
  ``839 demonstrations per hour``, ``17.8 MB``, ``2.4x``, ``28-33-fold``, ``62%``;
- a count out of a total: ``31 of 50``;
- a number written without a unit that can only be a measurement, a decimal (in a table also a number over 999),
  in a sentence or table cell whose surroundings name a unit: ``scored 18.84 px (20.40 on the Intel Xeon)``, or
  ``10.08`` in a table row about a "Chamfer px" score.

Where a claim agrees: every number of it is a number BENCHMARKS.md states with the same kind of unit. There, a number
written with its unit has that kind; any other number has each kind its surroundings name: for a table cell, the
cell, its column's header, its row and the paragraph before the table; in prose, its sentence.

What is not a claim: a size written as a compound adjective (``a 224-px camera``); numbers in a table of settings
(a header naming a limit, an option, a default or a setting) or in a sentence or cell that gives a default ("64 MiB
by default", "(default: 128)"); and the few settings, definitions and published facts :data:`NOT_MEASURED` lists,
each with its reason.

The source code is held to the same rule in the texts a command's ``--help`` shows (the docstrings of the dataclasses
of src/bpp and of their fields) and wherever it cites BENCHMARKS.md (any docstring, string or comment).
"""

from __future__ import annotations

import ast
import functools
import io
import re
import tokenize
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "BENCHMARKS.md"
RESULTS_PAGE = ROOT / "docs" / "results.md"
PAPER_HEADING = "## The paper's numbers"
DOCUMENTS = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")], key=lambda p: p.relative_to(ROOT).as_posix())
SOURCE = ROOT / "src" / "bpp"
MAX_BENCHMARKS_LINES = 1000

UNITS: dict[str, tuple[str | None, str]] = {
    # kind: (the unit written after a number, the unit named in a number's surroundings)
    "px": (r"px\b(?!/)|pixels\b", r"(?<!\d-)\bpx\b(?!/)|pixels\b|Chamfer"),
    "percent": (r"%|percent\b", r"%|percent\b|success"),
    "ms": (r"ms\b", r"\bms\b"),
    "s": (r"s\b(?!/)|seconds\b", r"(?<!['/])\bs\b|seconds?\b|wall time|wall clock"),
    "min": (r"min\b|minutes?\b|-minute\b", r"\bmin\b|minutes?\b|-minute\b"),
    "hours": (r"h\b|hours?\b|GPU-hours\b", r"\bh\b|hours?\b"),
    "rate": (
        r"(?:samples|steps|env steps|frames|req|requests)(?:/s\b| per second\b)",
        r"/s\b|per second\b|per wall-clock s\b",
    ),
    "per_hour": (
        r"(?:demonstrations|demos|rollouts)(?: (?:per|an|a) hour\b|/h\b)|/ ?hour\b",
        r"per hour\b|an hour\b|/ ?hour\b",
    ),
    "bytes": (r"(?:[KMGT]i?B|kB)\b(?!/)", r"\b(?:[KMGT]i?B|kB)\b"),
    "flops": (r"[GT]FLOP(?:/s)?\b", r"\b[GT]FLOP"),
    "ratio": (
        r"x\b(?!\s?\d)|-fold\b|times (?:faster|slower|more|less|as)\b",
        r"(?<=\d)x\b|-fold\b|times (?:faster|slower)|\bfaster|\bslower",
    ),
    # Lengths and angles in the guides are nearly all settings (a marker's size, the board's lean): only a decimal
    # beside one of these units is a claim, through its surroundings.
    "mm": (None, r"(?<!\d-)\bmm\b"),
    "degrees": (None, r"\bdeg\b|degrees\b"),
}
_NUMBER = r"\d{1,3}(?:,\d{3})+(?:\.\d+)?|\d+(?:\.\d+)?"
_NUMBER_TOKEN = re.compile(rf"(?<![\w.])(?:{_NUMBER})(?![\d.]?[A-Za-wyz\d])")  # not a commit, a version, 1e-6
_VALUE = rf"(?:{_NUMBER})(?:(?:\s?(?:±|-|–|/|->)\s?| and | or | to | against )(?:{_NUMBER}))*"
_WITH_UNIT = re.compile(
    rf"(?<![\w.,/±-])(?P<value>{_VALUE})(?P<gap>\s?)(?:"
    + "|".join(f"(?P<{kind}>{written})" for kind, (written, _) in UNITS.items() if written)
    + ")"
)
_NAMED = {kind: re.compile(named) for kind, (_, named) in UNITS.items()}
_OUT_OF = re.compile(rf"(?<![\w.,/±-])({_NUMBER}) of ({_NUMBER})(?![\d.]|,\d)(?!\s?(?:px|%|s|ms|min)\b)")
_COMPOUND = re.compile(r"-(?:px|mm)\b")  # a 224-px camera
_OTHER_UNIT = re.compile(r"\)?\s?(?:cm|m|m/s|rad|Hz|°|M)(?![\w/])")  # 5.5 cm, 1.5 m/s, 7.5M parameters
_SETTINGS_HEADER = re.compile(r"\b(?:default|limit|option|setting)s?\b", re.IGNORECASE)
_DEFAULT = re.compile(r"\bby default\b|\(default\b|\bdefault:", re.IGNORECASE)  # 64 MiB by default

NOT_MEASURED: dict[tuple[str, str], str] = {
    # (file, claim as written): why it is not a measured result
    ("README.md", "2.1 GB"): "the download size of the libero extra: a property of a third-party package",
    ("docs/installation.md", "2.1 GB"): "the download size of the libero extra: a property of a third-party package",
    ("docs/drawanything.md", "15 px"): "the cursor's radius: the geometry of the authors' DrawAnything-Sim",
    ("docs/drawanything.md", "724.1 px"): "the 512-px canvas's diagonal, the score of empty ink by definition",
    ("docs/drawanything.md", "10-30 px"): "the scripted demonstrator's speed range per step: a setting",
    ("src/bpp/benchmarks/lerobot/commands.py", "32 px"): "the smallest frame the AV1 encoder takes: a limit",
    ("src/bpp/benchmarks/draw/studio/state.py", "0.1 px"): "the resolution polylines are rounded to: a setting",
    ("docs/libero-gen/combination.md", "15 of 20"): "how many of the appendix's 20 counts another reading of the "
    "published task list reproduces: a fact of published data",
}
"""Claims that state a setting, a definition or a published fact rather than a measured result."""


class Place(NamedTuple):
    line: int
    own: str
    """The text whose numbers are read (a sentence, or a table cell), line breaks kept."""
    around: str
    """What may name their unit (the sentence; or the cell, its column's header, its row, the table's caption)."""
    settings: bool
    """A cell of a table of settings, or a sentence or cell that gives a default: no claims there."""


# ----------------------------------------------------------------------------------------------------- reading


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _normal(number: str) -> str:
    return number.replace(",", "")


def _prose(text: str) -> list[tuple[int, str]]:
    """(line number, line) outside fenced code blocks, inline code blanked."""
    lines, fenced = [], False
    for number, line in enumerate(text.splitlines(), 1):
        if re.match(r"^\s{0,3}(`{3,}|~{3,})", line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, re.sub(r"(`+)(?:(?!\1).)+?\1", "", line)))
    return lines


def _sentences(paragraph: list[tuple[int, str]]) -> list[Place]:
    text, starts = "", []
    for number, line in paragraph:
        starts.append((len(text), number))
        text += line.strip() + "\n"
    out, start = [], 0
    for match in [*re.finditer(r"(?<=[.;:!?])\s+(?=[A-Z(*\d])", text), None]:
        end = match.start() if match else len(text)
        sentence = text[start:end].strip()
        if sentence:
            line = max(number for offset, number in starts if offset <= start)
            out.append(Place(line, sentence, sentence, bool(_DEFAULT.search(sentence))))
        start = match.end() if match else end
    return out


def places(text: str) -> list[Place]:
    """Every sentence of `text`'s prose and every cell of its tables."""
    out, header, settings, paragraph, caption = [], None, False, [], ""
    for number, line in [*_prose(text), (0, "")]:
        if line.lstrip().startswith("|"):
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            if header is None:
                header, settings = cells, any(_SETTINGS_HEADER.search(cell) for cell in cells)
                caption = " ".join(words for _, words in paragraph) or caption
                out += _sentences(paragraph)
                paragraph = []
            elif not all(re.fullmatch(r":?-{3,}:?", cell) for cell in cells):
                for i, cell in enumerate(cells):
                    name = header[i] if i < len(header) else ""
                    default = bool(_DEFAULT.search(cell) or _DEFAULT.search(name))
                    around = " || ".join((cell, name, " | ".join(cells), caption))
                    out.append(Place(number, cell, around, settings or default))
            continue
        header = None
        if line.strip():
            paragraph.append((number, line))
        elif paragraph:
            out += _sentences(paragraph)
            caption, paragraph = " ".join(words for _, words in paragraph), []
    return out


def _named(around: str) -> frozenset[str]:
    return frozenset(kind for kind, named in _NAMED.items() if named.search(around))


def _with_units(flat: str) -> list[tuple[tuple[int, int], str, str, list[str]]]:
    """(span, as written, kind, numbers) of each number, range or list written with its unit in `flat`."""
    out = []
    for match in _WITH_UNIT.finditer(flat):
        if not match["gap"] and _COMPOUND.match(flat, match.end("value")):
            continue
        if match["ratio"] == "x" and match["gap"]:
            continue  # 500 x 5: a product
        values = [_normal(value) for value in re.findall(_NUMBER, match["value"])]
        out.append((match.span(), match[0].strip(), match.lastgroup, values))
    return out


def claims(text: str) -> list[tuple[int, str, frozenset[str], list[str]]]:
    """(line, claim as written, the kinds of unit it may have, its numbers) for every claim of `text`."""
    out = []
    for place in places(text):
        if place.settings:
            continue
        flat = place.own.replace("\n", " ")
        found = [(span, written, frozenset({kind}), values) for span, written, kind, values in _with_units(flat)]
        found += [
            (m.span(), m[0], frozenset({"count"}), [f"{_normal(m[1])} of {_normal(m[2])}"])
            for m in _OUT_OF.finditer(flat)
        ]
        kinds = _named(place.around.replace("\n", " "))
        surely = r"\." if place.own == place.around else r"[.,]"  # in a table, numbers over 999 too
        for match in _NUMBER_TOKEN.finditer(flat):
            taken = any(start <= match.start() < end for (start, end), *_ in found)
            if kinds and not taken and re.search(surely, match[0]) and not _OTHER_UNIT.match(flat, match.end()):
                found.append((match.span(), match[0], kinds, [_normal(match[0])]))
        out += [(place.line + place.own.count("\n", 0, span[0]), *rest) for span, *rest in sorted(found)]
    return out


def measured(text: str) -> dict[str, set[str]]:
    """Kind of unit -> the numbers `text` states with that kind; "count" -> "N of M" for every number N and every
    number M of the same place."""
    found: dict[str, set[str]] = {kind: set() for kind in [*UNITS, "count"]}
    for place in places(text):
        own, around = place.own.replace("\n", " "), place.around.replace("\n", " ")
        numbers = {_normal(n) for n in _NUMBER_TOKEN.findall(own)}
        found["count"] |= {f"{n} of {_normal(m)}" for n in numbers for m in _NUMBER_TOKEN.findall(around)}
        for _, _, kind, values in _with_units(own):
            found[kind] |= set(values)
            numbers -= set(values)
        for kind in _named(around):
            found[kind] |= numbers
    return found


def _agrees(kinds: frozenset[str], values: list[str], sources: dict[str, set[str]]) -> bool:
    return any(all(value in sources[kind] for value in values) for kind in kinds)


def disagreements(path: str, text: str, sources: dict[str, set[str]], first_line: int = 1) -> list[str]:
    """The claims of `text` (of the file `path`) that `sources` does not hold, less :data:`NOT_MEASURED`."""
    return [
        f"{path}:{line + first_line - 1}: {claim!r} ({'/'.join(sorted(kinds))})"
        for line, claim, kinds, values in claims(text)
        if (path, claim) not in NOT_MEASURED and not _agrees(kinds, values, sources)
    ]


def _document_text(doc: Path) -> str:
    """A document's text; docs/results.md's without the paper's numbers it quotes (a source, not a claim)."""
    text = doc.read_text(encoding="utf-8")
    return text[: text.index(PAPER_HEADING)] if doc == RESULTS_PAGE else text


@functools.cache
def sources() -> dict[str, set[str]]:
    """BENCHMARKS.md's numbers and the paper's, by kind of unit."""
    paper = RESULTS_PAGE.read_text(encoding="utf-8")
    current, published = measured(BENCHMARKS.read_text(encoding="utf-8")), measured(paper[paper.index(PAPER_HEADING) :])
    return {kind: current[kind] | published[kind] for kind in current}


def _is_dataclass(node: ast.ClassDef) -> bool:
    return any(ast.unparse(d).split("(")[0].endswith("dataclass") for d in node.decorator_list)


def source_texts(path: Path) -> list[tuple[int, str]]:
    """(first line, text on one line) of the texts of a module that must quote BENCHMARKS.md's numbers: the
    docstrings of its dataclasses and of their fields (a command's ``--help``), and every docstring, string and
    comment block that cites BENCHMARKS.md."""
    source = path.read_text(encoding="utf-8")
    tree = ast.parse(source)
    help_texts = {
        id(statement.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef) and _is_dataclass(node)
        for statement in node.body
        if isinstance(statement, ast.Expr) and isinstance(statement.value, ast.Constant)
    }
    texts = [
        (node.lineno, node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant)
        and isinstance(node.value, str)
        and (id(node) in help_texts or "BENCHMARKS.md" in node.value)
    ]
    comments: list[tuple[int, str]] = []
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            line, text = token.start[0], token.string.lstrip("#").strip()
            if comments and comments[-1][0] + comments[-1][1].count("\n") + 1 == line:
                comments[-1] = (comments[-1][0], comments[-1][1] + "\n" + text)
            else:
                comments.append((line, text))
    texts += [(line, text) for line, text in comments if "BENCHMARKS.md" in text]
    return sorted({(line, " ".join(text.split())) for line, text in texts})


# ----------------------------------------------------------------------------------------------------- the rules


def test_benchmarks_md_stays_short():
    lines = len(BENCHMARKS.read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_BENCHMARKS_LINES, (
        f"BENCHMARKS.md has {lines} lines, more than {MAX_BENCHMARKS_LINES}: it holds current results only (older ones "
        "are in its git history; how things work belongs in docs/)"
    )


@pytest.mark.parametrize("doc", DOCUMENTS, ids=_rel)
def test_measured_numbers_in_the_documents_are_those_of_benchmarks_md(doc):
    problems = disagreements(_rel(doc), _document_text(doc), sources())
    assert not problems, "numbers BENCHMARKS.md does not hold (fix the text, or list a setting in NOT_MEASURED):\n" + (
        "\n".join(problems)
    )


def test_source_texts_that_cite_benchmarks_md_quote_its_numbers():
    current = sources()
    problems = [
        problem
        for path in sorted(SOURCE.rglob("*.py"))
        for line, text in source_texts(path)
        for problem in disagreements(_rel(path), text, current, first_line=line)
    ]
    assert not problems, "numbers BENCHMARKS.md does not hold:\n" + "\n".join(problems)


def test_not_measured_lists_only_what_it_needs():
    """Each entry names a claim that is still in its document and that BENCHMARKS.md does not hold."""
    current, needed = sources(), set()
    texts = [(_rel(doc), _document_text(doc)) for doc in DOCUMENTS]
    texts += [(_rel(path), text) for path in sorted(SOURCE.rglob("*.py")) for _, text in source_texts(path)]
    for path, text in texts:
        needed |= {(path, claim) for _, claim, kinds, values in claims(text) if not _agrees(kinds, values, current)}
    assert set(NOT_MEASURED) <= needed, f"entries no longer needed: {sorted(set(NOT_MEASURED) - needed)}"


def test_the_rule_sees_what_it_checks():
    """Claims are found and matched as the module's docstring says."""
    text = (
        "It took 39.9 min with the install (26.5-39.4 on another host) and scored 18.84 ± 0.79 px (20.40 on the "
        "other) with a 224-px camera: 2.4x faster, 28-33-fold, 1,390 samples/s, 839 demonstrations per hour,\n"
        "31 of 50, 62% and 10 min 25 s; 500 x 5 demonstrations, 146 second steps, 1.5 m/s. 64 MiB by default.\n\n"
        "```\nbpp demo  # 99.9 px\n```\n\nScores:\n\n"
        "| question | score |\n| --- | ---: |\n| Chamfer px, [a link](x.md) | 10.08 |\n\n"
        "| limit | value |\n| --- | --- |\n| file size | 16 MiB |\n"
    )
    found = claims(text)
    assert [(line, claim, values) for line, claim, _, values in found] == [
        (1, "39.9 min", ["39.9"]),
        (1, "26.5", ["26.5"]),
        (1, "39.4", ["39.4"]),
        (1, "18.84 ± 0.79 px", ["18.84", "0.79"]),
        (1, "20.40", ["20.40"]),
        (1, "2.4x", ["2.4"]),
        (1, "28-33-fold", ["28", "33"]),
        (1, "1,390 samples/s", ["1390"]),
        (1, "839 demonstrations per hour", ["839"]),
        (2, "31 of 50", ["31 of 50"]),
        (2, "62%", ["62"]),
        (2, "10 min", ["10"]),
        (2, "25 s", ["25"]),
        (12, "10.08", ["10.08"]),
    ]
    kinds = [kinds for _, _, kinds, _ in found]
    assert kinds[0] == {"min"} and kinds[3] == {"px"} and kinds[5] == {"ratio"} and kinds[9] == {"count"}
    assert {"min", "px"} <= kinds[1] == kinds[2] == kinds[4] and kinds[13] == {"px"}  # from the sentence, the row

    table = "Main job:\n\n| run | time (min) | score (px) |\n| --- | ---: | ---: |\n| main | 39.9 | 18.84 |\n\n"
    table += "It took 10 s."
    numbers = measured(table)
    assert "39.9" in numbers["min"] and "39.9" not in numbers["px"] and "18.84" in numbers["px"]
    assert "10" in numbers["s"] and "10" not in numbers["min"]
    assert disagreements("x.md", "It scored 18.84 px in 39.9 min.", numbers) == []
    assert disagreements("x.md", "It scored 18.8 px in 18.84 min.", numbers) == [
        "x.md:1: '18.8 px' (px)",
        "x.md:1: '18.84 min' (min)",
    ]
