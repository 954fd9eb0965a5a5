"""BDDL, LIBERO's task language, as data: parse a problem into nested lists, edit it, and write it back.

A BDDL problem is one S-expression: ``(define (problem NAME) (:domain robosuite) (:language words ...)
(:regions ...) (:fixtures ...) (:objects ...) (:obj_of_interest ...) (:init ...) (:goal ...))``. :func:`parse`
keeps every token as a string and the order of everything, so ``parse(dumps(parse(text))) == parse(text)``;
:func:`dumps` writes one section per line group, indented, in the layout LIBERO's own files use.

The suites build their problems with it (Combination's in :mod:`bpp.benchmarks.libero.suites`, Chain's in
:mod:`bpp.benchmarks.libero.chain`); this module knows the language, not the tasks.
"""

from __future__ import annotations

import re

from bpp.errors import UserError

Expr = str | list

_TOKEN = re.compile(r"\(|\)|[^\s()]+")


class BDDLError(UserError):
    """A BDDL text that is not a well-formed problem; the message says where."""


def parse(text: str) -> list:
    """The S-expression of a BDDL problem (comments after ``;`` are dropped)."""
    text = "\n".join(line.split(";", 1)[0] for line in text.splitlines())
    stack: list[list] = [[]]
    for match in _TOKEN.finditer(text):
        token = match.group()
        if token == "(":
            stack.append([])
        elif token == ")":
            if len(stack) == 1:
                raise BDDLError(f"unbalanced ')' at character {match.start()}")
            done = stack.pop()
            stack[-1].append(done)
        else:
            stack[-1].append(token)
    if len(stack) != 1:
        raise BDDLError(f"{len(stack) - 1} unclosed '(' at the end")
    if len(stack[0]) != 1 or not isinstance(stack[0][0], list) or stack[0][0][:1] != ["define"]:
        raise BDDLError("expected one (define (problem ...) ...) expression")
    return stack[0][0]


def dumps(problem: list) -> str:
    """BDDL text for a parsed problem (sections on their own lines, nested lists indented)."""
    lines = [f"(define {_flat(problem[1])}"]
    for section in problem[2:]:
        lines.append(_block(section, 1))
    lines.append(")")
    return "\n".join(lines) + "\n"


def _flat(expr: Expr) -> str:
    return expr if isinstance(expr, str) else "(" + " ".join(_flat(e) for e in expr) + ")"


def _block(expr: Expr, depth: int) -> str:
    pad = "  " * depth
    if isinstance(expr, str) or all(isinstance(e, str) for e in expr) or len(_flat(expr)) <= 60:
        return pad + _flat(expr)
    head = [e for e in expr if isinstance(e, str)]
    if head != expr[: len(head)]:  # a string after a list: keep it flat rather than reorder
        return pad + _flat(expr)
    inner = "\n".join(_block(e, depth + 1) for e in expr[len(head) :])
    return f"{pad}({' '.join(head)}\n{inner}\n{pad})"


def section(problem: list, name: str) -> list:
    """The section ``(:name ...)`` of a problem (a BDDLError if it has none)."""
    for part in problem[2:]:
        if isinstance(part, list) and part[:1] == [name]:
            return part
    raise BDDLError(f"the problem has no ({name} ...) section")


def set_section(problem: list, name: str, body: list) -> None:
    """Replace the contents of section `name` (its items after the name)."""
    part = section(problem, name)
    part[1:] = body


def objects(problem: list, sections: tuple[str, ...] = (":fixtures", ":objects")) -> list[str]:
    """The names in the problem's ``(:objects a b - type ...)`` and ``(:fixtures ...)`` sections (or `sections`)."""
    names = []
    for name in sections:
        tokens = section(problem, name)[1:]
        names += [t for i, t in enumerate(tokens) if t != "-" and (i == 0 or tokens[i - 1] != "-")]
    return names
