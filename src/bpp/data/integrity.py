"""What an episode store is on disk, and how every read of one is checked.

A store's header (its root ``zarr.json``) names the format and its version, and records the SHA-256 of each array's
metadata (``arrays``), the checksum each chunk carries, by the chunk's key (``chunks``), and the SHA-256 of itself
(``digest``). Each chunk of every array ends with a crc32c checksum of its compressed bytes (zarr's ``crc32c`` codec,
after zstd), and every chunk is written, even one that holds only zeros.

Opening a store checks the header and each array's metadata against their digests (:func:`read_header`), so that
changed statistics, tasks, shapes or a deleted array are refused. Every chunk read is checked by one function,
:func:`chunk_problem`: it must be there, match the checksum it carries, and carry the checksum the header records for
its key, so that a chunk of another store, or from elsewhere in this one, is refused as much as a damaged one. A
StoreError names the store, the array and the chunk, where zarr alone would read the array's fill value, decode
changed bytes or read the wrong data.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
from google_crc32c import value as _crc32c  # what zarr's own crc32c codec uses (a requirement of zarr since 3.1)

from bpp.errors import UserError
from bpp.utils import read_json

FORMAT = "bpp-episodes"
VERSION = 3
"""1: the first format. 2: every chunk carries a crc32c checksum and is written even if it holds only zeros; the
header records digests of itself and of each array's metadata. 3: the header also records the checksum of each chunk
by its key, so that a chunk read in another's place is refused."""
READ_VERSIONS = (2, 3)
"""The versions this bpp reads: a version 2 store's chunks are checked against the checksums they carry alone."""
ZARR_FORMAT = 3

CHUNK_KEY = re.compile(r"(?P<array>.+)/c(?P<index>(?:/[0-9]+)*)")
"""A chunk's key in zarr v3's default chunk key encoding: ``data/action/c/3/0`` is chunk (3, 0) of data/action."""
ARRAY_NAME = re.compile(r"(?:data|meta|tasks)(?:/(?!\.\.?(?:/|$))[^/\\]+)+")
"""The name of an array a store may record: under data/, meta/ or tasks/, with no empty, ``.`` or ``..`` part."""


class StoreError(UserError):
    """A store is missing, incomplete, of another format/version, or used wrongly."""


class StoreBusy(StoreError):
    """Another process is writing the store's destination now."""


class StoreKeyError(StoreError, KeyError):
    """A per-step key or episode column the store does not have (a KeyError too, for callers that look one up)."""

    __str__ = Exception.__str__  # the message as written, not KeyError's quoted form


class EpisodeIndexError(StoreError, IndexError):
    """An episode index outside the store."""


def array_settings() -> dict:
    """How every array of a store is written: zstd, then a crc32c checksum of the compressed bytes, on each chunk;
    and every chunk written, even one that holds only zeros (zarr skips those by default and reads the fill value in
    their place), so that a missing chunk is damage, never data."""
    # zarr: a third of a second to import, when a store is read or written
    from zarr.codecs import Crc32cCodec, ZstdCodec

    return {"compressors": (ZstdCodec(level=5), Crc32cCodec()), "config": {"write_empty_chunks": True}}


# ------------------------------------------------------------------ chunks
def chunk_manifest(path: Path, arrays: Iterable[str]) -> dict[str, int]:
    """The checksum each chunk of `arrays` carries (its last 4 bytes, as zarr's crc32c codec writes them), by the
    chunk's key: what the header of the store being written at `path` records (``chunks``)."""
    manifest = {}
    for name in arrays:
        for file in sorted(p for p in (path / name / "c").rglob("*") if p.is_file()):
            with open(file, "rb") as f:
                f.seek(-4, os.SEEK_END)
                manifest[file.relative_to(path).as_posix()] = int.from_bytes(f.read(4), "little")
    return manifest


def chunk_problem(key: str, data: np.ndarray | None, manifest: Mapping[str, int] | None) -> str | None:
    """What is wrong with the chunk stored under `key` (its bytes, uint8, or None if there is none), or None: missing,
    failing the crc32c it carries, or carrying another checksum than the store's record of `key` (`manifest`; None
    for a version 2 store, which has none)."""
    if data is None:
        return "is missing"
    if len(data) < 4:
        return "fails its checksum"
    carried = int.from_bytes(data[-4:].tobytes(), "little")
    if _crc32c(data[:-4]) != carried:
        return "fails its checksum"
    if manifest is not None and manifest.get(key) != carried:
        return (
            "is not the chunk the store recorded there (another checksum than its record: a chunk of another store, "
            "or from elsewhere in this one)"
        )
    return None


def _checked_chunk(root, key: str, value, whole: bool, manifest: Mapping[str, int] | None):
    """`value`, what the store at `root` holds under `key` (zarr's Buffer, or None), if `key` is not a chunk's or the
    chunk is there and, if `whole`, passes :func:`chunk_problem`; else a StoreError naming the store, the array and
    the chunk."""
    chunk = CHUNK_KEY.fullmatch(key)
    if chunk is None:  # metadata, or a key zarr probes for
        return value
    if value is None:
        problem = chunk_problem(key, None, manifest)
    elif whole:
        problem = chunk_problem(key, value.as_numpy_array(), manifest)
    else:
        problem = None
    if problem is None:
        return value
    index = tuple(int(i) for i in chunk["index"].split("/")[1:])
    raise StoreError(
        f"{root}: damaged store, cannot read {chunk['array']}: its chunk {index} ({key}) {problem}; generate it again"
    )


@functools.cache
def checked_store_class() -> type:
    """A read-only zarr LocalStore that refuses a chunk :func:`chunk_problem` finds wrong with a StoreError naming the
    store, the array and the chunk: every read of an array goes through it, whoever reads. Made with the store's
    record of its chunks: ``CheckedStore(path, read_only=True, manifest=...)``."""
    # zarr: a third of a second to import, when a store is read or written
    from zarr.storage import LocalStore

    class CheckedStore(LocalStore):
        def __init__(self, root, *, read_only: bool = False, manifest: Mapping[str, int] | None = None):
            super().__init__(root, read_only=read_only)
            self.manifest = manifest

        def with_read_only(self, read_only: bool = False):
            return type(self)(self.root, read_only=read_only, manifest=self.manifest)

        async def get(self, key, prototype=None, byte_range=None):
            value = await super().get(key, prototype, byte_range)
            return _checked_chunk(self.root, key, value, byte_range is None, self.manifest)

        def get_sync(self, key, *, prototype=None, byte_range=None):  # zarr >= 3.1's synchronous reads
            value = super().get_sync(key, prototype=prototype, byte_range=byte_range)
            return _checked_chunk(self.root, key, value, byte_range is None, self.manifest)

    return CheckedStore


# ------------------------------------------------------------------ header
def header_digest(attrs: dict) -> str:
    """SHA-256 of a store's header attributes other than the digest itself, as parsed from its zarr.json."""
    content = {k: v for k, v in attrs.items() if k != "digest"}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def metadata_digest(path: Path, name: str) -> str | None:
    """SHA-256 of the metadata file of array `name` of the store at `path` (None if there is none)."""
    try:
        return hashlib.sha256((path / name / "zarr.json").read_bytes()).hexdigest()
    except (FileNotFoundError, NotADirectoryError):
        return None


def _valid_manifest(chunks, arrays: dict) -> bool:
    """Whether `chunks` is a header's record of chunk checksums: chunk keys of recorded arrays -> 32-bit values."""
    if not isinstance(chunks, dict):
        return False
    for key, value in chunks.items():
        chunk = CHUNK_KEY.fullmatch(key)
        if chunk is None or chunk["array"] not in arrays:
            return False
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < 1 << 32:
            return False
    return True


def read_header(path: str | Path) -> dict:
    """The header attributes of the episode store at `path`, checked: a zarr v3 group, of this format and a version
    this bpp reads, complete, with the header and every array's metadata matching their digests. Reads only metadata
    files; a StoreError says what is wrong, by the format marker and version first."""
    path = Path(path)
    if not path.exists():
        raise StoreError(f"{path}: no such store")
    if not (path / "zarr.json").is_file():
        if (path / ".zgroup").is_file() or (path / ".zarray").is_file():
            raise StoreError(f"{path}: a zarr format 2 folder, not an episode store (zarr format {ZARR_FORMAT})")
        raise StoreError(f"{path}: not an episode store (no zarr.json)")
    try:
        doc = read_json(path / "zarr.json", "store header")
    except UserError as err:
        raise StoreError(f"{path}: damaged store header ({err}); generate it again") from None
    if not isinstance(doc, dict):
        raise StoreError(f"{path}: damaged store header (not a zarr metadata document); generate it again")
    if doc.get("zarr_format") != ZARR_FORMAT or doc.get("node_type") != "group":
        what = f"zarr format {doc.get('zarr_format')!r}" + (
            f", a zarr {doc.get('node_type')}" if doc.get("node_type") != "group" else ""
        )
        raise StoreError(
            f"{path}: not an episode store ({what}; an episode store is a zarr format {ZARR_FORMAT} group)"
        )
    attrs = doc.get("attributes", {})
    if not isinstance(attrs, dict):
        raise StoreError(f"{path}: damaged store header (its attributes are not a mapping); generate it again")
    if attrs.get("format") != FORMAT:
        raise StoreError(f"{path}: not an episode store (format {attrs.get('format')!r}, expected {FORMAT!r})")
    version = attrs.get("version")
    readable = f"versions {' and '.join(map(str, READ_VERSIONS))}"
    if type(version) is not int or version not in READ_VERSIONS:
        if type(version) is int and 0 < version < READ_VERSIONS[0]:
            raise StoreError(
                f"{path}: store version {version}, written by an older bpp; this bpp reads {readable} "
                "(checksummed chunks): generate it again"
            )
        raise StoreError(f"{path}: store version {version!r}, this bpp reads {readable}")
    if not attrs.get("complete"):
        raise StoreError(f"{path}: incomplete store (its generation was interrupted); generate it again")
    if attrs.get("digest") != header_digest(attrs):
        raise StoreError(f"{path}: damaged store header (it does not match its digest); generate it again")
    arrays = attrs.get("arrays")
    if not isinstance(arrays, dict) or not all(isinstance(n, str) and ARRAY_NAME.fullmatch(n) for n in arrays):
        raise StoreError(f"{path}: damaged store header (no valid table of arrays); generate it again")
    if version >= 3 and not _valid_manifest(attrs.get("chunks"), arrays):
        raise StoreError(f"{path}: damaged store header (no valid table of chunk checksums); generate it again")
    for name, digest in arrays.items():
        found = metadata_digest(path, name)
        if found is None:
            raise StoreError(f"{path}: damaged store (no {name}); generate it again")
        if found != digest:
            raise StoreError(
                f"{path}: damaged store, the metadata of {name} ({name}/zarr.json) does not match its digest; "
                "generate it again"
            )
    return attrs


def is_store(path: Path) -> bool:
    """Whether `path` is a folder holding an episode store (complete or not), judged by its zarr.json alone."""
    try:
        attrs = read_json(path / "zarr.json", "store header").get("attributes", {})
    except (ValueError, AttributeError):
        return False
    return isinstance(attrs, dict) and attrs.get("format") == FORMAT
