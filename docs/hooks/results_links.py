"""MkDocs hook: the links of text included from the repository's root, rewritten for the site.

The results page includes the repository's BENCHMARKS.md (pymdownx.snippets), so that the results have one source.
BENCHMARKS.md is written to be read at the repository's root, on GitHub for instance, so its relative links start
there: ``docs/figures/x.png``, ``docs/training.md#resume``, ``bench/x.py``, ``README.md``. The site is built from
docs/ alone, where those links would be broken. A page marks the included text with two comments::

    <!-- root-relative -->
    --8<-- "BENCHMARKS.md"
    <!-- /root-relative -->

and, once the snippet is in, this hook rewrites every link between the markers: a file under docs/ becomes a link
relative to the page, BENCHMARKS.md itself becomes the including page, and any other file of the repository (a
script, the README) becomes its text alone, since the site has no copy of it. Links that name a scheme, start with
a slash or are only an anchor are kept. The rewritten links are then checked by MkDocs like any other.
"""

from __future__ import annotations

import posixpath
import re

from markdown import Extension
from markdown.preprocessors import Preprocessor

BEGIN, END = "<!-- root-relative -->", "<!-- /root-relative -->"
DOCS = "docs/"
INCLUDED_AS_PAGE = {"BENCHMARKS.md"}
"""Repository files that a page of the site includes whole: links to them go to that page."""

_INLINE = re.compile(
    r"(?P<bang>!?)\[(?P<text>(?:[^\[\]]|\[[^\]]*\])*)\]\(\s*<?(?P<target>[^)\s>]*)>?(?P<title>\s+\"[^\"]*\")?\s*\)"
)
_REFERENCE = re.compile(r"^(?P<head>\s{0,3}\[[^\]]+\]:\s*)<?(?P<target>\S+?)>?(?P<tail>\s.*)?$")
_HTML_SRC = re.compile(r"(?P<attr>\b(?:src|href)=)\"(?P<target>[^\"]*)\"")
_FENCE = re.compile(r"^\s{0,3}(```|~~~)")

_page = {"src_uri": ""}


def _site_target(target: str, page_dir: str, page_name: str) -> str | None:
    """`target` (relative to the repository's root) as seen from the page; None if the site has no such file."""
    if not target or target.startswith(("#", "/")) or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):
        return target
    path, hash_, anchor = target.partition("#")
    path = posixpath.normpath(path)
    if path in INCLUDED_AS_PAGE:
        return f"#{anchor}" if hash_ else page_name
    if path.startswith(DOCS):
        return posixpath.relpath(path[len(DOCS) :], page_dir or ".") + hash_ + anchor
    return None


def _rewrite_line(line: str, page_dir: str, page_name: str) -> str:
    def inline(match: re.Match) -> str:
        new = _site_target(match["target"], page_dir, page_name)
        if new is None:
            return match["text"]
        return f"{match['bang']}[{match['text']}]({new}{match['title'] or ''})"

    def html(match: re.Match) -> str:
        new = _site_target(match["target"], page_dir, page_name)
        return f'{match["attr"]}"{new if new is not None else "#"}"'

    reference = _REFERENCE.match(line)
    if reference:
        new = _site_target(reference["target"], page_dir, page_name)
        return f"{reference['head']}{new if new is not None else '#'}{reference['tail'] or ''}"
    return _HTML_SRC.sub(html, _INLINE.sub(inline, line))


class _RootRelative(Preprocessor):
    def run(self, lines: list[str]) -> list[str]:
        src_uri = _page["src_uri"]
        page_dir, page_name = posixpath.dirname(src_uri), posixpath.basename(src_uri)
        out, inside, fenced = [], False, False
        for line in lines:
            if line.strip() == BEGIN:
                inside = True
                continue
            if line.strip() == END:
                inside = False
                continue
            if inside and _FENCE.match(line):
                fenced = not fenced
            out.append(_rewrite_line(line, page_dir, page_name) if inside and not fenced else line)
        return out


class _Extension(Extension):
    def extendMarkdown(self, md):  # noqa: N802 (Python-Markdown's name)
        # After pymdownx.snippets (32) has included the text, before raw HTML is set aside (20).
        md.preprocessors.register(_RootRelative(md), "root_relative_links", 31)


def on_config(config):
    config.markdown_extensions.append(_Extension())
    return config


def on_page_markdown(markdown, page, config, files):
    _page["src_uri"] = page.file.src_uri
    return markdown
