"""The documentation's references resolve inside the repository.

README.md, BENCHMARKS.md and the guides in docs/ (built as a site by ``mkdocs build --strict``, which checks the
site's own links) must hold up on their own, as GitHub shows them: every relative link names a file of the
repository and every ``#anchor`` a heading of its target (GitHub's heading slugs, which the site uses too); no text
in the repository points at a ``shared`` folder beside it; and every ``bench/`` script the documents name exists.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
DOCUMENTS = sorted(
    [p for p in (ROOT / "README.md", ROOT / "BENCHMARKS.md") if p.exists()] + list(DOCS.rglob("*.md")),
    key=lambda p: p.relative_to(ROOT).as_posix(),
)
TEXT_TREES = ("docs", "src", "tests", "bench")
SKIPPED_DIRS = {"__pycache__", ".site"}

_FENCE = re.compile(r"^\s{0,3}(`{3,}|~{3,})")
_CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")
_INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
_REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s.*)?$")
_HTML_LINK = re.compile(r"\b(?:href|src)=\"([^\"]*)\"")
_HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
_HTML_ANCHOR = re.compile(r"<a\s+(?:name|id)=\"([^\"]+)\"")
_SNIPPET = re.compile(r"^\s*--8<--\s+\"([^\"]+)\"\s*$")
_BENCH_SCRIPT = re.compile(r"(?<![\w/.-])bench/([\w.-]+\.(?:py|sh))\b")


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _prose_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, line) outside fenced code blocks, with inline code spans blanked."""
    lines, fenced = [], False
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, _CODE_SPAN.sub("", line)))
    return lines


def _expanded_lines(path: Path) -> list[str]:
    """The file's lines with pymdownx.snippets inclusions (``--8<-- "FILE"``, from the repository's root) expanded, as
    the site shows the page."""
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        match = _SNIPPET.match(line)
        out.extend(_expanded_lines(ROOT / match[1]) if match else [line])
    return out


def github_slug(heading: str) -> str:
    """GitHub's anchor for a heading: its text, lower case, without punctuation, spaces as hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text
    text = re.sub(r"<[^>]+>", "", text)  # HTML tags
    text = re.sub(r"(?<!\w)_+|_+(?!\w)", "", text)  # _emphasis_, not snake_case
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor a link may name in `path`: its headings' slugs (repeats numbered as GitHub does) and HTML
    anchors."""
    found, seen, fenced = set(), {}, False
    for line in _expanded_lines(path):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            continue
        found.update(_HTML_ANCHOR.findall(line))
        heading = _HEADING.match(line)
        if heading:
            slug = github_slug(heading[2])
            found.add(f"{slug}-{seen[slug]}" if slug in seen else slug)
            seen[slug] = seen.get(slug, 0) + 1
    return found


def links(path: Path) -> list[tuple[int, str]]:
    """(line number, target) of every link and image in `path`'s prose."""
    out = []
    for number, line in _prose_lines(path):
        reference = _REFERENCE.match(line)
        targets = [reference[1]] if reference else _INLINE_LINK.findall(line) + _HTML_LINK.findall(line)
        out.extend((number, target) for target in targets)
    return out


def _is_external(target: str) -> bool:
    return bool(re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target)) or target.startswith("//")


@pytest.mark.parametrize("doc", DOCUMENTS, ids=_rel)
def test_relative_links_and_anchors_resolve_inside_the_repository(doc):
    problems = []
    for number, target in links(doc):
        if not target or _is_external(target):
            continue
        where = f"{_rel(doc)}:{number}: {target}"
        path_part, _, anchor = target.partition("#")
        if path_part.startswith("/"):
            problems.append(f"{where}: an absolute path (write it relative to the file)")
            continue
        resolved = (doc.parent / path_part).resolve() if path_part else doc
        try:
            inside = resolved.relative_to(ROOT)
        except ValueError:
            problems.append(f"{where}: outside the repository")
            continue
        if not resolved.exists():
            problems.append(f"{where}: no such file")
            continue
        if doc.is_relative_to(DOCS) and not resolved.is_relative_to(DOCS):
            problems.append(f"{where}: the site holds only docs/, not {inside.as_posix()}")
            continue
        if anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            problems.append(f"{where}: no heading with the anchor #{anchor} in {inside.as_posix()}")
    assert not problems, "\n".join(problems)


def _text_files():
    yield from (p for p in (ROOT / "README.md", ROOT / "BENCHMARKS.md") if p.exists())
    for tree in TEXT_TREES:
        for path in sorted((ROOT / tree).rglob("*")):
            parts = set(path.relative_to(ROOT).parts)
            if path.is_file() and not parts & SKIPPED_DIRS and not any(p.endswith(".egg-info") for p in parts):
                yield path


def _lines_where(matches, paths) -> list[str]:
    """``path:number: line`` for every line of the text files among `paths` that `matches`."""
    found = []
    for path in paths:
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue  # not text
        found += [f"{_rel(path)}:{n}: {line.strip()}" for n, line in enumerate(text.splitlines(), 1) if matches(line)]
    return found


def test_nothing_points_outside_the_repository_at_shared():
    needle = "../" + "shared"  # spelt in two pieces, so that this file does not match itself
    problems = _lines_where(lambda line: needle in line, _text_files())
    assert not problems, "\n".join(problems)


_TRACKER_NOTE = re.compile(r"(?i:\bissue\s*#?\s*\d+|\bin" + r" progress\b)|\b(?:TO" + r"DO|FIX" + r"ME|X" + r"XX)\b")
"""Notes that belong in an issue tracker, not in the project's files (spelt in pieces so as not to match here)."""


def test_no_tracker_notes_in_the_code_docs_or_benchmarks():
    paths = [*_text_files(), ROOT / "README.md", ROOT / "BENCHMARKS.md"]
    problems = _lines_where(_TRACKER_NOTE.search, paths)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("doc", DOCUMENTS, ids=_rel)
def test_named_bench_scripts_exist(doc):
    missing = [
        f"{_rel(doc)}:{number}: bench/{script}"
        for number, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1)
        for script in _BENCH_SCRIPT.findall(line)
        if not (ROOT / "bench" / script).is_file()
    ]
    assert not missing, "\n".join(missing)


def test_the_checks_see_what_they_check():
    assert github_slug("LIBERO-Gen Combination") == "libero-gen-combination"
    assert github_slug("The paper's numbers") == "the-papers-numbers"
    assert github_slug("`bpp eval` and its options") == "bpp-eval-and-its-options"
    assert github_slug("Overriding model fields: ablations") == "overriding-model-fields-ablations"
    results = anchors(DOCS / "results.md")
    assert "the-papers-numbers" in results and len(results) > 1  # the page's own headings and BENCHMARKS.md's
    assert (0, "installation.md") in [(0, target) for _, target in links(DOCS / "index.md")]
