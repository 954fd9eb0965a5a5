"""The episode store's integrity: one writer per destination, every read verified (a chunk missing, changed or
another's), merges that neither double demonstrations nor change their inputs, stores of another format or version
refused by it, and numbers in names read from ASCII digits alone."""

import json
import multiprocessing as mp
import os
import re
import shutil
import threading
import time

import numpy as np
import pytest

from bpp.cli import main
from bpp.data.destination import destination_lock
from bpp.data.integrity import CHUNK_KEY, VERSION, StoreError, header_digest
from bpp.data.merge import merge_stores
from bpp.data.store import EpisodeStore, EpisodeWriter, stored_or_made


def _fill(writer: EpisodeWriter, episodes: int = 3, offset: float = 0.0) -> None:
    t = writer.add_task("task-a", points=np.arange(6.0).reshape(3, 2))
    for e in range(episodes):
        steps = {
            "obs": np.full((3 + e, 2), e + offset, np.float32),
            "action": np.arange(3 + e, dtype=np.float64)[:, None] + offset,
            "pen": np.zeros((3 + e, 1), np.float32),  # only zeros: a chunk zarr would not write by default
        }
        writer.add_episode(steps, t, angle=0.1 * e)


def _write(path, episodes: int = 3, offset: float = 0.0, **kw) -> EpisodeStore:
    with EpisodeWriter(path, benchmark="test", chunk_steps=4, **kw) as w:
        _fill(w, episodes, offset)
    return EpisodeStore(path)


def _chunks(path, array: str) -> list:
    return sorted(p for p in (path / array / "c").rglob("*") if p.is_file())


# ----------------------------------------------------------------------------- one writer per destination


def test_a_second_writer_of_the_same_path_is_refused_and_the_first_store_kept(tmp_path):
    path = tmp_path / "s.zarr"
    first = EpisodeWriter(path, benchmark="test", chunk_steps=4)
    with pytest.raises(StoreError, match=f"{path} is being written by another writer \\(process {os.getpid()}\\)"):
        EpisodeWriter(path, benchmark="test")
    with pytest.raises(StoreError, match="being written by another writer"):
        EpisodeWriter(path, benchmark="test", overwrite=True)  # --overwrite does not take another's destination
    _fill(first)
    assert first.close().num_episodes == 3
    with pytest.raises(StoreError, match="already exists"):
        EpisodeWriter(path, benchmark="test")
    assert _write(path, episodes=1, overwrite=True).num_episodes == 1  # the lock was released with the store
    with destination_lock(path), pytest.raises(StoreError, match="being written by another writer"):
        _write(path, overwrite=True)  # work that prepares a store holds the same lock
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]
    assert EpisodeStore(path).num_episodes == 1


def test_stored_or_made_makes_a_missing_store_once_then_reuses_it(tmp_path):
    path, made = tmp_path / "s.zarr", []

    def make(path):
        made.append(path)
        return _write(path, episodes=2, overwrite=True)

    assert stored_or_made(path, make).num_episodes == 2
    assert stored_or_made(path, make).num_episodes == 2
    assert made == [path]


def test_stored_or_made_waits_for_another_writer_and_takes_its_store(tmp_path, capsys):
    path, tried = tmp_path / "s.zarr", []
    other = EpisodeWriter(path, benchmark="test", chunk_steps=4)  # another writer of the same path, still writing

    def finish_the_other():
        time.sleep(0.3)
        _fill(other, episodes=2)
        other.close()

    def make(path):
        tried.append(path)
        return _write(path, episodes=1, overwrite=True)

    thread = threading.Thread(target=finish_the_other)
    thread.start()
    store = stored_or_made(path, make, poll_s=0.02)
    thread.join()
    assert store.num_episodes == 2  # the other writer's store, not one of its own
    assert len(tried) >= 2  # refused while the other wrote, and asked again
    assert capsys.readouterr().out.count("is being written by another process; waiting for it") == 1


def _hold_a_writer(path, started, finish):
    with EpisodeWriter(path, benchmark="test", chunk_steps=4) as w:
        started.set()
        finish.wait(60)
        _fill(w, episodes=2)


def test_a_writer_in_another_process_owns_its_destination(tmp_path):
    path = tmp_path / "s.zarr"
    ctx = mp.get_context("spawn")
    started, finish = ctx.Event(), ctx.Event()
    child = ctx.Process(target=_hold_a_writer, args=(path, started, finish))
    child.start()
    try:
        assert started.wait(60)
        with pytest.raises(StoreError, match=f"being written by another writer \\(process {child.pid}\\)"):
            _write(path)
    finally:
        finish.set()
        child.join(60)
    assert child.exitcode == 0
    assert EpisodeStore(path).num_episodes == 2  # the first writer's store, not replaced


def test_a_store_that_appears_while_writing_is_never_replaced(tmp_path):
    path = tmp_path / "s.zarr"
    writer = EpisodeWriter(path, benchmark="test", chunk_steps=4)
    _fill(writer)
    _write(tmp_path / "other.zarr", episodes=1)
    shutil.copytree(tmp_path / "other.zarr", path)  # a writer that took no lock (another machine, another program)
    with pytest.raises(StoreError, match="s.zarr appeared while this store was being written"):
        writer.close()
    assert EpisodeStore(path).num_episodes == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.zarr", "s.zarr"]  # no partial, no lock left


def test_a_store_is_never_written_inside_another(tmp_path):
    outer = _write(tmp_path / "outer.zarr")
    before = outer.fingerprint()
    with pytest.raises(StoreError, match="inner.zarr is inside the episode store .*outer.zarr"):
        _write(tmp_path / "outer.zarr" / "data" / "inner.zarr")
    assert EpisodeStore(tmp_path / "outer.zarr").fingerprint() == before


# ----------------------------------------------------------------------------- every read verified


def test_every_chunk_is_written_checksummed_recorded_and_verified(tmp_path):
    store = _write(tmp_path / "s.zarr")
    assert store.attrs["version"] == VERSION == 3 and store.chunks_recorded
    assert len(_chunks(store.path, "data/pen")) == 3  # 12 steps in chunks of 4, zeros included
    files = [f for a in store.attrs["arrays"] for f in _chunks(store.path, a)]
    assert {f.relative_to(store.path).as_posix(): f.read_bytes()[-4:] for f in files} == {
        key: value.to_bytes(4, "little") for key, value in store.attrs["chunks"].items()
    }
    codecs = json.loads((store.path / "data" / "action" / "zarr.json").read_text())["codecs"]
    assert [c["name"] for c in codecs] == ["bytes", "zstd", "crc32c"]
    assert store.verify() == sum(len(_chunks(store.path, a)) for a in store.attrs["arrays"])
    np.testing.assert_array_equal(store.array("pen"), np.zeros((12, 1), np.float32))


def test_every_single_bit_flip_in_a_chunk_is_refused_naming_the_array_and_the_chunk(tmp_path):
    path = _write(tmp_path / "s.zarr").path
    chunk = path / "data" / "action" / "c" / "1" / "0"
    intact = chunk.read_bytes()
    for i in range(len(intact)):
        flipped = bytearray(intact)
        flipped[i] ^= 1 << (i % 8)
        chunk.write_bytes(bytes(flipped))
        store = EpisodeStore(path)
        message = "cannot read data/action: its chunk \\(1, 0\\) \\(data/action/c/1/0\\) fails its checksum"
        with pytest.raises(StoreError, match=f"s.zarr: damaged store, {message}"):
            store.array("action")
        with pytest.raises(StoreError, match=message):
            store["action"][4:8]  # the lazy array is checked too
        with pytest.raises(StoreError, match=message):
            store.episode(1)  # steps 3-6: chunks 0 and 1
    chunk.write_bytes(intact)
    np.testing.assert_array_equal(EpisodeStore(path).episode(1)["action"], np.arange(4.0)[:, None])


@pytest.mark.parametrize(
    ("array", "read"),
    [
        ("data/action", lambda s: s.array("action")),
        ("data/pen", lambda s: s.episode(0)),  # a chunk of zeros: its absence is not the fill value either
        ("tasks/points", lambda s: s.task_array("points", 0)),  # a drawing's strokes, say
        ("meta/angle", lambda s: s.column("angle")),
    ],
)
def test_a_deleted_chunk_is_refused_naming_the_array_and_the_chunk(tmp_path, array, read):
    path = _write(tmp_path / "s.zarr").path
    chunk = _chunks(path, array)[0]
    chunk.unlink()
    key = chunk.relative_to(path).as_posix()
    index = tuple(int(p) for p in key.split("/c/")[1].split("/"))
    message = f"damaged store, cannot read {array}: its chunk {index} ({key}) is missing"
    with pytest.raises(StoreError, match=re.escape(message)):
        read(EpisodeStore(path))


@pytest.mark.parametrize(
    "source",
    ["another store's", "another position's"],
)
def test_a_chunk_read_in_another_s_place_is_refused_naming_the_array_and_the_chunk(tmp_path, source):
    path = _write(tmp_path / "s.zarr").path
    other = _write(tmp_path / "other.zarr", offset=10.0).path  # the same layout, other numbers
    chunk = path / "data" / "action" / "c" / "1" / "0"
    donor = other / "data" / "action" / "c" / "1" / "0" if source == "another store's" else path / "data/action/c/2/0"
    shutil.copyfile(donor, chunk)  # a whole chunk, matching the checksum it carries
    message = (
        "s.zarr: damaged store, cannot read data/action: its chunk (1, 0) (data/action/c/1/0) is not the chunk the "
        "store recorded there"
    )
    store = EpisodeStore(path)
    with pytest.raises(StoreError, match=re.escape(message)):
        store.verify()
    with pytest.raises(StoreError, match=re.escape(message)):
        store.array("action")
    with pytest.raises(StoreError, match=re.escape(message)):
        store["action"][4:8]
    np.testing.assert_array_equal(store.episode(0)["action"], np.arange(3.0)[:, None])  # chunk 0 alone: still read


def _as_version_2(path) -> None:
    """Make the store at `path` what bpp wrote as version 2: no record of its chunks' checksums."""

    def change(doc):
        attrs = doc["attributes"]
        del attrs["chunks"]
        attrs["version"] = 2
        attrs["digest"] = header_digest(attrs)

    _edit(path, "zarr.json", change)


def test_a_version_2_store_is_read_checked_against_the_checksums_its_chunks_carry(tmp_path, capsys):
    path = _write(tmp_path / "s.zarr").path
    _as_version_2(path)
    store = EpisodeStore(path)
    assert not store.chunks_recorded
    assert store.verify() == sum(len(_chunks(path, a)) for a in store.attrs["arrays"])
    np.testing.assert_array_equal(store.array("action"), _write(tmp_path / "v3.zarr").array("action"))
    main(["store", "info", str(path), "--verify"])
    assert "a version 2 store records no checksum per chunk key" in capsys.readouterr().out
    chunk = path / "data" / "action" / "c" / "1" / "0"
    chunk.write_bytes(chunk.read_bytes()[:-1] + b"\0")
    with pytest.raises(StoreError, match="its chunk \\(1, 0\\) \\(data/action/c/1/0\\) fails its checksum"):
        EpisodeStore(path).verify()


def test_a_header_without_a_valid_record_of_its_chunks_is_refused(tmp_path):
    path = _write(tmp_path / "s.zarr").path

    def change(doc):
        attrs = doc["attributes"]
        attrs["chunks"] = {**attrs["chunks"], "data/nothing/c/0/0": 1}  # an array the header does not record
        attrs["digest"] = header_digest(attrs)

    _edit(path, "zarr.json", change)
    with pytest.raises(StoreError, match="s.zarr: damaged store header \\(no valid table of chunk checksums\\)"):
        EpisodeStore(path)


def _edit(path, file: str, change) -> None:
    doc = json.loads((path / file).read_text())
    change(doc)
    (path / file).write_text(json.dumps(doc))


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (
            lambda p: _edit(p, "zarr.json", lambda d: d["attributes"]["stats"]["action"]["std"].__setitem__(0, 2.0)),
            "damaged store header \\(it does not match its digest\\)",
        ),
        (
            lambda p: _edit(p, "zarr.json", lambda d: d["attributes"]["tasks"][0].__setitem__("id", "x")),
            "damaged store header \\(it does not match its digest\\)",
        ),
        (
            lambda p: _edit(p, "data/action/zarr.json", lambda d: d.__setitem__("shape", [8, 1])),
            "damaged store, the metadata of data/action \\(data/action/zarr.json\\) does not match its digest",
        ),
        (lambda p: shutil.rmtree(p / "data" / "obs"), "damaged store \\(no data/obs\\)"),
        (lambda p: shutil.rmtree(p / "meta" / "angle"), "damaged store \\(no meta/angle\\)"),
    ],
    ids=["statistics", "task table", "an array's shape", "a per-step array", "an episode column"],
)
def test_a_changed_header_or_array_metadata_is_refused_when_opened(tmp_path, damage, message):
    path = _write(tmp_path / "s.zarr").path
    damage(path)
    with pytest.raises(StoreError, match=f"s.zarr: {message}"):
        EpisodeStore(path)


# ----------------------------------------------------------------------------- merging


def test_a_merge_never_doubles_demonstrations(tmp_path):
    a, b = _write(tmp_path / "a.zarr"), _write(tmp_path / "b.zarr", offset=10.0)
    out = tmp_path / "m.zarr"
    with pytest.raises(StoreError, match="a.zarr is .*a.zarr given again: a store merged with itself"):
        merge_stores([a.path, b.path, a.path], out)
    os.symlink(a.path, tmp_path / "alias.zarr")
    with pytest.raises(StoreError, match="alias.zarr is .*a.zarr given again"):
        merge_stores([a.path, tmp_path / "alias.zarr"], out)
    shutil.copytree(a.path, tmp_path / "copy.zarr")
    with pytest.raises(StoreError, match="episode 0 of .*copy.zarr is episode 0 of .*a.zarr again"):
        merge_stores([a.path, tmp_path / "copy.zarr"], out)
    both = merge_stores([a.path, b.path], tmp_path / "ab.zarr")
    with pytest.raises(StoreError, match="episode 0 of .*ab.zarr is episode 0 of .*a.zarr again"):
        merge_stores([a.path, both.path], out)  # a merge that includes the other store
    assert not out.exists()
    assert both.num_episodes == 6


def test_a_merge_never_writes_into_or_over_its_inputs(tmp_path):
    a, b = _write(tmp_path / "a.zarr"), _write(tmp_path / "b.zarr", offset=10.0)
    before = {s.path: s.fingerprint() for s in (a, b)}
    with pytest.raises(StoreError, match="the merge would be written inside its input .*a.zarr"):
        merge_stores([a.path, b.path], a.path / "data" / "m.zarr")
    with pytest.raises(StoreError, match="the merge would be written over its input .*b.zarr"):
        merge_stores([a.path, b.path], b.path, overwrite=True)
    with pytest.raises(StoreError, match="the merge would replace a folder holding its input .*a.zarr"):
        merge_stores([a.path, b.path], tmp_path, overwrite=True)
    assert {p: EpisodeStore(p).fingerprint() for p in before} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.zarr", "b.zarr"]


# ----------------------------------------------------------------------------- format and version


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            lambda d: d.__setitem__("zarr_format", 2),
            "not an episode store \\(zarr format 2; an episode store is a zarr",
        ),
        (lambda d: d.__setitem__("node_type", "array"), "not an episode store \\(zarr format 3, a zarr array"),
        (
            lambda d: d["attributes"].__setitem__("format", "replay-buffer"),
            "not an episode store \\(format 'replay-buffer', expected",
        ),
        (
            lambda d: d["attributes"].__setitem__("version", 1),
            "store version 1, written by an older bpp; this bpp reads versions 2 and 3 \\(checksummed chunks\\)",
        ),
        (lambda d: d["attributes"].__setitem__("version", 4), "store version 4, this bpp reads versions 2 and 3"),
        (lambda d: d["attributes"].__setitem__("version", 3.0), "store version 3.0, this bpp reads versions 2 and 3"),
        (
            lambda d: d["attributes"].__setitem__("version", 2),  # a version 3 store passed off as one without records
            "damaged store header \\(it does not match its digest\\)",
        ),
    ],
    ids=["zarr format 2", "a zarr array", "another format", "version 1", "a newer version", "3.0", "version 2"],
)
def test_a_store_of_another_format_or_version_is_reported_by_it(tmp_path, change, message):
    path = _write(tmp_path / "s.zarr").path
    _edit(path, "zarr.json", change)
    with pytest.raises(StoreError, match=f"s.zarr: {message}"):
        EpisodeStore(path)


def test_a_zarr_format_2_folder_is_reported_as_one(tmp_path):
    folder = tmp_path / "buffer.zarr"
    folder.mkdir()
    (folder / ".zgroup").write_text('{"zarr_format": 2}')
    with pytest.raises(StoreError, match="buffer.zarr: a zarr format 2 folder, not an episode store"):
        EpisodeStore(folder)


# ----------------------------------------------------------------------------- numbers in names


def test_only_ascii_digits_are_read_as_numbers_in_names(tmp_path):
    path = tmp_path / "s.zarr"
    stale = tmp_path / ".s.zarr.partial-999999999-0123abcd"  # no such process: a killed writer's
    others = [tmp_path / f".s.zarr.partial-{pid}-0123abcd" for pid in ("\u00b2", "\u0669" * 9, "\uff19" * 9)]
    for folder in [stale, *others]:
        folder.mkdir()
    _write(path)  # a writer removes what killed writers of its path left
    assert not stale.exists() and all(folder.exists() for folder in others)  # superscript, Arabic-Indic, full-width
    assert CHUNK_KEY.fullmatch("data/action/c/12/0")["index"] == "/12/0"
    assert CHUNK_KEY.fullmatch("data/action/c/\u0661/0") is None
