"""The package's structure, read from its source with ``ast`` (nothing of it is imported):

1. no import cycle among bpp's modules, counting the imports a module makes when it is imported (``TYPE_CHECKING``
   imports, for annotations only, are not run and not counted);
2. imports stand at the top of their module; one inside a function imports a heavy or optional module (an extra's,
   or torch on a command that must start without it), says so in a comment on its line or the line above, and brings
   something its module's own imports do not: a third-party module of :data:`DEFERRED`, or a bpp module whose imports
   reach one;
3. a benchmark imports no other benchmark: what two share is a module outside ``bpp/benchmarks/``;
4. nothing outside ``bpp/benchmarks/`` imports a benchmark: the core and the generic layers reach one through the
   registry, by the name a store records.
"""

from __future__ import annotations

import ast
import io
import tokenize
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "bpp"

DEFERRED = {
    "torch": "two seconds to import; the command line starts without it",
    "diffusers": "imports torch",
    "transformers": "the language extra",
    "ray": "the ray extra",
    "libero": "the libero extra",
    "robosuite": "the libero extra",
    "mujoco": "the libero extra",
    "cv2": "the iphumi extra (OpenCV)",
    "av": "the lerobot extra (PyAV)",
    "datasets": "the lerobot extra",
    "huggingface_hub": "the lerobot extra",
    "pyarrow": "the lerobot extra",
    "websockets": "the serve extra",
    "openpi_client": "openpi's client, in the robot-side environment only",
    "matplotlib": "half a second to import; pictures only",
    "svgpathtools": "half a second to import; SVG drawing files only",
    "imageio": "video and GIF files only",
    "imageio_ffmpeg": "video files only",
    "zarr": "a third of a second to import; reading or writing a store only",
    "fastapi": "the studio extra",
    "uvicorn": "the studio extra",
    "h11": "the studio extra (uvicorn's HTTP/1.1 parser)",
    "triton": "torch's compiler, loaded before LIBERO's renderer (in that order only)",
}
"""Third-party modules a function may import where it needs them, and why they are not imported with the module."""

LOCAL_BY_DESIGN = {
    ("bpp.launch", "bpp.cli"): "the program's signal handlers are in place before the command line loads",
}
"""(module, bpp module) pairs imported inside a function for a reason other than weight."""


@dataclass
class Module:
    name: str
    path: Path
    is_package: bool
    imports: list[tuple[str, bool, int, int]] = field(default_factory=list)
    """(imported module, inside a function, first line, last line) for every import run when the module is."""
    typing_imports: list[str] = field(default_factory=list)
    """Modules imported under ``if TYPE_CHECKING:`` (annotations only)."""
    comments: set[int] = field(default_factory=set)
    """Lines that hold a comment."""
    comment_lines: set[int] = field(default_factory=set)
    """Lines that hold a comment alone."""
    blank_lines: set[int] = field(default_factory=set)
    """Lines that hold nothing."""


def _name(path: Path) -> tuple[str, bool]:
    parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
    package = parts[-1] == "__init__"
    return ".".join(parts[:-1] if package else parts), package


@cache
def modules() -> dict[str, Module]:
    found = {}
    for path in sorted(SRC.rglob("*.py")):
        name, package = _name(path)
        found[name] = Module(name, path, package)
    for module in found.values():
        _read(module, found)
    return found


def _resolve(target: str, known: dict[str, Module]) -> str:
    """The bpp module that importing `target` loads last (a name imported from a module is that module)."""
    while target not in known and "." in target:
        target = target.rpartition(".")[0]
    return target


def _read(module: Module, known: dict[str, Module]) -> None:
    source = module.path.read_text()
    module.blank_lines = {n for n, line in enumerate(source.splitlines(), 1) if not line.strip()}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            module.comments.add(token.start[0])
            if not token.line[: token.start[1]].strip():
                module.comment_lines.add(token.start[0])
    package = module.name if module.is_package else module.name.rpartition(".")[0]

    def targets(node: ast.Import | ast.ImportFrom) -> list[str]:
        if isinstance(node, ast.Import):
            return [alias.name for alias in node.names]
        base = node.module or ""
        if node.level:
            parts = package.split(".")
            base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
        if base.split(".")[0] != "bpp":
            return [base]
        return [_resolve(f"{base}.{alias.name}", known) for alias in node.names]

    def visit(node: ast.AST, local: bool, typing: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child, True, typing)
            elif isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                for part in child.body:
                    visit(ast.Module(body=[part], type_ignores=[]), local, True)
                for part in child.orelse:
                    visit(ast.Module(body=[part], type_ignores=[]), local, typing)
            elif isinstance(child, (ast.Import, ast.ImportFrom)):
                for target in targets(child):
                    if typing:
                        module.typing_imports.append(target)
                    else:
                        module.imports.append((target, local, child.lineno, child.end_lineno or child.lineno))
            else:
                visit(child, local, typing)

    visit(ast.parse(source), False, False)


def _loads(importer: str, target: str) -> list[str]:
    """The bpp modules that importing `target` from `importer` runs: it and its packages, but for those of the
    importer itself (already imported by then)."""
    known = modules()
    parts = target.split(".")
    chain = [".".join(parts[:i]) for i in range(1, len(parts) + 1)]
    own = {".".join(importer.split(".")[:i]) for i in range(1, importer.count(".") + 2)}
    return [m for m in chain if m in known and m not in own and m != importer]


@cache
def graph() -> dict[str, set[str]]:
    """Module -> the bpp modules its import runs (imports at module level)."""
    edges = {}
    for name, module in modules().items():
        targets = [target for target, local, *_ in module.imports if not local and target.startswith("bpp")]
        edges[name] = {loaded for target in targets for loaded in _loads(name, target)}
    return edges


@cache
def third_party(name: str) -> frozenset[str]:
    """The third-party top-level packages that importing bpp module `name` imports, through bpp modules too."""
    seen, todo, found = {name}, [name], set()
    while todo:
        module = todo.pop()
        for target, local, *_ in modules()[module].imports:
            if not local and not target.startswith("bpp"):
                found.add(target.split(".")[0])
        for other in graph()[module] - seen:
            seen.add(other)
            todo.append(other)
    return frozenset(found)


def _cycles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan's algorithm, iteratively)."""
    edges = graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def _benchmark(name: str) -> str | None:
    """The benchmark folder a module lies in (``draw`` for bpp.benchmarks.draw.env), or None."""
    parts = name.split(".")
    return parts[2] if len(parts) > 2 and parts[:2] == ["bpp", "benchmarks"] else None


def _all_imports(module: Module) -> list[str]:
    return [target for target, *_ in module.imports] + module.typing_imports


def test_the_modules_import_each_other_in_no_circle():
    assert len(modules()) > 100  # the package was read
    cycles = _cycles()
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def _commented(module: Module) -> set[int]:
    """The first lines of the function-local imports that a comment explains: one on its lines or the line above; a
    comment above a run of imports (nothing but blank lines between them) explains them all."""
    local = sorted({(first, last) for _, is_local, first, last in module.imports if is_local})
    explained, previous = set(), None
    for first, last in local:
        own = bool(module.comments & set(range(first, last + 1))) or first - 1 in module.comment_lines
        run = previous is not None and set(range(previous[1] + 1, first)) <= module.blank_lines
        if own or (run and previous[0] in explained):
            explained.add(first)
        previous = (first, last)
    return explained


def test_imports_stand_at_the_top_but_heavy_or_optional_ones():
    offences = []
    for name, module in modules().items():
        own, commented = third_party(name), _commented(module)
        for target, local, first, _ in module.imports:
            if not local or (name, target) in LOCAL_BY_DESIGN:
                continue
            where = f"{module.path.relative_to(SRC.parent)}:{first}: {target}"
            if target.startswith("bpp"):
                if not (third_party(target) - own) & DEFERRED.keys():
                    offences.append(f"{where} (a bpp module that imports nothing heavy: import it at the top)")
                    continue
            elif target.split(".")[0] not in DEFERRED:
                offences.append(f"{where} (light or always installed: import it at the top)")
                continue
            elif target.split(".")[0] in own:
                offences.append(f"{where} (the module imports it already: import it at the top)")
                continue
            if first not in commented:
                offences.append(f"{where} (say in a comment why it is imported here)")
    assert not offences, "\n".join(offences)


def test_a_benchmark_imports_no_other_benchmark():
    offences = []
    for name, module in modules().items():
        own = _benchmark(name)
        if own is None:
            continue
        for target in _all_imports(module):
            other = _benchmark(target)
            if other is not None and other != own:
                offences.append(f"{name} imports {target}")
    assert not offences, offences


def test_the_core_and_generic_layers_import_no_benchmark():
    offences = [
        f"{name} imports {target}"
        for name, module in modules().items()
        if not name.startswith("bpp.benchmarks")
        for target in _all_imports(module)
        if target.startswith("bpp.benchmarks")
    ]
    assert not offences, offences
